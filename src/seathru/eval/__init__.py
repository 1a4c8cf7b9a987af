"""Evaluation and display: image, depth and water metrics, alignment of results to the truth,
display transforms (exposure, sRGB, colour maps) and camera paths for videos.

Reads simulator truth and trained models only through ``seathru.io`` contracts; never imports
``seathru.sim`` or ``seathru.nerf``.
"""
