"""The water refit against a variance-weighted one, and how much one draw of refit rays moves it.
A diagnostic, not a test.

The refit (``seathru.nerf.water_fit``) fits one clean colour per group of pixels. What a group's
pixels do not share (texture of a slightly different spot, a footprint averaging more or less of
it) is transmitted by the water like the signal, so it shrinks with range; with the clean colour
profiled out, such noise pulls the attenuation up (docs/water.md, "Noise that fades with range
pulls the attenuation up", which also says why it was not taken into the refit). The candidate here weights every pixel by the inverse of a variance
function of its predicted direct signal ``D = J exp(-sigma_attn z)``, ``s0^2 + v^2 D^2`` per
channel (robust variances of the residuals in bins of ``D^2``, a line through them), and fits the
clean colours and the water with those weights, three rounds (iteratively reweighted). No
dark-pixel bound in either fit.

Two parts:

- ``--truth DIR ...``: a simulated dive's own exact pixels (its cameras, true ranges, noise-free
  images with water): the refit unweighted, with its brightness weights (the default) and
  variance-weighted.
- ``--runs RUN ...``: a finished workflow run's last checkpoint (``results/<dataset>`` with
  ``checkpoints/checkpoint.pt``, default settings at 3 min): the final assessment's surfaces
  drawn with ``--rays`` refit rays and two seeds, the training's own fit (trimmed, dark-pixel
  bound) and the variance-weighted fit of the pixels it kept.

Usage::

    python benchmarks/bench_refit_variance.py --truth results/demo/simulate/truth \\
        --runs results/demo --out benchmarks/results/refit_variance.md
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import platform
import sys
from pathlib import Path

import numpy as np
import torch

from bench_refit_decoding import trained_run
from machine import cpu_name

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from seathru import settings  # noqa: E402
from seathru.io.cameras import read_cameras  # noqa: E402
from seathru.io.images import read_image  # noqa: E402
from seathru.io.tracks import training_depth_observations  # noqa: E402
from seathru.io.training import load_checkpoint, read_training_inputs  # noqa: E402
from seathru.io.water import read_truth_water  # noqa: E402
from seathru.nerf import water_fit, water_surfaces  # noqa: E402
from seathru.nerf.config import TrainConfig  # noqa: E402
from seathru.nerf.prepare import prepare_run, seed_everything  # noqa: E402
from seathru.nerf.rays import frame_rays  # noqa: E402
from seathru.nerf.training import Trainer  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "refit_variance.md"
KEYS = ("sigma_attn", "sigma_bs", "c_med")


def weighted_residuals(attn, bs, c_med, ranges, observed, ids, groups, weights):
    """(N, 3) residuals at each group's weighted best clean colour, and (N, 3) ``J T``."""
    ranges = ranges.clamp_max(1e6)
    transmitted = torch.exp(-attn * ranges[:, None])
    backscatter = c_med * (1.0 - torch.exp(-bs * ranges[:, None]))
    num = observed.new_zeros(groups, 3).index_add_(
        0, ids, weights * transmitted * (observed - backscatter))
    den = observed.new_zeros(groups, 3).index_add_(0, ids, weights * transmitted ** 2)
    clean = (num / den.clamp_min(1e-12)).clamp_min(0.0)
    direct = clean[ids] * transmitted
    return observed - direct - backscatter, direct


def fit_weighted(ranges, observed, ids, groups, start: dict, weights, colour_max=1.5,
                 steps=300) -> dict:
    """The water minimising the pixel-weighted squared residuals (L-BFGS, as ``fit_water``,
    run to the strict tolerances ``fit_water`` had before session 30, so that the comparison
    is not about where the fits stop)."""
    raw = water_fit.water_raw(start, colour_max)

    def objective():
        residual = weighted_residuals(*water_fit.water_of_raw(raw, colour_max), ranges,
                                      observed, ids, groups, weights)[0]
        return (residual ** 2 * weights).mean()

    water_fit.minimise_relative(raw, objective, steps, tolerance_change=1e-16,
                                tolerance_grad=1e-12)
    with torch.no_grad():
        return dict(zip(KEYS, (t.tolist() for t in water_fit.water_of_raw(raw, colour_max))))


