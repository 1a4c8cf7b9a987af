"""The render step's output folder (file contract): held-out views, path videos, render stats.

Layout::

    test/<view>/{full,restored,direct,backscatter}.tiff   linear radiance, float32 (H, W, 3)
    test/<view>/{full,restored,direct,backscatter}.png    display copies, 8-bit sRGB
    test/<view>/gt.png        the view's image with the same display exposure (when readable)
    test/<view>/depth.tiff    expected ray distance, normalised scene units, float32 (H, W)
    test/<view>/depth.png     depth colour-mapped (near warm, far cool; one range per dataset)
    test/<view>/opacity.tiff  accumulated object opacity, float32 (H, W) (when rendered)
    test/<view>/restored_photo.{tiff,png}  the view's photograph with the water removed by the
                              model's render (``seathru.radiometry.restore``; when readable)
    test/<view>/restored_reprojected.{tiff,png}  the restored render with the restored training
                              photographs' detail reprojected into it
                              (``seathru.nerf.reproject``; ``photos.restore: all``)
    test/<view>/restored_support.{tiff,png}  how much the training photographs back each pixel
                              of it, float32 (H, W): the sum of the angle weights of the views
                              that see its surface (from ``reproject.SUPPORTED``, 1: backed;
                              0: the model's restored render alone); the PNG is grey, white
                              from twice that
    photos/<view>.{tiff,png}  every camera's photograph restored alike (``photos.restore: all``)
    path/{full,restored,depth}.mp4   camera-path videos ('mp4v'; odd sizes padded by one pixel;
                              restored with the photographs' detail with ``photos.restore: all``)
    render_stats.json         seconds per frame, frames per second, resolution, display
                              exposure, depth range, settings (format seathru-render-stats/1)

Writers take float32 arrays (display copies already sRGB-encoded in [0, 1]); readers raise
``PipelineError`` naming the file.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Collection, Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypedDict

import cv2
import numpy as np

from seathru.errors import PipelineError
from seathru.io.atomic import write_json
from seathru.io.cameras import CameraSet
from seathru.io.contract import check_contract
from seathru.io.images import read_image, write_8bit, write_float_tiff
from seathru.io.jsonfile import read_json
from seathru.radiometry.glare import GlareCorrection

if TYPE_CHECKING:
    from seathru.nerf.reproject import SourceView
    from seathru.radiometry.restore import PhotoRestoration

log = logging.getLogger(__name__)

STATS_FORMAT = "seathru-render-stats/1"
STATS_NAME = "render_stats.json"
COMPONENTS = ("full", "restored", "direct", "backscatter")
# the inference dict's key (seathru.nerf.inference.RENDER_KEYS) of each output name
RENDER_KEYS = {"full": "rgb", "restored": "restored", "direct": "direct",
               "backscatter": "backscatter"}
VIDEO_OUTPUTS = ("full", "restored", "depth")
RESTORED_PHOTO = "restored_photo"
RESTORED_REPROJECTED = "restored_reprojected"
RESTORED_SUPPORT = "restored_support"
PHOTOS_DIR = "photos"
MAX_EXPOSURE_IMAGES = 24
_HINT = "re-run the 'render' step"


class FrameRecord(TypedDict):
    name: str
    split: str                  # test | path
    seconds: float
    width: int
    height: int


class SpeedSummary(TypedDict):
    count: int
    seconds_per_frame: float | None
    fps: float | None
    resolution: list | None     # [width, height], or a list of them
    total_seconds: float


class DisplayRecord(TypedDict):
    exposure_scale: float
    exposure_source: str        # "training images" or "render of <view>"
    depth_range: list[float]
    depth_units: str
    depth_cmap: str


class RenderStats(TypedDict):
    format: str                 # STATS_FORMAT
    test: SpeedSummary
    path: SpeedSummary
    seconds_per_frame: float | None  # the headline figures: held-out views
    fps: float | None
    resolution: list | None
    display: DisplayRecord
    normalisation: dict
    videos: dict                # name -> {"file": "path/<name>.mp4", "frames": n}
    settings: dict
    frames: list[FrameRecord]


def render_path(root: str | os.PathLike, view: str, name: str, suffix: str = ".tiff") -> Path:
    """``root/test/<view>/<name><suffix>``."""
    return Path(root) / "test" / view / f"{name}{suffix}"


def exposure_references(cameras: CameraSet, max_images: int = MAX_EXPOSURE_IMAGES
                        ) -> Iterator[np.ndarray]:
    """Up to ``max_images`` training images, evenly spread in name order, one at a time (for
    the display exposure); unreadable ones are skipped with a warning."""
    frames = sorted(cameras.split("train"), key=lambda f: f.name)
    if not frames:
        return
    picks = np.unique(np.linspace(0, len(frames) - 1, min(len(frames), max_images))
                      .round().astype(int))
    for index in picks:
        try:
            yield read_image(cameras.image_path(frames[index]))
        except PipelineError as exc:
            log.warning("exposure: skipping %s (%s)", frames[index].name, exc)


def photograph_glare(model_path: str | os.PathLike) -> GlareCorrection | None:
    """The ``seathru.radiometry.glare.GlareCorrection`` the model of ``model_path``
    (``model.pt``) was trained with (its photographs divided by it), or None: none applied,
    or no model file."""
    from seathru.io.model import read_training_record

    glare = (read_training_record(model_path) or {}).get("glare")
    return None if glare is None else GlareCorrection.from_dict(glare)


def split_glare(photograph: np.ndarray | None, images: Mapping[str, np.ndarray],
                gain: np.ndarray | None) -> tuple[np.ndarray | None, dict[str, np.ndarray]]:
    """A held-out view's photograph without the glare correction the model was trained with
    (what its restored photograph starts from), and the model's renders of the view with it
    put back into the image formation (``rgb``, ``direct``, ``backscatter``: what the camera
    records, compared with the photograph as it is); both as given without ``gain`` or
    ``photograph``.

    Args:
        photograph: (H, W, 3) linear, at the renders' size, or None.
        images: the inference dict of the view (``seathru.nerf.inference.render_frame``).
        gain: (H, W) the correction's gain at the renders' size (:func:`read_view_photograph`,
            resized), or None: no correction.
    """
    if gain is None or photograph is None:
        return photograph, dict(images)
    photograph = np.asarray(photograph, dtype=np.float64)[..., :3]
    gain = np.asarray(gain, dtype=np.float64)[..., None]
    recorded = {key: (value * gain if key in ("rgb", "direct", "backscatter") else value)
                for key, value in images.items()}
    return photograph / gain, recorded


def read_view_photograph(cameras: CameraSet, frame, glare: GlareCorrection | None = None,
                         size: tuple[int, int] | None = None
                         ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The camera file's image of ``frame`` as it is (the ground truth of a held-out view) and
    the gain (H, W) of the ``glare`` correction the model was trained with, found around the
    open water on the frame's valid pixels as the train step finds it
    (``seathru.io.training.glare_gain_of``: its mask file counts); the gain is None without
    ``glare``, both are None, with a warning, when the image cannot be read. ``size``
    ``(width, height)``: both area-resampled to it (the renders' size)."""
    from seathru.io.training import glare_gain_of, read_frame
    from seathru.radiometry.linearise import resize_area

    try:
        image, mask = read_frame(cameras, frame)
    except PipelineError as exc:
        log.warning("no ground-truth display copy for %s (%s)", frame.name, exc)
        return None, None
    gain = None if glare is None else glare_gain_of(image, mask, glare)
    if size is not None:
        image = resize_area(image, size)
        gain = None if gain is None else resize_area(gain, size)
    return image, gain


