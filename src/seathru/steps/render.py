"""Render held-out views and a camera path: full, restored, depth, backscatter, direct; videos.

Writes ``OUT/test/<view>/`` (linear ``.tiff`` and display ``.png`` of every component, ``gt.png``,
depth, the view's photograph with the water removed), ``OUT/photos/`` (with ``photos.restore:
all``: every photograph restored, their detail reprojected into the held-out views and the
path's restored video), ``OUT/path/*.mp4`` and ``OUT/render_stats.json``: the layout is
``seathru.io.renders``. Display copies share one exposure per dataset: the
``exposure_percentile`` of the training images maps to ``exposure_target`` before sRGB encoding
(``seathru.eval.display``); linear outputs are never scaled. Frames render in ray chunks
(``seathru.nerf.inference``), so memory stays bounded at any resolution; the output folder
appears only once complete.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from seathru import settings
from seathru.errors import PipelineError
from seathru.eval import display
from seathru.io import renders
from seathru.io.atomic import atomic_dir
from seathru.io.cameras import CameraSet, read_cameras
from seathru.radiometry.restore import PhotoRestoration
from seathru.settings import section, setting

log = logging.getLogger(__name__)


@dataclass
class Settings:
    """Rendering of the held-out views and the camera-path videos."""

    path_frames: int = setting(120, help="frames of the camera-path videos (0: no videos)")
    fps: float = setting(24.0, help="video frame rate")
    chunk: int = setting(8192, help="rays rendered at once; lower it if memory runs out")
    downscale: int = setting(1, help="render test views at 1/N resolution")
    path_downscale: int | None = setting(None, help="render the path videos at 1/N "
                                                    "resolution (unset: as downscale)")
    exposure_percentile: float = setting(display.DEFAULT_PERCENTILE, help="percentile of the "
                                         "training images' values mapped to exposure_target")
    exposure_target: float = setting(display.DEFAULT_TARGET, help="display value of that "
                                     "percentile before sRGB encoding")
    depth_cmap: str = setting(display.DEFAULT_DEPTH_CMAP,
                              help="matplotlib colour map for depth images")
    photos: PhotoRestoration = section(PhotoRestoration)
    device: str = setting("auto", help="torch device: auto (CUDA when available), cpu, cuda:N")

    @property
    def video_downscale(self) -> int:
        return self.path_downscale or self.downscale

    def validate(self) -> None:
        from matplotlib import colormaps

        for name, least in (("path_frames", 0), ("chunk", 1), ("downscale", 1),
                            ("path_downscale", 1)):
            value = getattr(self, name)
            if value is not None and value < least:
                raise ValueError(f"{name} must be >= {least}, got {value}")
        if self.fps <= 0:
            raise ValueError(f"fps must be positive, got {self.fps}")
        if not 0 < self.exposure_percentile <= 100 or self.exposure_target <= 0:
            raise ValueError("exposure_percentile must be in (0, 100] and exposure_target > 0")
        if self.depth_cmap not in colormaps:
            raise ValueError(f"depth_cmap {self.depth_cmap!r} is not a matplotlib colour map")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, type=Path, help="model.pt from the train step")
    parser.add_argument("--cameras", required=True, type=Path,
                        help="cameras.json from the poses step")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--threads", type=int, default=None, help="CPU threads for torch")
    settings.add_arguments(parser, Settings)


def run(args: argparse.Namespace) -> None:
    cfg = settings.from_namespace(Settings, args)
    cameras = read_cameras(args.cameras)
    if not cameras.split("test"):
        raise PipelineError(f"{args.cameras}: no frame has split 'test'; set the poses step's "
                            "--test-every so that some views are held out")
    if not cameras.split("train"):
        raise PipelineError(f"{args.cameras}: no frame has split 'train'")
    from seathru.io.model import load_model
    from seathru.nerf.device import select_device
    from seathru.nerf.inference import frame_renderer

    device = select_device(cfg.device, args.threads)
    model = load_model(args.model, device)
    glare = renders.photograph_glare(args.model)
    render_dataset(frame_renderer(model, cfg.chunk), cameras, args.out, cfg,
                   {"model": str(args.model), "device": str(device),
                    "glare": None if glare is None else glare.to_dict()}, glare=glare)


def render_dataset(render_fn, cameras: CameraSet, out: Path, cfg: Settings | Mapping,
                   record: Mapping | None = None,
                   glare: renders.GlareCorrection | None = None) -> renders.RenderStats:
    """Render the test views and the camera path of ``cameras`` into ``out``; returns the stats.

    ``render_fn(frame, downscale)`` returns ``seathru.nerf.inference.render_frame``'s dict;
    ``cfg`` is the render :class:`Settings` (or a mapping of them); ``record`` is added to the
    stats' settings (model file, device); ``glare``: the model's training correction, out of the
    photographs it restores and back in the held-out full renders (``renders.split_glare``).
    """
    from seathru.nerf.inference import timed_renders

    if not isinstance(cfg, Settings):
        cfg = settings.from_mapping(Settings, cfg, "render")
    percentile, target = cfg.exposure_percentile, cfg.exposure_target
    samples = [display.sample_values(image) for image in renders.exposure_references(cameras)]
    scale = display.exposure_scale(samples, percentile, target) if samples else None
    exposure_source = "training images"
    test_frames = sorted(cameras.split("test"), key=lambda f: f.name)
    test_stats, depth_samples, sources = [], [], []
    with atomic_dir(out) as tmp:
        if cfg.photos.restore == "all" and scale is not None:  # None: no photograph readable
            sources = renders.restore_all_photos(render_fn, cameras, tmp, scale, cfg.downscale,
                                                 cfg.photos, {f.name for f in test_frames}, glare)
        for frame, images, seconds in timed_renders(render_fn, test_frames, cfg.downscale):
            if scale is None:  # no readable training image: expose for the first render instead
                scale = display.exposure_scale([images["rgb"]], percentile, target)
                exposure_source = f"render of {frame.name}"
            height, width = images["depth"].shape[:2]
            truth, gain = renders.read_view_photograph(cameras, frame, glare, (width, height))
            photograph, recorded = renders.split_glare(truth, images, gain)
            shown = {name: display.to_display(recorded[key], scale)
                     for name, key in renders.RENDER_KEYS.items()}
            if truth is not None:
                shown["gt"] = display.to_display(truth, scale)
            renders.write_test_view(tmp, frame.name, recorded, shown)
            if truth is not None and cfg.photos.restore != "none":
                renders.write_restored_photo(tmp, frame.name, photograph, images, scale,
                                             cfg.photos)
            renders.write_reprojected(tmp, frame, images, sources, cfg.downscale, scale, cfg.photos)
            depth_samples.append(display.sample_values(images["depth"], 20_000))
            test_stats.append(renders.frame_record(frame.name, "test", seconds, images))
            log.info("rendered %s (%dx%d) in %.2f s", frame.name, width, height, seconds)
        depth_range = display.depth_range(depth_samples)

        def colour(depth):  # one colour scale for every depth image and video frame
            return display.colourise_depth(depth, *depth_range, cfg.depth_cmap)

        renders.write_depth_displays(tmp, [f.name for f in test_frames], colour)
        path_stats, videos = [], {}
        if cfg.path_frames > 0:
            from seathru.eval.camera_path import path_frames  # scipy.interpolate: seconds

            with renders.PathVideos(tmp / "path", cfg.fps) as writer:
                for frame, images, seconds in timed_renders(
                        render_fn, path_frames(cameras, cfg.path_frames), cfg.video_downscale):
                    restored = renders.restored_view(frame, images, sources,
                                                     cfg.video_downscale, cfg.photos)
                    writer.write({"full": display.to_display(images["rgb"], scale),
                                  "restored": display.to_display(restored, scale),
                                  "depth": colour(images["depth"])})
                    path_stats.append(renders.frame_record(frame.name, "path", seconds, images))
                videos = writer.check(cfg.path_frames)
            log.info("camera path: %d frames", len(path_stats))
        shown = renders.display_record(scale, exposure_source, depth_range, cfg.depth_cmap)
        used = {**settings.to_dict(cfg), "path_downscale": cfg.video_downscale, **(record or {})}
        stats = renders.render_stats(test_stats, path_stats, shown, cameras, videos, used)
        renders.write_render_stats(tmp, stats)
    return stats
