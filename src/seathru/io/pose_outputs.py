"""The poses step's outputs from a posed dataset: undistorted linear images and masks, and
``cameras.json`` (``seathru.io.cameras``) in normalised units.

Normalisation: normalised = (source - centre) * scale where centre is the middle of the
bounding box of all camera centres and all frustum corners at each image's far bound, and scale
puts the furthest of those points on the unit sphere; every ray segment [near, far] of every
camera then lies inside the unit ball (``seathru.geometry.poses.unit_ball_normalisation``).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import numpy as np

from seathru.errors import PipelineError
from seathru.geometry.poses import (complete_bounds, normalise_c2w, range_bounds,
                                    unit_ball_normalisation)
from seathru.io.cameras import CameraSet, Frame, every_nth_split, write_cameras
from seathru.io.colmap import (Interpolation, Undistortion, camera_at_size, camera_dict,
                               undistortion)
from seathru.io.dataset_readers import PosedDataset, PosedView
from seathru.io.images import read_image, read_mask, write_float_tiff, write_mask
from seathru.io.manifest import IngestFolder
from seathru.io.pose_report import OutputSummary
from seathru.io.source_model import keep_source_model
from seathru.radiometry.deblur import processing_blur

log = logging.getLogger(__name__)

NORMALISATION_METHOD = ("centre = middle of the axis-aligned bounding box of all camera centres "
                        "and all image-corner points at each frame's far bound; scale = 1 / "
                        "distance from the centre to the furthest of those points, so every "
                        "camera's [near, far] frustum lies inside the unit ball")


def fill_bounds(views: list[PosedView], near: float | None, far: float | None,
                where: str) -> None:
    """Apply overrides; give frames without bounds the scene-wide ones (in place)."""
    try:
        nears, fars, filled = complete_bounds([v.near for v in views], [v.far for v in views],
                                              near, far)
    except ValueError:
        raise PipelineError(f"{where}: no near/far bounds in the source (no sparse points); "
                            f"pass --near and --far in the source's units") from None
    for view, view_near, view_far, was_filled in zip(views, nears, fars, filled):
        if was_filled:
            log.warning("%s: no bounds of its own; using the scene's", view.name)
        view.near, view.far = view_near, view_far
        if not 0 < view.near < view.far:
            raise PipelineError(f"{view.name}: invalid bounds near={view.near}, far={view.far}")


def image_blur(record: dict | None, warp: Undistortion,
               interpolation: Interpolation) -> list[float] | None:
    """The blur (Gaussian sigma per channel, pixels) the ingest's demosaic and the undistortion
    put into a view's training image (``seathru.radiometry.deblur.processing_blur``), from the
    view's manifest ``record``; None without one (how it was decoded is not known)."""
    if record is None:
        return None
    demosaic = (record.get("decoder") or {}).get("demosaic") if record.get("kind") == "raw" \
        else None
    decoded_width = (record.get("source_size") or [0])[0]
    scale = warp.width / decoded_width if decoded_width else 1.0
    resampled = interpolation if warp.map_x is not None else None
    return processing_blur(demosaic, scale, resampled)


def _undistort(views: list[PosedView], ingest: IngestFolder, out: Path,
               interpolation: Interpolation
               ) -> tuple[list[tuple[PosedView, Undistortion]], dict[tuple, Undistortion]]:
    """Write ``images/`` and ``masks/`` warped onto pinhole cameras; each view with its warp."""
    (out / "images").mkdir()
    (out / "masks").mkdir()
    cache: dict[tuple, Undistortion] = {}
    records = []
    for view in views:
        image = read_image(ingest.linear[view.name])
        if image.ndim == 2:
            image = np.repeat(image[..., None], 3, axis=2)
        height, width = image.shape[:2]
        camera = camera_at_size(view.camera, width, height)
        key = (camera.model_name, width, height, tuple(np.round(camera.params, 9)))
        if key not in cache:
            cache[key] = undistortion(camera)
        warp = cache[key]
        mask = np.ones((height, width), bool)
        if view.name in ingest.masks:
            mask = read_mask(ingest.masks[view.name])
            if mask.shape != (height, width):
                mask = cv2.resize(mask.astype(np.uint8), (width, height),
                                  interpolation=cv2.INTER_NEAREST) > 0
        write_float_tiff(out / "images" / f"{view.name}.tiff",
                         warp.warp_image(image, interpolation))
        write_mask(out / "masks" / f"{view.name}.png", warp.warp_mask(mask, interpolation))
        records.append((view, warp))
    return records, cache


