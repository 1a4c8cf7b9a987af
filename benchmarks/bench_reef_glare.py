"""The glare correction on a real dive: trained with ``train.glare`` auto and off, side by side.

On d3_reef the photographs are brighter next to the open water in the frame
(``seathru.radiometry.glare``). This trains the same poses (``--poses``: a finished poses step's
folder) with the correction (``auto``) and without it (``off``) for each seed, renders and
evaluates each run with the pipeline's own steps, and writes ``benchmarks/results/
reef_glare.md``: the correction fitted, how much of the input's colour change with range along
the COLMAP tracks each restoration removes (all tracks, the nearest 90%, and beside the
distance to the open water), held-out PSNR (against the photographs as they are: the
corrected runs' full renders get the glare back), the share of the held-out open water rendered empty and the water
fitted. The arms run one after the other on the same threads, so their step counts compare.

Usage::

    python benchmarks/bench_reef_glare.py --poses /tmp/reef/results/d3_reef/poses \\
        --work /tmp/reef_glare [--seeds 0 1] [--minutes 3] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from bench_reef import open_water_scores
from machine import cpu_name

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "reef_glare.md"
ARMS = ("off", "auto")


def _run(command: list[str], log: Path) -> None:
    with open(log, "w") as handle:
        done = subprocess.run(command, stdout=handle, stderr=subprocess.STDOUT)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed: see {log}")


def run_arm(poses: Path, work: Path, arm: str, seed: int, minutes: float, threads: int,
            glare: str | None = None, train_args: tuple[str, ...] = ()) -> Path:
    """Train (``train.glare`` ``glare``, else ``arm``; ``train_args`` on top), render and
    evaluate one arm; returns its folder. A step whose output is there already is not run
    again (delete ``render/`` and ``eval/`` to measure a trained model again)."""
    folder = work / f"{arm}_seed{seed}"
    folder.mkdir(parents=True, exist_ok=True)
    seathru = [sys.executable, "-m", "seathru.cli"]
    cameras = str(poses / "cameras.json")
    if not (folder / "train" / "model.pt").is_file():
        _run(seathru + ["train", "--cameras", cameras, "--out", str(folder / "train"),
                        "--checkpoint-dir", str(folder / "checkpoints"), "--threads",
                        str(threads), "--max-minutes", str(minutes), "--seed", str(seed),
                        "--glare", glare or arm, "--no-progress", *train_args],
             folder / "train.log")
    if not (folder / "render" / "render_stats.json").is_file():
        _run(seathru + ["render", "--model", str(folder / "train" / "model.pt"), "--cameras",
                        cameras, "--out", str(folder / "render"), "--threads", str(threads),
                        "--path-frames", "0", "--photos.restore", "all"], folder / "render.log")
    if not (folder / "eval" / "summary.json").is_file():
        _run(seathru + ["evaluate", "--renders", str(folder / "render"), "--cameras", cameras,
                        "--train-dir", str(folder / "train"), "--out", str(folder / "eval"),
                        "--threads", str(threads)], folder / "evaluate.log")
    return folder


def _percent(value) -> str:
    return "-" if value is None else f"{100 * value:.0f}%"


def _triple(values, digits: int = 3) -> str:
    return ", ".join(f"{v:.{digits}f}" for v in values)


def row(folder: Path, poses: Path) -> dict:
    summary = json.loads((folder / "eval" / "summary.json").read_text())
    selection = json.loads((folder / "train" / "selection.json").read_text())
    water = json.loads((folder / "train" / "water.json").read_text())
    slope = summary["track_colour_slope"]
    every, near = slope["all_views"], slope["near_tracks"]
    beside = every.get("near_open_water") or {}
    glare = selection.get("glare_correction")
    log_rows = (folder / "train" / "train_log.csv").read_text().strip().splitlines()
    steps = int(log_rows[-1].split(",")[0]) if len(log_rows) > 1 else 0
    return {
        "glare": "-" if glare is None else f"{glare['coefficient']:+.3f}",
        "steps": steps,
        "psnr": summary["means"]["psnr_linear"],
        "render": _percent(every.get("reduction_overall")),
        "photos": _percent(every["photographs"].get("reduction_overall")),
        "render_near": _percent(near.get("reduction_overall")),
        "render_beside": _percent((beside.get("restored") or {}).get("reduction_overall")),
        "photos_beside": _percent((beside.get("photographs") or {}).get("reduction_overall")),
        "restored_slope": _triple(every["restored"]["slope"]),
        "photos_slope": _triple(every["photographs"]["restored"]["slope"]),
        "full_slope": _triple(every["rendered"]["slope"]),
        "input_slope": _triple(every["input"]["slope"]),
        "open_water_empty": open_water_scores(folder, poses / "cameras.json")["empty_share"],
        "medium": selection.get("chosen"),
        "sigma_attn": _triple(water["sigma_attn"]), "sigma_bs": _triple(water["sigma_bs"]),
        "c_med": _triple(water["c_med"]),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--poses", type=Path, required=True, help="a poses step's folder")
    parser.add_argument("--work", type=Path, required=True, help="where the runs go")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--minutes", type=float, default=3.0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    started = time.time()
    rows = []
    for seed in args.seeds:
        for arm in ARMS:
            folder = run_arm(args.poses.resolve(), args.work.resolve(), arm, seed, args.minutes,
                             args.threads)
            rows.append({"arm": arm, "seed": seed, **row(folder, args.poses.resolve())})
            print(f"{arm} seed {seed}: {rows[-1]}", flush=True)
    lines = [
        "# The glare correction on d3_reef (`benchmarks/bench_reef_glare.py`)", "",
        f"Poses: `{args.poses}`; {args.minutes:g}-min trainings, {args.threads} threads, one at "
        f"a time, on {cpu_name()}; {time.strftime('%Y-%m-%d')}, {len(rows)} runs (steps "
        f"already done in the work folder are reused; this call took "
        f"{(time.time() - started) / 60:.0f} min). `train.glare` off against auto (the "
        "correction's coefficient: log colour per unit of log distance to the open water in "
        "the image, one for every channel). Share of the input's change of colour with range "
        "along the COLMAP tracks (log colour per unit, over windows) that each restoration "
        "removes, overall as the report gives it: all tracks (the issue's figure), the "
        "nearest 90% of the tracks, and fitted beside the distance to the open water. "
        "Held-out PSNR is against the photographs as they are (a corrected run's full render "
        "gets the glare back, `seathru.io.renders.split_glare`).", "",
        "| arm | seed | correction | steps | held-out PSNR | restored render | restored "
        "photographs | render, nearest 90% | render beside distance | photographs beside "
        "distance | open water empty |",
        "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['arm']} | {r['seed']} | {r['glare']} | {r['steps']} | "
                     f"{r['psnr']:.2f} | {r['render']} | {r['photos']} | {r['render_near']} | "
                     f"{r['render_beside']} | {r['photos_beside']} | "
                     f"{_percent(r['open_water_empty'])} |")
    lines += ["", f"Slopes (R, G, B; the input's: {rows[0]['input_slope']}) and the water "
              "fitted (COLMAP units):", "",
              "| arm | seed | restored render | restored photographs | full render | medium "
              "| sigma_attn | sigma_bs | c_med |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['arm']} | {r['seed']} | {r['restored_slope']} | "
                     f"{r['photos_slope']} | {r['full_slope']} | {r['medium']} | "
                     f"{r['sigma_attn']} | {r['sigma_bs']} | {r['c_med']} |")
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
