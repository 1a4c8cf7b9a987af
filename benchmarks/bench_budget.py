"""What a longer training budget buys the demo: its survey through the whole workflow (simulate,
ingest, COLMAP, train, render, evaluate) once, trained for 3 minutes (the demo's budget) and,
as sweep variants on the same COLMAP cameras, for longer.

    python benchmarks/bench_budget.py --work /tmp/budget [--minutes 3,6,12]

Writes ``benchmarks/results/budget.md``: per budget the training steps, the held-out PSNR, the
restored render against the clean truth (and on the pixels two training views see), with the
photographs' detail reprojected, the restored photographs, and the fitted water's signed error
per channel (``?``: flagged as not determined; ``!``: its interval misses the truth), each
held-out view's unseen surface share with its held-out PSNR; and, from
the longest run's quality snapshots, the restored render against the clean truth over its
training time (at the snapshots' reduced resolution, so not comparable with the table's
figures, only along the curve). ``--summarise-only`` tabulates a finished ``--work``.
"""

from __future__ import annotations

import csv
import time
from pathlib import Path

from machine import footer, load_average
from workflow_sheet import (metric_mean, read_run, run_sheet, sheet_arguments, unseen_cell,
                            water_cells)

OUT = Path(__file__).resolve().parent / "results" / "budget.md"
DEMO = "demo"


def variant_name(minutes: float) -> str:
    return f"min{minutes:g}".replace(".", "_")


def budget_row(work: Path, run: str, minutes: float) -> str:
    finished = read_run(work, run)
    if finished is None:
        return f"| {minutes:g} | failed (see {work}/logs/{run}) |" + " |" * 8
    summary, rows = finished
    training = summary.get("training") or {}
    water = (summary.get("truth") or {}).get("water")
    return (f"| {minutes:g} | {training.get('steps', '-')} | {metric_mean(rows, 'psnr_linear')} | "
            f"{metric_mean(rows, 'restored_psnr_linear')} "
            f"({metric_mean(rows, 'restored_psnr_linear_covered')}) | "
            f"{metric_mean(rows, 'reprojected_restored_psnr_linear')} "
            f"({metric_mean(rows, 'reprojected_restored_psnr_linear_covered')}) | "
            f"{metric_mean(rows, 'photo_restored_psnr_linear')} | "
            + " | ".join(water_cells(water) if water else ["-"] * 3)
            + f" | {unseen_cell(rows)} |")


def curve_lines(work: Path, run: str) -> list[str]:
    path = work / "results" / run / "evaluate" / "frontier.csv"
    if not path.is_file():
        return []
    lines = ["| training (s) | step | held-out PSNR (snapshot) | restored vs clean (snapshot) |",
             "|---|---|---|---|"]
    for row in csv.DictReader(path.open()):
        if row.get("restored_psnr_linear") not in (None, "", "nan"):
            lines.append(f"| {float(row['elapsed_s']):.0f} | {row['step']} | "
                         f"{float(row['test_psnr_images']):.2f} | "
                         f"{float(row['restored_psnr_linear']):.2f} |")
    return lines


def main() -> None:
    args = sheet_arguments(
        __doc__.splitlines()[0], Path("/tmp/budget"), OUT,
        {"--minutes": {"default": "3,6,12", "help": "training budgets, comma-separated"}})
    minutes = sorted({float(m) for m in args.minutes.split(",")})
    base, longer = minutes[0], minutes[1:]
    runs = {DEMO: base, **{f"{DEMO}+{variant_name(m)}": m for m in longer}}
    load_before, start = load_average(), time.time()
    if not args.summarise_only:
        sweep = {variant_name(m): f"train.max_minutes={m:g}" for m in longer}
        row = f"{DEMO}\tsimulated\t\ttrain.max_minutes={base:g}\t" + ",".join(sweep)
        run_sheet(args.work, [row], args.cores, sweep=sweep)
    longest = max(runs, key=runs.get)
    lines = [
        "# What a longer training budget buys the demo (`benchmarks/bench_budget.py`)", "",
        "The demo's survey (default water, seed 0, 24 views at 320x240, RAW) through the whole "
        "workflow once; each budget trains on the same COLMAP cameras (sweep variants), one "
        "training at a time. Means over the 3 held-out views, linear PSNR in dB; restored: "
        "the restored render against the clean truth (in brackets on the pixels two training "
        "views see); reprojected: with the training photographs' detail; water as signed "
        "error against the truth (R, G, B; `?` flagged as not determined, `!` the interval "
        "misses the truth); unseen: each held-out view's `unseen_surface_share` (its surface "
        "no training photograph sees, by the model's depth) with its held-out PSNR.", "",
        "| budget (min) | steps | held-out PSNR | restored (covered) | reprojected (covered) "
        "| restored photographs | `sigma_attn` | `sigma_bs` | `c_med` | unseen (PSNR) |",
        "|---|---|---|---|---|---|---|---|---|---|",
        *(budget_row(args.work, run, m) for run, m in runs.items()), "",
        f"The {runs[longest]:g}-minute run's quality snapshots (held-out and restored PSNR at "
        "the snapshots' reduced resolution; the water refits come at fixed shares of the "
        "budget, so a snapshot is not a shorter run):", "",
        *curve_lines(args.work, longest), "",
        footer(load_before, start),
    ]
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
