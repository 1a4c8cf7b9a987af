"""Readers for camera poses that already exist: LLFF / SeaThru-NeRF, COLMAP models, nerfstudio.

Each reader returns a :class:`PosedDataset`: per image stem, a COLMAP camera (possibly
distorted, at the resolution the file describes), an OpenCV camera-to-world pose in the source's
units and, when the source has them, near/far bounds (LLFF style, margins included). The
``poses`` step turns any of them into the one ``cameras.json`` training reads.

:func:`layout_images` is the other half: which image files such a dataset holds, in its own
layout, for the ``ingest`` step (``--layout llff|colmap|nerfstudio``), named as the readers name
the views (:func:`frame_names`):

- ``llff``: one image folder beside ``poses_bounds.npy``; ``images=auto`` takes the first of
  images_wb, Images_wb, images, images_<N> (smallest N first) that holds one image per row of
  ``poses_bounds.npy``. images_wb comes first because the SeaThru-NeRF release's images_wb are
  the linear, white-balanced images the paper trains on (read as linear, not sRGB).
- ``colmap``: the images the model (``sparse/0``, text or binary) names, in ``images/`` (else
  ``images_wb/``, as the SeaThru-NeRF release has it; or the folder ``images`` names, e.g.
  images_4), subfolders included; a file of the same stem stands in for a name whose extension
  differs (IMG_1.JPG in the model, IMG_1.png on disk).
- ``nerfstudio``: the file each frame's ``file_path`` points to (relative to transforms.json,
  subfolders included; with ``images=images_<N>`` the leading ``images/`` becomes images_<N>,
  nerfstudio's downscale convention). Frames whose file is missing are skipped and listed. A
  frame's ``mask_path`` (nerfstudio's convention: one image, 0 = ignore the pixel; with
  ``images=images_<N>``, ``masks_<N>/<file>`` where that exists) is kept in
  :attr:`LayoutImages.masks`; ingest ands it into the clipping mask (:func:`read_source_mask`).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from seathru.geometry.poses import (FAR_MARGIN, NEAR_MARGIN, depth_bounds, llff_to_opencv,
                                   opengl_to_opencv, point_depths)
from seathru.errors import PipelineError
from seathru.io.colmap import find_model_dir, make_camera, model_images, read_model
from seathru.io.images import IMAGE_EXTENSIONS, read_image
from seathru.io.raw import RAW_EXTENSIONS

log = logging.getLogger(__name__)

# Image folders of the LLFF / SeaThru-NeRF layout, in order of preference; images_<N> come last,
# smallest N first.
LLFF_IMAGE_FOLDERS = ("images_wb", "Images_wb", "images")
#: Layouts of posed datasets whose images ingest finds itself (``seathru ingest --layout``).
LAYOUTS = ("llff", "colmap", "nerfstudio")
#: Image folders whose files are linear whatever their bit depth (SeaThru-NeRF's images_wb).
LINEAR_FOLDERS = ("images_wb",)


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

def image_files(folder: Path) -> list[Path]:
    """Image files (encoded or RAW, by extension) of one folder, sorted by name."""
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")
                  and p.suffix.lower() in (*IMAGE_EXTENSIONS, *RAW_EXTENSIONS))


def llff_image_folders(source_dir: Path) -> list[Path]:
    """The image folders of an LLFF / SeaThru-NeRF dataset that exist, in order of preference."""
    folders = [source_dir / name for name in LLFF_IMAGE_FOLDERS]
    downscaled = []
    for path in source_dir.glob("images_*"):
        match = re.fullmatch(r"images_(\d+)", path.name)
        if match and path.is_dir():
            downscaled.append((int(match.group(1)), path))
    folders += [path for _, path in sorted(downscaled)]
    seen, existing = set(), []
    for folder in folders:  # Images_wb and images_wb are one folder on a case-blind disk
        if folder.is_dir() and folder.resolve() not in seen:
            seen.add(folder.resolve())
            existing.append(folder)
    return existing


def _llff_rows(source_dir: Path) -> np.ndarray:
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
    return data


def subfolder(root: Path, name: str, what: str) -> Path:
    """``root/name``, matched case-insensitively; a PipelineError listing the subfolders else."""
    if (root / name).is_dir():
        return root / name
    matches = [p for p in root.iterdir() if p.is_dir() and p.name.lower() == name.lower()]
    if len(matches) == 1:
        return matches[0]
    available = sorted(p.name for p in root.iterdir() if p.is_dir())
    raise PipelineError(f"{root}: no image folder {name!r} ({what}); subfolders: "
                        f"{', '.join(available) or 'none'}")


def llff_image_folder(source_dir: Path, images: str = "auto") -> tuple[Path, str]:
    """The image folder of an LLFF / SeaThru-NeRF dataset and why it was chosen.

    ``images``: a folder name (images_wb, images, images_4, ...) or ``auto``: the first of
    :func:`llff_image_folders` holding one image per row of ``poses_bounds.npy``.
    """
    source_dir = Path(source_dir)
    if images != "auto":
        return subfolder(source_dir, images, "ingest.images"), f"ingest.images={images}"
    rows = len(_llff_rows(source_dir))
    folders = llff_image_folders(source_dir)
    for folder in folders:
        if len(image_files(folder)) == rows:
            why = ("the SeaThru-NeRF release's linear white-balanced images, what the paper "
                   "trains on" if folder.name.lower() in LINEAR_FOLDERS else
                   "the first of images_wb, images, images_<N> holding one image per row")
            return folder, f"auto: {folder.name} ({why} of poses_bounds.npy)"
    found = ", ".join(f"{f.name} ({len(image_files(f))})" for f in folders) or "none"
    raise PipelineError(f"{source_dir}: no image folder holds one image per row of "
                        f"poses_bounds.npy ({rows} rows; folders: {found}); the rows follow the "
                        f"sorted image names, so every image must be there. Choose a folder "
                        f"with ingest.images=<folder>")


def read_llff(source_dir: Path, fallback_names: list[str] | None = None,
              folder: Path | None = None) -> PosedDataset:
    """``poses_bounds.npy`` (N x 17): per row a 3x5 [R | t | (h, w, f)] then (near, far).

    R's columns are LLFF's (down, right, back) camera axes; (h, w, f) are for the full-size
    images. Rows are in sorted image-name order: the names come from ``folder`` (the one the
    ingest step read) when it holds exactly N images, else from the first of images_wb,
    Images_wb, images, images_<N> that does (else from ``fallback_names``). The camera is a
    centred pinhole at (w, h); the step rescales it to the images it uses. A COLMAP model
    beside the file (``sparse/0``) is named in the notes as ``model`` (the poses step keeps it
    if it is in the poses' frame: ``seathru.io.source_model``).
    """
    source_dir = Path(source_dir)
    path = source_dir / "poses_bounds.npy"
    data = _llff_rows(source_dir)
    count = len(data)
    names, folder_used = None, None
    for candidate in ([Path(folder)] if folder else []) + llff_image_folders(source_dir):
        images = image_files(candidate)
        if len(images) == count:
            names, folder_used = frame_names([p.name for p in images]), candidate
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
    model = llff_model_dir(source_dir)
    if model is not None:
        notes["model"] = str(model)
    return PosedDataset(views=views, source="llff", notes=notes)


def llff_model_dir(source_dir: Path) -> Path | None:
    """The COLMAP model beside an LLFF dataset's ``poses_bounds.npy`` (``sparse/0`` or
    ``sparse``; the SeaThru-NeRF release has one), or None."""
    if not (source_dir / "sparse").is_dir():
        return None
    with contextlib.suppress(PipelineError):
        return find_model_dir(source_dir / "sparse")
    return None


# -- COLMAP model ----------------------------------------------------------------------------

def read_colmap_model(source_dir: Path) -> PosedDataset:
    model = read_model(Path(source_dir))
    names = dict(zip((model.image(i).name for i in model.images),
                     frame_names([model.image(i).name for i in model.images])))
    views = [PosedView(name=names[image.name], camera=image.camera, c2w=image.c2w,
                       near=image.near, far=image.far) for image in model_images(model)]
    if not views:
        raise PipelineError(f"{source_dir}: the COLMAP model has no registered image")
    untracked = [v for v in views if v.near is None]
    if untracked and model.num_points3D():
        # points without tracks (some writers leave them out): each camera's bounds from the
        # points its frustum holds, as for a nerfstudio point cloud
        bounds_from_points(untracked, np.array([p.xyz for p in model.points3D.values()]))
        log.info("%s: %d images have no point tracks; their bounds come from the points in "
                 "front of them", source_dir, len(untracked))
    unposed = sorted(names[model.image(i).name] for i in model.images
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
        # nerfstudio's radial factor is 1 + k1 r^2 + ... + k4 r^8; COLMAP's FULL_OPENCV is a
        # ratio of cubics in r^2, fitted to it over the image.
        rational = _rational_radial((k1, k2, k3, k4), _max_radius2(width, height, fx, fy, cx, cy),
                                    max(fx, fy), where)
        return make_camera("FULL_OPENCV", width, height,
                           [fx, fy, cx, cy, rational[0], rational[1], p1, p2, *rational[2:]])
    if k3 != 0.0:
        # COLMAP's FULL_OPENCV is rational; with k4 = k5 = k6 = 0 it is nerfstudio's polynomial.
        return make_camera("FULL_OPENCV", width, height,
                           [fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0])
    if k1 == k2 == p1 == p2 == 0.0:
        return make_camera("PINHOLE", width, height, [fx, fy, cx, cy])
    return make_camera("OPENCV", width, height, [fx, fy, cx, cy, k1, k2, p1, p2])


def _max_radius2(width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> float:
    """The largest squared normalised radius of the image's corners."""
    return max(((u - cx) / fx) ** 2 + ((v - cy) / fy) ** 2
               for u in (0.0, width) for v in (0.0, height))