def write_pose_outputs(dataset: PosedDataset, ingest: IngestFolder, out: Path,
                       near: float | None = None, far: float | None = None,
                       test_every: int = 8, where: str = "",
                       interpolation: Interpolation = "linear",
                       metres_per_unit: float | None = None) -> OutputSummary:
    """Undistort the linear images and masks, normalise, write ``cameras.json`` (and a COLMAP
    source's COLMAP model beside it: ``seathru.io.source_model``).

    Views without a linear image, and linear images without a pose, are left out (with a
    warning). ``near`` / ``far`` override every frame's depth bounds (source units); ``where``
    names the source in error messages; ``interpolation`` resamples the images onto the
    undistorted cameras (``Undistortion.warp_image``); ``metres_per_unit``: the source's
    metric scale where the user knows it (``CameraSet.metres_per_source_unit``).

    Returns:
        the report's summary of what was written.
    """
    by_name = {view.name: view for view in dataset.views}
    views = [by_name[name] for name in sorted(by_name) if name in ingest.linear]
    without_image = sorted(set(by_name) - set(ingest.linear))
    without_pose = sorted(set(ingest.linear) - set(by_name))
    if without_image:
        log.warning("%d posed images have no linear image in %s and are skipped: %s",
                    len(without_image), ingest.linear_dir, ", ".join(without_image))
    if without_pose:
        log.warning("%d images have no pose and are left out: %s", len(without_pose),
                    ", ".join(without_pose))
    if not views:
        raise PipelineError(f"none of the posed images has a linear image in "
                            f"{ingest.linear_dir}; do the names match?")
    fill_bounds(views, near, far, where)
    records, cache = _undistort(views, ingest, out, interpolation)
    manifest = ingest.manifest if isinstance(ingest.manifest, dict) else {}
    decoded = {image.get("name"): image for image in manifest.get("images", [])}
    blur = {view.name: image_blur(decoded.get(view.name), warp, interpolation)
            for view, warp in records}
    c2w = np.array([view.c2w for view, _ in records])
    intrinsics = np.array([[[w.fx, 0, w.cx], [0, w.fy, w.cy], [0, 0, 1]] for _, w in records])
    sizes = np.array([[w.width, w.height] for _, w in records])
    try:
        centre, scale = unit_ball_normalisation(c2w, intrinsics, sizes,
                                                np.array([v.far for v, _ in records]))
    except ValueError as exc:
        raise PipelineError(f"cannot normalise the scene: {exc}") from None
    normalised = normalise_c2w(c2w, centre, scale)
    split = every_nth_split([v.name for v, _ in records], test_every)
    frames = []
    for (view, warp), pose, k in zip(records, normalised, intrinsics):
        view_near, view_far = range_bounds(view.near, view.far, k, warp.width, warp.height)
        frames.append(Frame(name=view.name, image=f"images/{view.name}.tiff",
                            mask=f"masks/{view.name}.png", width=warp.width, height=warp.height,
                            fx=warp.fx, fy=warp.fy, cx=warp.cx, cy=warp.cy, c2w=pose.tolist(),
                            near=view_near * scale, far=view_far * scale,
                            split=split[view.name], blur_px=blur[view.name]))
    cameras = CameraSet(frames=frames, near=min(f.near for f in frames),
                        far=max(f.far for f in frames), centre=centre.tolist(), scale=scale,
                        source=dataset.source, metres_per_source_unit=metres_per_unit)
    write_cameras(out / "cameras.json", cameras)
    source_model = keep_source_model(dataset, out)
    kept = source_model["points"] if source_model and source_model["kept"] else 0
    distorted = {json.dumps(camera_dict(view.camera), sort_keys=True) for view, _ in records}
    return {
        "frames": len(frames),
        "test_frames": sum(f.split == "test" for f in frames),
        "normalisation": {"centre": centre.tolist(), "scale": scale,
                          "method": NORMALISATION_METHOD},
        "near": cameras.near, "far": cameras.far,
        "source_cameras": [json.loads(d) for d in sorted(distorted)],
        "undistorted": len(cache) > 0 and any(w.map_x is not None for w in cache.values()),
        "undistort_interpolation": interpolation,
        "posed_without_linear_image": without_image,
        "linear_images_without_pose": without_pose,
        **({"source_points_kept": kept} if kept else {}),
        **({"source_model": source_model} if source_model else {}),
    }
