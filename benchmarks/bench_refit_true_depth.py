"""A water refit on the model's depth against the same refit on the true depth (simulated dives).

A diagnostic, not a test. For trained runs of a simulated dive (each ``RUN/train/model.pt`` with
``RUN/evaluate/summary.json`` for the metric scale), training pixels are rendered with the model
and given two ranges: the model's median depth and the simulator's true range of the same pixel
(the truth camera's pixel that sees the same direction). The refit of the training step
(``water_surfaces.surface_data`` and ``fit_water``) is run on each, without the dark-pixel bound,
with the bound from every surface pixel (what ``surface_data`` takes without open water) and with
the bound from the pixels of surfaces several views place alike (what it takes with open water).
Open water here is the pixels with no true surface (the training step takes it from the
photographs). Where the true depth gives the same water with and without a bound, a bound that
moves the model-depth fit comes from depth error.
Usage::

    python benchmarks/bench_refit_true_depth.py --cameras results/demo/poses/cameras.json \\
        --truth results/demo/simulate/truth RUN [RUN ...]

Writes ``benchmarks/results/refit_true_depth.md``.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path

import numpy as np
import torch

from machine import cpu_name

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from seathru.io.cameras import read_cameras  # noqa: E402
from seathru.io.images import read_image  # noqa: E402
from seathru.io.model import load_model  # noqa: E402
from seathru.io.water import read_truth_water  # noqa: E402
from seathru.nerf import water_fit, water_surfaces  # noqa: E402
from seathru.nerf.rays import frame_rays  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "refit_true_depth.md"


def true_ranges(frame, truth_frame, depth_path: Path) -> np.ndarray:
    """(H*W,) true range of each pixel of ``frame`` (normalised cameras may be cropped and
    rescaled by the poses step): the truth camera's pixel on the same direction."""
    depth = read_image(depth_path)
    rows, cols = np.meshgrid(np.arange(frame.height), np.arange(frame.width), indexing="ij")
    x, y = (cols + 0.5 - frame.cx) / frame.fx, (rows + 0.5 - frame.cy) / frame.fy
    u = np.clip(np.floor(truth_frame.fx * x + truth_frame.cx).astype(int), 0,
                truth_frame.width - 1)
    v = np.clip(np.floor(truth_frame.fy * y + truth_frame.cy).astype(int), 0,
                truth_frame.height - 1)
    return depth[v, u].reshape(-1).astype(np.float64)


def rays_of_run(model, cameras, truth: Path, per_view: int, seed: int):
    truth_frames = {f.name: f for f in read_cameras(truth / "cameras.json").frames}
    rng = np.random.default_rng(seed)
    parts = {k: [] for k in ("origins", "directions", "rgb", "model", "opacity", "true")}
    for frame in cameras.split("train"):
        origins, directions = frame_rays(frame)
        image = read_image(cameras.image_path(frame))[..., :3].reshape(-1, 3)
        ranges = true_ranges(frame, truth_frames[frame.name],
                             truth / "depth" / f"{frame.name}.tiff")
        pick = torch.from_numpy(rng.choice(len(ranges), per_view, replace=False))
        count = len(pick)
        with torch.no_grad():
            render = model(origins[pick], directions[pick], torch.full((count,), frame.near),
                           torch.full((count,), frame.far)).render
        parts["origins"].append(origins[pick].double())
        parts["directions"].append(directions[pick].double())
        parts["rgb"].append(torch.from_numpy(image[pick.numpy()]).double())
        parts["model"].append(render.depth_median.double())
        parts["opacity"].append(render.opacity.double())
        parts["true"].append(torch.from_numpy(ranges[pick.numpy()]))
    return {k: torch.cat(v) for k, v in parts.items()}


def bound_from_every_pixel(rays, depth, opacity, open_water, voxel: float):
    """The bound ``surface_data`` takes where no open water is used: from every surface pixel."""
    return water_surfaces.surface_data(rays["origins"], rays["directions"], rays["rgb"], depth,
                                  opacity, voxel, 0.9, open_water_opacity=0.0,
                                  open_water=open_water).dark


