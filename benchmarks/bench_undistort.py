"""Bilinear against cubic undistortion, side by side on one COLMAP model (the demo's).

The poses step resamples every linear image onto COLMAP's undistorted pinhole camera. This
re-undistorts the demo's COLMAP model (``--source colmap-model``, so both arms share the poses)
with each ``--undistort-interpolation``, then trains, renders and scores each arm in turn
(interleaved, ``--repeats`` times, 3 min each by default), and writes
``benchmarks/results/undistort.md``: held-out PSNR, restored vs clean and the water against the
truth. Run it with nothing else on the machine: the budgets are wall-clock. Usage::

    python benchmarks/bench_undistort.py [--run results/demo] [--minutes 3] [--repeats 2]
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from bench_sooner import REPO, ROW_HEADER, run_once, seathru, table_cells
from machine import cpu_name, load_average

ARMS = ("linear", "cubic")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, default=REPO / "results" / "demo",
                        help="a finished run of a simulated dive (ingest/, poses/sparse, "
                             "simulate/truth)")
    parser.add_argument("--minutes", type=float, default=3.0)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--work", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results"
                        / "undistort.md")
    args = parser.parse_args()
    sparse, truth = args.run / "poses" / "sparse", args.run / "simulate" / "truth"
    if not sparse.is_dir():
        sys.exit(f"{sparse}: no COLMAP model; run the demo first (make demo) or pass --run")
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_undistort_"))
    work.mkdir(parents=True, exist_ok=True)
    for arm in ARMS:
        poses = work / f"poses_{arm}"
        if not (poses / "cameras.json").is_file():
            seathru(REPO / "src", ["poses", "--ingest", str(args.run / "ingest"), "--out",
                                   str(poses), "--source", "colmap-model", "--source-dir",
                                   str(sparse), "--undistort-interpolation", arm],
                    work / f"poses_{arm}.log")
            shutil.copytree(sparse, poses / "sparse")   # the sparse-depth loss reads it
    commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
                            capture_output=True, text=True).stdout.strip()
    load_before = load_average()
    rows = []
    for repeat in range(args.repeats):
        for arm in ARMS:
            row = run_once(f"{arm}_{repeat}", REPO / "src", args.minutes,
                           work / f"poses_{arm}" / "cameras.json",
                           truth if truth.is_dir() else None, work, args.threads)
            rows.append({**row, "arm": arm})
    lines = ["# Bilinear against cubic undistortion (`benchmarks/bench_undistort.py`)", "",
             f"Device: {cpu_name()}, {args.threads} training threads; load average before/after "
             f"{load_before} / {load_average()}. Code {commit} (working tree); the demo's COLMAP "
             f"model undistorted both ways; {args.minutes:g} min of training a run, the arms "
             "interleaved, one run at a time. Water: signed error against the truth, %, "
             "R, G, B.", "",
             ROW_HEADER, "|---" * 7 + "|"]
    lines += [table_cells(row) for row in rows]
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