def _rational_radial(k: tuple[float, ...], r2_max: float, focal: float,
                     where: str) -> list[float]:
    """COLMAP FULL_OPENCV radial terms (k1, k2, k3, k4, k5, k6) whose ratio
    (1 + k1 s + k2 s^2 + k3 s^3) / (1 + k4 s + k5 s^2 + k6 s^3), s = r^2, matches nerfstudio's
    polynomial 1 + k[0] s + ... + k[3] s^4 over the image (s up to 1.5 ``r2_max``) to within
    0.05 pixel at ``focal``; a PipelineError naming ``where`` if it cannot."""
    s = np.linspace(0.0, 1.5 * r2_max, 400)
    poly = 1.0 + s * (k[0] + s * (k[1] + s * (k[2] + s * k[3])))
    powers = np.stack([s, s ** 2, s ** 3], axis=1)
    system = np.concatenate([powers, -poly[:, None] * powers], axis=1)
    terms = np.linalg.lstsq(system, poly - 1.0, rcond=None)[0]
    fitted = (1.0 + powers @ terms[:3]) / (1.0 + powers @ terms[3:])
    error_px = float(np.max(np.abs(fitted - poly) * np.sqrt(s)) * focal)
    if not np.isfinite(error_px) or error_px > 0.05:
        raise PipelineError(f"{where}: the radial distortion k1..k4 = {list(k)} cannot be "
                            f"represented by COLMAP's FULL_OPENCV model over the image (off by "
                            f"{error_px:.3g} px)")
    return [float(v) for v in terms]


