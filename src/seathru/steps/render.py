"""Render held-out views and a camera path: full, restored, depth, backscatter, direct; videos.

For every test-split view of the camera file, writes to ``OUT/test/<name>/``:

- ``full``, ``restored``, ``direct``, ``backscatter``: linear radiance as float32 ``.tiff`` and a
  display copy as 8-bit sRGB ``.png`` (one exposure for the whole dataset, see below);
- ``gt.png``: the ground-truth image with the same display exposure (for side-by-side views);
- ``depth.tiff``: expected ray distance in normalised scene units (float32), and ``depth.png``
  colour-mapped (near warm, far cool; one range for the dataset).

For a smooth path through the training cameras (cubic spline through their centres in capture
order, slerp between rotations), ``OUT/path/full.mp4``, ``restored.mp4`` and ``depth.mp4``
('mp4v'; each file is reopened with OpenCV and its frames counted before the step succeeds).

``OUT/render_stats.json`` records the seconds per frame, frames per second and resolution, the
display exposure and depth range, and the settings used.

Display exposure: linear images from a camera (and the SeaThru-NeRF release's linear PNGs) look
grey; the display copies are multiplied by one scale per dataset so that the
``--exposure-percentile`` of the training images' values maps to ``--exposure-target``, then
sRGB-encoded. Linear ``.tiff`` outputs are never scaled.

Rendering goes through ``seathru.nerf.inference.render_frame`` in ray chunks (``--chunk``), so
memory stays bounded at any resolution; each output folder appears only once complete.
"""

from __future__ import annotations

import argparse
import logging
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from seathru.eval import display
from seathru.eval.camera_path import smooth_camera_path
from seathru.errors import PipelineError
from seathru.io.atomic import atomic_dir, write_json
from seathru.io.cameras import CameraSet, Frame, read_cameras
from seathru.io.images import read_image, write_8bit, write_float_tiff

log = logging.getLogger(__name__)

COMPONENTS = ("full", "restored", "direct", "backscatter")
# render_frame's key for each output name
RENDER_KEYS = {"full": "rgb", "restored": "restored", "direct": "direct",
               "backscatter": "backscatter"}
VIDEO_OUTPUTS = ("full", "restored", "depth")
MAX_EXPOSURE_IMAGES = 24

RenderFn = Callable[[Frame, int], dict]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, type=Path, help="model.pt from the train step")
    parser.add_argument("--cameras", required=True, type=Path,
                        help="cameras.json from the poses step")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--path-frames", type=int, default=120,
                        help="frames of the camera-path videos (0: no videos; default 120)")
    parser.add_argument("--fps", type=float, default=24.0, help="video frame rate (default 24)")
    parser.add_argument("--chunk", type=int, default=8192,
                        help="rays rendered at once; lower it if memory runs out (default 8192)")
    parser.add_argument("--downscale", type=int, default=1,
                        help="render test views at 1/N resolution (default 1)")
    parser.add_argument("--path-downscale", type=int, default=None,
                        help="resolution divisor for the path videos (default: --downscale)")
    parser.add_argument("--exposure-percentile", type=float, default=display.DEFAULT_PERCENTILE,
                        help="percentile of the training images' linear values that the display "
                             "exposure maps to --exposure-target (default 99)")
    parser.add_argument("--exposure-target", type=float, default=display.DEFAULT_TARGET,
                        help="display value of that percentile before sRGB encoding (default 0.9)")
    parser.add_argument("--depth-cmap", default=display.DEFAULT_DEPTH_CMAP,
                        help="matplotlib colour map for depth images (default turbo)")
    parser.add_argument("--device", default="auto",
                        help="torch device: auto (CUDA when available), cpu, cuda, cuda:1 ...")
    parser.add_argument("--threads", type=int, default=None, help="CPU threads for torch")


def run(args: argparse.Namespace) -> None:
    for name in ("path_frames", "chunk", "downscale"):
        value = getattr(args, name)
        if value < (0 if name == "path_frames" else 1):
            raise PipelineError(f"--{name.replace('_', '-')} must be "
                                f"{'>= 0' if name == 'path_frames' else '>= 1'}, got {value}")
    if args.path_downscale is not None and args.path_downscale < 1:
        raise PipelineError(f"--path-downscale must be >= 1, got {args.path_downscale}")
    if args.fps <= 0:
        raise PipelineError(f"--fps must be positive, got {args.fps}")
    if not 0 < args.exposure_percentile <= 100 or args.exposure_target <= 0:
        raise PipelineError("--exposure-percentile must be in (0, 100] and --exposure-target > 0")
    import matplotlib

    if args.depth_cmap not in matplotlib.colormaps:
        raise PipelineError(f"--depth-cmap {args.depth_cmap!r} is not a matplotlib colour map")

    cameras = read_cameras(args.cameras)
    if not cameras.split("test"):
        raise PipelineError(f"{args.cameras}: no frame has split 'test'; set the poses step's "
                            "--test-every so that some views are held out")
    if not cameras.split("train"):
        raise PipelineError(f"{args.cameras}: no frame has split 'train'")
    model, device = load_model(args.model, args.device, args.threads)

    from seathru.nerf.inference import render_frame

    def render_fn(frame: Frame, downscale: int) -> dict:
        return render_frame(model, frame, chunk=args.chunk, downscale=downscale)

    settings = {"model": str(args.model), "device": str(device), "chunk": args.chunk,
                "downscale": args.downscale,
                "path_downscale": args.path_downscale or args.downscale,
                "path_frames": args.path_frames, "fps": args.fps,
                "exposure_percentile": args.exposure_percentile,
                "exposure_target": args.exposure_target, "depth_cmap": args.depth_cmap}
    render_dataset(render_fn, cameras, args.out, settings)


