"""The ingest step's radiometric map of an encoded image, and its inverse.

Ingest turns a stored 8/16-bit or float image (JPEG, PNG, TIFF) into the pipeline's linear
radiance in two pixel-wise steps (``seathru.io.raw.read_encoded`` then
``seathru.radiometry.linearise.apply_colour`` with no colour matrix for encoded files)::

    linear = decode(stored) * gains * exposure_factor
    decode = inverse sRGB transfer   (encoding 'srgb': JPEG, 8-bit PNG/TIFF)
           | identity                (encoding 'linear': 16-bit/float PNG/TIFF, e.g. images_wb/)
           | stored ** g             (encoding 'gamma <g>': a profile's pure power curve,
                                      ProPhoto RGB's 1.8, Adobe RGB's 2.2)

with ``stored`` the file's values divided by their top code (255, 65535), ``gains`` the
dataset's white balance (``manifest.json`` ``white_balance.gains``) and ``exposure_factor`` the
image's exposure normalisation (``images[i].exposure_factor``). A render of the trained model is
linear radiance on that same scale; :func:`stored_values` takes it back to the values the
source file stores, so it can be compared with the stored image as it is on disk (no white
balance or exposure change applied to the ground truth). RAW files have no stored rendition to
go back to: their "stored" image is the ingest output itself (encoding 'linear', unit gains).

The encoding is the file's own where it records one (an ICC profile, a PNG ``sRGB`` or ``gAMA``
chunk: :func:`encoding_of_curves` names the curve), else the one its bit depth implies.

Pure numpy; no file I/O.
"""

from __future__ import annotations

import numpy as np

from seathru.radiometry.colour import linear_to_srgb, srgb_to_linear

#: ``srgb``, ``linear`` or ``gamma <g>`` (a pure power curve, e.g. ``gamma 1.8``).
Encoding = str
ENCODINGS: tuple[str, ...] = ("srgb", "linear", "gamma <g>")
#: How far (in linear values of [0, 1]) a recorded curve may lie from the one it is named as:
#: a quarter of an 8-bit code at the top of the range, well inside what an exporter's table
#: (1024 or 4096 samples of 16 bits) keeps of the curve it samples.
CURVE_TOLERANCE = 1e-3


def _gain(gains, exposure_factor: float) -> np.ndarray:
    gain = np.asarray(gains, dtype=np.float64).reshape(-1) * float(exposure_factor)
    if gain.shape != (3,) or not np.all(np.isfinite(gain)) or np.any(gain <= 0):
        raise ValueError(f"gains x exposure factor must be 3 positive numbers, got {gain}")
    return gain


def gamma_of(encoding: str) -> float | None:
    """The exponent of a ``gamma <g>`` encoding; None for ``srgb`` and ``linear``.

    Raises:
        ValueError: not one of the encodings (:data:`ENCODINGS`).
    """
    if encoding in ("srgb", "linear"):
        return None
    name, _, value = encoding.partition(" ")
    try:
        gamma = float(value)
    except ValueError:
        gamma = float("nan")
    if name != "gamma" or not (0.1 <= gamma <= 10.0):
        raise ValueError(f"encoding must be one of {ENCODINGS} (g in 0.1-10), not {encoding!r}")
    return gamma


def decode(stored, encoding: Encoding):
    """Stored values in [0, 1] to linear light by the encoding's curve (numpy or torch)."""
    gamma = gamma_of(encoding)
    if encoding == "srgb":
        return srgb_to_linear(stored)
    return stored if gamma is None else stored.clip(0.0, None) ** gamma


def encode(linear, encoding: Encoding):
    """The inverse of :func:`decode` on [0, 1] (values outside are clipped there)."""
    gamma = gamma_of(encoding)
    if encoding == "srgb":
        return linear_to_srgb(linear)
    linear = linear.clip(0.0, 1.0)
    return linear if gamma is None else linear ** (1.0 / gamma)


def encoding_of_curves(curves: np.ndarray) -> Encoding | None:
    """The encoding whose curve the recorded ones follow (every channel), or None.

    Args:
        curves: ``(C, N)`` linear light at stored values ``linspace(0, 1, N)`` per channel
            (an ICC profile's tone curves: ``seathru.io.icc.channel_curves``).

    Returns:
        ``linear``, ``srgb`` or ``gamma <g>`` (g to two decimals) where every channel lies within
        :data:`CURVE_TOLERANCE` of it; None for any other curve (Rec. 709's, a camera's log
        curve, channels that differ).

    Example:
        >>> x = np.linspace(0.0, 1.0, 256)
        >>> encoding_of_curves(np.stack([x ** 1.8] * 3)), encoding_of_curves(np.stack([x] * 3))
        ('gamma 1.8', 'linear')
    """
    curves = np.asarray(curves, dtype=np.float64)
    x = np.linspace(0.0, 1.0, curves.shape[-1])

    def follows(reference: np.ndarray) -> bool:
        return bool(np.max(np.abs(curves - reference)) <= CURVE_TOLERANCE)

    if follows(x):
        return "linear"
    if follows(srgb_to_linear(x)):
        return "srgb"
    middle = (x > 0.2) & (x < 0.8) & np.all(curves > 0, axis=0)
    if not middle.any():
        return None
    gamma = round(float(np.median(np.log(curves[:, middle]) / np.log(x[middle]))), 2)
    if 0.1 <= gamma <= 10.0 and follows(x ** gamma):
        return "linear" if gamma == 1.0 else f"gamma {gamma:g}"
    return None


def ingest_linear(stored: np.ndarray, gains, exposure_factor: float,
                  encoding: Encoding) -> np.ndarray:
    """The pipeline's linear radiance of a stored image (what ingest computes), float64.

    Args:
        stored: ``(H, W, 3)`` stored values in [0, 1] (file codes / top code).
        gains: ``(3,)`` white balance gains of the dataset.
        exposure_factor: the image's exposure normalisation factor.
        encoding: how the file encodes radiance (:data:`Encoding`).

    Returns:
        ``(H, W, 3)`` linear radiance.
    """
    return decode(np.asarray(stored, dtype=np.float64), encoding) * _gain(gains, exposure_factor)


def stored_values(linear: np.ndarray, gains, exposure_factor: float,
                  encoding: Encoding) -> np.ndarray:
    """The inverse of :func:`ingest_linear`: linear radiance back to stored values, float64.

    Values outside what the file can hold are clipped to [0, 1] (the sRGB transfer is defined
    there only), as a file would store them.

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
    gamma_of(encoding)
    values = np.asarray(linear, dtype=np.float64) / _gain(gains, exposure_factor)
    return encode(np.nan_to_num(values, nan=0.0, posinf=1.0, neginf=0.0), encoding)
