"""2x sooner? The current code at half the budget against an older commit at the full budget.

Issue 14 asks that the demo reach its 3-minute PSNR in half the time. This trains, one after
the other on the same camera set (the demo's poses by default), the code of ``--baseline`` (a
git commit: by default c9edca9, main when the issue was filed) for ``--minutes`` and the
working tree for the same budget and for half of it, renders the held-out views with each run's
own code and scores all of them with the working tree's evaluate step (held-out PSNR on whole
images, linear; restored vs clean where the dataset has a truth folder). Written to
``benchmarks/results/sooner.md``; the verdict is whether the half-budget run reaches the
baseline's full-budget PSNR. Run it with nothing else on the machine: the budgets are wall-clock
training time. Usage::

    python benchmarks/bench_sooner.py [--cameras results/demo/poses/cameras.json] \\
        [--truth results/demo/simulate/truth] [--baseline c9edca9] [--minutes 3] [--repeats 1]
    python benchmarks/bench_sooner.py --summarise-only --work DIR --repeats 2  # existing runs
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pandas as pd

from machine import cpu_name, load_average

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from seathru.io.evaluation import read_summary  # noqa: E402
from seathru.io.water import read_water  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "sooner.md"
BASELINE = "c9edca9"


def export_source(ref: str, into: Path) -> Path:
    """The ``src`` folder of commit ``ref`` under ``into`` (git archive: no checkout needed)."""
    into.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(["git", "-C", str(REPO), "archive", ref, "src"], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    return into / "src"


def seathru(source: Path, args: list[str], log: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(source)}
    with log.open("w") as handle:
        subprocess.run([sys.executable, "-m", "seathru.cli", *args], env=env, check=True,
                       stdout=handle, stderr=subprocess.STDOUT)


def run_once(name: str, source: Path, minutes: float, cameras: Path, truth: Path | None,
             work: Path, threads: int, train_args: tuple[str, ...] = ()) -> dict:
    """Train (with ``train_args`` on top of the defaults), render and evaluate one run in
    ``work/name``; its figures (:func:`read_row`)."""
    out = work / name
    seathru(source, ["train", "--cameras", str(cameras), "--out", str(out / "train"),
                     "--checkpoint-dir", str(out / "checkpoints"), "--threads", str(threads),
                     "--max-minutes", str(minutes), *train_args], out.with_suffix(".train.log"))
    seathru(source, ["render", "--model", str(out / "train" / "model.pt"), "--cameras",
                     str(cameras), "--out", str(out / "render"), "--threads", str(threads),
                     "--path-frames", "0"], out.with_suffix(".render.log"))
    evaluate = ["evaluate", "--cameras", str(cameras), "--renders", str(out / "render"),
                "--train-dir", str(out / "train"), "--out", str(out / "evaluate"),
                "--threads", str(threads)]
    if truth is not None:
        evaluate += ["--truth", str(truth)]
    seathru(REPO / "src", evaluate, out.with_suffix(".evaluate.log"))
    return read_row(name, minutes, work)


def water_errors(summary) -> str:
    """Signed error of each fitted water parameter against the truth, per channel, in %."""
    water = summary.truth.water if summary.truth else None
    if water is None or not water.fitted:
        return "—"
    def error(fitted: float, true: float) -> str:   # clear water: the truth is 0
        return f"{100 * (fitted / true - 1):+.0f}" if true else f"{fitted:.2g} (truth 0)"

    return "; ".join(f"{key} " + ", ".join(error(fitted, true) for fitted, true
                                           in zip(water.fitted[key], water.truth[key]))
                     for key in ("sigma_attn", "sigma_bs", "c_med"))


def final_fit_errors(summary, water_path: Path) -> str:
    """Signed error of the final assessment's own attenuation fit (water.json's
    ``uncertainty.surface_fit``, on the trained model's final surfaces) against the truth, in %:
    where it differs from the trained value, the water was held from geometry that changed."""
    water = summary.truth.water if summary.truth else None
    if water is None or not water.fitted or not water_path.is_file():
        return "—"
    report = read_water(water_path)
    if not report.uncertainty:
        return "—"
    fit = report.uncertainty["surface_fit"]
    trained = report.normalised.sigma_attn
    return ", ".join(f"{100 * (fitted / true * final / held - 1):+.0f}" for fitted, true, final, held
                     in zip(water.fitted["sigma_attn"], water.truth["sigma_attn"],
                            fit["sigma_attn"], trained))


ROW_HEADER = ("| run | steps | held-out PSNR (dB) | restored vs clean (dB) | restored photographs "
              "vs clean (dB) | water | sigma_attn by the final surfaces |")


def table_cells(row: dict) -> str:
    """``| run | steps | held-out PSNR | restored vs clean | restored photographs | water |
    final fit |`` of a :func:`read_row` (restored figures: all pixels with a surface, and in
    brackets those two or more training views see)."""
    def both(key: str) -> str:
        if row.get(key) is None:
            return "—"
        covered = row.get(f"{key}_covered")
        return f"{row[key]:.2f}" + ("" if covered is None else f" ({covered:.2f})")

    return (f"| {row['run']} | {row['steps']} | {row['psnr']:.2f} | {both('restored')} "
            f"| {both('photos')} | {row['water']} | {row.get('final_fit', '—')} |")


def arm_table(rows: list[tuple[str, dict]]) -> list[str]:
    """A markdown table of ``(arm, read_row(...))`` pairs, one line per run."""
    return ["| arm " + ROW_HEADER, "|---" * 8 + "|", *(f"| {arm} {table_cells(row)}" for arm, row in rows)]


def read_row(name: str, minutes: float, work: Path) -> dict:
    """One run's figures from its evaluate step's ``summary.json``."""
    summary = read_summary(work / name / "evaluate" / "summary.json")
    training = summary.training
    row = {"run": name, "budget_s": 60 * minutes,
           "steps": training.steps if training else None,
           "training_s": training.time_s if training else None,
           "psnr": summary.means["psnr_linear"],
           "restored": summary.means.get("restored_psnr_linear"),
           "restored_covered": summary.means.get("restored_psnr_linear_covered"),
           "photos": summary.means.get("photo_restored_psnr_linear"),
           "photos_covered": summary.means.get("photo_restored_psnr_linear_covered"),
           "water": water_errors(summary),
           "final_fit": final_fit_errors(summary, work / name / "train" / "water.json")}
    print(row, flush=True)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cameras", type=Path,
                        default=REPO / "results" / "demo" / "poses" / "cameras.json")
    parser.add_argument("--truth", type=Path, default=REPO / "results" / "demo" / "simulate"
                        / "truth", help="simulator truth folder (skipped when absent)")
    parser.add_argument("--baseline", default=BASELINE, help="git commit to compare against")
    parser.add_argument("--baseline-src", type=Path, default=None,
                        help="the baseline's src folder, already exported (instead of git)")
    parser.add_argument("--minutes", type=float, default=3.0)
    parser.add_argument("--repeats", type=int, default=1, help="runs of each configuration")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--work", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--summarise-only", action="store_true",
                        help="only write the table from the runs already in --work")
    args = parser.parse_args()
    if not args.cameras.is_file():
        sys.exit(f"{args.cameras}: camera file not found; run the demo first (make demo) or "
                 "pass --cameras")
    truth = args.truth if args.truth.is_dir() else None
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_sooner_"))
    work.mkdir(parents=True, exist_ok=True)
    commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
                            capture_output=True, text=True).stdout.strip()
    commit = f"{commit} (working tree)" if commit else "working tree"
    baseline_src = args.baseline_src or (work / "baseline" / "src" if args.summarise_only
                                         else export_source(args.baseline, work / "baseline"))
    load_before = load_average()
    rows = []
    for repeat in range(args.repeats):
        for name, source, minutes in (("baseline", baseline_src, args.minutes),
                                      ("current_half", REPO / "src", args.minutes / 2),
                                      ("current", REPO / "src", args.minutes)):
            row = read_row(f"{name}_{repeat}", minutes, work) if args.summarise_only else \
                run_once(f"{name}_{repeat}", source, minutes, args.cameras, truth, work,
                         args.threads)
            rows.append({**row, "config": name})
    table = pd.DataFrame(rows)
    mean = table.groupby("config")["psnr"].mean()
    reached = mean["current_half"] >= mean["baseline"]
    lines = [
        "# 2x sooner: the current code at half the budget against an older commit "
        "(`benchmarks/bench_sooner.py`)", "",
        f"Device: {cpu_name()}, {args.threads} training threads; load average before/after "
        f"{load_before} / {load_average()}. Camera set `{args.cameras}`; baseline commit "
        f"{args.baseline}, current {commit}; each configuration run "
        f"{args.repeats} time(s), one run at a time. Held-out PSNR on whole images (linear), "
        "all runs scored by the current evaluate step.", "",
        "| run | code | budget (s) | steps | training (s) | held-out PSNR (dB) "
        "| restored vs clean (dB) | water against the truth (R, G, B, %) |",
        "|---|---|---|---|---|---|---|---|"]
    for row in rows:
        code = args.baseline if row["config"] == "baseline" else commit
        restored = f"{row['restored']:.2f}" if pd.notna(row["restored"]) else "—"
        lines.append(f"| {row['run']} | {code} | {row['budget_s']:.0f} | {row['steps']} | "
                     f"{row['training_s']:.0f} | {row['psnr']:.2f} | {restored} | {row['water']} |")
    lines += ["", f"Mean held-out PSNR: baseline at {60 * args.minutes:.0f} s "
              f"{mean['baseline']:.2f} dB; current at {30 * args.minutes:.0f} s "
              f"{mean['current_half']:.2f} dB, at {60 * args.minutes:.0f} s "
              f"{mean['current']:.2f} dB. Half the budget "
              + ("reaches" if reached else "does not reach")
              + f" the baseline's full-budget PSNR ({mean['current_half'] - mean['baseline']:+.2f}"
              " dB): 2x sooner " + ("reached." if reached else "not reached.")]
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
