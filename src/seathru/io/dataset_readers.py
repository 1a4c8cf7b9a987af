"""Readers for camera poses that already exist: LLFF / SeaThru-NeRF, COLMAP models, nerfstudio.

Each reader returns a :class:`PosedDataset`: per image stem, a COLMAP camera (possibly
distorted, at the resolution the file describes), an OpenCV camera-to-world pose in the source's
units and, when the source has them, near/far bounds (LLFF style, margins included). The
``poses`` step turns any of them into the one ``cameras.json`` training reads.
"""

from __future__ import annotations

import json
import logging
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from seathru.geometry.poses import (FAR_MARGIN, NEAR_MARGIN, depth_bounds, llff_to_opencv,
                                   opengl_to_opencv, point_depths)
from seathru.errors import PipelineError
from seathru.io.colmap import make_camera, model_images, read_model
from seathru.io.images import list_images

log = logging.getLogger(__name__)

# Image folders of the LLFF / SeaThru-NeRF layout, in order of preference; images_<N> come last,
# smallest N first.
LLFF_IMAGE_FOLDERS = ("images_wb", "Images_wb", "images")


@dataclass
class PosedView:
    name: str                # image stem, the key every stage uses
    camera: pycolmap.Camera  # at the resolution the source describes; may have distortion
    c2w: np.ndarray          # (4, 4) OpenCV camera-to-world, source units
    near: float | None = None
    far: float | None = None


@dataclass
class PosedDataset:
    views: list[PosedView]
    source: str
    notes: dict = field(default_factory=dict)


# -- LLFF / SeaThru-NeRF ---------------------------------------------------------------------

def llff_image_folders(source_dir: Path) -> list[Path]:
    folders = [source_dir / name for name in LLFF_IMAGE_FOLDERS]
    downscaled = []
    for path in source_dir.glob("images_*"):
        match = re.fullmatch(r"images_(\d+)", path.name)
        if match and path.is_dir():
            downscaled.append((int(match.group(1)), path))
    folders += [path for _, path in sorted(downscaled)]
    return [folder for folder in folders if folder.is_dir()]


def read_llff(source_dir: Path, fallback_names: list[str] | None = None) -> PosedDataset:
    """``poses_bounds.npy`` (N x 17): per row a 3x5 [R | t | (h, w, f)] then (near, far).

    R's columns are LLFF's (down, right, back) camera axes; (h, w, f) are for the full-size
    images. Rows are in sorted image-name order: the names come from the first of images_wb,
    Images_wb, images, images_<N> holding exactly N images (else from ``fallback_names``).
    The camera is a centred pinhole at (w, h); the step rescales it to the images it uses.
    """
    source_dir = Path(source_dir)
    path = source_dir / "poses_bounds.npy"
    if not path.exists():
        raise PipelineError(f"{path}: not found; an LLFF / SeaThru-NeRF folder has "
                            f"poses_bounds.npy next to its image folders")
    try:
        data = np.load(path)
    except Exception as exc:
        raise PipelineError(f"{path}: cannot be read as a numpy array ({exc})") from None
    if data.ndim != 2 or data.shape[1] != 17:
        raise PipelineError(f"{path}: expected shape (N, 17) (3x5 pose + 2 bounds per image), "
                            f"found {data.shape}")
    count = len(data)
    names, folder_used = None, None
    for folder in llff_image_folders(source_dir):
        images = list_images(folder)
        if len(images) == count:
            names, folder_used = [p.stem for p in images], folder
            break
    if names is None:
        if fallback_names is not None and len(fallback_names) == count:
            names = sorted(fallback_names)
        else:
            raise PipelineError(
                f"{path}: has {count} rows but no image folder of {source_dir} "
                f"({', '.join(LLFF_IMAGE_FOLDERS)}, images_<N>) holds {count} images to name "
                f"them; the rows follow the sorted image names")
    poses = data[:, :15].reshape(count, 3, 5)
    c2w = llff_to_opencv(poses[:, :, :4])
    views = []
    for name, pose, bounds, view_c2w in zip(names, poses, data[:, 15:], c2w):
        height, width, focal = (float(v) for v in pose[:, 4])
        camera = make_camera("PINHOLE", round(width), round(height),
                             [focal, focal, width / 2.0, height / 2.0])
        views.append(PosedView(name=name, camera=camera, c2w=view_c2w,
                               near=float(bounds[0]) * NEAR_MARGIN,
                               far=float(bounds[1]) * FAR_MARGIN))
    notes = {"poses_bounds": str(path),
             "names_from": str(folder_used) if folder_used else "ingest linear images",
             "full_size_hwf": [float(v) for v in poses[0, :, 4]]}
    return PosedDataset(views=views, source="llff", notes=notes)


