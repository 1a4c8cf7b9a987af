"""Exports of the poses step's cameras that other tools open: nerfstudio, COLMAP and the
SeaThru-NeRF release's layout.

Folder ``results/<dataset>/export`` (replaced atomically)::

    nerfstudio/transforms.json   nerfstudio's format (as ns-process-data writes it)
    nerfstudio/images/<name>.png 8-bit sRGB copies of the undistorted linear images
    nerfstudio/masks/<name>.png  validity masks (0 = ignore), where the poses step has them
    nerfstudio/sparse_pc.ply     the sparse points (when the poses step has a COLMAP model)
    colmap/sparse/0/{cameras,images,points3D}.txt   a COLMAP text model (written by pycolmap,
                                 which adds rigs.txt and frames.txt for COLMAP >= 3.12)
    colmap/images/<name>.png     the same 8-bit copies (hard links where possible)
    seathru_nerf/images_wb/<name>.png  8-bit *linear* copies (the release's images_wb)
    seathru_nerf/poses_bounds.npy      LLFF poses and bounds, rows in file-name order
    seathru_nerf/sparse/0/*.bin        the COLMAP model (tracks included), the poses' frame
    seathru_nerf/export.json           the gain the linear copies carry (``LlffExportRecord``)

Cameras are the poses step's pinhole cameras (images with lens distortion were undistorted
there, and the copies are those undistorted images); the writers take distortion parameters
for other callers (OPENCV: k1, k2, p1, p2). Poses are in the source reconstruction's units
(``cameras.json`` de-normalised: ``source = normalised / scale + centre``), the frame the
sparse points are in.

nerfstudio: ``transform_matrix`` is an OpenGL camera-to-world (x right, y up, z back) in
nerfstudio's world, ``applied_transform`` the 3x4 map from our world to it: the one
``nerfstudio/process_data/colmap_utils.py`` (``colmap_to_json``) applies to a COLMAP world,
(x, y, z) -> (x, z, -y), so a COLMAP-style y-down world is z-up in the viewer. COLMAP:
``cam_from_world`` per image, OpenCV axes; points without tracks (their observations are on
the distorted images, not on these copies).

seathru_nerf: what the SeaThru-NeRF code and NerfBaselines' ``seathru-nerf`` loader read (and
this pipeline's ``llff`` source): linear, white-balanced 8-bit PNGs (the loaders read them as
stored, ``uint8 / 255``), scaled by one gain for the whole set so that the brightest 0.1% of
pixels are not clipped (recorded in ``export.json``: divide by it to return to the training
images' scale; the water's coefficients do not change, its colour scales with it). LLFF rows
are ``[R | t | (h, w, f)]`` with (down, right, back) camera axes and the frame's (near, far)
(the poses step's range bounds: looser than LLFF's depth percentiles). LLFF has one centred
focal length, so cameras with ``fx != fy`` or an off-centre principal point are not exported
in this layout (``export_poses`` says why).
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import TypedDict

import numpy as np
import pycolmap

from seathru.errors import PipelineError
from seathru.geometry.poses import denormalise_c2w, opencv_to_llff, opencv_to_opengl
from seathru.io.atomic import atomic_dir, write_json
from seathru.io.cameras import CameraSet, Frame, read_cameras
from seathru.io.images import read_image, write_8bit
from seathru.radiometry.colour import linear_to_srgb

#: nerfstudio's applied_transform for a COLMAP world (colmap_to_json): (x, y, z) -> (x, z, -y).
NERFSTUDIO_APPLIED = np.array([[1.0, 0.0, 0.0, 0.0],
                               [0.0, 0.0, 1.0, 0.0],
                               [0.0, -1.0, 0.0, 0.0]])
DISTORTION_KEYS = ("k1", "k2", "p1", "p2")
LLFF_FORMAT = "seathru-export-llff/1"
#: The linear copies are scaled so that this share of all pixel values is not clipped.
LLFF_UNCLIPPED_SHARE = 0.999
#: Cameras an LLFF row represents: fx and fy within this ratio, the principal point within
#: this many pixels of the image centre.
LLFF_FOCAL_TOLERANCE = 1e-3
LLFF_CENTRE_TOLERANCE_PX = 0.5


class LlffExportRecord(TypedDict):
    """``seathru_nerf/export.json``."""

    format: str                  # LLFF_FORMAT
    linear_gain: float           # images_wb = clip(gain * training image, 0, 1), 8-bit
    frames: int
    units: str                   # what poses_bounds.npy's translations and bounds are in


def source_c2w(cameras: CameraSet, frame: Frame) -> np.ndarray:
    """``(4, 4)`` OpenCV camera-to-world of ``frame`` in the source units."""
    return denormalise_c2w(frame.c2w_array, np.asarray(cameras.centre), cameras.scale)


def _intrinsics(frame: Frame, distortion: dict[str, float] | None) -> dict[str, float]:
    values = {"w": int(frame.width), "h": int(frame.height), "fl_x": float(frame.fx),
              "fl_y": float(frame.fy), "cx": float(frame.cx), "cy": float(frame.cy)}
    return {**values, **{k: float((distortion or {}).get(k, 0.0)) for k in DISTORTION_KEYS}}


def nerfstudio_transforms(cameras: CameraSet, image_paths: dict[str, str],
                          mask_paths: dict[str, str] | None = None,
                          distortion: dict[str, dict[str, float]] | None = None,
                          ply_path: str | None = None) -> dict:
    """The content of nerfstudio's ``transforms.json`` for ``cameras``.

    Args:
        image_paths, mask_paths: per frame name, the file relative to transforms.json.
        distortion: per frame name, OPENCV ``k1, k2, p1, p2`` (absent: none).
        ply_path: the sparse point cloud relative to transforms.json, in nerfstudio's world.

    Returns:
        shared intrinsics at the top level when every frame has the same, else per frame;
        ``camera_model`` OPENCV; frames in name order.
    """
    frames = sorted(cameras.frames, key=lambda f: f.name)
    intrinsics = {f.name: _intrinsics(f, (distortion or {}).get(f.name)) for f in frames}
    shared = len({tuple(v.items()) for v in intrinsics.values()}) == 1
    transform = np.vstack([NERFSTUDIO_APPLIED, [0.0, 0.0, 0.0, 1.0]])
    out: dict = {"camera_model": "OPENCV"}
    if shared:
        out.update(intrinsics[frames[0].name])
    out["frames"] = []
    for frame in frames:
        c2w = transform @ opencv_to_opengl(source_c2w(cameras, frame))
        entry = {"file_path": image_paths[frame.name], "transform_matrix": c2w.tolist()}
        if mask_paths and frame.name in mask_paths:
            entry["mask_path"] = mask_paths[frame.name]
        if not shared:
            entry.update(intrinsics[frame.name])
        out["frames"].append(entry)
    out["applied_transform"] = NERFSTUDIO_APPLIED.tolist()
    if ply_path:
        out["ply_file_path"] = ply_path
    return out


def colmap_reconstruction(cameras: CameraSet, image_names: dict[str, str],
                          points: np.ndarray | None = None, colours: np.ndarray | None = None,
                          distortion: dict[str, dict[str, float]] | None = None,
                          seen: np.ndarray | None = None) -> pycolmap.Reconstruction:
    """A COLMAP model of ``cameras``: one camera per distinct intrinsics (PINHOLE, or OPENCV
    with distortion), one image per frame (``image_names``: the file names), and ``points``
    ``(M, 3)`` (source units) with ``colours`` ``(M, 3)`` uint8. Without ``seen`` the points
    have no tracks; with it (``(M, V)`` bool over ``cameras.frames``) point m is observed in
    every frame v where ``seen[m, v]``, at the pixel it projects to there (undistorted), where
    that lies in front of the camera and inside its image (a point seen near the edge of a
    distorted photograph may fall outside the undistorted one)."""
    observations: dict[str, list[tuple[int, np.ndarray]]] = {}
    if seen is not None:
        if points is None or seen.shape != (len(points), len(cameras.frames)):
            raise ValueError("seen must be (points, frames) bool")
        xyz = np.asarray(points, np.float64)
        for view, frame in enumerate(cameras.frames):
            w2c = np.linalg.inv(source_c2w(cameras, frame))
            local = xyz[seen[:, view]] @ w2c[:3, :3].T + w2c[:3, 3]
            with np.errstate(divide="ignore", invalid="ignore"):
                xy = np.stack([frame.fx * local[:, 0] / local[:, 2] + frame.cx,
                               frame.fy * local[:, 1] / local[:, 2] + frame.cy], -1)
            inside = (local[:, 2] > 0) & (xy[:, 0] >= 0) & (xy[:, 0] <= frame.width) \
                & (xy[:, 1] >= 0) & (xy[:, 1] <= frame.height)
            observations[frame.name] = list(zip(
                np.flatnonzero(seen[:, view])[inside].tolist(), xy[inside]))
    model = pycolmap.Reconstruction()
    camera_ids: dict[tuple, int] = {}
    elements: dict[int, list[pycolmap.TrackElement]] = {}
    for image_id, frame in enumerate(sorted(cameras.frames, key=lambda f: f.name), start=1):
        k = (distortion or {}).get(frame.name) or {}
        coeffs = [float(k.get(key, 0.0)) for key in DISTORTION_KEYS]
        pinhole = [frame.fx, frame.fy, frame.cx, frame.cy]
        key = (frame.width, frame.height, *pinhole, *coeffs)
        if key not in camera_ids:
            camera_ids[key] = len(camera_ids) + 1
            model_name, params = (("OPENCV", pinhole + coeffs) if any(coeffs)
                                  else ("PINHOLE", pinhole))
            model.add_camera_with_trivial_rig(pycolmap.Camera(
                model=model_name, width=int(frame.width), height=int(frame.height),
                params=[float(p) for p in params], camera_id=camera_ids[key]))
        w2c = np.linalg.inv(source_c2w(cameras, frame))
        seen_here = observations.get(frame.name, [])
        for index, (point, _) in enumerate(seen_here):
            elements.setdefault(point, []).append(pycolmap.TrackElement(image_id, index))
        image = pycolmap.Image(name=image_names[frame.name], camera_id=camera_ids[key],
                               image_id=image_id,
                               points2D=[pycolmap.Point2D(np.asarray(xy, np.float64))
                                         for _, xy in seen_here])
        model.add_image_with_trivial_frame(image, pycolmap.Rigid3d(w2c[:3, :4]))
    if points is not None:
        colours = np.zeros((len(points), 3), np.uint8) if colours is None else colours
        for index, (xyz, rgb) in enumerate(zip(np.asarray(points, np.float64),
                                               np.asarray(colours, np.uint8))):
            model.add_point3D(xyz, pycolmap.Track(elements.get(index, [])), rgb)
    return model


def sparse_points(poses_dir: Path, frames: Sequence[Frame] = ()
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``(xyz, rgb, seen)`` of the poses step's COLMAP model (``sparse/``), or None without
    one: ``seen`` (M, len(frames)) bool, whether a point's track holds an observation in the
    frame (the model's image names matched to the frames' names by stem)."""
    sparse = Path(poses_dir) / "sparse"
    if not any((sparse / f"points3D.{ext}").is_file() for ext in ("bin", "txt")):
        return None
    model = pycolmap.Reconstruction(sparse)
    if model.num_points3D() == 0:
        return None
    points = list(model.points3D.values())
    columns = {frame.name: column for column, frame in enumerate(frames)}
    image_column = {image_id: columns.get(Path(image.name).stem, -1)
                    for image_id, image in model.images.items()}
    seen = np.zeros((len(points), len(frames)), bool)
    for row, point in enumerate(points):
        for element in point.track.elements:
            column = image_column.get(element.image_id, -1)
            if column >= 0:
                seen[row, column] = True
    return (np.array([p.xyz for p in points]), np.array([p.color for p in points], np.uint8),
            seen)


