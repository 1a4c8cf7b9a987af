"""Train the SeaThru-NeRF model of one dataset (object field + water), resumable.

Reads ``--cameras`` (cameras.json; its frames' linear images and optional masks), trains on
the 'train' split and measures the PSNR on pixels of the 'test' split at log-spaced steps.
Writes to ``--out``: ``model.pt`` (``torch.load(weights_only=True)``-safe: format, config,
state_dict, scene), ``water.json`` (fitted water per channel, normalised and per source unit),
``train_log.csv`` (step, wall_time_s, loss, train_psnr, test_psnr) and ``selection.json`` (the
water model chosen and why). Checkpoints go to ``--checkpoint-dir`` (keep it outside the
outputs); a run that finds a checkpoint with the same settings there resumes from it.

Training stops at ``--steps`` or after ``--max-minutes``, whichever comes first; the schedules
follow whichever is closer to its end, so a run cut short by time still converges.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import logging
import math
import os
import sys
import time
from dataclasses import fields
from pathlib import Path

import numpy as np

# Idle OpenMP threads sleep instead of spinning: on a shared machine spinning threads steal the
# cores the other thread waits for. Effective only if torch is not imported yet.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from seathru.errors import PipelineError
from seathru.io.atomic import atomic_path, write_json, write_text
from seathru.io.cameras import CameraSet, read_cameras
from seathru.io.images import read_image, read_mask

log = logging.getLogger(__name__)

# Rays per step on CUDA: on an H200 1024 rays ran 64 steps/s and 4096 rays 52 steps/s (4x the
# rays for 20% fewer steps), reaching the paper configuration's PSNR 22x instead of 15x sooner.
GPU_BATCH_RAYS = 4096

CHECKPOINT_NAME = "checkpoint.pt"
LOG_COLUMNS = ("step", "wall_time_s", "loss", "train_psnr", "test_psnr")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from seathru.nerf.model import ModelConfig

    d = ModelConfig()
    parser.add_argument("--cameras", required=True, type=Path, help="cameras.json to train on")
    parser.add_argument("--out", required=True, type=Path,
                        help="output folder: model.pt, water.json, train_log.csv, selection.json")
    parser.add_argument("--checkpoint-dir", type=Path, default=None,
                        help="checkpoints (resume after a kill); default: OUT/../checkpoints")
    parser.add_argument("--steps", type=int, default=d.steps,
                        help=f"maximum optimisation steps (default {d.steps})")
    parser.add_argument("--max-minutes", type=float, default=d.max_minutes,
                        help="wall-time budget in minutes; training stops gracefully and writes "
                             f"its outputs (default {d.max_minutes}; 0 = no limit)")
    parser.add_argument("--batch-rays", type=int, default=None,
                        help=f"rays per step (default {d.batch_rays} on CPU, {GPU_BATCH_RAYS} on "
                             "CUDA, where smaller batches leave the GPU idle: "
                             "benchmarks/results/training_h200*.md)")
    parser.add_argument("--lr", type=float, default=d.lr,
                        help=f"base learning rate of the feature grids (default {d.lr})")
    parser.add_argument("--medium", choices=("auto", "off", "global", "view"), default=d.medium,
                        help="water model: auto (pick the simplest the images support), off "
                             "(clear water / air), global (one per scene), view (depends on the "
                             "view direction, as the paper)")
    parser.add_argument("--view-dependent-colour", action=argparse.BooleanOptionalAction,
                        default=d.view_dependent_colour,
                        help="object colour depends on the view direction")
    parser.add_argument("--transmittance-prior-weight", type=float,
                        default=d.transmittance_prior_weight,
                        help="weight of -log P(T_obj), T_obj pushed to 0 or 1 (default "
                             f"{d.transmittance_prior_weight})")
    parser.add_argument("--samples-per-ray", type=int, default=d.samples_per_ray,
                        help=f"object samples per ray (default {d.samples_per_ray})")
    parser.add_argument("--seed", type=int, default=d.seed, help="random seed")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    parser.add_argument("--device", default="auto", help="auto | cpu | cuda[:N]")
    parser.add_argument("--log-every", type=int, default=d.log_every,
                        help=f"steps between train_log rows (default {d.log_every})")
    parser.add_argument("--checkpoint-every", type=int, default=d.checkpoint_every,
                        help=f"steps between checkpoints (default {d.checkpoint_every}; 0 = "
                             "only at the end)")
    parser.add_argument("--eval-rays", type=int, default=d.eval_rays,
                        help="held-out test pixels used for the PSNR in the log")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="any other ModelConfig field (JSON value), e.g. --set "
                             "samples_per_ray=24 --set field='\"mlp\"'")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def build_config(args: argparse.Namespace, device_type: str = "cpu"):
    from seathru.nerf.model import ModelConfig

    known = {f.name: f for f in fields(ModelConfig)}
    values = {"steps": args.steps, "max_minutes": args.max_minutes,
              "batch_rays": args.batch_rays if args.batch_rays is not None else
              (GPU_BATCH_RAYS if device_type == "cuda" else ModelConfig.batch_rays),
              "lr": args.lr, "medium": args.medium,
              "view_dependent_colour": bool(args.view_dependent_colour),
              "transmittance_prior_weight": args.transmittance_prior_weight,
              "samples_per_ray": args.samples_per_ray, "seed": args.seed,
              "log_every": args.log_every, "checkpoint_every": args.checkpoint_every,
              "eval_rays": args.eval_rays}
    for item in args.set:
        key, sep, raw = item.partition("=")
        key = key.strip().replace("-", "_")
        if not sep or key not in known:
            raise PipelineError(f"--set {item!r}: expected KEY=VALUE with KEY one of "
                                f"{', '.join(sorted(known))}")
        try:
            values[key] = json.loads(raw)
        except json.JSONDecodeError:
            values[key] = raw  # a bare string
    config = ModelConfig(**values)
    try:
        config.validate()
    except ValueError as exc:
        raise PipelineError(f"invalid training settings: {exc}") from None
    return config


def _device(name: str):
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError as exc:
        raise PipelineError(f"--device {name!r} is not a torch device ({exc})") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise PipelineError(f"--device {name}: no CUDA device is available; use cpu or auto")
    return device


def load_split(cameras: CameraSet, frames) -> tuple[list, list]:
    """Images (and masks) of ``frames``, checked against the camera file."""
    images, masks = [], []
    for frame in frames:
        path = cameras.image_path(frame)
        image = read_image(path)
        if image.ndim != 3 or image.shape[2] < 3:
            raise PipelineError(f"{path}: expected an RGB image, found shape {image.shape}")
        image = image[..., :3]
        if image.shape[:2] != (frame.height, frame.width):
            raise PipelineError(f"{path}: image is {image.shape[1]}x{image.shape[0]} but "
                                f"{cameras.root}/cameras.json says {frame.width}x{frame.height}")
        mask = None
        mask_path = cameras.mask_path(frame)
        if mask_path is not None:
            mask = read_mask(mask_path)
            if mask.ndim == 3:
                mask = mask[..., 0]
            if mask.shape != image.shape[:2]:
                raise PipelineError(f"{mask_path}: mask is {mask.shape[1]}x{mask.shape[0]}, its "
                                    f"image {image.shape[1]}x{image.shape[0]}")
        images.append(image)
        masks.append(mask)
    return images, masks


def _checkpoint_matches(ckpt: dict, config, scene: dict) -> str | None:
    """None if ``ckpt`` can be resumed with these settings, else the reason it cannot."""
    from seathru.nerf.model import ModelConfig
    from seathru.nerf.training import CHECKPOINT_FORMAT

    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        return f"not a {CHECKPOINT_FORMAT} file"
    theirs = ModelConfig.from_dict(ckpt.get("config", {})).identity()
    ours = config.identity()
    changed = sorted(k for k in ours if theirs.get(k) != ours[k])
    if changed:
        return "settings changed: " + ", ".join(
            f"{k} {theirs.get(k)!r} -> {ours[k]!r}" for k in changed[:6])
    if json.dumps(ckpt.get("scene"), sort_keys=True) != json.dumps(scene, sort_keys=True):
        return "the camera file (scene box or normalisation) changed"
    return None


def write_log_csv(path: Path, rows: list[dict]) -> None:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(LOG_COLUMNS)
    for row in rows:
        out = []
        for key in LOG_COLUMNS:
            value = row.get(key)
            if value is None or (isinstance(value, float) and not math.isfinite(value)):
                out.append("")
            elif isinstance(value, float):
                out.append(f"{value:.6g}")
            else:
                out.append(str(value))
        writer.writerow(out)
    write_text(path, buffer.getvalue())


def water_report(model, scale: float, directions=None) -> dict:
    """water.json: fitted water per channel, normalised units and per source unit."""
    params = model.water_parameters(directions)
    mode = params["mode"]

    def per_source(values):
        return [float(v) * scale for v in values]

    report = {
        "mode": mode,
        "units": ("sigma_attn and sigma_bs: 1/(source unit) = normalised value * scale "
                  "(metres for simulated data); c_med: linear radiance of the training images"),
        "scale": scale,
        "sigma_attn": per_source(params["sigma_attn"]),
        "sigma_bs": per_source(params["sigma_bs"]),
        "c_med": params["c_med"],
        "normalised": {k: params[k] for k in ("sigma_attn", "sigma_bs", "c_med")},
        "per_source_unit": {k: per_source(params[k]) for k in ("sigma_attn", "sigma_bs")},
    }
    if mode == "view":
        report["note"] = ("view-dependent water: values are the mean over training rays; "
                          "min and max over the same rays")
        for bound in ("min", "max"):
            report[f"normalised_{bound}"] = params[bound]
            report[f"{bound}"] = {"sigma_attn": per_source(params[bound]["sigma_attn"]),
                                  "sigma_bs": per_source(params[bound]["sigma_bs"]),
                                  "c_med": params[bound]["c_med"]}
    return report


def run(args: argparse.Namespace) -> None:
    import torch

    # exp(-large) underflows to denormals, 10x slower on CPU; the flag is process-wide, so it
    # is switched off again for whoever calls this step in-process (tests, notebooks).
    torch.set_flush_denormal(True)
    try:
        _train(args)
    finally:
        torch.set_flush_denormal(False)


def _train(args: argparse.Namespace) -> None:
    import torch

    from seathru.nerf.model import SeaThruModel, build_scene
    from seathru.nerf.rays import RayDataset
    from seathru.nerf.training import TrainCallbacks, Trainer

    device = _device(args.device)
    config = build_config(args, device.type)
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(config.seed)
    np.random.seed(config.seed)

    cameras = read_cameras(args.cameras)
    train_frames, test_frames = cameras.split("train"), cameras.split("test")
    if not train_frames:
        raise PipelineError(f"{args.cameras}: no frame has split 'train'")
    started = time.perf_counter()
    images, masks = load_split(cameras, train_frames)
    data = RayDataset(train_frames, images, masks, device=device)
    del images
    if len(data) == 0:
        raise PipelineError(f"{args.cameras}: the training images have no valid pixel (masks?)")
    if data.dropped_nonfinite:
        log.warning("%d training pixels are NaN/Inf and are left out", data.dropped_nonfinite)
    test = None
    if test_frames:
        test_images, test_masks = load_split(cameras, test_frames)
        test = RayDataset(test_frames, test_images, test_masks).fixed_subset(
            config.eval_rays, config.seed + 3)
    else:
        log.warning("%s: no test frames; the log has no held-out PSNR", args.cameras)
    rgb = data.rays.rgb
    high = float(torch.quantile(rgb[torch.randperm(len(rgb))[:200000].to(rgb.device)].float(),
                                0.999))
    config.colour_max = max(config.colour_max, round(2.0 * high, 3))
    scene = build_scene(train_frames, cameras.near, cameras.far, cameras.centre, cameras.scale,
                        rgb.mean(0).tolist())
    log.info("%d training rays from %d images, %d test pixels; loaded in %.1f s; scene box %s "
             "to %s", len(data), len(train_frames), 0 if test is None else len(test),
             time.perf_counter() - started, [round(v, 3) for v in scene["box_min"]],
             [round(v, 3) for v in scene["box_max"]])

    model = SeaThruModel(config, scene).to(device)
    checkpoint_dir = args.checkpoint_dir or (Path(args.out).parent / "checkpoints")
    checkpoint_path = Path(checkpoint_dir) / CHECKPOINT_NAME

    def save_checkpoint(state: dict) -> None:
        with atomic_path(checkpoint_path) as tmp:
            torch.save(state, tmp)

    bar = None
    if not args.no_progress:
        from tqdm import tqdm
        # a log file (Snakemake redirects stderr) gets one line every 30 s, a terminal every 1 s
        interactive = sys.stderr.isatty()
        bar = tqdm(total=config.steps, desc="train", unit="step", dynamic_ncols=True,
                   mininterval=1.0 if interactive else 30.0)

    def progress(step: int, stats: dict) -> None:
        if bar is not None:
            bar.n = step
            bar.set_postfix(loss=f"{stats['loss']:.4f}", psnr=f"{stats['psnr']:.2f}",
                            rays_s=f"{stats['rays_per_s']:.0f}", medium=stats["medium"],
                            refresh=False)
            bar.update(0)

    def message(text: str) -> None:
        if bar is not None:
            bar.write(text)
        log.info("%s", text)

    trainer = Trainer(model, data, test, TrainCallbacks(
        progress=progress, checkpoint=save_checkpoint, message=message), device=device,
        frames=train_frames)
    if checkpoint_path.exists():
        try:
            ckpt = torch.load(checkpoint_path, map_location=device, weights_only=True)
            why = _checkpoint_matches(ckpt, config, scene)
        except Exception as exc:  # truncated or foreign file
            ckpt, why = None, f"unreadable ({exc})"
        if why is None:
            trainer.load_checkpoint(ckpt)
            message(f"resuming from {checkpoint_path} at step {trainer.step} "
                    f"({trainer.elapsed_s:.0f} s trained)")
        else:
            message(f"{checkpoint_path}: not resumed, starting fresh ({why})")
    if bar is not None:
        bar.n = trainer.step
        bar.refresh()
    try:
        result = trainer.run()
    finally:
        if bar is not None:
            bar.close()

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    export = model.export()
    export["training"] = {"steps": result.steps, "elapsed_s": result.elapsed_s,
                          "stopped_by": result.stopped_by, "rollbacks": result.rollbacks,
                          "final_test_psnr": result.final_test_psnr,
                          "steps_per_s": result.train_step_rate,
                          "rays_per_s": result.rays_per_second, "device": str(device),
                          "threads": torch.get_num_threads()}
    with atomic_path(out / "model.pt") as tmp:
        torch.save(export, tmp)
    directions = data.fixed_subset(8192, config.seed + 4).directions
    water = water_report(model, float(cameras.scale), directions)
    write_json(out / "water.json", water)
    write_log_csv(out / "train_log.csv", result.log)
    selection = dict(result.selection)
    selection["final_mode"] = model.medium.mode
    write_json(out / "selection.json", selection)
    test_text = "n/a" if result.final_test_psnr is None else f"{result.final_test_psnr:.2f} dB"
    log.info("trained %d steps in %.0f s (stopped by %s; %.1f steps/s, %.0f rays/s); held-out "
             "PSNR %s; medium %s", result.steps, result.elapsed_s, result.stopped_by,
             result.train_step_rate, result.rays_per_second, test_text, model.medium.mode)
