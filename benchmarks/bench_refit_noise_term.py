"""Is the refit's red backscatter bias the incidental-parameter term? (a script)

The refit fits one clean colour per voxel group from the group's own pixels. What the pixels do
not share (each sees a slightly different spot of texture) then biases the water: a group's
expected squared residual is its signal misfit plus ``tr S - f'Sf / f'f`` (``f`` the group's
transmission ``exp(-sigma_attn z)``, ``S`` its pixels' unshared variances, docs/water.md "Noise
that fades with range pulls the attenuation up"). Adding ``f'Sf / f'f`` back to each group's
loss takes that term's pull away, if ``S`` is right. On the simulator's exact pixels (a 10-view
survey at 160x120, noise-free, true ranges, 0.054 m voxels, 2,000 open-water pixels at the true
``c_med``; ``fit_water`` with brightness weights, no dark bound), side by side:

- the plain fit;
- with the term (``fit_water(noise_term=True)``), ``S`` from the truth: the spread of each
  pixel's clean colour about its group's mean, per range bin (12 quantile bins), transmitted by
  the true water (``water_fit.unshared_variance`` patched to return it);
- with the term as the refit has it (``fit_water(noise_term=True)``: ``S`` estimated from the
  residuals per range bin, ``water_fit.unshared_variance``).

at one ray a pixel, at 2 x 2 (the simulator's default; the plain fit's red backscatter +0 and
+5%, ``refit_rays_per_pixel.md``) and at 4 x 4 (nearer a camera, whose pixel integrates its
whole footprint). A second table asks which part of the pixels' colours carries the bias: each
pixel rebuilt as its own clean colour (the mean of its rays' clean radiance) through the true
water at its mean range, then the same with the deviations from the group's mean shuffled
among the group's pixels (the same deviations, no longer tied to range), and with none.

    python benchmarks/bench_refit_noise_term.py [--waters default,coastal_3c] [--rays 1,2,4]
    python benchmarks/bench_refit_noise_term.py --trained WORK --out FILE

With ``--trained``, the same question on trained models instead: every ``*/train_cues`` model
of a ``bench_water.py`` work folder (trained without the term), its final surfaces refitted
once each way with the training's settings (``fit_surfaces``: trim, dark bound, brightness
weights), no training noise between the two.

Writes benchmarks/results/refit_noise_term.md. About 3 min a water on 2 CPU cores.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from bench_refit_rays_per_pixel import START, VOXEL, errors, survey_rays
from machine import cpu_name

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
RESULTS = REPO / "benchmarks" / "results" / "refit_noise_term.md"
BINS = 12
OPEN_WATER_PIXELS = 2000


def exact_groups(px: dict) -> dict:
    """The surface pixels seen over a spread of ranges, grouped by voxel, with their range bin."""
    import seathru.nerf.water_surfaces as water_surfaces

    surface = np.isfinite(px["range"])
    points = px["origins"][surface] + px["dirs"][surface] * px["range"][surface, None]
    ranges = px["range"][surface]
    ids, groups = water_surfaces.voxel_groups(torch.from_numpy(points), VOXEL)
    keep = water_surfaces.ranged_groups(torch.from_numpy(ranges), ids, groups).numpy()
    ids, groups = water_surfaces.voxel_groups(torch.from_numpy(points[keep]), VOXEL)
    ranges = ranges[keep]
    edges = np.quantile(ranges, np.linspace(0.0, 1.0, BINS + 1))
    return {"ranges": ranges, "image": px["image"][surface][keep],
            "clean": px["clean"][surface][keep], "ids": ids.numpy(), "groups": groups,
            "bin": np.clip(np.searchsorted(edges, ranges) - 1, 0, BINS - 1), "edges": edges}


def group_means(g: dict) -> tuple[np.ndarray, np.ndarray]:
    """(groups,) pixel counts and (groups, 3) mean clean colour of each group."""
    count = np.bincount(g["ids"], minlength=g["groups"])
    return count, np.stack([np.bincount(g["ids"], g["clean"][:, c], g["groups"]) / count
                            for c in range(3)], 1)


def bin_means(g: dict, per_pixel: np.ndarray) -> np.ndarray:
    """(BINS, 3) mean of an (N, 3) per-pixel quantity over each range bin."""
    per_bin = np.bincount(g["bin"], minlength=BINS)[:, None]
    return np.stack([np.bincount(g["bin"], per_pixel[:, c], BINS) for c in range(3)], 1) / per_bin


def truth_variance(g: dict) -> np.ndarray:
    """(BINS, 3) mean squared spread of the pixels' clean colour about their group's mean."""
    count, mean = group_means(g)
    unbiased = (count / np.maximum(count - 1, 1))[g["ids"], None]
    return bin_means(g, (g["clean"] - mean[g["ids"]]) ** 2 * unbiased)


def estimated_variance(fit, g: dict, tensors: tuple) -> np.ndarray:
    """(BINS, 3) the same variance as the refit estimates it from the fit's residuals
    (``water_fit.unshared_variance``, whose bins are these)."""
    import seathru.nerf.water_fit as water_fit

    unshared = water_fit.unshared_variance(fit, *tensors)[:len(g["ranges"])].numpy()
    return bin_means(g, unshared / np.exp(-2.0 * np.asarray(fit.sigma_attn)
                                          * g["ranges"][:, None]))


def rebuilt_rows(water: str, supersample: int, truth, g: dict, tensors: tuple) -> list[str]:
    """The plain fit of pixels rebuilt from their clean colours (see the module's docstring)."""
    import seathru.nerf.water_fit as water_fit

    attn, bs, c_med = (np.asarray(getattr(truth, k)) for k in ("sigma_attn", "sigma_bs", "c_med"))
    transmission = np.exp(-attn * g["ranges"][:, None])
    backscatter = c_med * (1.0 - np.exp(-bs * g["ranges"][:, None]))
    ids = g["ids"]
    mean = group_means(g)[1]
    deviation = g["clean"] - mean[ids]
    by_group = np.argsort(ids, kind="stable")
    shuffled_order = np.lexsort((np.random.default_rng(0).random(len(ids)), ids))
    shuffled = np.empty_like(deviation)
    shuffled[by_group] = deviation[shuffled_order]
    arms = (("own clean colour", g["clean"]), ("deviations shuffled in the group",
                                                mean[ids] + shuffled),
            ("no deviations", mean[ids]))
    rows = []
    for label, clean in arms:
        image = torch.from_numpy(clean * transmission + backscatter)
        observed = torch.cat([image, tensors[1][len(image):]])
        fit = water_fit.fit_water(tensors[0], observed, *tensors[2:], START)
        rows.append(f"| {water} | {supersample} x {supersample} | {label} | "
                    f"{errors(fit, truth)} |")
    return rows


def one_dive(water: str, supersample: int) -> tuple[list[str], str, list[str]]:
    import seathru.nerf.water_fit as water_fit

    truth, px = survey_rays(water, supersample)
    g = exact_groups(px)
    veiling = torch.tensor(truth.c_med, dtype=torch.float64).repeat(OPEN_WATER_PIXELS, 1)
    tensors = (torch.cat([torch.from_numpy(g["ranges"]),
                          torch.full((OPEN_WATER_PIXELS,), float("inf"), dtype=torch.float64)]),
               torch.cat([torch.from_numpy(g["image"]), veiling]),
               torch.cat([torch.from_numpy(g["ids"]),
                          torch.full((OPEN_WATER_PIXELS,), g["groups"])]),
               g["groups"] + 1)
    plain_fit = water_fit.fit_water(*tensors, START)
    rays = f"{supersample} x {supersample}"
    rows = [f"| {water} | {rays} | plain | {errors(plain_fit, truth)} |"]
    transmitted = np.exp(-2.0 * np.asarray(truth.sigma_attn) * g["ranges"][:, None])
    truth_var = truth_variance(g)
    estimated = estimated_variance(plain_fit, g, tensors)
    estimate = water_fit.unshared_variance
    unshared = torch.cat([torch.from_numpy(transmitted * truth_var[g["bin"]]),
                          torch.zeros(OPEN_WATER_PIXELS, 3, dtype=torch.float64)])
    water_fit.unshared_variance = lambda *args, **kwargs: unshared
    try:
        fit = water_fit.fit_water(*tensors, START, noise_term=True)
    finally:
        water_fit.unshared_variance = estimate
    rows.append(f"| {water} | {rays} | term, variance from the truth | {errors(fit, truth)} |")
    fit = water_fit.fit_water(*tensors, START, noise_term=True)
    rows.append(f"| {water} | {rays} | term, variance from the residuals (`noise_term=True`) | "
                f"{errors(fit, truth)} |")
    rows_rebuilt = rebuilt_rows(water, supersample, truth, g, tensors)
    for row in rows + rows_rebuilt:
        print(row, flush=True)
    bins = " ".join(f"{a:.1f}" for a in g["edges"])
    spread = (f"| {water} | {rays} | {' '.join(f'{1e3 * v:.1f}' for v in truth_var[:, 0])} | "
              f"{' '.join(f'{1e3 * v:.1f}' for v in estimated[:, 0])} | {bins} |")
    return rows, spread, rows_rebuilt


def trained_rows(work: Path) -> list[str]:
    """Per trained model: the final surfaces' refit without and with the term (% errors)."""
    from bench_water_intervals import KEYS, model_surfaces
    from seathru.nerf.water_fit import fit_surfaces

    rows, within = [], {False: 0, True: 0}
    for train in sorted(work.glob("*/train_cues")):
        data, model, truth, trained, _, _ = model_surfaces(train.parent, train)
        if isinstance(data, str):
            rows.append(f"| {train.parent.name} | {data} | |")
            continue
        medium, cells = model.config.medium, [train.parent.name]
        for term in (False, True):
            fit, _ = fit_surfaces(data, trained, medium.refit_steps, model.medium.colour_max,
                                  medium.dark_pixel_bound, medium.balance_brightness,
                                  medium.refit_trim, term)
            error = [100 * (v / t - 1) for k in KEYS for v, t in zip(getattr(fit, k), truth[k])]
            within[term] += sum(abs(e) <= 5 for e in error)
            cells.append("; ".join(", ".join(f"{e:+.1f}" for e in error[i:i + 3])
                                   for i in (0, 3, 6)))
        rows.append("| " + " | ".join(cells) + " |")
        print(rows[-1], flush=True)
    rows.append(f"| values within 5% | {within[False]} | {within[True]} |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--waters", default="default,coastal_3c")
    parser.add_argument("--rays", default="1,2,4", help="rays a pixel's side, comma-separated")
    parser.add_argument("--trained", type=Path, help="a bench_water.py work folder")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    torch.set_num_threads(2)
    started = time.time()
    if args.trained:
        lines = ["# The incidental-parameter term on trained models' final surfaces "
                 "(`benchmarks/bench_refit_noise_term.py --trained`)", "",
                 f"Models: `{args.trained}/*/train_cues` (3-min `bench_water.py` runs without "
                 "the term); each model's final surfaces refitted with the training's settings, "
                 "without and with the term; errors against the simulator's water "
                 "(%: `sigma_attn` R, G, B; `sigma_bs`; `c_med`).", "",
                 "| dive | without the term | with it |", "|---|---|---|",
                 *trained_rows(args.trained), "",
                 f"Machine: {cpu_name()}; {time.strftime('%Y-%m-%d')}; "
                 f"{(time.time() - started) / 60:.0f} min in all.", ""]
        args.out.write_text("\n".join(lines))
        print("\n".join(lines))
        return
    results = [one_dive(water, supersample) for water in args.waters.split(",")
               for supersample in map(int, args.rays.split(","))]
    lines = ["# The incidental-parameter term and the water refit (`benchmarks/"
             "bench_refit_noise_term.py`)", "",
             "A 10-view survey at 160x120 (seed 0), the simulator's noise-free images with water "
             "and true ranges, voxels of 0.054 m, 2,000 open-water pixels at the true `c_med`; "
             "`fit_water` with brightness weights, no dark bound; errors against the simulator's "
             "water (%: `sigma_attn` R, G, B; `sigma_bs`; `c_med`).", "",
             "| water | rays a pixel | fit | error (%) |", "|---|---|---|---|",
             *[row for rows, _, _ in results for row in rows], "",
             "The plain fit of the pixels rebuilt from their clean colours through the true "
             "water at their mean range:", "",
             "| water | rays a pixel | clean colours | error (%) |", "|---|---|---|---|",
             *[row for _, _, rows in results for row in rows], "",
             "Red unshared variance per range bin (x 1e-3, clean colour), from the truth and "
             "as `unshared_variance` estimates it at the plain fit; the bins' edges in metres:", "",
             "| water | rays a pixel | truth | estimated | bin edges (m) |",
             "|---|---|---|---|---|",
             *[spread for _, spread, _ in results], "",
             f"Machine: {cpu_name()}; {time.strftime('%Y-%m-%d')}; "
             f"{(time.time() - started) / 60:.0f} min in all.", ""]
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
