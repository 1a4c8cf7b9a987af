"""Where a training run's time budget goes: the train step run as the workflow runs it, with the
trainer's parts timed from outside (the optimisation steps, the model trials, the water refits,
checkpoints, snapshots). Usage::

    python benchmarks/bench_run_time.py [--cameras results/demo/poses/cameras.json] \\
        [--minutes 3] [--threads 2] [--out benchmarks/results/run_time.md]

The optimisation steps inside the trials are counted in both rows (``_optimise_once`` and the
trial's own); one arm of each trial is thrown away (``seathru.nerf.selection``).
"""

from __future__ import annotations

import argparse
import collections
import functools
import shutil
import sys
import tempfile
import time
from pathlib import Path

from machine import cpu_name, load_average

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from seathru import cli  # noqa: E402
from seathru.nerf import model as model_module  # noqa: E402
from seathru.nerf import training  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "run_time.md"
TRAINER_PARTS = {"_optimise_once": "optimisation steps (trials' included)",
                 "select_view_dependence": "view-dependent colour trial",
                 "select_medium": "water trial", "refit_water": "water refits",
                 "_checkpoint": "checkpoints", "_take_snapshot": "in-memory snapshots",
                 "_quality_snapshot": "quality snapshots (not budget time)",
                 "test_psnr": "held-out PSNR for the log (not budget time)"}


def timed(owner, name: str, totals: collections.Counter, calls: collections.Counter) -> None:
    """Wrap ``owner.name`` so that its time and calls add to ``totals`` and ``calls``."""
    original = getattr(owner, name)

    @functools.wraps(original)
    def wrapper(*args, **kwargs):
        start = time.perf_counter()
        try:
            return original(*args, **kwargs)
        finally:
            totals[name] += time.perf_counter() - start
            calls[name] += 1

    setattr(owner, name, wrapper)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cameras", type=Path,
                        default=REPO / "results" / "demo" / "poses" / "cameras.json")
    parser.add_argument("--minutes", type=float, default=3.0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    totals, calls = collections.Counter(), collections.Counter()
    for name in TRAINER_PARTS:
        timed(training.Trainer, name, totals, calls)
    timed(training.Trainer, "run", totals, calls)
    timed(model_module.SeaThruModel, "set_progress", totals, calls)   # one per loop turn
    load_before = load_average()
    work = Path(tempfile.mkdtemp(prefix="bench_run_time_"))
    try:
        code = cli.main(["train", "--cameras", str(args.cameras), "--out", str(work / "train"),
                         "--checkpoint-dir", str(work / "checkpoints"), "--threads",
                         str(args.threads), "--max-minutes", str(args.minutes), "--no-progress"])
        steps = (work / "train" / "train_log.csv").read_text().splitlines()[-1].split(",")[0]
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if code:
        raise SystemExit(f"the train step failed ({code})")
    budget = args.minutes * 60
    lines = ["# Where a training run's time goes (`benchmarks/bench_run_time.py`)", "",
             f"Device: {cpu_name()}, {args.threads} thread(s); load {load_before} before, "
             f"{load_average()} after. Camera set: `{args.cameras}`, the train step's defaults "
             f"with a {args.minutes:g}-min budget: {steps} steps (the step counter, trial steps "
             f"kept included), {calls['set_progress']} turns of the training loop, "
             f"`Trainer.run` {totals['run']:.1f} s.", "",
             "| part | seconds | share of the budget | calls |", "|---|---|---|---|"]
    for name, label in TRAINER_PARTS.items():
        lines.append(f"| {label} | {totals[name]:.1f} | {100 * totals[name] / budget:.0f}% | "
                     f"{calls[name]} |")
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