def refits(rays, scale: float, model, start: dict) -> dict:
    """{depth name: {variant: WaterFit}} and the depth ratio statistics."""
    open_water = ~torch.isfinite(rays["true"])
    true_depth = torch.where(open_water, torch.nan, rays["true"] / scale)
    diagonal = float(torch.linalg.norm(model.box.box_max - model.box.box_min))
    results = {}
    for name, depth, opacity in (("model", rays["model"], rays["opacity"]),
                                 ("true", true_depth, (~open_water).double())):
        data = water_surfaces.surface_data(rays["origins"], rays["directions"], rays["rgb"], depth,
                                      opacity, 0.005 * diagonal, 0.9, open_water_opacity=0.5,
                                      open_water=open_water)
        args = (data.ranges, data.observed, data.ids, data.groups, start, 300,
                model.medium.colour_max)
        results[name] = {
            "no bound": water_fit.fit_water(*args),
            "bound, every surface pixel": water_fit.fit_water(
                *args, bound_from_every_pixel(rays, depth, opacity, open_water,
                                              0.005 * diagonal)),
            "bound, surfaces placed alike (default)": water_fit.fit_water(*args, data.dark)}
    surface = ~open_water & (rays["opacity"] > 0.9) & torch.isfinite(rays["model"])
    ratio = (rays["model"][surface] / true_depth[surface]).numpy()
    return results, ratio


