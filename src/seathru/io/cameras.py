"""The one camera file that training, rendering and evaluation read, whatever the source.

``cameras.json`` (format ``seathru-cameras/1``)::

    {
      "format": "seathru-cameras/1",
      "convention": "...",                 # human-readable statement of the conventions below
      "normalisation": {"centre": [x, y, z], "scale": s,
                        "metres_per_source_unit": m},   # optional: the source's metric scale
                                                        # (simulator's cameras: 1; COLMAP's: as
                                                        # the user gave it); absent: not known
      "near": float, "far": float,         # scene-wide bounds, normalised units
      "source": "simulated|colmap|llff|nerfstudio",
      "frames": [
        {"name": "IMG_0001",               # image stem, the key used by every stage
         "image": "images/IMG_0001.tiff",  # linear image, path relative to this file
         "mask": "masks/IMG_0001.png",     # optional validity mask, relative path
         "width": W, "height": H,
         "fx": ..., "fy": ..., "cx": ..., "cy": ...,   # pinhole, pixels
         "c2w": [[...4], [...4], [...4], [0, 0, 0, 1]],
         "near": float, "far": float,      # per-frame bounds on the range, normalised units
         "split": "train" | "test",
         "blur_px": [r, g, b]}             # optional: Gaussian sigma (pixels) of the blur the
                                           # pipeline's decoding and undistortion added
                                           # (seathru.radiometry.deblur); absent: not known
      ]
    }

Conventions:
- camera axes are OpenCV/COLMAP: x right, y down, z forward (looking along +z);
- ``c2w`` maps camera coordinates to normalised world coordinates;
- a frame's ``near`` / ``far`` bound the range (distance from the camera centre along each
  pixel's ray, the ``t`` of the rendering equation), not the depth along the optical axis:
  readers of LLFF-style depth bounds convert them (``seathru.geometry.poses.range_bounds``);
- the centre of pixel (u, v) (column, row) is at (u + 0.5, v + 0.5);
- normalised world = (source world - centre) * scale, so a distance d in source units is
  d * scale in normalised units and a coefficient sigma fitted in normalised units is
  sigma * scale per source unit.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from seathru.errors import PipelineError
from seathru.io.atomic import write_json

FORMAT = "seathru-cameras/1"
CONVENTION = ("OpenCV camera axes (x right, y down, z forward); c2w maps camera to normalised "
              "world; pixel (u, v) centre at (u + 0.5, v + 0.5); normalised = (source - centre) "
              "* scale")


@dataclass
class Frame:
    name: str
    image: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    c2w: list[list[float]]
    near: float
    far: float
    split: str = "train"
    mask: str | None = None
    blur_px: list[float] | None = None

    @property
    def c2w_array(self) -> np.ndarray:
        return np.asarray(self.c2w, dtype=np.float64)

    @property
    def intrinsics(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass
class CameraSet:
    frames: list[Frame]
    near: float
    far: float
    centre: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    scale: float = 1.0
    source: str = "unknown"
    root: Path | None = None  # folder of the camera file; image paths are relative to it
    metres_per_source_unit: float | None = None  # the source's metric scale, where known

    def split(self, which: str) -> list[Frame]:
        return [f for f in self.frames if f.split == which]

    def image_path(self, frame: Frame) -> Path:
        return (self.root or Path(".")) / frame.image

    def mask_path(self, frame: Frame) -> Path | None:
        return None if frame.mask is None else (self.root or Path(".")) / frame.mask

    def to_dict(self) -> dict:
        return {
            "format": FORMAT,
            "convention": CONVENTION,
            "normalisation": {"centre": [float(c) for c in self.centre], "scale": float(self.scale),
                              **({} if self.metres_per_source_unit is None else
                                 {"metres_per_source_unit": float(self.metres_per_source_unit)})},
            "near": float(self.near),
            "far": float(self.far),
            "source": self.source,
            "frames": [_frame_dict(f) for f in self.frames],
        }


def _frame_dict(frame: Frame) -> dict:
    data = asdict(frame)
    data["c2w"] = [[float(v) for v in row] for row in frame.c2w]
    for optional in ("mask", "blur_px"):
        if data[optional] is None:
            del data[optional]
    return data


def every_nth_split(names: list[str], test_every: int = 8) -> dict[str, str]:
    """The paper's split: in sorted name order, image 0, n, 2n, ... are held out for testing."""
    if test_every <= 0:
        return {name: "train" for name in names}
    return {name: ("test" if i % test_every == 0 else "train")
            for i, name in enumerate(sorted(names))}


def write_cameras(path: str | os.PathLike, cameras: CameraSet) -> None:
    write_json(path, cameras.to_dict())


def read_cameras(path: str | os.PathLike) -> CameraSet:
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise PipelineError(f"{path}: camera file not found; run the 'poses' step first") from None
    except json.JSONDecodeError as exc:
        raise PipelineError(f"{path}: camera file is not valid JSON ({exc})") from None
    if data.get("format") != FORMAT:
        raise PipelineError(f"{path}: expected format {FORMAT!r}, found {data.get('format')!r}")
    try:
        frames = [Frame(**frame) for frame in data["frames"]]
    except TypeError as exc:
        raise PipelineError(f"{path}: a frame has missing or unknown fields ({exc})") from None
    norm = data.get("normalisation", {})
    return CameraSet(frames=frames, near=float(data["near"]), far=float(data["far"]),
                     centre=list(norm.get("centre", [0.0, 0.0, 0.0])),
                     scale=float(norm.get("scale", 1.0)), source=data.get("source", "unknown"),
                     root=path.parent, metres_per_source_unit=_positive_or_none(
                         norm.get("metres_per_source_unit"), path))


def _positive_or_none(value, path: Path) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
        raise PipelineError(f"{path}: normalisation.metres_per_source_unit must be a positive "
                            f"number, found {value!r}; re-run the 'poses' step")
    return float(value)
