"""Which surface pixels move the water refit on a trained model: a diagnostic on simulated dives.

For each trained model of a ``bench_water.py`` work folder, every training pixel is rendered
(median depth, opacity) and compared with the simulator's range; the water is then fitted
(``seathru.nerf.water_fit.fit_surfaces``, voxel groups, dark-pixel bound, as a refit) to the
same surface pixels four ways: at the model's depth; at their true range; at the model's
depth without the pixels whose true surface point only one training view sees
(``seathru.eval.truth.training_view_coverage``, known only in simulation); and at the model's
depth without the residual outliers (``medium.refit_trim``). Errors against the simulator's
water, signed, per channel.

    python benchmarks/bench_refit_misplaced.py --work /tmp/bench_water [--dives survey_default]

Writes benchmarks/results/refit_misplaced.md.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from machine import footer, load_average

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
RESULTS = REPO / "benchmarks" / "results" / "refit_misplaced.md"


@torch.no_grad()
def _median_depth(model, frame, origins, directions, chunk: int = 8192):
    """(R,) median depth and (R,) object opacity of a frame's rays."""
    depth, opacity = [], []
    for start in range(0, len(origins), chunk):
        count = len(origins[start:start + chunk])
        render = model(origins[start:start + chunk], directions[start:start + chunk],
                       torch.full((count,), float(frame.near)),
                       torch.full((count,), float(frame.far))).render
        depth.append(render.depth_median)
        opacity.append(render.opacity)
    return torch.cat(depth), torch.cat(opacity)


def measure(train: Path, trim: float) -> dict:
    from bench_water import _truth_range
    from bench_water_intervals import trained_dive
    from seathru.eval.truth import training_view_coverage
    from seathru.io.water import read_truth_water, read_water
    from seathru.nerf.rays import frame_rays
    from seathru.nerf.water_fit import fit_surfaces
    from seathru.nerf.water_surfaces import surface_data

    sim = train.parent
    model, cameras, frames, images, _, water_masks, in_view = trained_dive(sim, train)
    config = model.config
    ranges = [_truth_range(sim, f, cameras.scale) for f in frames]
    columns = {k: [] for k in ("origins", "directions", "rgb", "depth", "opacity", "truth",
                               "water", "views")}
    for frame, image, water, view_range in zip(frames, images, water_masks, ranges):
        origins, directions = frame_rays(frame)
        rendered = _median_depth(model, frame, origins, directions)
        views = training_view_coverage(frame, view_range, list(zip(frames, ranges)))
        for key, value in (("origins", origins), ("directions", directions),
                           ("rgb", np.asarray(image, np.float32).reshape(-1, 3)),
                           ("depth", rendered[0]), ("opacity", rendered[1]),
                           ("truth", view_range.reshape(-1).astype(np.float32)),
                           ("water", np.asarray(water).reshape(-1)),
                           ("views", views.reshape(-1))):
            columns[key].append(torch.as_tensor(value))
    c = {k: torch.cat(v) for k, v in columns.items()}
    surface = torch.isfinite(c["truth"]) & (c["opacity"] > config.medium.refit_opacity)
    ratio = c["depth"] / c["truth"]
    true_range = torch.where(torch.isfinite(c["truth"]), c["truth"], torch.full_like(c["truth"],
                                                                                   1e3))
    report = read_water(train / "water.json")
    truth = read_truth_water(sim / "truth" / "water.json").scaled(1 / report.scale).as_dict()
    start = report.normalised.as_dict()
    diagonal = float(torch.linalg.norm(model.box.box_max - model.box.box_min))
    single = c["views"] <= 1

    def fit(depth, opacity, trim_at=0.0):
        data = surface_data(c["origins"], c["directions"], c["rgb"], depth, opacity,
                            config.medium.refit_voxel * diagonal, config.medium.refit_opacity,
                            open_water_opacity=0.5, open_water=c["water"] if in_view else None)
        if isinstance(data, str):
            return data
        result = fit_surfaces(data, start, config.medium.refit_steps, model.medium.colour_max,
                              config.medium.dark_pixel_bound, config.medium.balance_brightness,
                              trim_at)[0]
        return ", ".join(f"{100 * (v / t - 1):+.0f}" for v, t in
                         zip(result.sigma_attn, truth["sigma_attn"]))

    near = surface & (c["truth"] / cameras.scale < 1.5)
    long_near = near & (ratio > 1.03)
    return {
        "model": f"{train.parent.parent.name}/{sim.name}",
        "within 3%": float(((ratio - 1).abs() < 0.03)[surface].float().mean()),
        "single view": float(single[surface].float().mean()),
        "near long": float(long_near.sum() / near.sum().clamp_min(1)),
        "near long median": float(ratio[long_near].median()) if bool(long_near.any()) else None,
        "model depth": fit(c["depth"], c["opacity"]),
        "true range": fit(true_range, torch.isfinite(c["truth"]).float()),
        "without single-view": fit(c["depth"], c["opacity"] * (~single).float()),
        "without outliers": fit(c["depth"], c["opacity"], trim),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, action="append", required=True)
    parser.add_argument("--dives", default="survey_default,survey_coastal_3c")
    parser.add_argument("--trim", type=float, default=3.5)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    torch.set_num_threads(1)
    started, load = time.time(), load_average()
    rows = []
    for work in args.work:
        for dive in args.dives.split(","):
            train = work / dive / "train_cues"
            if (train / "model.pt").exists():
                rows.append(measure(train, args.trim))
                print(rows[-1], flush=True)
    head = ["model", "surface pixels within 3% of their range", "seen by one view",
            "< 1.5 m placed > 3% too far (median ratio)", "sigma_attn: model depth",
            "true range", "model depth, without single-view pixels",
            f"model depth, without outliers at {args.trim}"]
    lines = [f"# {__doc__.splitlines()[0].rstrip('.')} (`benchmarks/bench_refit_misplaced.py`)",
             "", "Every training pixel; `sigma_attn` error in % against the simulator's water "
             "(R, G, B).", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in rows:
        lines.append("| " + " | ".join([
            row["model"], f"{100 * row['within 3%']:.0f}%", f"{100 * row['single view']:.1f}%",
            f"{100 * row['near long']:.0f}% ({row['near long median']:.2f})"
            if row["near long median"] else "-",
            row["model depth"], row["true range"], row["without single-view"],
            row["without outliers"]]) + " |")
    lines += ["", footer(load, started), ""]
    args.out.write_text("\n".join(lines))
    print(args.out)


if __name__ == "__main__":
    main()