def variance_weights(water: dict, ranges, observed, ids, groups, weights, bins: int = 12):
    """(N, 3) weights ``1 / (s0^2 + v^2 D^2)`` (mean 1 per channel) at ``water``, and (s0, v)
    per channel."""
    theta = [torch.tensor(water[k], dtype=torch.float64) for k in KEYS]
    residual, direct = weighted_residuals(*theta, ranges, observed, ids, groups, weights)
    out, noise = torch.empty_like(observed), []
    for channel in range(3):
        level, r = direct[:, channel] ** 2, residual[:, channel]
        edges = torch.quantile(level, torch.linspace(0, 1, bins + 1, dtype=torch.float64))
        xs, ys = [], []
        for low, high in zip(edges[:-1], edges[1:]):
            inside = (level >= low) & (level <= high)
            if int(inside.sum()) < 50:
                continue
            part = r[inside]
            xs.append(float(level[inside].mean()))
            ys.append(float((1.4826 * (part - part.median()).abs().median()) ** 2))
        x, y = torch.tensor(xs, dtype=torch.float64), torch.tensor(ys, dtype=torch.float64)
        line = torch.linalg.lstsq(torch.stack([torch.ones_like(x), x], 1), y[:, None]).solution
        s0 = max(float(line[0, 0]), 0.05 * float(y.min()))
        v2 = max(float(line[1, 0]), 0.0)
        noise.append((math.sqrt(s0), math.sqrt(v2)))
        out[:, channel] = 1.0 / (s0 + v2 * level)
    return out / out.mean(0), noise


def variance_weighted_fit(data, start: dict, rounds: int = 3):
    """The variance-weighted water of surface ``data`` (``water_surfaces.SurfaceData``) and its
    noise model."""
    ranges, observed = data.ranges.double(), data.observed.double()
    weights, water, noise = torch.ones_like(observed), start, []
    for _ in range(rounds):
        weights, noise = variance_weights(water, ranges, observed, data.ids, data.groups,
                                          weights)
        water = fit_weighted(ranges, observed, data.ids, data.groups, water, weights)
    return water, noise


def errors(water: dict, truth: dict, scale: float = 1.0) -> str:
    return " | ".join(", ".join(f"{100 * (v / scale / t - 1):+.1f}"
                                for v, t in zip(water[k], truth[k])) for k in KEYS[:2])


def exact_rows(truth_dir: Path, per_view: int, voxel: float) -> tuple[list[str], list[str]]:
    truth = read_truth_water(truth_dir / "water.json").as_dict()
    rng = np.random.default_rng(0)
    columns = {"origins": [], "directions": [], "ranges": [], "rgb": []}
    for frame in read_cameras(truth_dir / "cameras.json").split("train"):
        origins, directions = frame_rays(frame)
        depth = read_image(truth_dir / "depth" / f"{frame.name}.tiff").reshape(-1)
        image = read_image(truth_dir / "water" / f"{frame.name}.tiff")[..., :3].reshape(-1, 3)
        pick = rng.choice(len(depth), per_view, replace=False)
        columns["origins"].append(origins[pick].double())
        columns["directions"].append(directions[pick].double())
        columns["ranges"].append(torch.from_numpy(depth[pick].astype(np.float64)))
        columns["rgb"].append(torch.from_numpy(image[pick].astype(np.float64)))
    c = {k: torch.cat(v) for k, v in columns.items()}
    water = ~torch.isfinite(c["ranges"])
    data = water_surfaces.surface_data(c["origins"], c["directions"], c["rgb"],
                                  torch.where(water, torch.nan, c["ranges"]), (~water).double(),
                                  voxel, 0.9, open_water_opacity=0.5, open_water=water)
    start = {k: [0.2] * 3 for k in KEYS}
    name = truth_dir.parent.parent.name
    rows = []
    plain = water_fit.fit_water(data.ranges, data.observed, data.ids, data.groups, start,
                                balance_brightness=False)
    plain = {k: getattr(plain, k) for k in KEYS}
    bright = water_fit.fit_water(data.ranges, data.observed, data.ids, data.groups, start)
    weighted, noise = variance_weighted_fit(data, plain)
    for label, water in (("unweighted", plain), ("brightness weights (the refit's)",
                         {k: getattr(bright, k) for k in KEYS}),
                         ("variance-weighted", weighted)):
        rows.append(f"| {name} | {label} | {errors(water, truth)} |")
        print(rows[-1], flush=True)
    notes = [f"{name}: the variance function's s0, v (R; G; B): "
             + "; ".join(f"{s:.4f}, {v:.3f}" for s, v in noise)]
    return rows, notes