def write_test_view(root: str | os.PathLike, view: str, images: Mapping[str, np.ndarray],
                    shown: Mapping[str, np.ndarray]) -> None:
    """A held-out view's linear renders and display copies.

    Args:
        images: the inference dict: ``rgb``, ``restored``, ``direct``, ``backscatter``
            (H, W, 3), ``depth`` and optionally ``opacity`` (H, W).
        shown: display copies (H, W, 3) in [0, 1] of each of :data:`COMPONENTS`, and ``gt``
            when there is one.
    """
    for name in COMPONENTS:
        write_float_tiff(render_path(root, view, name), images[RENDER_KEYS[name]])
        write_display(root, view, name, shown[name])
    write_float_tiff(render_path(root, view, "depth"), images["depth"])
    if "opacity" in images:
        write_float_tiff(render_path(root, view, "opacity"), images["opacity"])
    if "gt" in shown:
        write_display(root, view, "gt", shown["gt"])


def write_restored_photo(root: str | os.PathLike, view: str, photograph: np.ndarray,
                         images: Mapping[str, np.ndarray], scale: float,
                         photos: PhotoRestoration, test_view: bool = True
                         ) -> np.ndarray | None:
    """Restore a photograph through the model's render of its view
    (``seathru.radiometry.restore``) and write it, linear and display copy:
    ``test/<view>/restored_photo.*`` for a held-out view, and ``photos/<view>.*`` for any view
    when ``photos.restore`` is ``all``.

    Args:
        photograph: the view's linear image at the render's size.
        images: the inference dict of the view (``rgb``, ``restored``, ``direct_share``,
            ``opacity``); without the last two (a stand-in renderer) nothing is written.
        scale: the display exposure; photos: the render step's settings of the restoration.

    Returns:
        the restored photograph (H, W, 3) as written, or None: not written.
    """
    from seathru.eval.display import to_display
    from seathru.radiometry.restore import restore_photograph

    if "direct_share" not in images or "opacity" not in images:
        log.warning("%s: the renderer gives no direct_share/opacity; no restored photograph",
                    view)
        return None
    restored = restore_photograph(photograph, images, photos.max_gain, photos.detail_scale)
    shown = to_display(restored, scale)
    if test_view:
        write_float_tiff(render_path(root, view, RESTORED_PHOTO), restored)
        write_display(root, view, RESTORED_PHOTO, shown)
    if not test_view or photos.restore == "all":
        write_float_tiff(Path(root) / PHOTOS_DIR / f"{view}.tiff", restored)
        write_8bit(Path(root) / PHOTOS_DIR / f"{view}.png", shown)
    return restored


