"""The dive simulator: procedural scenes and camera paths (``scene``), the camera and raw sensor
(``sensor``), underwater image formation from per-pixel ranges (``water``) and whole dives, view
by view (``dive``).

Owns the ground truth of synthetic datasets (written by ``seathru.io.truth``). Pure numpy;
never imports ``seathru.nerf``.
"""