def llff_camera_problem(cameras: CameraSet) -> str | None:
    """Why ``cameras`` cannot be LLFF rows (one focal length, a centred principal point), or
    None when they can."""
    for frame in cameras.frames:
        if abs(frame.fx / frame.fy - 1.0) > LLFF_FOCAL_TOLERANCE:
            return f"{frame.name}: fx {frame.fx:.2f} and fy {frame.fy:.2f} differ"
        off = max(abs(frame.cx - frame.width / 2), abs(frame.cy - frame.height / 2))
        if off > LLFF_CENTRE_TOLERANCE_PX:
            return f"{frame.name}: principal point {off:.1f} px off the image centre"
    return None


def llff_rows(cameras: CameraSet, order: Sequence[Frame]) -> np.ndarray:
    """``(N, 17)`` ``poses_bounds.npy`` rows of the frames in ``order`` (source units):
    ``[R | t | (h, w, f)]`` with LLFF's (down, right, back) axes, then (near, far)."""
    rows = []
    for frame in order:
        pose = opencv_to_llff(source_c2w(cameras, frame))
        hwf = np.array([[frame.height], [frame.width], [frame.fx]], np.float64)
        rows.append(np.r_[np.concatenate([pose, hwf], axis=1).ravel(),
                          frame.near / cameras.scale, frame.far / cameras.scale])
    return np.array(rows)


