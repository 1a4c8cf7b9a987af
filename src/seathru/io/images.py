"""Reading and writing images in the project's formats, all as RGB ``float32`` arrays in memory.

On disk:
- linear radiance: ``.tiff`` float32 (values may exceed 1 after exposure normalisation) or
  ``.png`` 16-bit (scaled by 65535);
- display and matching copies: 8-bit ``.png`` or ``.jpg`` (sRGB encoded by the caller);
- masks: 8-bit ``.png``, 255 = valid.
Arrays are ``(H, W, 3)`` for colour, ``(H, W)`` for masks and depth.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import tifffile

from seathru.errors import PipelineError
from seathru.io.atomic import atomic_path

#: Extensions (lower case) :func:`list_images` takes as images.
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".bmp", ".webp")
JPEG_SAMPLING_FACTORS = {"4:4:4": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444,
                         "4:2:2": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_422,
                         "4:2:0": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420}


def list_images(folder: Path) -> list[Path]:
    """Image files of a folder (any common extension, case-insensitive), sorted by name."""
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir()
                  if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS
                  and not p.name.startswith("."))


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read an image as float32. 8-bit files map to [0, 1], 16-bit to [0, 1], float as stored."""
    path = Path(path)
    if not path.exists():
        raise PipelineError(f"{path}: image file not found")
    if path.suffix.lower() in (".tif", ".tiff"):
        array = tifffile.imread(path)
    else:
        array = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if array is None:
            raise PipelineError(f"{path}: cannot be read as an image (corrupt or unsupported)")
        if array.ndim == 3:
            array = cv2.cvtColor(array, cv2.COLOR_BGRA2RGB if array.shape[2] == 4
                                 else cv2.COLOR_BGR2RGB)
    if array.dtype == np.uint8:
        return array.astype(np.float32) / 255.0
    if array.dtype == np.uint16:
        return array.astype(np.float32) / 65535.0
    return np.asarray(array, dtype=np.float32)


def write_float_tiff(path: str | os.PathLike, array: np.ndarray) -> None:
    """Write a float32 TIFF atomically (linear images, depth maps)."""
    with atomic_path(path) as tmp:
        array = np.ascontiguousarray(array, dtype=np.float32)
        photometric = "rgb" if array.ndim == 3 and array.shape[2] == 3 else "minisblack"
        tifffile.imwrite(tmp, array, photometric=photometric)


def _write_cv2(path: str | os.PathLike, array: np.ndarray, params: list[int] | None = None) -> None:
    if array.ndim == 3:
        array = cv2.cvtColor(array, cv2.COLOR_RGB2BGR)
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), array, params or []):
            raise PipelineError(f"{path}: OpenCV could not write the image")


def write_png16(path: str | os.PathLike, array: np.ndarray) -> None:
    """Write values in [0, 1] as a 16-bit PNG (values outside are clipped)."""
    _write_cv2(path, np.round(np.clip(array, 0.0, 1.0) * 65535.0).astype(np.uint16))


def write_8bit(path: str | os.PathLike, array: np.ndarray, jpeg_quality: int = 95) -> None:
    """Write values in [0, 1] as an 8-bit PNG or JPEG (by the suffix); no colour transform."""
    data = np.round(np.clip(array, 0.0, 1.0) * 255.0).astype(np.uint8)
    params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if Path(path).suffix.lower() in (
        ".jpg", ".jpeg") else None
    _write_cv2(path, data, params)


def write_camera_jpeg(path: str | os.PathLike, array: np.ndarray, quality: int, *,
                      exposure_time_s: float, iso: int, f_number: float,
                      focal_length_35mm: int | None = None, chroma: str = "4:2:0") -> None:
    """Write values in [0, 1] as an 8-bit JPEG with a camera's EXIF exposure (ExposureTime,
    ISOSpeedRatings, FNumber, FocalLengthIn35mmFilm), atomically; the pixels as
    :func:`write_8bit` encodes them, the colour at ``chroma`` sampling ("4:2:0", "4:2:2" or
    "4:4:4")."""
    from PIL import Image
    from PIL.TiffImagePlugin import IFDRational

    if chroma not in JPEG_SAMPLING_FACTORS:
        raise ValueError(f"{path}: chroma sampling {chroma!r} is not one of "
                         f"{', '.join(JPEG_SAMPLING_FACTORS)}")
    data = np.round(np.clip(array, 0.0, 1.0) * 255.0).astype(np.uint8)
    ok, encoded = cv2.imencode(".jpg", cv2.cvtColor(data, cv2.COLOR_RGB2BGR),
                               [cv2.IMWRITE_JPEG_QUALITY, quality,
                                cv2.IMWRITE_JPEG_SAMPLING_FACTOR, JPEG_SAMPLING_FACTORS[chroma]])
    if not ok:
        raise PipelineError(f"{path}: OpenCV could not encode the JPEG")
    exif = Image.Exif()
    details = exif.get_ifd(0x8769)   # the Exif IFD
    details[0x829A] = IFDRational(exposure_time_s)
    details[0x8827] = int(iso)
    details[0x829D] = IFDRational(f_number)
    if focal_length_35mm is not None:
        details[0xA405] = int(focal_length_35mm)
    payload = exif.tobytes()          # b"Exif\0\0" and the TIFF structure
    segment = b"\xff\xe1" + (len(payload) + 2).to_bytes(2, "big") + payload
    jpeg = encoded.tobytes()
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(jpeg[:2] + segment + jpeg[2:])   # APP1 right after the start


def write_mask(path: str | os.PathLike, mask: np.ndarray) -> None:
    """Write a boolean validity mask as an 8-bit PNG (255 = valid)."""
    _write_cv2(path, np.where(mask, 255, 0).astype(np.uint8))


def read_mask(path: str | os.PathLike) -> np.ndarray:
    return read_image(path) > 0.5
