"""PSNR / SSIM on held-out views; against the truth for simulated datasets.

Per held-out (test split) view, the render step's ``test/<name>/full.tiff`` against the view's
linear image from the camera file, 8-bit quantised as in the NeRF papers: PSNR, SSIM (linear,
the official SeaThru-NeRF evaluation, and sRGB-encoded) and LPIPS when ``--lpips-weights`` points
at weights on disk (else ``unavailable``; weights are never downloaded); see
``seathru.eval.summary``. With ``--truth`` (a simulated dataset's ``simulate/truth``): restored
renders against the clean truth after one colour gain per channel, depth in metres and fitted
water against the truth; see ``seathru.eval.truth``.

Writes ``metrics.csv`` (one row per held-out view) and ``summary.json`` (means, render speed,
training time, fitted water, the medium selection) to ``--out``; see ``seathru.io.evaluation``.
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from seathru import settings
from seathru.errors import PipelineError
from seathru.eval import summary as dataset_summary, truth as truth_eval
from seathru.eval.summary import TruthSummary
from seathru.io.cameras import CameraSet, read_cameras
from seathru.io.evaluation import (camera_centres, read_lpips_weights, read_render,
                                   read_train_log, read_truth_image, write_metrics,
                                   write_summary)
from seathru.io.images import read_image
from seathru.io.jsonfile import read_json
from seathru.io.water import WaterReport, read_truth_water, read_water
from seathru.radiometry.linearise import resize_area
from seathru.settings import setting

log = logging.getLogger(__name__)


@dataclass
class Settings:
    """Evaluation of held-out views (and against the truth for simulated datasets)."""

    lpips_weights: Path | None = setting(
        None, help="LPIPS weights on disk: one .pth holding the trunk and the linear layers, or "
                   "a folder with the torchvision backbone (alexnet/vgg16) and the lpips v0.1 "
                   "linear layers; absent: LPIPS 'unavailable'")
    dataset: str | None = setting(None, help="dataset id for the tables (automatic: the folder "
                                             "above the output folder)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--renders", required=True, type=Path,
                        help="output folder of the render step")
    parser.add_argument("--cameras", required=True, type=Path,
                        help="cameras.json from the poses step (held-out views: split 'test')")
    parser.add_argument("--train-dir", required=True, type=Path,
                        help="output folder of the train step (water.json, train_log.csv, "
                             "selection.json)")
    parser.add_argument("--truth", type=Path, default=None,
                        help="simulated datasets: the simulate step's truth/ folder")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--threads", type=int, default=None, help="CPU threads for torch")
    settings.add_arguments(parser, Settings)


def run(args: argparse.Namespace) -> None:
    cfg = settings.from_namespace(Settings, args)
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    out = Path(args.out).resolve()
    dataset = cfg.dataset or (out.parent.name if out.name == "evaluate" else out.name)
    cameras = read_cameras(args.cameras)
    views = sorted(cameras.split("test"), key=lambda f: f.name)
    if not views:
        raise PipelineError(f"{args.cameras}: no frame has split 'test'; nothing to evaluate")
    if not args.renders.is_dir():
        raise PipelineError(f"{args.renders}: render folder not found; run the 'render' step")
    weights = None if cfg.lpips_weights is None else read_lpips_weights(cfg.lpips_weights)
    try:
        lpips_net, lpips_status = dataset_summary.lpips_network(weights, cfg.lpips_weights)
    except ValueError as exc:
        raise PipelineError(f"--lpips-weights {cfg.lpips_weights}: {exc}") from None

    rows = []
    for frame in views:
        full = read_render(args.renders, frame.name, "full")
        target = _resized(read_image(cameras.image_path(frame)), full)
        rows.append(dataset_summary.view_metrics(dataset, frame.name, full, target, lpips_net))
        log.info("%s: PSNR %.2f dB, SSIM %.4f (linear)", frame.name, rows[-1]["psnr_linear"],
                 rows[-1]["ssim_linear"])

    water = read_water(args.train_dir / "water.json", missing_ok=True)
    if water is None:
        log.warning("%s not found: water parameters not evaluated", args.train_dir / "water.json")
    truth = None if args.truth is None else _against_truth(args.truth, args.renders, cameras,
                                                           rows, water)
    table = dataset_summary.metrics_table(rows)
    summary = dataset_summary.build_summary(
        dataset, table, lpips_status=lpips_status,
        render_stats=read_json(args.renders / "render_stats.json", missing_ok=True),
        train_log=read_train_log(args.train_dir / "train_log.csv"),
        water=None if water is None else water.to_dict(),
        selection=read_json(args.train_dir / "selection.json", missing_ok=True), truth=truth)
    args.out.mkdir(parents=True, exist_ok=True)
    write_metrics(args.out / "metrics.csv", table)
    write_summary(args.out / "summary.json", summary)
    log.info("%s: mean PSNR %.2f dB over %d views", dataset, table["psnr_linear"].mean(),
             len(table))


def _resized(image: np.ndarray, like: np.ndarray) -> np.ndarray:
    """``image`` area-resized to the render's size (renders may be downscaled)."""
    return resize_area(image, (like.shape[1], like.shape[0]))


def _against_truth(truth_dir: Path, renders: Path, cameras: CameraSet, rows: list[dict],
                   water: WaterReport | None) -> TruthSummary:
    """Adds the truth columns to ``rows`` (one per held-out view); the summary's truth part."""
    truth_centres = camera_centres(read_cameras(truth_dir / "cameras.json"), source_units=True)
    views = [row["view"] for row in rows]
    missing = [view for view in views if view not in truth_centres]
    if missing:
        raise PipelineError(f"{truth_dir / 'cameras.json'}: no truth for held-out views "
                            f"{missing[:3]}; the camera file and the simulation do not match")
    scale = truth_eval.camera_metric_scale(camera_centres(cameras), truth_centres, cameras.scale)

    def truth(kind: str, view: str, like: np.ndarray) -> np.ndarray:
        return _resized(read_truth_image(truth_dir, kind, view), like)

    # one view in memory at a time
    renders_full = ((view, read_render(renders, view, "full")) for view in views)
    gain = truth_eval.pooled_gain((full, truth("water", view, full))
                                  for view, full in renders_full)
    for row in rows:
        view = row["view"]
        full = read_render(renders, view, "full")
        row.update(truth_eval.view_truth_metrics(
            full=full, restored=read_render(renders, view, "restored"),
            depth=read_render(renders, view, "depth"), clean=truth("clean", view, full),
            water=truth("water", view, full), truth_depth=truth("depth", view, full),
            gain=gain, metres_per_unit=scale.scale))
    fitted = None if water is None else water.normalised.as_dict()
    comparison = truth_eval.compare_water(fitted, read_truth_water(truth_dir / "water.json")
                                          .as_dict(), scale.scale, gain)
    return truth_eval.truth_summary(gain, scale, comparison)