def write_llff(cameras: CameraSet, out: Path, model: pycolmap.Reconstruction | None) -> int:
    """The SeaThru-NeRF release's layout in ``out`` (see the module docstring): images_wb,
    poses_bounds.npy, sparse/0 (when ``model``, whose images are named ``<frame>.png``) and
    export.json. Returns the frames written."""
    order = sorted(cameras.frames, key=lambda f: f"{f.name}.png")   # LLFF sorts file names
    samples = []
    for frame in order:    # a strided sample of each image: the gain without holding them all
        image = read_image(cameras.image_path(frame))[..., :3]
        stride = max(1, round((image.shape[0] * image.shape[1] / 100_000) ** 0.5))
        samples.append(np.nan_to_num(image[::stride, ::stride]).ravel())
    bright = float(np.quantile(np.concatenate(samples), LLFF_UNCLIPPED_SHARE))
    gain = 1.0 / bright if bright > 1.0 else 1.0
    for frame in order:
        image = np.nan_to_num(read_image(cameras.image_path(frame))[..., :3])
        write_8bit(out / "images_wb" / f"{frame.name}.png", np.clip(image * gain, 0.0, 1.0))
    np.save(out / "poses_bounds.npy", llff_rows(cameras, order))
    if model is not None:
        (out / "sparse" / "0").mkdir(parents=True)
        model.write(out / "sparse" / "0")
    record: LlffExportRecord = {"format": LLFF_FORMAT, "linear_gain": gain,
                                "frames": len(order),
                                "units": "the source reconstruction's (as the COLMAP export)"}
    write_json(out / "export.json", record)
    return len(order)


