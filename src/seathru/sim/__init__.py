"""The dive simulator: procedural scenes and camera paths (``scene``; the reef slope with open
water and its survey path, ``reef``), the camera and raw sensor (``sensor``), underwater image
formation from per-pixel ranges (``water``, with named water presets) and whole dives, view by
view (``dive``, which maps each camera path to its scene).

Owns the ground truth of synthetic datasets (written by ``seathru.io.truth``). Pure numpy;
never imports ``seathru.nerf``.
"""