def frame_names(files: list[str]) -> list[str]:
    """The view name of each image file (relative path) of a dataset: its stem, or where two
    files share a stem (cam0/1.jpg, cam1/1.jpg), the relative path without extension with
    ``/`` as ``__`` (cam0__1), so every name is unique and a plain file name.

    >>> frame_names(["images/a.jpg", "images/b.jpg"])
    ['a', 'b']
    >>> frame_names(["./cam0/1.jpg", "cam1/1.jpg"])
    ['cam0__1', 'cam1__1']
    """
    stems = [Path(f).stem for f in files]
    if len(set(stems)) == len(stems):
        return stems
    return ["__".join(part for part in Path(f).with_suffix("").parts if part not in (".", "/"))
            for f in files]


def read_transforms(source: Path) -> tuple[Path, dict, list[dict]]:
    """nerfstudio's ``transforms.json`` (``source``: the file or its folder): its path, content
    and frames, each frame an object with a ``file_path``."""
    source = Path(source)
    path = source / "transforms.json" if source.is_dir() else source
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise PipelineError(f"{path}: transforms.json not found") from None
    except json.JSONDecodeError as exc:
        raise PipelineError(f"{path}: not valid JSON ({exc})") from None
    frames = data.get("frames") if isinstance(data, dict) else None
    if not isinstance(frames, list) or not frames:
        raise PipelineError(f"{path}: no 'frames' list")
    for index, frame in enumerate(frames):
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            raise PipelineError(f"{path}: frame {index}: field 'file_path' missing")
    return path, data, frames


