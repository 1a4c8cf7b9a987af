"""Speed against error: every training preset on the same scenes, in one run of the workflow.

Runs the Snakemake workflow in a scratch folder on a sheet of datasets (default: the demo
dive, simulated, and the real d3_reef frames from ../shared/data when present), each under the
sweep variants ``balanced``, ``fast``, ``quality``, ``paper`` and shorter budgets, with the sheet
row itself on the default ``train.preset=auto``. Training budget per run ``--minutes``;
``--cores`` jobs share the machine one training at a time, so the runs are timed alike. Then
reads the report's ``frontier.csv`` and each run's quality snapshots
(``evaluate/frontier.csv``) and writes ``benchmarks/results/frontier.md``:

- per dataset and run: capacity level, passes over the training pixels, final held-out PSNR,
  training time, time to within 0.5 dB of its own final PSNR, render time per frame,
  restored-vs-clean PSNR for simulated dives;
- whether ``auto`` lands within 0.5 dB of the best named preset at equal or less training time;
- the time each run needed to reach the ``balanced`` preset's PSNR at the full budget (from the
  log-spaced snapshots: an upper bound, the first snapshot at or above it).

Usage::

    python benchmarks/bench_frontier.py [--minutes 3] [--datasets demo,d3_reef] [--work DIR]
        [--variants balanced,fast,quality,auto_half,fast_half]   # all but paper
    python benchmarks/bench_frontier.py --summarise-only --work DIR   # an existing run
"""

from __future__ import annotations

import argparse
import csv
import os
import platform
import subprocess
import sys
from pathlib import Path

import yaml

from machine import cpu_name, load_average

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "frontier.md"
REEF = REPO.parent / "shared" / "data" / "d3_reef"
WITHIN_DB = 0.5


def variants(minutes: float) -> dict[str, str]:
    half = round(minutes / 2, 3)
    return {"balanced": "train.preset=balanced", "fast": "train.preset=fast",
            "quality": "train.preset=quality",
            # its MLP renders ~40 rays/s on a CPU: small snapshots and test renders
            "paper": "train.preset=paper; train.quality_snapshot_downscale=16; "
                     "render.downscale=16",
            "auto_half": f"train.max_minutes={half}",
            "fast_half": f"train.preset=fast; train.max_minutes={half}"}


