"""Train the SeaThru-NeRF model of one dataset (object field + water), resumable.

Reads ``--cameras`` (cameras.json; its frames' linear images and optional masks), trains on
the 'train' split and measures the PSNR on pixels of the 'test' split at log-spaced steps.
Writes to ``--out``: ``model.pt`` (``torch.load(weights_only=True)``-safe), ``water.json``
(fitted water per channel), ``train_log.csv`` and ``selection.json`` (the water model chosen
and why). Checkpoints go to ``--checkpoint-dir`` (keep it outside the outputs); a run that
finds a checkpoint with the same settings there resumes from it.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from pathlib import Path

# Idle OpenMP threads sleep instead of spinning: on a shared machine spinning threads steal the
# cores the other thread waits for. Effective only if torch is not imported yet.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from seathru import settings
from seathru.errors import PipelineError
from seathru.io.atomic import write_json
from seathru.io.cameras import read_cameras
from seathru.nerf.config import TrainConfig as Settings

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cameras", required=True, type=Path, help="cameras.json to train on")
    parser.add_argument("--out", required=True, type=Path,
                        help="output folder: model.pt, water.json, train_log.csv, selection.json")
    parser.add_argument("--checkpoint-dir", type=Path, default=None,
                        help="checkpoints (resume after a kill); default: OUT/../checkpoints")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    settings.add_arguments(parser, Settings)


def run(args: argparse.Namespace) -> None:
    import torch

    # exp(-large) underflows to denormals, 10x slower on CPU; the flag is process-wide, so it
    # is switched off again for whoever calls this step in-process (tests, notebooks).
    torch.set_flush_denormal(True)
    try:
        train(settings.from_namespace(Settings, args), args.cameras, args.out,
              args.checkpoint_dir or Path(args.out).parent / "checkpoints", args.threads)
    finally:
        torch.set_flush_denormal(False)


def train(config: Settings, cameras_path: Path, out: Path, checkpoint_dir: Path,
          threads: int | None = None) -> None:
    import torch

    from seathru.io.model import save_model
    from seathru.io.tracks import training_depth_observations
    from seathru.io.training import (CHECKPOINT_NAME, load_checkpoint, read_snapshots,
                                     read_training_inputs, save_checkpoint, write_log_csv,
                                     write_snapshots)
    from seathru.io.warnings import step_warning, write_warnings
    from seathru.io.water import WaterReport, write_water
    from seathru.nerf.device import check_training_memory, select_device
    from seathru.nerf.prepare import prepare_run, seed_everything
    from seathru.nerf.snapshots import QualitySnapshots
    from seathru.nerf.training import TrainCallbacks, Trainer

    device = select_device(config.device, threads)
    seed_everything(config.seed)
    cameras = read_cameras(cameras_path)
    train_frames, test_frames = cameras.split("train"), cameras.split("test")
    if not train_frames:
        raise PipelineError(f"{cameras_path}: no frame has split 'train'")
    if not test_frames:
        log.warning("%s: no test frames; the log has no held-out PSNR", cameras_path)
    check_training_memory(train_frames + test_frames, str(cameras_path))
    started = time.perf_counter()
    inputs = read_training_inputs(cameras, train_frames, test_frames, config.glare,
                                  config.frame_colour)
    snapshots = QualitySnapshots.from_full_images(test_frames, inputs.test_images,
                                                  config.quality_snapshot_downscale)
    try:
        prepared = prepare_run(config, cameras, train_frames, inputs.train_images,
                               inputs.train_masks, test_frames, inputs.test_images,
                               inputs.test_masks, device=device, track_change=inputs.track_change,
                               sparse_points=training_depth_observations(cameras)
                               if config.loss.sparse_depth_weight > 0 else None)
    except PipelineError as exc:
        raise PipelineError(f"{cameras_path}: {exc}") from None
    inputs.release_images()   # the training set holds the pixels it needs
    model, data, scene = prepared.model, prepared.data, prepared.model.scene
    log.info("%d training rays from %d images, %d test pixels; loaded in %.1f s; scene box %s "
             "to %s", len(data), len(train_frames), 0 if prepared.test is None else
             len(prepared.test), time.perf_counter() - started,
             [round(v, 3) for v in scene["box_min"]], [round(v, 3) for v in scene["box_max"]])

    checkpoint_path = Path(checkpoint_dir) / CHECKPOINT_NAME
    bar = _progress_bar(prepared.config) if config.progress else None

    def progress(step: int, stats: dict) -> None:
        if bar is not None:
            bar.n = step
            bar.set_postfix(loss=f"{stats['loss']:.4f}", psnr=f"{stats['psnr']:.2f}",
                            rays_s=f"{stats['rays_per_s']:.0f}", medium=stats["medium"],
                            refresh=False)
            bar.update(0)

    trainer = Trainer(model, data, prepared.test, TrainCallbacks(
        progress=progress, checkpoint=lambda state: save_checkpoint(checkpoint_path, state),
        message=log.info, quality_snapshot=lambda step, elapsed: snapshots.measure(
            model, step, elapsed) if test_frames else None), device=device, frames=train_frames)
    ckpt, why = load_checkpoint(checkpoint_path, model.config.identity(), scene, device)
    if ckpt is not None:
        trainer.load_checkpoint(ckpt)
        log.info("resuming from %s at step %d (%.0f s trained)", checkpoint_path, trainer.step,
                 trainer.elapsed_s)
        snapshots.rows = [r for r in read_snapshots(out) if r["step"] <= trainer.step]
    elif checkpoint_path.exists():
        log.info("%s: not resumed, starting fresh (%s)", checkpoint_path, why)
    try:
        if bar is not None:
            bar.n = trainer.step
            bar.refresh()
        result = trainer.run()
    finally:
        if bar is not None:
            bar.close()

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    export = {**model.export(), "glare": inputs.glare and inputs.glare.to_dict(), "training": {
        "steps": result.steps, "elapsed_s": result.elapsed_s, "stopped_by": result.stopped_by,
        "rollbacks": result.rollbacks, "final_test_psnr": result.final_test_psnr,
        "steps_per_s": result.train_step_rate, "rays_per_s": result.rays_per_second,
        "device": str(device), "threads": torch.get_num_threads()}}
    save_model(out / "model.pt", export)
    directions = data.fixed_subset(8192, config.seed + 4).directions
    trained_water = model.water_parameters(directions)
    report = WaterReport.from_parameters(trained_water, float(cameras.scale),
                                         trainer.assess_water(trained_water),
                                         cameras.metres_per_source_unit)
    write_water(out / "water.json", report)
    warnings = [step_warning("train", "water_undetermined", report.undetermined_message(),
                             parameters=report.undetermined)] if report.undetermined else []
    write_warnings(out / "warnings.json", warnings, log)
    write_log_csv(out / "train_log.csv", result.log)
    write_snapshots(out, snapshots.rows, snapshots.renders, snapshots.downscale)
    write_json(out / "selection.json", {**result.selection, "final_mode": model.medium.mode,
                                         "water_refits": trainer.water_refits,
                                         "view_dependent_colour": trainer.view_selection,
                                         **inputs.corrections(),
                                         "capacity": prepared.capacity,
                                         "far_factor": model.far_bound})
    test_text = "n/a" if result.final_test_psnr is None else f"{result.final_test_psnr:.2f} dB"
    log.info("trained %d steps in %.0f s (stopped by %s; %.1f steps/s, %.0f rays/s); held-out "
             "PSNR %s; medium %s", result.steps, result.elapsed_s, result.stopped_by,
             result.train_step_rate, result.rays_per_second, test_text, model.medium.mode)


def _progress_bar(config: Settings):
    from tqdm import tqdm

    # a log file (Snakemake's stderr) gets a line every 30 s; no total where time alone limits
    return tqdm(total=int(config.step_limit) if config.step_limit < float("inf") else None,
                desc="train", unit="step", dynamic_ncols=True,
                mininterval=1.0 if sys.stderr.isatty() else 30.0)