def trainer_at_checkpoint(run: Path) -> Trainer:
    """A trainer at a finished workflow run's last checkpoint (default settings, 3 min)."""
    config = settings.from_mapping(TrainConfig, {"max_minutes": 3.0, "progress": False})
    seed_everything(config.seed)
    cameras = read_cameras(run / "poses" / "cameras.json")
    train, test = cameras.split("train"), cameras.split("test")
    inputs = read_training_inputs(cameras, train, test, config.glare)
    prepared = prepare_run(config, cameras, train, inputs.train_images, inputs.train_masks,
                           test, inputs.test_images, inputs.test_masks,
                           track_change=inputs.track_change,
                           sparse_points=training_depth_observations(cameras))
    trainer = Trainer(prepared.model, prepared.data, prepared.test, device="cpu", frames=train)
    state, why = load_checkpoint(run / "checkpoints" / "checkpoint.pt",
                                 prepared.model.config.identity(), prepared.model.scene,
                                 torch.device("cpu"))
    if state is None:
        raise SystemExit(f"{run}: the checkpoint does not load ({why})")
    trainer.load_checkpoint(state)
    return trainer


def run_rows(run: Path, rays: list[int], seeds: list[int]) -> list[str]:
    scale, truth, _ = trained_run(run)
    trainer = trainer_at_checkpoint(run)
    rows = []
    for count in rays:
        medium = dataclasses.replace(trainer.config.medium, refit_rays=count)
        trainer.config = dataclasses.replace(trainer.config, medium=medium)
        for seed in seeds:
            data = trainer._surface_data(trainer.config.seed + seed)[0]
            fit, used = trainer._fit_surfaces(data, trainer.model.water_parameters())
            trained = {k: getattr(fit, k) for k in KEYS}
            weighted, _ = variance_weighted_fit(used, trained)
            for label, water in (("the refit's", trained), ("variance-weighted", weighted)):
                rows.append(f"| {run.name} | {count} | {seed} | {fit.pixels} | {fit.groups} | "
                            f"{label} | {errors(water, truth, scale)} |")
                print(rows[-1], flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--truth", nargs="*", type=Path, default=[])
    parser.add_argument("--runs", nargs="*", type=Path, default=[])
    parser.add_argument("--per-view", type=int, default=3200)
    parser.add_argument("--voxel", type=float, default=0.054,
                        help="exact part: voxel side, m (the demo's refit voxel)")
    parser.add_argument("--rays", type=int, nargs="+", default=[65536, 262144])
    parser.add_argument("--seeds", type=int, nargs="+", default=[97, 11])
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    torch.set_num_threads(2)
    lines = ["# The water refit against a variance-weighted one "
             "(`benchmarks/bench_refit_variance.py`)", "",
             f"Device: {cpu_name()}, torch {torch.__version__}, Python "
             f"{platform.python_version()}. Errors against the true water, %, R, G, B; no "
             "dark-pixel bound but where said.", ""]
    if args.truth:
        lines += [f"Exact pixels: {args.per_view} a training view, the dive's own cameras, "
                  f"true ranges, noise-free images, voxels of {args.voxel} m.", "",
                  "| dive | fit | sigma_attn | sigma_bs |", "|---|---|---|---|"]
        notes = []
        for truth in args.truth:
            rows, more = exact_rows(truth, args.per_view, args.voxel)
            lines += rows
            notes += more
        lines += [""] + [f"- {note}" for note in notes] + [""]
    if args.runs:
        lines += ["Final surfaces of trained runs (the final assessment's pixels at each ray "
                  "count and seed; the refit's fit is trimmed, with its dark-pixel bound):", "",
                  "| run | refit rays | seed | pixels | groups | fit | sigma_attn | sigma_bs |",
                  "|---|---|---|---|---|---|---|---|"]
        for run in args.runs:
            lines += run_rows(run, args.rays, args.seeds)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
