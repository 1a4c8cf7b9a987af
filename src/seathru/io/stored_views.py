"""The dataset's images as they are stored in the source folder, and how a render maps onto them.

A render of the trained model is linear radiance on the ingest's scale, in the geometry of the
``cameras.json`` frame: the poses step's pinhole camera at the linear folder's size (images with
lens distortion are undistorted there). Comparing it with the stored image (the community's
protocol, colour charts annotated on a stored photo) needs both maps back:

- radiometry: ``seathru.radiometry.stored_encoding`` with the ingest manifest's white balance
  gains, the image's exposure factor and the file's encoding (:class:`StoredView`);
- geometry: the source camera (``report.json`` ``source_cameras`` of the poses step, possibly
  distorted) at the stored image's size; a render on the undistorted pinhole camera is warped
  back onto it (:func:`render_to_stored`), points on the stored image forward onto the render
  (:func:`stored_points_to_render`).

RAW sources have no stored rendition: their "stored" image is the ingest's linear image
(white-balanced, exposure-normalised, like the ``images_wb/`` of the SeaThru-NeRF release), with
unit gains and a linear encoding.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from seathru.errors import PipelineError
from seathru.io.cameras import CameraSet, Frame
from seathru.io.colmap import (Interpolation, Undistortion, camera_at_size, make_camera,
                               undistortion)
from seathru.io.images import read_image
from seathru.io.manifest import read_manifest
from seathru.io.pose_report import read_pose_report
from seathru.io.raw import DecodeError, read_stored_array
from seathru.io.video import read_video_frame
from seathru.radiometry.linearise import orient, resize_area

#: Relative tolerance on intrinsics when matching a frame to a source camera.
INTRINSICS_RTOL = 1e-3


@dataclass(frozen=True)
class StoredView:
    """One image of the dataset as stored.

    ``path``: the stored file (for RAW sources the ingest's linear TIFF); ``encoding``: the curve
    ingest decoded it by (``seathru.radiometry.stored_encoding``: ``srgb``, ``linear``,
    ``gamma <g>``); ``gains`` ``(3,)`` and ``exposure_factor``: what ingest multiplied by;
    ``flip``: the orientation ingest applied (LibRaw flip code); ``size``: ``(width, height)``
    after orientation; ``file_name``: the stored file's name (the protocol sorts these; a
    video's frame: its name);
    ``video_frame``: for a frame of a video (``path``), its index in it, else None.
    """

    name: str
    file_name: str
    path: Path
    kind: str
    encoding: str
    gains: tuple[float, float, float]
    exposure_factor: float
    flip: int
    size: tuple[int, int]
    video_frame: int | None = None


def ingest_folder_of(cameras: CameraSet) -> Path:
    """The ingest folder a camera file comes from: ``report.json``'s ``ingest`` beside it when
    that folder exists, else the sibling ``ingest`` folder (``results/<dataset>/ingest``)."""
    root = cameras.root or Path(".")
    report = root / "report.json"
    if report.is_file():
        given = Path(str(read_pose_report(report).get("ingest", "")))
        if given.name and (given / "manifest.json").is_file():
            return given
    return root.parent / "ingest"


def one_white_balance(cameras: CameraSet) -> bool:
    """Whether every frame of the camera file was developed with one white balance: the
    ingest step decoded camera RAW files itself, with one balance for the dataset
    (``seathru.radiometry.dataset_transform``), so no frame carries a colour cast of its own
    (a camera's automatic white balance lives in its JPEGs and videos), or the camera file is
    the simulator's own (its linear images: no camera between). False where the ingest
    manifest is not found."""
    if cameras.source == "simulated":
        return True
    path = ingest_folder_of(cameras) / "manifest.json"
    if not path.is_file():
        return False
    manifest = read_manifest(path, strict=False)
    return isinstance(manifest, dict) and (manifest.get("input") or {}).get("kind") == "raw"


def read_stored_views(ingest: Path) -> dict[str, StoredView]:
    """Every image of an ingest output's ``manifest.json``, by name.

    Raises:
        PipelineError: naming the manifest when it is missing or malformed.
    """
    manifest = read_manifest(Path(ingest) / "manifest.json")
    gains = tuple(float(g) for g in manifest["white_balance"]["gains"])
    views = {}
    for image in manifest["images"]:
        if image["kind"] == "raw":
            path, encoding, view_gains, factor, flip = (Path(ingest) / image["linear"], "linear",
                                                        (1.0, 1.0, 1.0), 1.0, 0)
            size = (int(image["width"]), int(image["height"]))
        else:
            # manifests written before ingest recorded the curve: the kind's own
            encoding = image["decoder"].get("transfer", image["kind"])
            path, view_gains = Path(image["source_path"]), gains
            factor, flip = float(image["exposure_factor"]), int(image["decoder"].get("flip", 0))
            size = (int(image["source_size"][0]), int(image["source_size"][1]))
        video_frame = image.get("video_frame")
        views[image["name"]] = StoredView(   # a video's frames are named in time order
            name=image["name"], file_name=image["source"] if video_frame is None else
            image["name"], path=path, kind=image["kind"],
            encoding=encoding, gains=view_gains, exposure_factor=factor, flip=flip, size=size,
            video_frame=None if video_frame is None else int(video_frame["index"]))
    return views


def read_stored_codes(view: StoredView) -> np.ndarray:
    """The stored image's values as the file holds them (uint8, uint16 or float), oriented as
    ingest oriented it, ``(H, W, 3)``. For RAW sources: the ingest's float linear image."""
    if view.kind == "raw":
        return read_image(view.path)
    if not view.path.is_file():
        raise PipelineError(f"{view.path}: stored image not found; the dataset folder changed "
                            "since ingest")
    if view.video_frame is not None:
        codes = cv2.cvtColor(read_video_frame(view.path, view.video_frame), cv2.COLOR_BGR2RGB)
    else:
        try:
            codes = read_stored_array(view.path)   # read as ingest read it
        except DecodeError as exc:
            raise PipelineError(f"{view.path}: stored image cannot be read: {exc}") from exc
    if codes.ndim == 2:
        codes = np.repeat(codes[..., None], 3, axis=2)
    return orient(codes[..., :3], view.flip)


def _pose_report(cameras: CameraSet) -> dict | None:
    """The poses step's ``report.json`` beside the camera file, or None without one."""
    report = (cameras.root or Path(".")) / "report.json"
    return read_pose_report(report) if report.is_file() else None


def undistort_interpolation(cameras: CameraSet) -> Interpolation:
    """How the poses step resampled the images onto these cameras (``report.json``; linear
    for reports that predate the choice, and without a report)."""
    report = _pose_report(cameras)
    return "linear" if report is None else report.get("undistort_interpolation", "linear")


def source_cameras(cameras: CameraSet) -> list[pycolmap.Camera]:
    """The poses step's source cameras (``report.json``), possibly distorted; [] without one."""
    report = _pose_report(cameras)
    if report is None:
        return []
    return [make_camera(c["model"], c["width"], c["height"], c["params"])
            for c in report["source_cameras"]]


def _same_pinhole(frame: Frame, fx, fy, cx, cy, width, height) -> bool:
    return (frame.width, frame.height) == (width, height) and np.allclose(
        [frame.fx, frame.fy, frame.cx, frame.cy], [fx, fy, cx, cy], rtol=INTRINSICS_RTOL,
        atol=1e-6)


def frame_source_camera(frame: Frame, size: tuple[int, int],
                        candidates: list[pycolmap.Camera]) -> pycolmap.Camera | None:
    """The distorted source camera, at the stored image's ``size``, whose undistortion is
    ``frame``'s pinhole camera; None when the frame is a pinhole camera at ``size`` itself
    (nothing to warp).

    Raises:
        PipelineError: the frame is neither (a resized linear folder, another camera): the
            comparison needs the full-resolution geometry.
    """
    width, height = size
    for camera in candidates:
        try:
            scaled = camera_at_size(camera, width, height)
        except PipelineError:
            continue
        warp = undistortion(scaled)
        if _same_pinhole(frame, warp.fx, warp.fy, warp.cx, warp.cy, warp.width, warp.height):
            return None if warp.map_x is None else scaled
    if not candidates and (frame.width, frame.height) == (width, height):
        return None
    raise PipelineError(
        f"{frame.name}: its camera ({frame.width}x{frame.height}) is not the stored image's "
        f"({width}x{height}) nor its undistortion; compare at full resolution: "
        "poses.linear_folder=linear, ingest.max_size=0")


def render_to_stored(image: np.ndarray, frame: Frame, camera: pycolmap.Camera | None
                     ) -> np.ndarray:
    """A render of ``frame`` warped onto the stored image's (distorted) camera, bilinear;
    pixels the pinhole render does not cover are 0. ``camera`` None: returned as it is."""
    if camera is None:
        return image
    if image.shape[:2] != (frame.height, frame.width):
        raise PipelineError(f"{frame.name}: render of {image.shape[1]}x{image.shape[0]} pixels, "
                            f"camera of {frame.width}x{frame.height}; render at full "
                            "resolution (render.downscale=1)")
    width, height = int(camera.width), int(camera.height)
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    rays = camera.cam_from_img(np.stack([u.ravel(), v.ravel()], axis=1))
    # COLMAP puts pixel centres at +0.5, cv2.remap at integers
    map_x = (frame.fx * rays[:, 0] + frame.cx - 0.5).reshape(height, width).astype(np.float32)
    map_y = (frame.fy * rays[:, 1] + frame.cy - 0.5).reshape(height, width).astype(np.float32)
    return cv2.remap(np.ascontiguousarray(image, dtype=np.float32), map_x, map_y,
                     interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=0)


def _frame_undistortion(size: tuple[int, int], frame: Frame, candidates: list[pycolmap.Camera]
                        ) -> tuple[pycolmap.Camera, Undistortion, float] | None:
    """The source camera at ``size``, its undistortion, and the frame's size over the
    undistortion's (a downscaled linear folder), for the source camera that gives ``frame``'s
    pinhole camera; None when none does."""
    for camera in candidates:
        try:
            scaled = camera_at_size(camera, *size)
        except PipelineError:
            continue
        warp = undistortion(scaled)
        ratio = frame.width / warp.width
        if np.allclose([frame.height / warp.height, frame.fx, frame.fy, frame.cx, frame.cy],
                       np.array([1.0, warp.fx, warp.fy, warp.cx, warp.cy]) * ratio, rtol=0.02):
            return scaled, warp, ratio
    return None


def stored_points_on_frame(points: np.ndarray, size: tuple[int, int], frame: Frame,
                           candidates: list[pycolmap.Camera]) -> np.ndarray:
    """Points ``(N, 2)`` on the stored image of ``size = (width, height)`` to ``frame``'s image
    (pixel (u, v) centred at (u + 0.5, v + 0.5) on both), through the source camera's
    undistortion when the frame is one, then scaled to the frame's size (a downscaled linear
    folder); without source cameras the frame is taken as the stored image resized.

    Raises:
        PipelineError: no source camera gives the frame's camera.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if not candidates:
        return points * np.array([frame.width / size[0], frame.height / size[1]])
    match = _frame_undistortion(size, frame, candidates)
    if match is None:
        raise PipelineError(f"{frame.name}: no source camera of the poses step gives its "
                            "camera; cannot place points of the stored image on it")
    scaled, warp, ratio = match
    if warp.map_x is None:
        return points * ratio
    rays = scaled.cam_from_img(points)
    return np.stack([warp.fx * rays[:, 0] + warp.cx,
                     warp.fy * rays[:, 1] + warp.cy], axis=1) * ratio


def stored_image_on_frame(image: np.ndarray, frame: Frame, candidates: list[pycolmap.Camera],
                          interpolation: Interpolation = "linear") -> np.ndarray:
    """An image in the stored images' geometry (a simulator's truth) mapped onto ``frame``'s
    camera the way the poses step mapped the training images: the source camera's
    undistortion (``interpolation``: :func:`undistort_interpolation` for colour images, linear
    for fields such as depth, whose edges a cubic kernel would overshoot), then an area resize
    to the frame's size.

    A resize alone misplaces pixels wherever the poses step undistorted: COLMAP's undistorted
    camera is a pixel or more smaller than the source, and the radial warp moves the corners
    further. Pixels that are not finite (open water's infinite range) stay undefined: an output
    pixel is NaN wherever the warp or the resize mixes in such a pixel.

    Args:
        image: ``(H, W)`` or ``(H, W, C)`` at the stored images' size.
        frame: the camera file's frame; candidates: :func:`source_cameras`.

    Returns:
        ``(frame.height, frame.width[, C])`` float32; the image only area-resized when no
        source camera gives the frame (none known, or a pinhole one).

    Example::

        clean = stored_image_on_frame(read_image(truth / "clean" / "v.tiff"), frame,
                                      source_cameras(cameras))
    """
    image = np.asarray(image, dtype=np.float32)
    size = (image.shape[1], image.shape[0])
    finite = np.isfinite(image)
    defined = finite if image.ndim == 2 else finite.all(axis=-1)
    values = np.where(finite, image, 0.0).astype(np.float32)
    weight = defined.astype(np.float32)
    match = _frame_undistortion(size, frame, candidates) if candidates else None
    if match is not None and match[1].map_x is not None:
        warp = match[1]
        values = warp.warp_image(values, interpolation)
        weight = warp.warp_image(weight, interpolation)
    target = (frame.width, frame.height)
    values, weight = resize_area(values, target), resize_area(weight, target)
    # a cubic kernel's outer taps weigh negative: missing ones push the weight above 1
    covered = np.abs(weight - 1.0) <= 1e-4
    if values.ndim == 3:
        covered = covered[..., None]
    return np.where(covered, values, np.nan).astype(np.float32)
