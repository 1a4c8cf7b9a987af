"""Radiometry: colour transfer functions (``colour``), the per-image maths that brings decoded
camera values to one linear scale: exposure, white balance, clipping masks, resizing, matching
copies (``linearise``), and the dataset-level exposure and white-balance estimate
(``dataset_transform``). Pure numpy; file decoding lives in ``seathru.io.raw``.
"""