# -- COLMAP model ----------------------------------------------------------------------------

def read_colmap_model(source_dir: Path) -> PosedDataset:
    model = read_model(Path(source_dir))
    views = [PosedView(name=Path(image.name).stem, camera=image.camera, c2w=image.c2w,
                       near=image.near, far=image.far) for image in model_images(model)]
    if not views:
        raise PipelineError(f"{source_dir}: the COLMAP model has no registered image")
    unposed = sorted(Path(model.image(i).name).stem for i in model.images
                     if not model.image(i).has_pose)
    return PosedDataset(views=views, source="colmap",
                        notes={"model": str(source_dir), "images_in_model_without_pose": unposed,
                               "points": int(model.num_points3D())})


# -- nerfstudio ------------------------------------------------------------------------------

_NS_INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "k4", "p1", "p2",
                  "camera_model", "camera_angle_x")


def _nerfstudio_camera(params: dict, where: str) -> pycolmap.Camera:
    try:
        width, height = int(params["w"]), int(params["h"])
    except KeyError:
        raise PipelineError(f"{where}: image size 'w' and 'h' missing") from None
    if "fl_x" in params:
        fx = float(params["fl_x"])
    elif "camera_angle_x" in params:
        fx = 0.5 * width / math.tan(0.5 * float(params["camera_angle_x"]))
    else:
        raise PipelineError(f"{where}: focal length missing (fl_x or camera_angle_x)")
    fy = float(params.get("fl_y", fx))
    cx = float(params.get("cx", width / 2.0))
    cy = float(params.get("cy", height / 2.0))
    k1, k2, k3, k4, p1, p2 = (float(params.get(k, 0.0)) for k in
                              ("k1", "k2", "k3", "k4", "p1", "p2"))
    model = str(params.get("camera_model", "OPENCV")).upper()
    if model == "OPENCV_FISHEYE":
        return make_camera("OPENCV_FISHEYE", width, height, [fx, fy, cx, cy, k1, k2, k3, k4])
    if model not in ("OPENCV", "PINHOLE", "PERSPECTIVE"):
        raise PipelineError(f"{where}: camera_model {model!r} not supported "
                            f"(OPENCV, PINHOLE, OPENCV_FISHEYE)")
    if k4 != 0.0:
        raise PipelineError(f"{where}: radial term k4 is not supported for an OPENCV camera")
    if k3 != 0.0:
        # COLMAP's FULL_OPENCV is rational; with k4 = k5 = k6 = 0 it is nerfstudio's polynomial.
        return make_camera("FULL_OPENCV", width, height,
                           [fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0])
    if k1 == k2 == p1 == p2 == 0.0:
        return make_camera("PINHOLE", width, height, [fx, fy, cx, cy])
    return make_camera("OPENCV", width, height, [fx, fy, cx, cy, k1, k2, p1, p2])


