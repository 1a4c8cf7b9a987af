"""PSNR / SSIM on held-out views; the community's protocol; colour charts; the simulator's truth.

Per held-out (test split) view, the render step's ``test/<name>/full.tiff`` against the view's
linear image from the camera file, 8-bit quantised (rounded) as in the NeRF papers: PSNR, SSIM
(linear, the official SeaThru-NeRF evaluation, and sRGB-encoded) and LPIPS when
``--lpips-weights`` points at weights on disk (else ``unavailable``; weights are never
downloaded); see ``seathru.eval.summary``. These are on the pipeline's white-balanced,
exposure-normalised images.

``--protocol nerfbaselines`` adds NerfBaselines' default protocol for the SeaThru-NeRF dataset:
predictions taken back to the stored images' encoding and compared with the stored images as
they are on disk, uint8-truncated, written in NerfBaselines' layout to ``--out/nerfbaselines``
(``seathru.io.nerfbaselines``). A colour chart (``--chart`` annotation, ``colour_chart.json`` in
the dataset folder, else OpenCV's mcc detector) is measured on the photo, the ingest image and
the restored render: CIEDE2000 and grey angular error (``seathru.io.chart``). With the poses
step's COLMAP model: colour against range along its tracks, in the input, the restored render
and the restored photographs (``seathru.io.tracks``). With ``--truth`` (``simulate/truth``):
restorations against the clean truth, depth, water (``seathru.io.evaluation``).

Writes ``metrics.csv`` (one row per held-out view), ``summary.json`` (means, render speed,
training time, fitted water, the medium selection, protocol and chart results) and
``frontier.csv`` (quality against training time from the train step's snapshots, scored
against the truth when there is one: ``seathru.io.frontier``) to ``--out``.
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from seathru import settings
from seathru.errors import PipelineError
from seathru.eval import summary as dataset_summary
from seathru.io.cameras import CameraSet, Frame, read_cameras
from seathru.io.chart import evaluate_colour_chart, find_annotation
from seathru.io.evaluation import (load_lpips, read_render, read_train_log, resized_like,
                                   truth_evaluation, view_support, write_metrics, write_summary)
from seathru.io.frontier import FRONTIER_NAME, frontier_table, write_frontier
from seathru.io.atomic import write_json
from seathru.io.images import read_image
from seathru.io.jsonfile import json_safe, read_json
from seathru.io.nerfbaselines import evaluate_nerfbaselines
from seathru.io.stored_views import ingest_folder_of
from seathru.io.tracks import track_colour_slope
from seathru.io.water import read_water
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
    protocol: Literal["seathru", "nerfbaselines"] = setting(
        "seathru", help="seathru: PSNR/SSIM on the pipeline's linear images (always computed); "
                        "nerfbaselines: also NerfBaselines' protocol against the stored images "
                        "(needs poses.test_every=8, full resolution)")
    chart: Path | None = setting(
        None, help="colour-chart annotation (JSON, seathru.io.chart); unset: colour_chart.json "
                   "in the dataset folder, else OpenCV mcc detection")
    chart_detect: bool = setting(
        True, help="without an annotation, look for a ColorChecker with OpenCV's mcc detector")
    chart_render: bool = setting(
        True, help="render the chart's view with the trained model when it is not held out")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--renders", required=True, type=Path,
                        help="output folder of the render step")
    parser.add_argument("--cameras", required=True, type=Path,
                        help="cameras.json from the poses step (held-out views: split 'test')")
    parser.add_argument("--train-dir", required=True, type=Path,
                        help="output folder of the train step (water.json, train_log.csv, "
                             "selection.json, model.pt)")
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
    lpips_net, lpips_status = load_lpips(cfg.lpips_weights)

    rows = []
    for frame in views:
        full = read_render(args.renders, frame.name, "full")
        target = resized_like(read_image(cameras.image_path(frame)), full)
        rows.append({**dataset_summary.view_metrics(dataset, frame.name, full, target, lpips_net),
                     **view_support(args.renders, frame.name)})
        log.info("%s: PSNR %.2f dB, SSIM %.4f (linear)", frame.name, rows[-1]["psnr_linear"],
                 rows[-1]["ssim_linear"])

    water = read_water(args.train_dir / "water.json", missing_ok=True)
    if water is None:
        log.warning("%s not found: water parameters not evaluated", args.train_dir / "water.json")
    truth = None if args.truth is None else truth_evaluation(args.truth, args.renders, cameras,
                                                             rows, water)
    train_log = read_train_log(args.train_dir / "train_log.csv")
    training = dataset_summary.training_summary(train_log)
    protocol = None
    if cfg.protocol == "nerfbaselines":
        protocol = evaluate_nerfbaselines(
            cameras, args.renders, out / "nerfbaselines", dataset, lpips_net,
            None if training is None else {"steps": training.steps, "time_s": training.time_s})
        log.info("%s (nerfbaselines protocol): PSNR %.2f dB, SSIM %.4f", dataset,
                 protocol["means"]["psnr"], protocol["means"]["ssim"])
    chart = _colour_chart(cfg, cameras, args)
    table = dataset_summary.metrics_table(rows)
    summary = dataset_summary.build_summary(
        dataset, table, lpips_status=lpips_status,
        render_stats=read_json(args.renders / "render_stats.json", missing_ok=True),
        train_log=train_log, water=None if water is None else water.to_dict(),
        selection=read_json(args.train_dir / "selection.json", missing_ok=True), truth=truth,
        protocol=protocol, colour_chart=chart,
        track_colour_slope=track_colour_slope(cameras, args.train_dir / "model.pt", args.threads,
                                              renders=args.renders))
    args.out.mkdir(parents=True, exist_ok=True)
    write_metrics(args.out / "metrics.csv", table)
    write_summary(args.out / "summary.json", summary)
    write_frontier(args.out / FRONTIER_NAME,
                   frontier_table(args.train_dir, args.truth, truth, cameras))
    if chart.get("source") != "none":
        write_json(args.out / "colour_chart.json", json_safe(chart))
    log.info("%s: mean PSNR %.2f dB, %d views", dataset, table["psnr_linear"].mean(), len(table))


def _colour_chart(cfg: Settings, cameras: CameraSet, args: argparse.Namespace) -> dict:
    """The chart's measurement, or why there is none (no manifest: a hand-made camera file)."""
    ingest = ingest_folder_of(cameras)
    if not (ingest / "manifest.json").is_file():
        return {"source": "none", "reason": f"{ingest / 'manifest.json'} not found"}
    annotation = find_annotation(cfg.chart, ingest)
    model = args.train_dir / "model.pt"

    def render_restored(frame: Frame):
        from seathru.io.model import load_model
        from seathru.nerf.device import select_device
        from seathru.nerf.inference import render_frame

        log.info("colour chart: rendering %s (not a held-out view)", frame.name)
        return render_frame(load_model(model, select_device("auto", args.threads)),
                            frame)["restored"]

    return evaluate_colour_chart(cameras, args.renders, annotation, cfg.chart_detect,
                                 render_restored if cfg.chart_render and model.is_file()
                                 else None)
