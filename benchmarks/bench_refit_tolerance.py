"""The water refit's stopping rule: time and result of the old tolerances against the new ones,
side by side on the same pixels of finished runs. A diagnostic, not a test.

For each finished workflow run (``results/<dataset>`` with ``checkpoints/checkpoint.pt``; default
settings at 3 min), the final checkpoint is loaded and, with each stopping rule in turn
(``water_fit.LBFGS_TOLERANCE_CHANGE`` / ``_GRAD``, relative to a fit's start loss):

- a refit as training makes one (``_fit_surfaces`` and its Laplace half-widths) on one draw of
  refit rays, the render left out of the time;
- the final assessment (``assess_water``: the surface fit and its robust intervals).

Usage::

    python benchmarks/bench_refit_tolerance.py results/demo [RUN ...] \\
        --out benchmarks/results/refit_tolerance.md
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import torch

from bench_refit_variance import trainer_at_checkpoint
from machine import cpu_name, load_average

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from seathru.nerf import water_fit  # noqa: E402
from seathru.nerf.water_uncertainty import laplace_halfwidths  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "refit_tolerance.md"
KEYS = ("sigma_attn", "sigma_bs", "c_med")
RULES = {"old (1e-16, 1e-12)": (1e-16, 1e-12),
         "new (1e-10, 1e-9)": (water_fit.LBFGS_TOLERANCE_CHANGE, water_fit.LBFGS_TOLERANCE_GRAD)}


def vector(values: dict) -> torch.Tensor:
    return torch.tensor([v for k in KEYS for v in values[k]], dtype=torch.float64)


def measure(trainer, data) -> dict:
    """Seconds and results of one refit and one final assessment with the current rule."""
    start = time.perf_counter()
    fit, used = trainer._fit_surfaces(data, trainer.model.water_parameters())
    laplace_halfwidths(fit, used.ranges, used.observed, used.ids, used.groups)
    refit_s = time.perf_counter() - start
    start = time.perf_counter()
    assessment = trainer.assess_water()
    return {"refit_s": refit_s, "refit": vector({k: getattr(fit, k) for k in KEYS}),
            "assess_s": time.perf_counter() - start,
            "fit": vector(assessment["surface_fit"]),
            "halfwidth": vector(assessment["halfwidth95"]),
            "determined": assessment["determined"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    torch.set_num_threads(2)
    before = load_average()
    rows = ["| run | rule | refit s | final assessment s | refit water vs old | "
            "assessed water vs old | half-widths vs old (median, largest) | "
            "determined flags as old |", "|---|---|---|---|---|---|---|---|"]
    totals = {name: [0.0, 0.0] for name in RULES}
    for run in args.runs:
        trainer = trainer_at_checkpoint(run)
        data = trainer._surface_data(trainer.config.seed + 5)[0]
        results = {}
        for name, (change, grad) in RULES.items():
            water_fit.LBFGS_TOLERANCE_CHANGE, water_fit.LBFGS_TOLERANCE_GRAD = change, grad
            results[name] = measure(trainer, data)
            totals[name][0] += results[name]["refit_s"]
            totals[name][1] += results[name]["assess_s"]
        old = results[next(iter(RULES))]
        for name, r in results.items():
            refit_move = float(((r["refit"] - old["refit"]) / old["refit"]).abs().max())
            fit_move = float(((r["fit"] - old["fit"]) / old["fit"]).abs().max())
            widths = ((r["halfwidth"] - old["halfwidth"]) / old["halfwidth"]).abs()
            rows.append(f"| {run.name} | {name} | {r['refit_s']:.2f} | {r['assess_s']:.2f} | "
                        f"{100 * refit_move:.3f}% | {100 * fit_move:.3f}% | "
                        f"{100 * float(widths.median()):.1f}%, {100 * float(widths.max()):.1f}% | "
                        f"{'yes' if r['determined'] == old['determined'] else 'no'} |")
            print(rows[-1], flush=True)
    (old_refit, old_assess), (new_refit, new_assess) = totals.values()
    lines = ["# The water refit's stopping rule (`benchmarks/bench_refit_tolerance.py`)", "",
             f"Device: {cpu_name()}, 2 threads, torch {torch.__version__}, Python "
             f"{platform.python_version()}; load average before/after: {before} / "
             f"{load_average()}. Each run's last checkpoint, the same pixels for both rules, "
             "one rule after the other. Water and half-widths: largest relative difference "
             "from the old rule's over the nine values.", "", *rows, "",
             f"All runs: a refit {old_refit / max(new_refit, 1e-9):.1f}x faster "
             f"({old_refit:.1f} s against {new_refit:.1f} s), the final assessment "
             f"{old_assess / max(new_assess, 1e-9):.1f}x ({old_assess:.1f} s against "
             f"{new_assess:.1f} s)."]
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
