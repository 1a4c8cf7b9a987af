"""The water refit with and without its outliers, on trained models' own surfaces.

For every trained model in ``bench_water.py`` work folders, the surfaces its final water
assessment uses are rebuilt (``bench_water_intervals.model_surfaces``: training rays, median
depth, opacity, voxels, open water, dark-pixel bound) and the water is fitted to them as a
refit does (``seathru.nerf.water_fit.fit_surfaces``), once on every pixel and once more
without the residual outliers at each ``--trims`` value. Errors against the simulator's
water, signed, per channel (R, G, B). The fits share each model's pixels, so the difference
between columns is the trimming alone; the trained value in water.json is shown beside them.

    python benchmarks/bench_refit_trim.py --work /tmp/bench_water [--work ...] [--trims 2.5,3.5]

Writes benchmarks/results/refit_trim.md.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from machine import footer, load_average

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
RESULTS = REPO / "benchmarks" / "results" / "refit_trim.md"
KEYS = ("sigma_attn", "sigma_bs")


def signed(values: dict, truth: dict) -> str:
    return " / ".join(", ".join(f"{100 * (v / t - 1):+.0f}" for v, t in zip(values[k], truth[k]))
                      for k in KEYS)


def measure(train: Path, trims: list[float]) -> dict:
    from bench_water_intervals import model_surfaces
    from seathru.nerf.water_fit import fit_surfaces

    data, model, truth, trained, _, _ = model_surfaces(train.parent, train)
    row = {"model": f"{train.parent.parent.name}/{train.parent.name}",
           "trained": signed(trained, truth)}
    if isinstance(data, str):
        return {**row, "skipped": data}
    for trim in [0.0, *trims]:
        fit, used = fit_surfaces(data, trained, model.config.medium.refit_steps,
                                 model.medium.colour_max, model.config.medium.dark_pixel_bound,
                                 model.config.medium.balance_brightness, trim)
        row[trim] = signed({k: getattr(fit, k) for k in KEYS}, truth)
        row[f"{trim} left out"] = len(data.ranges) - len(used.ranges)
    row["pixels"] = len(data.ranges)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, action="append", required=True)
    parser.add_argument("--trims", default="3.5")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    torch.set_num_threads(1)
    trims = [float(t) for t in args.trims.split(",")]
    started, load = time.time(), load_average()
    rows = []
    for work in args.work:
        for train in sorted(work.glob("*/train_*")):
            if (train / "model.pt").exists():
                rows.append(measure(train, trims))
                print(rows[-1], flush=True)
    head = ["model", "trained (water.json)", "every pixel",
            *[f"without outliers at {t}" for t in trims]]
    lines = [f"# {__doc__.splitlines()[0].rstrip('.')} (`benchmarks/bench_refit_trim.py`)", "",
             "Errors in % against the simulator's water: `sigma_attn` R, G, B / `sigma_bs` R, "
             "G, B; in brackets: the pixels offered (every pixel), and those left out "
             "(without outliers).", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in rows:
        if "skipped" in row:
            lines.append(f"| {row['model']} | {row['trained']} | {row['skipped']} |")
            continue
        cells = [row["model"], row["trained"], f"{row[0.0]} ({row['pixels']} pixels)",
                 *[f"{row[t]} ({row[f'{t} left out']})" for t in trims]]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", footer(load, started), ""]
    args.out.write_text("\n".join(lines))
    print(args.out)


if __name__ == "__main__":
    main()
