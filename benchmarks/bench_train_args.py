"""Training settings against each other on one camera file, side by side.

Each arm is a name and the ``seathru train`` flags it adds to the defaults; every arm is
trained for the same budget, rendered and scored by the evaluate step (against the simulator's
truth when given), the arms interleaved within each repeat, one run at a time. Usage::

    python benchmarks/bench_train_args.py --cameras results/demo/poses/cameras.json \\
        --truth results/demo/simulate/truth --arm default= \\
        --arm far3="--sampler.far-factor 3" --repeats 2 --out benchmarks/results/far_factor.md

``--summarise-only`` writes the table from the runs already in ``--work`` (``<arm>_<repeat>``).
Every run uses a copy of ``src/`` taken when the benchmark starts (``--work``/``src``), so the
working tree may change while it runs.
"""

from __future__ import annotations

import argparse
import shlex
import shutil
import time
from pathlib import Path

from bench_sooner import REPO, arm_table, read_row, run_once
from machine import cpu_name, load_average


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cameras", type=Path, required=True, help="a poses step's cameras.json")
    parser.add_argument("--truth", type=Path, default=None,
                        help="the simulator's truth folder (results/<dataset>/simulate/truth)")
    parser.add_argument("--arm", action="append", required=True,
                        help='NAME=FLAGS, e.g. far3="--sampler.far-factor 3" (FLAGS may be empty)')
    parser.add_argument("--minutes", type=float, default=3.0)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--work", type=Path, default=Path("/tmp/bench_train_args"))
    parser.add_argument("--summarise-only", action="store_true")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    arms = {}
    for arm in args.arm:
        name, _, flags = arm.partition("=")
        arms[name] = tuple(shlex.split(flags))
    load_before = load_average()
    source = args.work / "src"
    if not args.summarise_only:
        shutil.rmtree(source, ignore_errors=True)
        shutil.copytree(REPO / "src", source, ignore=shutil.ignore_patterns("__pycache__"))
    rows = []
    for repeat in range(args.repeats):
        for name, flags in arms.items():
            run = f"{name}_{repeat}"
            if args.summarise_only:
                row = read_row(run, args.minutes, args.work)
            else:
                args.work.mkdir(parents=True, exist_ok=True)
                row = run_once(run, source, args.minutes, args.cameras, args.truth,
                               args.work, args.threads, flags)
            rows.append((name, row))
    lines = ["# Training settings side by side (`benchmarks/bench_train_args.py`)", "",
             f"Device: {cpu_name()}, {args.threads} training threads; load average before/after "
             f"{load_before} / {load_average()}; {time.strftime('%Y-%m-%d')}. Camera file "
             f"`{args.cameras}`; {args.minutes:g} min of training a run, the arms interleaved "
             "within each repeat, one run at a time; scored by the evaluate step (PSNR linear; "
             "water: signed error against the truth, %, R, G, B).", "",
             "Arms: " + "; ".join(f"`{name}`: `{' '.join(flags) or '(defaults)'}`"
                                  for name, flags in arms.items()) + ".", "",
             *arm_table(rows)]
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