def read_nerfstudio(source: Path) -> PosedDataset:
    """nerfstudio ``transforms.json``: OpenGL c2w per frame, intrinsics at top level or per frame.

    Bounds come from the point cloud named by ``ply_file_path`` when there is one (as
    ns-process-data writes it, in the same world frame); otherwise they stay unset.
    """
    source = Path(source)
    path = source / "transforms.json" if source.is_dir() else source
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise PipelineError(f"{path}: transforms.json not found") from None
    except json.JSONDecodeError as exc:
        raise PipelineError(f"{path}: not valid JSON ({exc})") from None
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise PipelineError(f"{path}: no 'frames' list")
    shared = {k: data[k] for k in _NS_INTRINSICS if k in data}
    views = []
    for index, frame in enumerate(frames):
        where = f"{path}: frame {index}"
        try:
            file_path = frame["file_path"]
            matrix = np.asarray(frame["transform_matrix"], np.float64)
        except KeyError as exc:
            raise PipelineError(f"{where}: field {exc} missing") from None
        if matrix.shape == (3, 4):
            matrix = np.vstack([matrix, [0.0, 0.0, 0.0, 1.0]])
        if matrix.shape != (4, 4):
            raise PipelineError(f"{where}: transform_matrix must be 4x4, found {matrix.shape}")
        params = {**shared, **{k: frame[k] for k in _NS_INTRINSICS if k in frame}}
        views.append(PosedView(name=Path(file_path).stem,
                               camera=_nerfstudio_camera(params, where),
                               c2w=opengl_to_opencv(matrix)))
    notes = {"transforms": str(path)}
    ply = data.get("ply_file_path")
    if ply:
        points = _read_ply_points(path.parent / ply)
        if points is not None:
            notes["bounds_from"] = str(path.parent / ply)
            for view in views:
                try:
                    view.near, view.far = depth_bounds(visible_depths(view, points))
                except ValueError:
                    pass
    return PosedDataset(views=views, source="nerfstudio", notes=notes)


def visible_depths(view: PosedView, points: np.ndarray) -> np.ndarray:
    """Depths of the points ``(M, 3)`` in front of the camera that project inside its image."""
    depths = point_depths(view.c2w, points)
    in_front = depths > 0
    cam_points = (points[in_front] - view.c2w[:3, 3]) @ view.c2w[:3, :3]
    if len(cam_points) == 0:
        return depths[in_front]
    pixels = view.camera.img_from_cam(cam_points, check_cheirality=False)
    inside = ((pixels[:, 0] >= 0) & (pixels[:, 0] <= view.camera.width)
              & (pixels[:, 1] >= 0) & (pixels[:, 1] <= view.camera.height))
    return depths[in_front][inside]


def _read_ply_points(path: Path) -> np.ndarray | None:
    if not path.exists():
        log.warning("%s: point cloud named in transforms.json not found; no bounds from it", path)
        return None
    model = pycolmap.Reconstruction()
    try:
        model.import_PLY(path)
    except Exception as exc:
        log.warning("%s: point cloud cannot be read (%s); no bounds from it", path, exc)
        return None
    if model.num_points3D() == 0:
        return None
    return np.array([point.xyz for point in model.points3D.values()])


#: ``--source`` values that read existing poses, by reader.
READERS = ("llff", "colmap-model", "nerfstudio")


def read_posed_dataset(source: str, source_dir: Path | None,
                       fallback_names: list[str] | None = None) -> PosedDataset:
    """Poses that already exist: ``source`` is one of :data:`READERS`; ``fallback_names``: the
    image names an LLFF folder without images is taken to hold, in order."""
    if source_dir is None:
        raise PipelineError(f"--source {source} needs --source-dir")
    if not source_dir.exists():
        raise PipelineError(f"{source_dir}: --source-dir not found")
    if source == "llff":
        return read_llff(source_dir, fallback_names=fallback_names)
    if source == "colmap-model":
        return read_colmap_model(source_dir)
    if source == "nerfstudio":
        return read_nerfstudio(source_dir)
    raise ValueError(f"unknown source {source!r}; readers are {', '.join(READERS)}")
