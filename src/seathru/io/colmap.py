"""COLMAP models and cameras with pycolmap 4.2.1: reading models, camera rescaling and the
undistortion of images onto pinhole cameras. Running COLMAP is ``seathru.io.sfm``.
"""

from __future__ import annotations

import contextlib
import copy
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import pycolmap

from seathru.errors import PipelineError
from seathru.geometry.poses import c2w_from_cam_from_world, depth_bounds, point_depths


# -- reading models --------------------------------------------------------------------------

def find_model_dir(path: Path) -> Path:
    """A COLMAP model folder: ``path`` itself, or ``path/sparse/0``, ``path/sparse``, ``path/0``."""
    for candidate in (path, path / "sparse" / "0", path / "sparse", path / "0"):
        if any((candidate / f"cameras.{ext}").exists() for ext in ("bin", "txt")):
            return candidate
    raise PipelineError(f"{path}: no COLMAP model found (looked for cameras.bin or cameras.txt "
                        f"in it and in sparse/0, sparse, 0); pass the model folder")


def read_model(path: Path) -> pycolmap.Reconstruction:
    model_dir = find_model_dir(Path(path))
    try:
        return pycolmap.Reconstruction(model_dir)
    except Exception as exc:
        raise PipelineError(f"{model_dir}: COLMAP model cannot be read ({exc})") from None


def registered_c2w(model: pycolmap.Reconstruction) -> dict[str, np.ndarray]:
    """OpenCV camera-to-world (4, 4) of every registered image, by image name."""
    return {model.image(i).name: c2w_from_cam_from_world(model.image(i).cam_from_world().matrix())
            for i in model.reg_image_ids()}


@dataclass
class ModelImage:
    """One registered image of a COLMAP model, in source units."""

    name: str                # file name as stored in the model
    camera: pycolmap.Camera  # possibly distorted, at the model's resolution
    c2w: np.ndarray          # (4, 4) OpenCV camera-to-world
    near: float | None
    far: float | None


def model_images(model: pycolmap.Reconstruction) -> list[ModelImage]:
    """Registered images with OpenCV c2w and LLFF-style bounds from the points each one sees."""
    xyz_by_id = {point_id: point.xyz for point_id, point in model.points3D.items()}
    images = []
    for image_id in sorted(model.reg_image_ids()):
        image = model.image(image_id)
        c2w = c2w_from_cam_from_world(image.cam_from_world().matrix())
        seen = [xyz_by_id[p.point3D_id] for p in image.points2D
                if p.has_point3D() and p.point3D_id in xyz_by_id]
        near = far = None
        if seen:
            with contextlib.suppress(ValueError):
                near, far = depth_bounds(point_depths(c2w, np.asarray(seen)))
        images.append(ModelImage(name=image.name, camera=model.camera(image.camera_id),
                                 c2w=c2w, near=near, far=far))
    return images


# -- cameras and undistortion ----------------------------------------------------------------

def make_camera(model: str, width: int, height: int, params) -> pycolmap.Camera:
    return pycolmap.Camera(model=model, width=int(width), height=int(height),
                           params=[float(p) for p in params])


def camera_at_size(camera: pycolmap.Camera, width: int, height: int) -> pycolmap.Camera:
    """A copy of ``camera`` rescaled to ``width`` x ``height`` (same field of view)."""
    if (camera.width, camera.height) == (width, height):
        return copy.copy(camera)
    if abs(width / camera.width - height / camera.height) > 0.01 * width / camera.width:
        raise PipelineError(
            f"image size {width}x{height} does not have the aspect ratio of the camera "
            f"({camera.width}x{camera.height}); the images must be a scaled version of those "
            f"the poses were computed on")
    scaled = copy.copy(camera)
    scaled.rescale(int(width), int(height))
    return scaled


def camera_dict(camera: pycolmap.Camera) -> dict:
    return {"model": camera.model_name, "width": int(camera.width), "height": int(camera.height),
            "params": [float(p) for p in camera.params]}


#: How the poses step resamples images onto the undistorted camera.
Interpolation = Literal["linear", "cubic"]


@dataclass
class Undistortion:
    """A pinhole camera and the remap tables that warp a distorted image onto it.

    ``map_x``, ``map_y`` are ``(H', W')`` float32 source pixel positions in OpenCV's integer-
    centred convention (``cv2.remap``); None when the source camera is already a pinhole.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    map_x: np.ndarray | None
    map_y: np.ndarray | None

    def warp_image(self, image: np.ndarray, interpolation: Interpolation = "linear"
                   ) -> np.ndarray:
        """The image on the pinhole camera.

        ``cubic`` keeps the detail that bilinear resampling blurs at fractional source
        positions (every pixel of a warp whose focal length or centre moves); its overshoot
        at edges is clipped at 0, since these are linear radiances (docs/water.md, "The demo's
        green and blue attenuation").
        """
        if self.map_x is None:
            return image
        if interpolation == "linear":
            return cv2.remap(image, self.map_x, self.map_y, interpolation=cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        # the kernel reaches a pixel past the image at its edge: read the edge, not black
        warped = cv2.remap(image, self.map_x, self.map_y, interpolation=cv2.INTER_CUBIC,
                           borderMode=cv2.BORDER_REPLICATE)
        return np.maximum(warped, 0)

    def warp_mask(self, mask: np.ndarray, interpolation: Interpolation = "linear"
                  ) -> np.ndarray:
        """Warp a boolean mask; pixels that come from outside the source are False. For
        ``linear``, nearest; for ``cubic``, a pixel is True only where every source pixel its
        4x4 kernel reads is (a clipped pixel's value spreads two pixels under that kernel)."""
        if self.map_x is None:
            return mask
        if interpolation == "cubic":
            inner = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8),
                              borderType=cv2.BORDER_CONSTANT, borderValue=1)
            warped = cv2.remap(inner.astype(np.float32), self.map_x, self.map_y,
                               interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                               borderValue=0)
            return warped >= 1.0 - 1e-6
        warped = cv2.remap(mask.astype(np.uint8), self.map_x, self.map_y,
                           interpolation=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                           borderValue=0)
        return warped > 0


def undistortion(camera: pycolmap.Camera) -> Undistortion:
    """Pinhole camera (COLMAP's undistorter choice: no blank pixels) and its remap tables."""
    if camera.is_undistorted() or camera.model_name in ("SIMPLE_PINHOLE", "PINHOLE"):
        k = camera.calibration_matrix()
        return Undistortion(float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]),
                            int(camera.width), int(camera.height), None, None)
    pinhole = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), camera)
    fx, fy, cx, cy = (float(v) for v in pinhole.params[:4])
    width, height = int(pinhole.width), int(pinhole.height)
    map_x = np.empty((height, width), np.float32)
    map_y = np.empty((height, width), np.float32)
    u = (np.arange(width) + 0.5 - cx) / fx
    rows_per_chunk = max(1, 2_000_000 // width)
    for top in range(0, height, rows_per_chunk):
        rows = np.arange(top, min(height, top + rows_per_chunk))
        v = (rows + 0.5 - cy) / fy
        xx, yy = np.meshgrid(u, v)
        rays = np.stack([xx.ravel(), yy.ravel(), np.ones(xx.size)], axis=1)
        pixels = camera.img_from_cam(rays, check_cheirality=False)
        # COLMAP puts pixel centres at +0.5, cv2.remap at integers.
        map_x[rows] = (pixels[:, 0] - 0.5).reshape(len(rows), width)
        map_y[rows] = (pixels[:, 1] - 0.5).reshape(len(rows), width)
    return Undistortion(fx, fy, cx, cy, width, height, map_x, map_y)