def read_nerfstudio(source: Path) -> PosedDataset:
    """nerfstudio ``transforms.json``: OpenGL c2w per frame, intrinsics at top level or per frame
    (``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h``, ``k1``..``k4``, ``p1``, ``p2``,
    ``camera_model``; a frame's own values win). Views are named by :func:`frame_names`.

    Bounds come from the point cloud named by ``ply_file_path`` when there is one (as
    ns-process-data writes it, in the same world frame); otherwise they stay unset.
    """
    path, data, frames = read_transforms(source)
    shared = {k: data[k] for k in _NS_INTRINSICS if k in data}
    names = frame_names([frame["file_path"] for frame in frames])
    views = []
    for index, frame in enumerate(frames):
        where = f"{path}: frame {index} ({frame['file_path']})"
        if "transform_matrix" not in frame:
            raise PipelineError(f"{where}: field 'transform_matrix' missing")
        matrix = np.asarray(frame["transform_matrix"], np.float64)
        if matrix.shape == (3, 4):
            matrix = np.vstack([matrix, [0.0, 0.0, 0.0, 1.0]])
        if matrix.shape != (4, 4):
            raise PipelineError(f"{where}: transform_matrix must be 4x4, found {matrix.shape}")
        params = {**shared, **{k: frame[k] for k in _NS_INTRINSICS if k in frame}}
        views.append(PosedView(name=names[index], camera=_nerfstudio_camera(params, where),
                               c2w=opengl_to_opencv(matrix)))
    notes = {"transforms": str(path)}
    ply = data.get("ply_file_path")
    if ply:
        points = _read_ply_points(path.parent / ply)
        if points is not None:
            notes["bounds_from"] = str(path.parent / ply)
            bounds_from_points(views, points)
    return PosedDataset(views=views, source="nerfstudio", notes=notes)


def bounds_from_points(views: list[PosedView], points: np.ndarray) -> None:
    """Give each of ``views`` the bounds (``depth_bounds``) of the points ``(M, 3)`` in front
    of it and inside its image, in place; a view that sees none keeps its own."""
    for view in views:
        with contextlib.suppress(ValueError):
            view.near, view.far = depth_bounds(visible_depths(view, points))


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


# -- the image files of a layout (for ingest) -----------------------------------------------

@dataclass
class LayoutImages:
    """The image files of a posed dataset, in its own layout, as the ingest step decodes them.

    ``files``: ``(file, view name)``; ``folder``: the image folder relative to ``root`` (for
    nerfstudio the folders the frames point into); ``reason``: why these; ``kind``: ``linear``
    where the layout says the files are linear whatever their bit depth (images_wb), else None;
    ``missing``: files the dataset lists that are not there, ``{"name", "file"}``; ``masks``:
    view name -> the mask file its frame names (nerfstudio ``mask_path``; the file may be
    missing: ingest rejects such a view with the reason).
    """

    layout: str
    root: Path
    files: list[tuple[Path, str]]
    folder: str
    reason: str
    kind: str | None = None
    missing: list[dict] = field(default_factory=list)
    masks: dict[str, Path] = field(default_factory=dict)

    def record(self) -> dict:
        """The manifest's ``input.layout`` (``seathru.io.manifest.LayoutRecord``; ``masks``:
        how many of the views found have a mask of the dataset's own)."""
        return {"layout": self.layout, "root": str(self.root), "images": self.folder,
                "reason": self.reason, "kind": self.kind, "files": len(self.files),
                "missing": self.missing, "masks": len(self.masks)}


