"""The dive simulator: procedural scenes and camera paths (``scene``), the camera and raw sensor
(``sensor``) and underwater image formation from per-pixel ranges (``water``).

Owns the ground truth of synthetic datasets. Pure numpy; never imports ``seathru.nerf``.
"""