def restore_all_photos(render_fn, cameras: CameraSet, root: str | os.PathLike, scale: float,
                       downscale: int, photos: PhotoRestoration,
                       done: Collection[str] = (),
                       glare: GlareCorrection | None = None) -> list[SourceView]:
    """Every camera's photograph not in ``done`` restored into ``photos/``
    (:func:`write_restored_photo`), one render per view (``render_fn(frame, downscale)``),
    without the ``glare`` correction the model was trained with (:func:`read_view_photograph`,
    :func:`split_glare`); returns the training views' restored detail of those written
    (``seathru.nerf.reproject.SourceView``), for :func:`write_reprojected`."""
    from seathru.nerf.inference import timed_renders
    from seathru.nerf.reproject import SourceView

    frames = sorted((f for f in cameras.frames if f.name not in done), key=lambda f: f.name)
    sources = []
    for frame, images, seconds in timed_renders(render_fn, frames, downscale):
        height, width = images["depth"].shape[:2]
        photograph, gain = read_view_photograph(cameras, frame, glare, (width, height))
        if photograph is None:
            continue
        photograph, _ = split_glare(photograph, images, gain)
        restored = write_restored_photo(root, frame.name, photograph, images, scale, photos,
                                        test_view=False)
        if restored is not None and frame.split == "train":
            sources.append(SourceView.from_render(frame, images, restored, downscale))
        log.info("restored photograph %s in %.2f s", frame.name, seconds)
    log.info("restored %d more photographs into %s/", len(sources), PHOTOS_DIR)
    return sources