def _existing(path: Path, stems: dict[Path, dict[str, Path]]) -> Path | None:
    """``path``, or else the one image file in its folder with its stem (a model that names
    IMG_1.JPG where the folder holds IMG_1.png, a file_path without extension); ``stems``
    caches each folder's image files by stem."""
    if path.is_file():
        return path
    if path.parent not in stems:
        by_stem: dict[str, list[Path]] = {}
        for file in image_files(path.parent):
            by_stem.setdefault(file.stem, []).append(file)
        stems[path.parent] = {s: files[0] for s, files in by_stem.items() if len(files) == 1}
    return stems[path.parent].get(path.stem if path.suffix.lower() in (
        *IMAGE_EXTENSIONS, *RAW_EXTENSIONS) else path.name)


def _listed_images(layout: str, root: Path, listed: list[str], base: Path, folder: str,
                   reason: str, kind: str | None = None) -> LayoutImages:
    """Files the dataset lists (relative to ``base``), named, the missing ones set apart."""
    files, missing, stems = [], [], {}
    for relative, name in zip(listed, frame_names(listed)):
        found = _existing(base / relative, stems)
        if found is None:
            missing.append({"name": name, "file": str(base / relative)})
        else:
            files.append((found, name))
    if not files:
        raise PipelineError(f"{root}: none of the {len(listed)} images the {layout} dataset "
                            f"lists is there (first: {base / listed[0]})")
    return LayoutImages(layout, root, files, folder, reason, kind, missing)


def _nerfstudio_file(file_path: str, images: str) -> str:
    """``file_path`` with its leading ``images/`` replaced by ``images`` (images_2, ...)."""
    parts = Path(file_path).parts
    start = 1 if parts and parts[0] == "." else 0
    if images == "auto":
        return file_path
    if len(parts) > start + 1 and parts[start] == "images":
        return str(Path(images, *parts[start + 1:]))
    return str(Path(images, Path(file_path).name))


def _nerfstudio_mask(base: Path, mask_path: str, images: str) -> Path:
    """The mask file of a frame: ``mask_path`` relative to transforms.json's folder, or with
    ``images=images_<N>`` nerfstudio's ``masks_<N>/<file name>`` when that file exists (else the
    full-size mask, resized to the image by ingest)."""
    downscaled = re.fullmatch(r"images_(\d+)", images)
    if downscaled:
        smaller = base / f"masks_{downscaled[1]}" / Path(mask_path).name
        if smaller.is_file():
            return smaller
    return base / mask_path


def read_source_mask(path: str | Path, width: int, height: int) -> np.ndarray:
    """A dataset's own mask (nerfstudio ``mask_path``) as a boolean ``(height, width)`` array,
    True = use the pixel: nonzero in any channel (nerfstudio: 0 = ignore). A mask of another
    size with the image's aspect ratio (a downscaled image, RAW half size) is resized to it,
    nearest neighbour, as nerfstudio resizes masks.

    Raises:
        PipelineError: naming the mask when it is missing, unreadable, or of another shape.

    Example::

        read_source_mask("masks/f1.png", 4000, 3000)   # (3000, 4000) bool
    """
    path = Path(path)
    if not path.is_file():
        raise PipelineError(f"{path}: the frame's mask_path file is not there; add it, or "
                            "remove mask_path from the frame in transforms.json")
    mask = read_image(path)
    mask = np.any(mask > 0, axis=2) if mask.ndim == 3 else mask > 0
    found = (mask.shape[1], mask.shape[0])
    if found == (width, height):
        return mask
    if abs(found[0] * height - found[1] * width) > max(found[0], width):  # aspect differs
        raise PipelineError(f"{path}: mask of {found[0]}x{found[1]} pixels does not fit its "
                            f"image of {width}x{height} (a mask must be the image's size, or "
                            "that size scaled)")
    return cv2.resize(mask.astype(np.uint8), (width, height),
                      interpolation=cv2.INTER_NEAREST).astype(bool)


ARCHIVE_SUFFIXES = (".zip", ".tar", ".tgz", ".gz", ".bz2", ".xz", ".7z", ".rar")