def _link_or_copy(source: Path, target: Path) -> None:
    target.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(source, target)
    except OSError:
        shutil.copy2(source, target)


def export_poses(poses_dir: Path, out: Path, image_format: str = "png") -> dict:
    """Write the nerfstudio, COLMAP and SeaThru-NeRF exports of a poses output folder into
    ``out``.

    Returns:
        a summary: frames, points, the entry files (``seathru_nerf`` None, with
        ``seathru_nerf_skipped`` saying why, when the cameras are not LLFF's).

    Raises:
        PipelineError: the camera file or an image is missing.
    """
    poses_dir = Path(poses_dir)
    cameras = read_cameras(poses_dir / "cameras.json")
    if not cameras.frames:
        raise PipelineError(f"{poses_dir / 'cameras.json'}: no frames to export")
    names = {f.name: f"{f.name}.{image_format}" for f in cameras.frames}
    points = sparse_points(poses_dir, cameras.frames)
    with atomic_dir(out) as tmp:
        ns_dir, colmap_dir = tmp / "nerfstudio", tmp / "colmap"
        masks = {}
        for frame in cameras.frames:
            linear = read_image(cameras.image_path(frame))
            write_8bit(ns_dir / "images" / names[frame.name],
                       linear_to_srgb(np.clip(np.nan_to_num(linear), 0.0, 1.0)))
            _link_or_copy(ns_dir / "images" / names[frame.name],
                          colmap_dir / "images" / names[frame.name])
            mask = cameras.mask_path(frame)
            if mask is not None and mask.is_file():
                _link_or_copy(mask, ns_dir / "masks" / f"{frame.name}.png")
                masks[frame.name] = f"masks/{frame.name}.png"
        ply = None
        if points is not None:
            cloud = pycolmap.Reconstruction()
            moved = points[0] @ NERFSTUDIO_APPLIED[:, :3].T + NERFSTUDIO_APPLIED[:, 3]
            for xyz, rgb in zip(moved, points[1]):
                cloud.add_point3D(xyz, pycolmap.Track(), rgb)
            cloud.export_PLY(ns_dir / "sparse_pc.ply")
            ply = "sparse_pc.ply"
        write_json(ns_dir / "transforms.json", nerfstudio_transforms(
            cameras, {n: f"images/{f}" for n, f in names.items()}, masks, ply_path=ply))
        model_dir = colmap_dir / "sparse" / "0"
        model_dir.mkdir(parents=True)
        xyz, rgb, seen = points or (None, None, None)
        model = colmap_reconstruction(cameras, names, xyz, rgb, seen=seen)
        model.write_text(model_dir)
        llff_problem = llff_camera_problem(cameras)
        if llff_problem is None:
            png = {name: f"{name}.png" for name in names}
            llff_model = model if png == names else colmap_reconstruction(cameras, png, xyz,
                                                                           rgb, seen=seen)
            write_llff(cameras, tmp / "seathru_nerf", None if points is None else llff_model)
    return {"frames": len(cameras.frames), "points": 0 if points is None else len(points[0]),
            "nerfstudio": str(out / "nerfstudio" / "transforms.json"),
            "colmap": str(out / "colmap" / "sparse" / "0"),
            "seathru_nerf": None if llff_problem else str(out / "seathru_nerf"),
            "seathru_nerf_skipped": llff_problem}