def write_reprojected(root: str | os.PathLike, frame, images: Mapping[str, np.ndarray],
                      sources: Sequence[SourceView], downscale: int, scale: float,
                      photos: PhotoRestoration) -> bool:
    """``test/<view>/restored_reprojected.*``: the view's restored render with the training
    photographs' restored detail reprojected into it, and ``restored_support.*``, how much
    they back each pixel (``seathru.nerf.reproject.restored_and_support``); not written
    (False) without ``sources`` or an ``opacity`` render."""
    from seathru.eval.display import to_display
    from seathru.nerf.reproject import SUPPORTED, restored_and_support

    if not sources or "opacity" not in images:
        return False
    restored, support = restored_and_support(frame, images, sources, downscale,
                                             photos.reproject_tolerance, photos.reproject_angle)
    write_float_tiff(render_path(root, frame.name, RESTORED_REPROJECTED), restored)
    write_display(root, frame.name, RESTORED_REPROJECTED, to_display(restored, scale))
    write_float_tiff(render_path(root, frame.name, RESTORED_SUPPORT), support)
    grey = np.clip(support / (2.0 * SUPPORTED), 0.0, 1.0)
    write_display(root, frame.name, RESTORED_SUPPORT, np.repeat(grey[..., None], 3, axis=-1))
    return True


def restored_view(frame, images: Mapping[str, np.ndarray], sources: Sequence[SourceView],
                  downscale: int, photos: PhotoRestoration) -> np.ndarray:
    """A rendered view's restored image: with the training photographs' detail reprojected
    (``seathru.nerf.reproject.restored_with_detail``) where there are ``sources`` and an
    ``opacity`` render, else the model's restored render."""
    if not sources or "opacity" not in images:
        return images["restored"]
    from seathru.nerf.reproject import restored_with_detail

    return restored_with_detail(frame, images, sources, downscale, photos.reproject_tolerance,
                                photos.reproject_angle)


def write_depth_displays(root: str | os.PathLike, views: Sequence[str], colour) -> None:
    """``test/<view>/depth.png`` of each view from its ``depth.tiff``, through ``colour``
    (depth (H, W) -> display image (H, W, 3))."""
    for view in views:
        write_display(root, view, "depth", colour(read_image(render_path(root, view, "depth"))))


def write_display(root: str | os.PathLike, view: str, name: str, image: np.ndarray) -> None:
    """``test/<view>/<name>.png``: an 8-bit copy of display values (H, W, 3) in [0, 1]."""
    write_8bit(render_path(root, view, name, ".png"), image)


def count_video_frames(path: str | os.PathLike) -> int:
    """Number of frames OpenCV can decode from a video file (0 if it cannot be opened)."""
    capture = cv2.VideoCapture(str(path))
    try:
        if not capture.isOpened():
            return 0
        count = 0
        while True:
            ok, _ = capture.read()
            if not ok:
                return count
            count += 1
    finally:
        capture.release()


class PathVideos:
    """The camera-path videos, written a frame at a time (``with PathVideos(...) as videos``).

    Each video opens at the first frame's size (padded to even: MPEG-4 frames have even sizes);
    :meth:`check` reads every file back and returns the ``videos`` record of the stats.
    """

    def __init__(self, folder: str | os.PathLike, fps: float, names=VIDEO_OUTPUTS):
        self.folder, self.fps, self.names = Path(folder), float(fps), tuple(names)
        self.writers: dict[str, cv2.VideoWriter] = {}

    def __enter__(self) -> PathVideos:
        self.folder.mkdir(parents=True, exist_ok=True)
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        for writer in self.writers.values():
            writer.release()

    def write(self, images: Mapping[str, np.ndarray]) -> None:
        """One frame of every video: ``images[name]`` (H, W, 3) display values in [0, 1]."""
        height, width = next(iter(images.values())).shape[:2]
        if not self.writers:
            for name in self.names:
                writer = cv2.VideoWriter(str(self.folder / f"{name}.mp4"),
                                         cv2.VideoWriter_fourcc(*"mp4v"), self.fps,
                                         (width + width % 2, height + height % 2))
                if not writer.isOpened():
                    raise PipelineError(f"{self.folder.name}/{name}.mp4: OpenCV cannot open an "
                                        "'mp4v' video writer (built without video support?)")
                self.writers[name] = writer
        for name in self.names:
            data = np.round(np.clip(images[name], 0.0, 1.0) * 255.0).astype(np.uint8)
            data = cv2.copyMakeBorder(data, 0, height % 2, 0, width % 2, cv2.BORDER_REPLICATE)
            self.writers[name].write(cv2.cvtColor(data, cv2.COLOR_RGB2BGR))

    def check(self, expected: int) -> dict:
        """``{name: {"file", "frames"}}`` after closing; PipelineError when a video does not
        read back with ``expected`` frames."""
        self.close()
        videos = {}
        for name in self.writers:
            count = count_video_frames(self.folder / f"{name}.mp4")
            if count != expected:
                raise PipelineError(f"{self.folder.name}/{name}.mp4: OpenCV reads back {count} "
                                    f"of {expected} frames from the written video")
            videos[name] = {"file": f"{self.folder.name}/{name}.mp4", "frames": count}
        return videos


