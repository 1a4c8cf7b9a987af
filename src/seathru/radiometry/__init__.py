"""Radiometry: colour transfer functions (``colour``) and the ingest maths that brings decoded
camera values to one linear scale: exposure, white balance, clipping masks, resizing
(``linearise``). Pure numpy; file decoding lives in ``seathru.io.raw``.
"""