def not_a_folder(path: Path) -> str:
    """Why ``path`` cannot be read as a dataset folder, and what to do, for an error message."""
    if not path.exists():
        return "folder not found (check the sheet's path column)"
    if path.name.lower().endswith(ARCHIVE_SUFFIXES):
        return ("an archive, not a folder: unpack it and point the sheet's path at the folder "
                "that holds the images")
    return "a file, not a folder: point the sheet's path at the folder that holds the images"


def layout_images(layout: str, root: Path, images: str = "auto") -> LayoutImages:
    """The image files of the ``layout`` (one of :data:`LAYOUTS`) dataset in ``root``.

    ``images``: ``auto`` or the image folder to use (images_wb, images, images_4, ...; for
    colmap and nerfstudio it replaces ``images/``). See the module docstring for each layout.

    Raises:
        PipelineError: the layout's files are not there (naming the file or folder).
    """
    root = Path(root)
    if not root.is_dir():
        raise PipelineError(f"{root}: {not_a_folder(root)}")
    if layout == "llff":
        folder, reason = llff_image_folder(root, images)
        files = [(path, name) for path, name in zip(
            image_files(folder), frame_names([p.name for p in image_files(folder)]))]
        if not files:
            raise PipelineError(f"{folder}: no image files")
        kind = "linear" if folder.name.lower() in LINEAR_FOLDERS else None
        return LayoutImages(layout, root, files, folder.name, reason, kind)
    if layout == "colmap":
        model = read_model(root)
        # the SeaThru-NeRF release has sparse/0 beside images_wb/ and no images/
        name = images if images != "auto" else next(
            (n for n in ("images", "images_wb") if (root / n).is_dir()), "images")
        folder = subfolder(root, name, "the COLMAP layout's images/" if images == "auto"
                           else "ingest.images")
        listed = sorted(model.image(i).name for i in model.images)
        reason = (f"the {len(listed)} images the COLMAP model names, in {folder.name}/"
                  + ("" if images == "auto" else f" (ingest.images={images})"))
        return _listed_images(layout, root, listed, folder, folder.name, reason,
                              "linear" if folder.name.lower() in LINEAR_FOLDERS else None)
    if layout == "nerfstudio":
        path, _, frames = read_transforms(root)
        listed = [_nerfstudio_file(frame["file_path"], images) for frame in frames]
        folders = sorted({str(Path(f).parent) for f in listed})
        reason = (f"the files the {len(frames)} frames of {path.name} point to"
                  + ("" if images == "auto" else f", in {images}/ (ingest.images={images})"))
        found = _listed_images(layout, root, listed, path.parent, ", ".join(folders), reason)
        names = frame_names([frame["file_path"] for frame in frames])
        if names != frame_names(listed):  # keep the reader's names whatever the folder
            rename = dict(zip(frame_names(listed), names))
            found.files = [(file, rename[name]) for file, name in found.files]
            found.missing = [{**m, "name": rename[m["name"]]} for m in found.missing]
        present = {name for _, name in found.files}
        found.masks = {name: _nerfstudio_mask(path.parent, frame["mask_path"], images)
                       for name, frame in zip(names, frames) if name in present
                       and isinstance(frame.get("mask_path"), str) and frame["mask_path"]}
        return found
    raise ValueError(f"unknown layout {layout!r}; layouts are {', '.join(LAYOUTS)}")


#: ``--source`` values that read existing poses, by reader.
READERS = ("llff", "colmap-model", "nerfstudio")


def read_posed_dataset(source: str, source_dir: Path | None,
                       fallback_names: list[str] | None = None,
                       image_folder: Path | None = None) -> PosedDataset:
    """Poses that already exist: ``source`` is one of :data:`READERS`; ``fallback_names``: the
    image names an LLFF folder without images is taken to hold, in order; ``image_folder``: the
    LLFF image folder the ingest step read (its files name the rows)."""
    if source_dir is None:
        raise PipelineError(f"--source {source} needs --source-dir")
    if not source_dir.exists():
        raise PipelineError(f"{source_dir}: --source-dir not found")
    if source == "llff":
        return read_llff(source_dir, fallback_names=fallback_names, folder=image_folder)
    if source == "colmap-model":
        return read_colmap_model(source_dir)
    if source == "nerfstudio":
        return read_nerfstudio(source_dir)
    raise ValueError(f"unknown source {source!r}; readers are {', '.join(READERS)}")
