"""The ingest step's radiometric map of an encoded image, and its inverse.

Ingest turns a stored 8/16-bit or float image (JPEG, PNG, TIFF) into the pipeline's linear
radiance in two pixel-wise steps (``seathru.io.raw.read_encoded`` then
``seathru.radiometry.linearise.apply_colour`` with no colour matrix for encoded files)::

    linear = decode(stored) * gains * exposure_factor
    decode = inverse sRGB transfer   (encoding 'srgb': JPEG, 8-bit PNG/TIFF)
           | identity                (encoding 'linear': 16-bit/float PNG/TIFF, e.g. images_wb/)

with ``stored`` the file's values divided by their top code (255, 65535), ``gains`` the
dataset's white balance (``manifest.json`` ``white_balance.gains``) and ``exposure_factor`` the
image's exposure normalisation (``images[i].exposure_factor``). A render of the trained model is
linear radiance on that same scale; :func:`stored_values` takes it back to the values the
source file stores, so it can be compared with the stored image as it is on disk (no white
balance or exposure change applied to the ground truth). RAW files have no stored rendition to
go back to: their "stored" image is the ingest output itself (encoding 'linear', unit gains).

Pure numpy; no file I/O.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from seathru.radiometry.colour import linear_to_srgb, srgb_to_linear

Encoding = Literal["srgb", "linear"]
ENCODINGS: tuple[str, ...] = ("srgb", "linear")


def _gain(gains, exposure_factor: float) -> np.ndarray:
    gain = np.asarray(gains, dtype=np.float64).reshape(-1) * float(exposure_factor)
    if gain.shape != (3,) or not np.all(np.isfinite(gain)) or np.any(gain <= 0):
        raise ValueError(f"gains x exposure factor must be 3 positive numbers, got {gain}")
    return gain


def _check(encoding: str) -> None:
    if encoding not in ENCODINGS:
        raise ValueError(f"encoding must be one of {ENCODINGS}, not {encoding!r}")


def ingest_linear(stored: np.ndarray, gains, exposure_factor: float,
                  encoding: Encoding) -> np.ndarray:
    """The pipeline's linear radiance of a stored image (what ingest computes), float64.

    Args:
        stored: ``(H, W, 3)`` stored values in [0, 1] (file codes / top code).
        gains: ``(3,)`` white balance gains of the dataset.
        exposure_factor: the image's exposure normalisation factor.
        encoding: ``srgb`` or ``linear``, how the file encodes radiance.

    Returns:
        ``(H, W, 3)`` linear radiance.
    """
    _check(encoding)
    values = np.asarray(stored, dtype=np.float64)
    decoded = srgb_to_linear(values) if encoding == "srgb" else values
    return decoded * _gain(gains, exposure_factor)


def stored_values(linear: np.ndarray, gains, exposure_factor: float,
                  encoding: Encoding) -> np.ndarray:
    """The inverse of :func:`ingest_linear`: linear radiance back to stored values, float64.

    Values outside what the file can hold are clipped to [0, 1] (the sRGB transfer is defined
    there only), as an 8-bit file would store them.

    Args:
        linear: ``(H, W, 3)`` linear radiance on the ingest scale (e.g. a render).
        gains, exposure_factor, encoding: as for :func:`ingest_linear`.

    Returns:
        ``(H, W, 3)`` stored values in [0, 1].

    Example::

        >>> stored = np.full((1, 1, 3), 0.5)
        >>> linear = ingest_linear(stored, [1.2, 1.0, 2.0], 0.8, "srgb")
        >>> bool(np.allclose(stored_values(linear, [1.2, 1.0, 2.0], 0.8, "srgb"), stored))
        True
    """
    _check(encoding)
    values = np.asarray(linear, dtype=np.float64) / _gain(gains, exposure_factor)
    values = np.clip(np.nan_to_num(values, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    return linear_to_srgb(values) if encoding == "srgb" else values