def load_model(path: Path, device_name: str = "auto", threads: int | None = None):
    """Load ``model.pt`` (the train step's contract) onto a device; returns (model, device)."""
    import torch

    if threads:
        torch.set_num_threads(threads)
    if device_name == "auto":
        device_name = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        device = torch.device(device_name)
    except RuntimeError as exc:
        raise PipelineError(f"--device {device_name!r} is not a torch device ({exc})") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise PipelineError(f"--device {device_name}: no CUDA device is available here; use cpu")
    if not Path(path).is_file():
        raise PipelineError(f"{path}: model file not found; run the 'train' step first")
    from seathru.nerf.model import SeaThruModel

    try:
        checkpoint = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # a truncated or foreign file: say which file, not a traceback
        raise PipelineError(f"{path}: cannot be read as a model checkpoint ({exc}); re-run the "
                            "'train' step") from None
    model = SeaThruModel.from_checkpoint(checkpoint, device)
    if hasattr(model, "eval"):
        model.eval()
    return model, device


# ------------------------------------------------------------------------------------ rendering

def reference_exposure(cameras: CameraSet, percentile: float, target: float) -> float | None:
    """Display exposure from up to MAX_EXPOSURE_IMAGES training images; None if none is readable."""
    frames = sorted(cameras.split("train"), key=lambda f: f.name)
    picks = np.unique(np.linspace(0, len(frames) - 1, min(len(frames), MAX_EXPOSURE_IMAGES))
                      .round().astype(int))
    images = []
    for index in picks:
        try:
            images.append(display.sample_values(read_image(cameras.image_path(frames[index]))))
        except PipelineError as exc:
            log.warning("exposure: skipping %s (%s)", frames[index].name, exc)
    if not images:
        return None
    return display.exposure_scale(images, percentile, target)


def path_frames(cameras: CameraSet, n_frames: int) -> list[Frame]:
    """Frames along a smooth path through the training cameras, with the first training frame's
    intrinsics and the scene-wide near/far bounds."""
    train = sorted(cameras.split("train"), key=lambda f: f.name)
    poses = smooth_camera_path(np.stack([f.c2w_array for f in train]), n_frames,
                               names=[f.name for f in train])
    template = train[0]
    return [replace(template, name=f"path_{i:04d}", image="", mask=None, split="path",
                    c2w=pose.tolist(), near=float(cameras.near), far=float(cameras.far))
            for i, pose in enumerate(poses)]


