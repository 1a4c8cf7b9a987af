"""Writing and reading minimal, standard DNG raw files (what the simulator writes).

A file is one uncompressed 16-bit CFA image in the main IFD (PhotometricInterpretation 32803)
with the DNG tags set explicitly: DNGVersion 1.4, CFARepeatPatternDim 2x2, CFAPattern,
CFAPlaneColor, BlackLevel, WhiteLevel, ColorMatrix1 (XYZ D65 -> camera; the camera space is
linear sRGB, so LibRaw derives an identity camera-to-sRGB matrix), CalibrationIlluminant1 D65,
AsShotNeutral (1, 1, 1). tifffile cannot write an EXIF sub-IFD, so ExposureTime (33434),
FNumber (33437), ISOSpeedRatings (34855) and FocalLengthIn35mmFilm (41989) sit in the main IFD,
where both LibRaw and exifread find them.

Read back with :func:`read_dng_metadata` (tags, via tifffile) and :func:`decode_linear` (rawpy,
linear and unscaled: the result is ``(raw - black) / (white - black)`` after demosaicing).
"""

from __future__ import annotations

import os
from fractions import Fraction
from pathlib import Path

import numpy as np
import tifffile

from seathru.errors import PipelineError
from seathru.io.atomic import atomic_path

CFA_CODES = {"R": 0, "G": 1, "B": 2}
# XYZ (D65) -> linear sRGB (IEC 61966-2-1).
XYZ_TO_LINEAR_SRGB = (3.2404542, -1.5371385, -0.4985314,
                      -0.9692660, 1.8760108, 0.0415560,
                      0.0556434, -0.2040259, 1.0572252)
D65 = 21  # EXIF LightSource code used by CalibrationIlluminant1


def _rational(value: float, max_denominator: int = 1_000_000) -> tuple[int, int]:
    fraction = Fraction(value).limit_denominator(max_denominator)
    return fraction.numerator, fraction.denominator


def write_dng(path: str | os.PathLike, raw: np.ndarray, *, black_level: int, white_level: int,
              exposure_time_s: float, iso: int, f_number: float, cfa_pattern: str = "RGGB",
              make: str = "SeaThru", model: str = "Simulated dive camera",
              focal_length_35mm: int | None = None) -> None:
    """Write the (H, W) ``uint16`` mosaic ``raw`` as a DNG, atomically (``focal_length_35mm``:
    the EXIF 35 mm equivalent focal length, whole millimetres, as cameras record it)."""
    raw = np.ascontiguousarray(raw)
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise ValueError(f"raw must be a 2-D uint16 mosaic, got {raw.dtype} {raw.shape}")
    if len(cfa_pattern) != 4 or any(c not in CFA_CODES for c in cfa_pattern):
        raise ValueError(f"cfa_pattern must be four of R, G, B, got {cfa_pattern!r}")
    matrix: list[int] = []
    for value in XYZ_TO_LINEAR_SRGB:
        matrix.extend(_rational(value, 100_000))
    extratags = [
        (50706, "B", 4, (1, 4, 0, 0), True),                      # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0), True),                      # DNGBackwardVersion
        (50708, "s", 0, f"{make} {model}", True),                 # UniqueCameraModel
        (33421, "H", 2, (2, 2), True),                            # CFARepeatPatternDim
        (33422, "B", 4, tuple(CFA_CODES[c] for c in cfa_pattern), True),  # CFAPattern
        (50710, "B", 3, (0, 1, 2), True),                         # CFAPlaneColor
        (50711, "H", 1, 1, True),                                 # CFALayout: rectangular
        (50713, "H", 2, (1, 1), True),                            # BlackLevelRepeatDim
        (50714, "I", 1, int(black_level), True),                  # BlackLevel
        (50717, "I", 1, int(white_level), True),                  # WhiteLevel
        (50721, "2i", 9, tuple(matrix), True),                    # ColorMatrix1
        (50778, "H", 1, D65, True),                               # CalibrationIlluminant1
        (50728, "2I", 3, (1, 1, 1, 1, 1, 1), True),               # AsShotNeutral
        (33434, "2I", 1, _rational(exposure_time_s), True),       # ExposureTime
        (33437, "2I", 1, _rational(f_number, 100), True),         # FNumber
        (34855, "H", 1, int(iso), True),                          # ISOSpeedRatings
        (271, "s", 0, make, True),                                # Make
        (272, "s", 0, model, True),                               # Model
        (274, "H", 1, 1, True),                                   # Orientation: top-left
    ]
    if focal_length_35mm is not None:
        extratags.append((41989, "H", 1, int(focal_length_35mm), True))  # FocalLengthIn35mmFilm
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, raw, photometric=32803, extratags=extratags, subfiletype=0,
                         metadata=None, software="seathru simulate")


def _fraction(value) -> float:
    if isinstance(value, tuple) and len(value) == 2:
        return value[0] / value[1]
    return float(value)


def read_dng_metadata(path: str | os.PathLike) -> dict:
    """Black/white level, CFA pattern, exposure time (s), ISO and F-number of a DNG, read from
    its main IFD with tifffile."""
    path = Path(path)
    if not path.exists():
        raise PipelineError(f"{path}: DNG file not found")
    with tifffile.TiffFile(path) as tif:
        tags = {tag.code: tag.value for tag in tif.pages[0].tags}
    if 50706 not in tags:
        raise PipelineError(f"{path}: not a DNG (no DNGVersion tag)")
    pattern = tags.get(33422)
    names = "RGB"
    black = tags.get(50714, 0)
    black = black[0] if isinstance(black, tuple) else black
    return {
        "width": int(tags[256]), "height": int(tags[257]),
        "black_level": float(_fraction(black)),
        "white_level": float(tags.get(50717, 2 ** int(tags.get(258, 16)) - 1)),
        "cfa_pattern": "".join(names[c] for c in bytes(pattern)) if pattern is not None else None,
        "exposure_time_s": _fraction(tags[33434]) if 33434 in tags else None,
        "f_number": _fraction(tags[33437]) if 33437 in tags else None,
        "iso": int(tags[34855]) if 34855 in tags else None,
        "focal_length_35mm": int(tags[41989]) if 41989 in tags else None,
    }


def decode_linear(path: str | os.PathLike) -> np.ndarray:
    """Demosaiced linear camera RGB (H, W, 3) float32 ``(raw - black) / (white - black)`` in
    [0, 1], by LibRaw (AHD) with no white balance, no colour conversion, no auto brightness and
    no data-driven maximum adjustment."""
    import rawpy

    with rawpy.imread(str(path)) as raw:
        rgb = raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16,
                              use_camera_wb=False, use_auto_wb=False, user_wb=[1.0, 1.0, 1.0, 1.0],
                              output_color=rawpy.ColorSpace.raw, adjust_maximum_thr=0.0,
                              user_flip=0)
    return rgb.astype(np.float32) / 65535.0
