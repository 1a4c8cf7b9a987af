"""Camera intrinsics known before structure from motion: focal lengths from the user or from
EXIF metadata, and the initial COLMAP camera they give. Pure Python/numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal, get_args

import numpy as np

#: COLMAP camera models the poses step offers.
CameraModel = Literal["SIMPLE_RADIAL", "OPENCV", "RADIAL", "SIMPLE_PINHOLE", "PINHOLE"]
CAMERA_MODELS: tuple[str, ...] = get_args(CameraModel)

#: 35 mm equivalent focal lengths are defined on the 36 x 24 mm frame diagonal.
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)


def focal_px_from_35mm(focal_35mm: float, width: int, height: int) -> float:
    """The focal length in pixels of a ``width`` x ``height`` image whose 35 mm equivalent is
    ``focal_35mm`` (by the diagonal: independent of the image's orientation and scale)."""
    return focal_35mm / FULL_FRAME_DIAGONAL_MM * math.hypot(width, height)


def focal_35mm_from_px(focal_px: float, width: int, height: int) -> float:
    """The inverse of :func:`focal_px_from_35mm`."""
    return focal_px * FULL_FRAME_DIAGONAL_MM / math.hypot(width, height)

#: Metadata keys (lower case) that hold a focal length, by kind.
FOCAL_KEYS = {
    "px": ("focal_length_px", "focal_px"),
    "mm": ("focal_length_mm", "focal_mm", "focallength", "exif focallength"),
    "35mm": ("focal_length_35mm", "focal_35mm", "focallengthin35mmfilm",
             "exif focallengthin35mmfilm"),
    "sensor": ("sensor_width_mm",),
}


def _number(value: Any) -> float | None:
    """EXIF numbers arrive as numbers, '24', '24/1' or [24]."""
    if isinstance(value, (list, tuple)) and len(value) == 1:
        value = value[0]
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, str):
        try:
            if "/" in value:
                num, den = value.split("/", 1)
                return float(num) / float(den)
            return float(value)
        except (ValueError, ZeroDivisionError):
            return None
    return None


def _collect(data: Any, found: dict[str, list[float]]) -> None:
    if isinstance(data, dict):
        for key, value in data.items():
            lowered = str(key).lower()
            for kind, keys in FOCAL_KEYS.items():
                if lowered in keys:
                    number = _number(value)
                    if number is not None and number > 0:
                        found[kind].append(number)
            _collect(value, found)
    elif isinstance(data, list):
        for item in data:
            _collect(item, found)


def focal_from_metadata(metadata: Any, width: int, height: int) -> tuple[float | None, str]:
    """Focal length in pixels at ``width`` x ``height`` from EXIF-like metadata.

    Looks anywhere in ``metadata`` (nested dicts and lists, e.g. an ingest manifest) for
    focal_length_px, focal_length_mm (+ sensor_width_mm) or focal_length_35mm (EXIF
    FocalLengthIn35mmFilm) keys, case-insensitively. All values of a kind must agree within 1 %.

    Returns:
        ``(focal_px, how)``: the focal length (None if unknown) and where it came from, or why
        there is none.

    Example::

        >>> focal_from_metadata({"focal_length_mm": "12/1", "sensor_width_mm": 24.0}, 800, 600)
        (400.0, 'manifest focal_length_mm / sensor_width_mm')
    """
    if not metadata:
        return None, "no manifest"
    found: dict[str, list[float]] = {kind: [] for kind in FOCAL_KEYS}
    _collect(metadata, found)

    def agreed(values: list[float]) -> float | None:
        if not values:
            return None
        middle = float(np.median(values))
        return middle if max(abs(v - middle) for v in values) <= 0.01 * middle else None

    focal_px, focal_mm, focal_35 = agreed(found["px"]), agreed(found["mm"]), agreed(found["35mm"])
    sensor = agreed(found["sensor"])
    if focal_px is not None:
        return focal_px, "manifest focal_length_px"
    if focal_mm is not None and sensor is not None:
        return focal_mm / sensor * width, "manifest focal_length_mm / sensor_width_mm"
    if focal_35 is not None:
        return (focal_px_from_35mm(focal_35, width, height),
                "manifest 35 mm equivalent focal length")
    if any(found.values()):
        return None, "manifest focal lengths missing a sensor width or not the same for all"
    return None, "no focal length in the manifest"


@dataclass(frozen=True)
class FocalPrior:
    """What is known of the focal length before SfM: given in pixels, in mm with the sensor
    width, or in metadata (:func:`focal_from_metadata`), in that order of precedence."""

    focal_px: float | None = None
    focal_mm: float | None = None
    sensor_width_mm: float | None = None
    metadata: Any = None

    def at_size(self, width: int, height: int) -> tuple[float | None, str]:
        """``(focal_px, how)`` for images of ``width`` x ``height`` pixels.

        Raises:
            ValueError: ``focal_mm`` without ``sensor_width_mm``.
        """
        if self.focal_px is not None:
            return self.focal_px, "--focal-px"
        if self.focal_mm is not None:
            if self.sensor_width_mm is None:
                raise ValueError("--focal-mm needs --sensor-width-mm (or give --focal-px)")
            return self.focal_mm / self.sensor_width_mm * width, "--focal-mm / --sensor-width-mm"
        return focal_from_metadata(self.metadata, width, height)


def initial_camera_params(model: str, focal_px: float, width: int, height: int) -> str:
    """COLMAP parameter string for a camera with a known focal length and no distortion yet.

    Example::

        >>> initial_camera_params("SIMPLE_RADIAL", 500.0, 640, 480)
        '500.0,320.0,240.0,0.0'
    """
    cx, cy = width / 2.0, height / 2.0
    params = {
        "SIMPLE_PINHOLE": [focal_px, cx, cy],
        "PINHOLE": [focal_px, focal_px, cx, cy],
        "SIMPLE_RADIAL": [focal_px, cx, cy, 0.0],
        "RADIAL": [focal_px, cx, cy, 0.0, 0.0],
        "OPENCV": [focal_px, focal_px, cx, cy, 0.0, 0.0, 0.0, 0.0],
    }[model]
    return ",".join(repr(float(p)) for p in params)