def _resize_to(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    if image.shape[:2] == tuple(shape):
        return image
    return cv2.resize(image, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)


def _check_outputs(outputs: dict, frame: Frame) -> None:
    missing = [key for key in (*RENDER_KEYS.values(), "depth") if key not in outputs]
    if missing:
        raise PipelineError(f"the model's render of {frame.name} lacks {missing}; the model and "
                            "the render step disagree on the inference contract")


def render_dataset(render_fn: RenderFn, cameras: CameraSet, out: Path, settings: dict) -> dict:
    """Render the test views and the camera path of ``cameras`` into ``out``; returns the stats.

    ``render_fn(frame, downscale)`` returns ``seathru.nerf.inference.render_frame``'s dict.
    ``settings`` holds downscale, path_downscale, path_frames, fps, exposure_percentile,
    exposure_target and depth_cmap (see the CLI flags), plus anything to record in the stats.
    """
    out = Path(out)
    scale = reference_exposure(cameras, settings["exposure_percentile"],
                               settings["exposure_target"])
    exposure_source = "training images"
    test_frames = sorted(cameras.split("test"), key=lambda f: f.name)
    stats_frames = []
    depth_samples = []
    with atomic_dir(out) as tmp:
        for frame in test_frames:
            start = time.perf_counter()
            outputs = render_fn(frame, settings["downscale"])
            seconds = time.perf_counter() - start
            _check_outputs(outputs, frame)
            if scale is None:  # no readable training image: expose for the first render instead
                scale = display.exposure_scale([outputs["rgb"]], settings["exposure_percentile"],
                                               settings["exposure_target"])
                exposure_source = f"render of {frame.name}"
            height, width = outputs["depth"].shape[:2]
            folder = tmp / "test" / frame.name
            for name in COMPONENTS:
                linear = np.asarray(outputs[RENDER_KEYS[name]], dtype=np.float32)
                write_float_tiff(folder / f"{name}.tiff", linear)
                write_8bit(folder / f"{name}.png", display.to_display(linear, scale))
            depth = np.asarray(outputs["depth"], dtype=np.float32)
            write_float_tiff(folder / "depth.tiff", depth)
            if "opacity" in outputs:
                write_float_tiff(folder / "opacity.tiff", outputs["opacity"])
            depth_samples.append(display.sample_values(depth, 20_000))
            try:
                truth = _resize_to(read_image(cameras.image_path(frame)), (height, width))
                write_8bit(folder / "gt.png", display.to_display(truth, scale))
            except PipelineError as exc:
                log.warning("no ground-truth display copy for %s (%s)", frame.name, exc)
            stats_frames.append({"name": frame.name, "split": "test", "seconds": seconds,
                                 "width": int(width), "height": int(height)})
            log.info("rendered %s (%dx%d) in %.2f s", frame.name, width, height, seconds)

        depth_lo, depth_hi = display.depth_range(depth_samples)
        for frame in test_frames:
            folder = tmp / "test" / frame.name
            depth = read_image(folder / "depth.tiff")
            write_8bit(folder / "depth.png", display.colourise_depth(
                depth, depth_lo, depth_hi, settings["depth_cmap"]))

        path_stats = []
        videos = {}
        if settings["path_frames"] > 0:
            path_stats, videos = _render_path(
                render_fn, path_frames(cameras, settings["path_frames"]), tmp / "path", scale,
                (depth_lo, depth_hi), settings)

        stats = {
            "format": "seathru-render-stats/1",
            "test": _summarise(stats_frames),
            "path": _summarise(path_stats),
            # the headline figures: held-out views at evaluation resolution
            "seconds_per_frame": _summarise(stats_frames)["seconds_per_frame"],
            "fps": _summarise(stats_frames)["fps"],
            "resolution": _summarise(stats_frames)["resolution"],
            "display": {"exposure_scale": float(scale), "exposure_source": exposure_source,
                        "depth_range": [depth_lo, depth_hi], "depth_units": "normalised",
                        "depth_cmap": settings["depth_cmap"]},
            "normalisation": {"centre": list(map(float, cameras.centre)),
                              "scale": float(cameras.scale)},
            "videos": videos,
            "settings": settings,
            "frames": stats_frames + path_stats,
        }
        write_json(tmp / "render_stats.json", stats)
    return stats


def _summarise(frames: list[dict]) -> dict:
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


def _render_path(render_fn: RenderFn, frames: list[Frame], folder: Path, scale: float,
                 depth_range: tuple[float, float], settings: dict) -> tuple[list[dict], dict]:
    """Render the path frames straight into the videos (one frame in memory at a time).

    ``folder`` lies inside the step's temporary output folder, which appears atomically.
    """
    downscale = settings["path_downscale"]
    stats, writers = [], {}
    folder.mkdir(parents=True, exist_ok=True)
    try:
        for frame in frames:
            start = time.perf_counter()
            outputs = render_fn(frame, downscale)
            seconds = time.perf_counter() - start
            _check_outputs(outputs, frame)
            height, width = outputs["depth"].shape[:2]
            images = {
                "full": display.to_display(outputs["rgb"], scale),
                "restored": display.to_display(outputs["restored"], scale),
                "depth": display.colourise_depth(outputs["depth"], *depth_range,
                                                 settings["depth_cmap"]),
            }
            if not writers:
                for name in VIDEO_OUTPUTS:
                    # MPEG-4 frames have even sizes: odd ones are padded by one edge pixel
                    writer = cv2.VideoWriter(str(folder / f"{name}.mp4"),
                                             cv2.VideoWriter_fourcc(*"mp4v"),
                                             float(settings["fps"]),
                                             (width + width % 2, height + height % 2))
                    if not writer.isOpened():
                        raise PipelineError(f"{folder.name}/{name}.mp4: OpenCV cannot open an "
                                            "'mp4v' video writer (built without video support?)")
                    writers[name] = writer
            for name, image in images.items():
                data = np.round(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8)
                data = cv2.copyMakeBorder(data, 0, height % 2, 0, width % 2,
                                          cv2.BORDER_REPLICATE)
                writers[name].write(cv2.cvtColor(data, cv2.COLOR_RGB2BGR))
            stats.append({"name": frame.name, "split": "path", "seconds": seconds,
                          "width": int(width), "height": int(height)})
    finally:
        for writer in writers.values():
            writer.release()
    videos = {}
    for name in writers:
        count = count_video_frames(folder / f"{name}.mp4")
        if count != len(frames):
            raise PipelineError(f"path/{name}.mp4: OpenCV reads back {count} of {len(frames)} "
                                "frames from the written video")
        videos[name] = {"file": f"path/{name}.mp4", "frames": count}
    log.info("camera path: %d frames", len(stats))
    return stats, videos


def count_video_frames(path: Path) -> int:
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
