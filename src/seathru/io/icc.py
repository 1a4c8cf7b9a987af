"""ICC colour profiles embedded in image files: the tone curves of their colour channels.

A photograph exported from a RAW converter (Lightroom, darktable, RawTherapee, Capture One)
carries the profile of its colour space, and with it the curve from the stored values to linear
light: ProPhoto RGB's gamma 1.8, Adobe RGB's 2.2, sRGB's piecewise curve, or a linear working
space's identity. A 16-bit TIFF is as likely to hold one of the encoded curves as linear data,
so ingest reads the curve instead of guessing from the bit depth.

Only the per-channel tone reproduction curves of matrix/TRC profiles (tags ``rTRC``, ``gTRC``,
``bTRC``, or ``kTRC`` for grey) are read, in the two forms the ICC specification (ICC.1:2010,
10.6 and 10.18) gives them: ``curv`` (identity, one gamma, or a sampled table) and ``para``
(the five parametric functions). Profiles built on lookup tables only (``A2B0``) give no curve.
"""

from __future__ import annotations

import struct

import numpy as np

#: Where the curves are sampled (stored value in [0, 1]) by :func:`channel_curves`.
CURVE_SAMPLES = 1024
_RGB_TAGS = (b"rTRC", b"gTRC", b"bTRC")
_GREY_TAG = b"kTRC"


def _tags(profile: bytes) -> dict[bytes, bytes]:
    if len(profile) < 132 or profile[36:40] != b"acsp":
        return {}
    count = struct.unpack(">I", profile[128:132])[0]
    tags = {}
    for index in range(min(count, (len(profile) - 132) // 12)):
        signature, offset, size = struct.unpack(">4sII", profile[132 + 12 * index:144 + 12 * index])
        if offset + size <= len(profile):
            tags[signature] = profile[offset:offset + size]
    return tags


def _s15fixed16(data: bytes, count: int) -> list[float]:
    return [value / 65536.0 for value in struct.unpack(f">{count}i", data[:4 * count])]


def _parametric(x: np.ndarray, function: int, p: list[float]) -> np.ndarray:
    """ICC.1:2010 table 68: the five parametric curves, ``p = [g, a, b, c, d, e, f]``."""
    g = p[0]
    if function == 0:
        return x ** g
    a, b = p[1], p[2]
    base = np.clip(a * x + b, 0.0, None) ** g
    if function == 1:
        return np.where(x >= -b / a, base, 0.0)
    if function == 2:
        return np.where(x >= -b / a, base + p[3], p[3])
    if function == 3:
        return np.where(x >= p[4], base, p[3] * x)
    return np.where(x >= p[4], base + p[5], p[3] * x + p[6])


_PARAMETERS = {0: 1, 1: 3, 2: 4, 3: 5, 4: 7}


def _curve(tag: bytes, x: np.ndarray) -> np.ndarray | None:
    kind = tag[:4]
    if kind == b"curv" and len(tag) >= 12:
        count = struct.unpack(">I", tag[8:12])[0]
        if count == 0:
            return x.copy()
        if count == 1:
            return x ** (struct.unpack(">H", tag[12:14])[0] / 256.0)
        if len(tag) < 12 + 2 * count:
            return None
        table = np.asarray(struct.unpack(f">{count}H", tag[12:12 + 2 * count]), float) / 65535
        return np.interp(x, np.linspace(0.0, 1.0, count), table)
    if kind == b"para" and len(tag) >= 12:
        function = struct.unpack(">H", tag[8:10])[0]
        needed = _PARAMETERS.get(function)
        if needed is None or len(tag) < 12 + 4 * needed:
            return None
        return _parametric(x, function, _s15fixed16(tag[12:], needed))
    return None


def channel_curves(profile: bytes) -> np.ndarray | None:
    """The profile's tone curves, stored value to linear light, sampled per colour channel.

    Args:
        profile: the ICC profile's bytes, as embedded in the image file.

    Returns:
        ``(3, CURVE_SAMPLES)`` linear values at ``linspace(0, 1, CURVE_SAMPLES)`` for R, G, B
        (a grey profile's one curve three times), or None where the profile holds no tone
        curves it can be read by (not an ICC profile, a lookup-table profile, a damaged tag).

    Example:
        >>> from PIL import ImageCms
        >>> srgb = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
        >>> round(float(channel_curves(srgb)[1, -1]), 3)
        1.0
    """
    tags = _tags(profile)
    x = np.linspace(0.0, 1.0, CURVE_SAMPLES)
    if all(name in tags for name in _RGB_TAGS):
        curves = [_curve(tags[name], x) for name in _RGB_TAGS]
    elif _GREY_TAG in tags:
        curves = [_curve(tags[_GREY_TAG], x)] * 3
    else:
        return None
    if any(curve is None or not np.all(np.isfinite(curve)) for curve in curves):
        return None
    return np.stack(curves)


def description(profile: bytes) -> str | None:
    """The profile's name (its ``desc`` tag: ICC v2 text or v4 multi-localised), or None."""
    tag = _tags(profile).get(b"desc")
    if tag is None or len(tag) < 12:
        return None
    try:
        if tag[:4] == b"desc":
            length = struct.unpack(">I", tag[8:12])[0]
            text = tag[12:12 + length].decode("latin-1")
        elif tag[:4] == b"mluc":
            size, offset = struct.unpack(">II", tag[20:28])
            text = tag[offset:offset + size].decode("utf-16-be")
        else:
            return None
    except (struct.error, UnicodeDecodeError):
        return None
    return text.rstrip("\x00").strip() or None
