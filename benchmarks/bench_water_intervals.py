"""Do the water fit's 95% intervals hold the truth? Curvature against robust, side by side.

The water fitted to surfaces seen at several ranges (``seathru.nerf.water_fit``) comes with
95% half-widths, either from the curvature of the profile loss (``laplace_halfwidths``) or
cluster-robust with a between-part systematic term (``robust_halfwidths``). Two checks:

1. Synthetic surfaces with a known water (cheap, a minute): independent pixel noise, and the
   errors a NeRF's geometry makes -- each surface's depth off by 5% (one error per voxel),
   each surface's colour off (texture), far surfaces placed up to 10% short, floaters (5% of
   pixels at 20-70% of their range). Each over ``--seeds`` draws.
2. ``--work DIR`` (a ``bench_water.py`` work folder with trained models): every model's own
   surfaces, rebuilt as the train step's final water assessment builds them (its training
   rays, median depth, opacity, voxels, open water and dark-pixel bound), fitted, and the
   intervals checked against the simulator's truth: centred on that fit, and centred on the
   trained value widened by its distance to the fit (what ``water.json`` reports).

    python benchmarks/bench_water_intervals.py [--seeds 40] [--work /tmp/bench_water]

Writes benchmarks/results/water_intervals.md (and .json with every number).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from machine import cpu_name, load_average

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
RESULTS = REPO / "benchmarks" / "results" / "water_intervals.md"
KEYS = ("sigma_attn", "sigma_bs", "c_med")
TRUE = {"sigma_attn": [0.55, 0.25, 0.20], "sigma_bs": [0.45, 0.30, 0.25],
        "c_med": [0.08, 0.20, 0.30]}
SCENARIOS = {
    "independent noise": {},
    "independent noise + open water": {"water": 300},
    "depth off 5% per surface": {"depth_sd": 0.05},
    "colour off per surface": {"colour_sd": 0.03, "noise": 0.003},
    "floaters (5% of pixels)": {"floaters": 0.05},
    "far surfaces up to 10% short": {"far_bias": 0.10},
    # texture each pixel sees at its own spot, transmitted like the signal: fitted with the
    # incidental term (train.medium.refit_noise_term), the parts refitted with it as the robust
    # intervals do since session 44, and without it as they did before
    "texture fading with range, term": {"texture": 0.3, "noise": 0.003, "noise_term": True},
    "texture fading with range, term; parts refitted without it": {
        "texture": 0.3, "noise": 0.003, "noise_term": True, "parts_plain": True},
}


def synthetic(rng: np.random.Generator, groups: int = 150, per_group: int = 8,
              noise: float = 0.01, depth_sd: float = 0.0, colour_sd: float = 0.0,
              far_bias: float = 0.0, floaters: float = 0.0, water: int = 0,
              texture: float = 0.0):
    """Surfaces at 0.5-8 m under TRUE water, and the ranges a model with the given errors
    would give them: (ranges, observed, ids, groups) as float64 / long tensors."""
    clean = rng.uniform(0.05, 0.9, (groups, 3))
    ids = np.repeat(np.arange(groups), per_group)
    z = rng.uniform(0.5, 8.0, ids.size)
    attn, bs, c_med = (np.array(TRUE[k]) for k in KEYS)
    observed = clean[ids] * np.exp(-attn * z[:, None]) + c_med * (1 - np.exp(-bs * z[:, None]))
    observed += noise * rng.standard_normal(observed.shape)
    observed += colour_sd * rng.standard_normal((groups, 3))[ids] * np.exp(-attn * z[:, None])
    observed += texture * clean[ids] * rng.standard_normal(observed.shape) \
        * np.exp(-attn * z[:, None])
    model_z = z * (1 + depth_sd * rng.standard_normal(groups))[ids]
    model_z = model_z * (1 - far_bias * np.clip((model_z - 4.0) / 4.0, 0.0, None))
    floater = rng.random(ids.size) < floaters
    model_z[floater] *= rng.uniform(0.2, 0.7, int(floater.sum()))
    if water:
        model_z = np.concatenate([model_z, np.full(water, np.inf)])
        ids = np.concatenate([ids, np.full(water, groups)])
        observed = np.concatenate([observed, c_med + noise * rng.standard_normal((water, 3))])
        groups += 1
    return (torch.from_numpy(model_z), torch.from_numpy(observed), torch.from_numpy(ids),
            groups)


def median_relative(halfwidth: dict, centre: dict) -> float:
    """Median over the 9 parameters of the half-width as a share of the value."""
    return float(np.median([h / abs(c) for k in KEYS for h, c in zip(halfwidth[k], centre[k])]))


def covered(centre: dict, halfwidth: dict, truth: dict) -> list[bool]:
    return [bool(abs(c - t) <= h) for k in KEYS
            for c, h, t in zip(centre[k], halfwidth[k], truth[k])]


def synthetic_check(seeds: int) -> list[dict]:
    from seathru.nerf.water_fit import fit_water
    from seathru.nerf.water_uncertainty import laplace_halfwidths, robust_halfwidths

    rows = []
    for name, options in SCENARIOS.items():
        counts = {"curvature": [], "robust": []}
        determined, seconds, relative = [], [], []
        options = dict(options)
        noise_term, parts_plain = options.pop("noise_term", False), options.pop("parts_plain",
                                                                                False)
        for seed in range(seeds):
            data = synthetic(np.random.default_rng(seed), **options)
            fit = fit_water(*data, {"sigma_attn": 0.3, "sigma_bs": 0.3, "c_med": 0.3},
                            noise_term=noise_term)
            centre = {k: getattr(fit, k) for k in KEYS}
            started = time.perf_counter()
            robust = robust_halfwidths(replace(fit, unshared=None) if parts_plain else fit,
                                       *data)
            seconds.append(time.perf_counter() - started)
            relative += [h / abs(c) for k in KEYS
                         for h, c in zip(robust.halfwidth[k], centre[k])]
            counts["robust"] += covered(centre, robust.halfwidth, TRUE)
            counts["curvature"] += covered(centre, laplace_halfwidths(fit, *data).halfwidth,
                                           TRUE)
            determined += [d for k in KEYS for d in robust.determined[k]]
        rows.append({"scenario": name, "intervals": len(counts["robust"]),
                     **{m: float(np.mean(v)) for m, v in counts.items()},
                     "robust_determined": float(np.mean(determined)),
                     "robust_relative_halfwidth": float(np.median(relative)),
                     "robust_seconds": float(np.median(seconds))})
        print(rows[-1], flush=True)
    return rows


def trained_dive(sim: Path, train: Path):
    """A trained model of a simulated dive with its training views as training reads them:
    (model, cameras, training frames, images, masks, open-water masks, open water in view)."""
    from seathru.io.cameras import read_cameras
    from seathru.io.model import load_model
    from seathru.io.training import read_frame_images
    from seathru.nerf.prepare import open_water_in_view

    model = load_model(train / "model.pt")
    cameras = read_cameras(sim / "truth" / "cameras.json")
    frames = cameras.split("train")
    images, masks = read_frame_images(cameras, frames)
    water_masks, _, in_view = open_water_in_view(model.config, images, masks)
    return model, cameras, frames, images, masks, water_masks, in_view


def model_surfaces(sim: Path, train: Path, regroup: bool = False, up_now: bool = False,
                   open_water_surfaces: bool | None = None):
    """The surface data of a trained model as its final water assessment builds it (all
    training rays, not less the medium-selection hold-out; open water from the photographs
    where in view, and whether it looks below the horizon), its model and the truth (in
    normalised units). Returns (data or reason, model, truth, trained water, scale, with
    ``regroup`` the same pixels grouped at each of the model's
    ``medium.interval_voxel_factors`` times the refit voxel, else []). ``up_now``: the
    vertical estimated from the training cameras by this code (``geometry.upright``), as a
    model trained now would hold it, instead of the one the model was saved with.
    ``open_water_surfaces``: whether the photographs' open water the model renders as a near
    surface is that surface (``water_surfaces.surface_data``; None: as the model's config
    says at the end of a run)."""
    from seathru.io.water import read_truth_water, read_water
    from seathru.nerf.rays import RayDataset
    from seathru.nerf.water_refit import below_horizon, refit_open_water_opacity
    from seathru.nerf.water_surfaces import surface_data

    model, cameras, frames, images, masks, water_masks, in_view = trained_dive(sim, train)
    config = model.config
    rays = RayDataset(frames, images, masks, open_water=water_masks if in_view else None
                      ).fixed_subset(config.medium.refit_rays, config.seed + 97)
    depth, opacity = [], []
    with torch.no_grad():
        for start in range(0, len(rays), 8192):
            part = rays.subset(slice(start, start + 8192))
            render = model(part.origins, part.directions, part.near, part.far).render
            depth.append(render.depth_median)
            opacity.append(render.opacity)
    diagonal = float(torch.linalg.norm(model.box.box_max - model.box.box_min))
    up = model.scene.get("up")
    if up_now:
        from seathru.geometry.upright import estimate_up

        estimate = estimate_up(np.stack([f.c2w_array for f in frames]))
        up = None if estimate is None else list(estimate.vector)
    below = below_horizon(rays.directions, up, config.medium.horizon_margin)
    if open_water_surfaces is None:
        open_water_surfaces = config.medium.open_water_surfaces_from <= 1.0
    within = config.medium.open_water_surface_share * rays.far.reshape(-1) \
        if open_water_surfaces else None
    data, *regrouped = [
        surface_data(rays.origins, rays.directions, rays.rgb, torch.cat(depth),
                     torch.cat(opacity), factor * config.medium.refit_voxel * diagonal,
                     config.medium.refit_opacity,
                     open_water_opacity=refit_open_water_opacity(config.medium, in_view, 1.0),
                     open_water=rays.open_water, below_horizon=below,
                     open_water_surface_within=within)
        for factor in (1.0, *(config.medium.interval_voxel_factors if regroup else ()))]
    report = read_water(train / "water.json")
    truth = read_truth_water(sim / "truth" / "water.json").scaled(1 / report.scale).as_dict()
    return data, model, truth, report.normalised.as_dict(), report.scale, regrouped


def assess_model(sim: Path, train: Path) -> dict:
    """Curvature and robust intervals of one trained model's surface fit against the truth
    (normalised units)."""
    from seathru.nerf.water_refit import medium_surface_fit
    from seathru.nerf.water_uncertainty import laplace_halfwidths, robust_halfwidths

    data, model, truth, trained, scale, _ = model_surfaces(sim, train)
    record = {"model": f"{sim.name}/{train.name}", "scale": scale, "truth": truth,
              "trained": trained}
    if isinstance(data, str):
        return {**record, "skipped": data}
    config = model.config
    dark = data.dark if config.medium.dark_pixel_bound else None
    fit, data = medium_surface_fit(data, trained, config.medium, model.medium.colour_max)
    centre = {k: getattr(fit, k) for k in KEYS}
    started = time.perf_counter()
    robust = robust_halfwidths(fit, data.ranges, data.observed, data.ids, data.groups,
                               colour_max=model.medium.colour_max, dark=dark)
    seconds = time.perf_counter() - started
    curvature = laplace_halfwidths(fit, data.ranges, data.observed, data.ids, data.groups)
    methods = {"curvature": curvature.halfwidth, "robust": robust.halfwidth}
    if fit.unshared is not None:    # as before session 44: the parts refitted without the term
        methods["robust_parts_plain"] = robust_halfwidths(
            replace(fit, unshared=None), data.ranges, data.observed, data.ids, data.groups,
            colour_max=model.medium.colour_max, dark=dark).halfwidth
        record["robust_parts_plain"] = methods["robust_parts_plain"]
    record.update({"pixels": fit.pixels, "groups": fit.groups, "surface_fit": centre,
                   "robust_seconds": seconds, "robust": robust.halfwidth,
                   "robust_determined": robust.determined, "curvature": curvature.halfwidth,
                   "statistical": robust.statistical, "systematic": robust.systematic,
                   "splits": robust.splits})
    for method, half in methods.items():
        record[f"{method}_covers"] = covered(centre, half, truth)
        widened = {k: [h + abs(t - f) for h, t, f in zip(half[k], trained[k], centre[k])]
                   for k in KEYS}
        record[f"{method}_covers_trained"] = covered(trained, widened, truth)
    return record


def model_check(work: Path) -> list[dict]:
    rows = []
    for train in sorted(work.glob("*/train_*")):
        if (train / "model.pt").exists() and (train.parent / "truth" / "water.json").exists():
            rows.append(assess_model(train.parent, train))
            row = rows[-1]
            print(row["model"], row.get("skipped") or
                  {m: sum(row[f"{m}_covers"]) for m in ("curvature", "robust")}, flush=True)
    return rows


def write_results(synthetic_rows: list[dict], model_rows: list[dict], args,
                  seconds: float) -> None:
    lines = ["# Water intervals: do they hold the truth? (`benchmarks/bench_water_intervals.py`)",
             "", "Share of 95% intervals (9 per fit) that hold the true water; curvature = "
             "`laplace_halfwidths`, robust = `robust_halfwidths` (cluster-robust sandwich + "
             "between-part systematic term)."]
    if synthetic_rows:
        lines += ["", f"## Synthetic surfaces ({args.seeds} seeds, 150 voxels x 8 pixels, "
                  "0.5-8 m)", "", "| scenario | curvature | robust | robust: determined | robust: "
                  "median half-width (share of the value) | robust: seconds |",
                  "|---|---|---|---|---|---|"]
    for r in synthetic_rows:
        lines.append(f"| {r['scenario']} | {100 * r['curvature']:.0f}% | "
                     f"{100 * r['robust']:.0f}% | {100 * r['robust_determined']:.0f}% | "
                     f"{100 * r['robust_relative_halfwidth']:.0f}% | "
                     f"{r['robust_seconds']:.2f} |")
    if model_rows:
        done = [r for r in model_rows if "skipped" not in r]
        lines += ["", f"## Trained models' own surfaces (`{args.work}`)", "",
                  "| model | pixels / voxels | curvature | robust | robust, trained centre | "
                  "robust: determined | robust: median half-width | parts refitted without the "
                  "term: robust, trained centre, median half-width | seconds |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in model_rows:
            if "skipped" in r:
                lines.append(f"| {r['model']} | skipped: {r['skipped']} | | | | | | | |")
                continue
            determined = sum(d for k in KEYS for d in r["robust_determined"][k])
            plain = (f"{sum(r['robust_parts_plain_covers'])}/9, "
                     f"{sum(r['robust_parts_plain_covers_trained'])}/9, "
                     f"{100 * median_relative(r['robust_parts_plain'], r['surface_fit']):.0f}%"
                     if "robust_parts_plain" in r else "-")
            lines.append(f"| {r['model']} | {r['pixels']} / {r['groups']} | "
                         f"{sum(r['curvature_covers'])}/9 | {sum(r['robust_covers'])}/9 | "
                         f"{sum(r['robust_covers_trained'])}/9 | {determined}/9 | "
                         f"{100 * median_relative(r['robust'], r['surface_fit']):.0f}% | "
                         f"{plain} | {r['robust_seconds']:.1f} |")
        total = 9 * max(1, len(done))
        share = {key: sum(sum(r[key]) for r in done) / total for key in
                 ("curvature_covers", "robust_covers", "curvature_covers_trained",
                  "robust_covers_trained")}
        lines += ["", f"In all ({len(done)} fits): curvature {100 * share['curvature_covers']:.0f}%"
                  f", robust {100 * share['robust_covers']:.0f}% around the surface fit; around "
                  f"the trained value widened by its distance to the fit: curvature "
                  f"{100 * share['curvature_covers_trained']:.0f}%, robust "
                  f"{100 * share['robust_covers_trained']:.0f}%."]
        termed = [r for r in done if "robust_parts_plain" in r]
        if termed:
            count = {key: sum(sum(r[key]) for r in termed) for key in (
                "robust_covers", "robust_covers_trained", "robust_parts_plain_covers",
                "robust_parts_plain_covers_trained")}
            widths = {key: float(np.median([median_relative(r[key], r["surface_fit"])
                                            for r in termed]))
                      for key in ("robust", "robust_parts_plain")}
            lines += ["", f"The {len(termed)} fits made with the incidental term, their parts "
                      f"refitted with it / without it (before session 44): robust intervals hold "
                      f"the truth in {count['robust_covers']} / "
                      f"{count['robust_parts_plain_covers']} of {9 * len(termed)} around the "
                      f"surface fit, {count['robust_covers_trained']} / "
                      f"{count['robust_parts_plain_covers_trained']} around the trained value; "
                      f"median half-width {100 * widths['robust']:.1f}% / "
                      f"{100 * widths['robust_parts_plain']:.1f}% of the value."]
    lines += ["", f"Machine: {cpu_name()}, 1 torch thread; load {load_average()}; "
              f"{time.strftime('%Y-%m-%d')}; {seconds / 60:.1f} min in all.", ""]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines))
    args.out.with_suffix(".json").write_text(json.dumps(
        {"synthetic": synthetic_rows, "models": model_rows}, indent=1))
    print("\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=40,
                        help="draws per synthetic scenario (0: no synthetic check)")
    parser.add_argument("--work", type=Path, default=None,
                        help="a bench_water.py work folder with trained models")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    torch.set_num_threads(1)
    started = time.time()
    synthetic_rows = synthetic_check(args.seeds) if args.seeds > 0 else []
    model_rows = model_check(args.work) if args.work else []
    write_results(synthetic_rows, model_rows, args, time.time() - started)


if __name__ == "__main__":
    main()