def frame_record(name: str, split: str, seconds: float, images: Mapping[str, np.ndarray]
                 ) -> FrameRecord:
    """A rendered frame's entry of the stats; its size is that of ``images["depth"]``."""
    height, width = images["depth"].shape[:2]
    return {"name": name, "split": split, "seconds": seconds, "width": int(width),
            "height": int(height)}


def display_record(exposure_scale: float, exposure_source: str,
                   depth_range: tuple[float, float], depth_cmap: str) -> DisplayRecord:
    """How the display copies were made: one exposure scale and one depth range per dataset."""
    return {"exposure_scale": float(exposure_scale), "exposure_source": exposure_source,
            "depth_range": list(depth_range), "depth_units": "normalised",
            "depth_cmap": depth_cmap}


def summarise(frames: list[FrameRecord]) -> SpeedSummary:
    """Count, mean seconds per frame, frames per second, resolution(s) and total seconds."""
    if not frames:
        return {"count": 0, "seconds_per_frame": None, "fps": None, "resolution": None,
                "total_seconds": 0.0}
    seconds = [f["seconds"] for f in frames]
    mean = float(np.mean(seconds))
    sizes = sorted({(f["width"], f["height"]) for f in frames})
    return {"count": len(frames), "seconds_per_frame": mean,
            "fps": 1.0 / mean if mean > 0 else None,
            "resolution": list(sizes[0]) if len(sizes) == 1 else [list(s) for s in sizes],
            "total_seconds": float(np.sum(seconds))}


def render_stats(test: list[FrameRecord], path: list[FrameRecord], display: DisplayRecord,
                 cameras: CameraSet, videos: dict, settings: dict) -> RenderStats:
    """The content of ``render_stats.json``; the headline speed is the held-out views'."""
    summary = summarise(test)
    return {"format": STATS_FORMAT, "test": summary, "path": summarise(path),
            "seconds_per_frame": summary["seconds_per_frame"], "fps": summary["fps"],
            "resolution": summary["resolution"], "display": display,
            "normalisation": {"centre": list(map(float, cameras.centre)),
                              "scale": float(cameras.scale)},
            "videos": videos, "settings": settings, "frames": test + path}


def write_render_stats(root: str | os.PathLike, stats: RenderStats) -> None:
    """``root/render_stats.json``, atomically (checked against the contract first)."""
    path = Path(root) / STATS_NAME
    check_contract(stats, RenderStats, path, STATS_FORMAT)
    write_json(path, stats)


def read_render_stats(root: str | os.PathLike) -> RenderStats:
    """``root/render_stats.json`` of a render folder.

    Raises:
        PipelineError: naming the file when it is missing, not JSON, of another format or
            missing a key.
    """
    path = Path(root) / STATS_NAME
    data: Any = read_json(path, hint=_HINT)
    check_contract(data, RenderStats, path, STATS_FORMAT, _HINT)
    return data