def write_config(work: Path, datasets: list[str], minutes: float, threads: int,
                 sweep: str = "all") -> None:
    (work / "config").mkdir(parents=True, exist_ok=True)
    config = {"datasets": "config/datasets.tsv", "results": "results", "logs": "logs",
              "simulate": {"path": "survey"}, "train": {"max_minutes": minutes},
              "render": {"path_frames": 0}, "sweep": variants(minutes),
              "resources": {"default": {"threads": 1, "mem_mb": 4000, "runtime": 30, "gpu": 0},
                            "train": {"threads": threads, "mem_mb": 16000, "runtime": 240},
                            "render": {"threads": threads, "mem_mb": 8000, "runtime": 60},
                            "ingest": {"threads": threads}, "poses": {"threads": threads}}}
    (work / "config" / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    rows = ["dataset\tsource\tpath\toptions\tsweep"]
    for name in datasets:
        if name == "demo":
            rows.append(f"demo\tsimulated\t\t\t{sweep}")
        elif name == "d3_reef":
            rows.append(f"d3_reef\timages\t{REEF}\t\t{sweep}")
    (work / "config" / "datasets.tsv").write_text("\n".join(rows) + "\n")


def run_workflow(work: Path, cores: int) -> int:
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    command = [sys.executable, "-m", "snakemake", "--snakefile",
               str(REPO / "workflow" / "Snakefile"), "--directory", str(work), "--configfile",
               str(work / "config" / "config.yaml"), "--cores", str(cores), "--keep-going",
               "--rerun-incomplete"]
    with open(work / "workflow.log", "w") as log:
        return subprocess.call(command, env=env, stdout=log, stderr=subprocess.STDOUT)


def _number(value) -> float | None:
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if number == number else None


def snapshot_curve(work: Path, run: str) -> list[tuple[float, float]]:
    path = work / "results" / run / "evaluate" / "frontier.csv"
    if not path.is_file():
        return []
    rows = list(csv.DictReader(path.open()))
    return [(t, p) for t, p in ((_number(r.get("elapsed_s")), _number(r.get("test_psnr_images")))
                                for r in rows) if t is not None and p is not None]


def first_time_at(curve: list[tuple[float, float]], level: float) -> float | None:
    return next((t for t, p in curve if p >= level), None)


def _fmt(value, digits: int = 2) -> str:
    number = _number(value)
    return "—" if number is None else f"{number:.{digits}f}"


def summarise(work: Path, out: Path, note: str) -> str:
    rows = list(csv.DictReader((work / "results" / "report" / "frontier.csv").open()))
    lines = ["# Speed against error (`benchmarks/bench_frontier.py`)", "", note, ""]
    for dataset in dict.fromkeys(r["dataset"] for r in rows):
        runs = [r for r in rows if r["dataset"] == dataset]
        curves = {r["run"]: snapshot_curve(work, r["run"]) for r in runs}
        balanced = next((r for r in runs if r["variant"] == "balanced"), None)
        reference = _number(balanced["snapshot_final_psnr"]) if balanced else None
        lines += [f"## {dataset}", "",
                  "| run | capacity | passes | held-out PSNR (dB) | training (s) | "
                  f"to within {WITHIN_DB:g} dB (s) | to balanced's final PSNR (s) | "
                  "render (s/frame) | restored vs clean (dB) |", "|---" * 9 + "|"]
        for r in runs:
            reach = first_time_at(curves[r["run"]], reference) if reference else None
            lines.append(
                f"| {r['run']} | {r.get('capacity') or '—'} | {_fmt(r.get('passes'))} | "
                f"{_fmt(r['psnr_linear'])} | {_fmt(r['train_time_s'], 0)} | "
                f"{_fmt(r.get('time_to_within_0.5db_s'), 0)} | {_fmt(reach, 0)} | "
                f"{_fmt(r['render_s_per_frame'])} | {_fmt(r['restored_psnr_linear'])} |")
        auto = next((r for r in runs if r["variant"] in ("", "(sheet row)")), None)
        named = [r for r in runs if r["variant"] in ("balanced", "fast", "quality", "paper")
                 and _number(r["psnr_linear"]) is not None]
        if auto and named and _number(auto["psnr_linear"]) is not None:
            best = max(named, key=lambda r: _number(r["psnr_linear"]))
            gap = _number(best["psnr_linear"]) - _number(auto["psnr_linear"])
            verdict = "within" if gap <= WITHIN_DB else "NOT within"
            lines += ["", f"auto ({auto.get('capacity')}) reaches "
                      f"{_fmt(auto['psnr_linear'])} dB in {_fmt(auto['train_time_s'], 0)} s; the "
                      f"best named preset, {best['variant']}, {_fmt(best['psnr_linear'])} dB in "
                      f"{_fmt(best['train_time_s'], 0)} s: auto is {verdict} {WITHIN_DB:g} dB "
                      f"({gap:+.2f} dB)."]
        lines.append("")
    text = "\n".join(lines)
    out.write_text(text)
    return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=Path("/tmp/bench_frontier"))
    parser.add_argument("--datasets", default="demo,d3_reef")
    parser.add_argument("--minutes", type=float, default=3.0)
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--variants", default="all",
                        help="comma-separated sweep variants beside the sheet row (default all: "
                             f"{', '.join(variants(3.0))}); 'paper' alone takes over 30 min to "
                             "evaluate on a 2-core CPU")
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--summarise-only", action="store_true")
    args = parser.parse_args()
    datasets = [d for d in args.datasets.split(",") if d != "d3_reef" or REEF.is_dir()]
    before = load_average()
    if not args.summarise_only:
        write_config(args.work, datasets, args.minutes, args.threads, args.variants)
        code = run_workflow(args.work, args.cores)
        print(f"workflow exit code {code} (log: {args.work / 'workflow.log'})")
    note = (f"Device: {cpu_name()}, {args.threads} training thread(s), {args.cores} cores for "
            f"the workflow; Python {platform.python_version()}; load average before/after "
            f"{before} / {load_average()}. Each run trained up to {args.minutes:g} min "
            f"(`_half`: half that) one after the other in one workflow run at `{args.work}`; "
            "PSNR on the held-out views (linear); times from the quality snapshots (log-spaced "
            "training times, so 'to ...' is the first snapshot at or above the level). The "
            "sheet row itself runs `train.preset=auto`.")
    print(summarise(args.work, args.out, note))


if __name__ == "__main__":
    main()