def exact_depth_fits(truth: Path, per_view: int, noise_levels=(0.0, 0.05)) -> list[str]:
    """Table rows: the refit on the simulator's own water images and exact ranges (no pose
    estimate, no model), with the ranges multiplied by log-normal noise of each level; with
    noise, also without the dark-pixel bound, and with the voxel groups formed on the true
    points while the regression sees the noisy ranges (no bound), which separates the error the
    grouping brings from the error in the regressor."""
    cameras = read_cameras(truth / "cameras.json")
    water_truth = read_truth_water(truth / "water.json").as_dict()
    rng = np.random.default_rng(0)
    origins, directions, ranges, observed = [], [], [], []
    for frame in cameras.split("train"):
        frame_origins, frame_directions = frame_rays(frame)
        depth = read_image(truth / "depth" / f"{frame.name}.tiff").reshape(-1)
        image = read_image(truth / "water" / f"{frame.name}.tiff")[..., :3].reshape(-1, 3)
        pick = rng.choice(len(depth), per_view, replace=False)
        origins.append(frame_origins[pick].double())
        directions.append(frame_directions[pick].double())
        ranges.append(torch.from_numpy(depth[pick].astype(np.float64)))
        observed.append(torch.from_numpy(image[pick].astype(np.float64)))
    origins, directions = torch.cat(origins), torch.cat(directions)
    ranges, observed = torch.cat(ranges), torch.cat(observed)
    open_water = ~torch.isfinite(ranges)
    start = {"sigma_attn": 0.2, "sigma_bs": 0.2, "c_med": 0.2}

    def data_for(depth):
        return water_surfaces.surface_data(origins, directions, observed, depth,
                                      (~open_water).double(), 0.02, 0.9,
                                      open_water_opacity=0.5, open_water=open_water)

    def row(level: float, variant: str, data, dark: bool) -> str:
        if isinstance(data, str):
            return f"| {100 * level:.0f}% | {variant} | {data} | |"
        fit = water_fit.fit_water(data.ranges, data.observed, data.ids, data.groups, start,
                                  dark=data.dark if dark else None)
        errors = [", ".join(f"{100 * (value / true - 1):+.0f}" for value, true
                            in zip(getattr(fit, key), water_truth[key]))
                  for key in ("sigma_attn", "sigma_bs")]
        line = f"| {100 * level:.0f}% | {variant} | {errors[0]} | {errors[1]} |"
        print(line, flush=True)
        return line

    rows = []
    exact = data_for(torch.where(open_water, torch.nan, ranges))
    for level in noise_levels:
        noise = torch.from_numpy(np.random.default_rng(1).standard_normal(len(ranges)))
        noisy = data_for(torch.where(open_water, torch.nan, ranges * torch.exp(level * noise)))
        rows.append(row(level, "on the noisy points, dark-pixel bound (the refit)", noisy, True))
        if level > 0:
            rows.append(row(level, "on the noisy points, no bound", noisy, False))
            if not isinstance(exact, str):
                # the same groups as exact ranges give, each pixel's range given the noise
                pixel_noise = torch.from_numpy(
                    np.random.default_rng(2).standard_normal(len(exact.ranges)))
                regressor = torch.where(torch.isfinite(exact.ranges),
                                        exact.ranges * torch.exp(level * pixel_noise),
                                        exact.ranges)
                exact_groups = water_surfaces.SurfaceData(regressor, exact.observed, exact.ids,
                                                     exact.groups, exact.dark)
                rows.append(row(level, "on the true points, no bound", exact_groups, False))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--cameras", type=Path, required=True)
    parser.add_argument("--truth", type=Path, required=True)
    parser.add_argument("--per-view", type=int, default=3200)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    torch.set_num_threads(1)
    cameras = read_cameras(args.cameras)
    truth = read_truth_water(args.truth / "water.json").as_dict()
    lines = ["# The water refit on the model's depth and on the true depth "
             "(`benchmarks/bench_refit_true_depth.py`)", "",
             f"Device: {cpu_name()}, 1 thread, torch {torch.__version__}, Python "
             f"{platform.python_version()}. Camera set `{args.cameras}`, truth `{args.truth}`; "
             f"{args.per_view} pixels from each training view, rendered with each run's model; "
             "the refit of the training step (started at the model's water) on the model's "
             "median depth and on the true range of the same pixels. Errors against the true "
             "water, per channel (R, G, B), %; `c_med` is not compared (training images are "
             "white-balanced), it is the same in every fit (the open water pins it).", "",
             "| run | model depth / true: median, robust spread, 5-95% | depth | fit | "
             "sigma_attn error | sigma_bs error |", "|---|---|---|---|---|---|"]
    for run in args.runs:
        summary = json.loads((run / "evaluate" / "summary.json").read_text())
        scale = float(summary["truth"]["metric_scale"]["scale"])
        model = load_model(run / "train" / "model.pt", torch.device("cpu"))
        model.eval()
        rays = rays_of_run(model, cameras, args.truth, args.per_view, seed=0)
        results, ratio = refits(rays, scale, model, model.water_parameters())
        log_ratio = np.log(ratio)
        spread = 1.4826 * np.median(np.abs(log_ratio - np.median(log_ratio)))
        quantiles = np.percentile(ratio, [5, 95])
        depth_note = (f"{np.median(ratio):.3f}, {100 * spread:.1f}%, "
                      f"{quantiles[0]:.2f}-{quantiles[1]:.2f}")
        for depth_name, fits in results.items():
            for variant, fit in fits.items():
                errors = [", ".join(f"{100 * (value / scale / true - 1):+.0f}" for value, true
                                    in zip(getattr(fit, key), truth[key]))
                          for key in ("sigma_attn", "sigma_bs")]
                lines.append(f"| {run.name} | {depth_note} | {depth_name} | {variant} | "
                             f"{errors[0]} | {errors[1]} |")
                print(lines[-1], flush=True)
    lines += ["", "The same refit on the simulator's own water images and exact ranges (metres; "
              "8000 pixels a view, voxels of 0.02 m), the ranges multiplied by "
              "log-normal noise; voxel groups formed on the noisy points (as the training "
              "step forms them on the model's depth) or on the true points:", "",
              "| range noise | groups | sigma_attn error | sigma_bs error |",
              "|---|---|---|---|"] + exact_depth_fits(args.truth, 8000)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
