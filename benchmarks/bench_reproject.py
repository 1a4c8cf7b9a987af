"""Restored held-out views with the training photographs' detail reprojected, per setting.

For finished workflow runs of simulated datasets (``results/<dataset>``: ``poses/cameras.json``,
``train/model.pt``, ``simulate/truth``), every view is rendered once; the held-out views are then
restored with the restored training photographs' detail reprojected into them
(``seathru.nerf.reproject``, the render step with ``photos.restore: all``) at each pair of
``--tolerances`` (``render.photos.reproject_tolerance``) and ``--angles``
(``render.photos.reproject_angle``), and scored against the clean truth exactly as the evaluate
step scores them (``seathru.io.evaluation.truth_evaluation``: one colour gain, open water left
out, "covered" = pixels two or more training views see). Each row also gives the model's
restored render and the held-out photograph restored through it (which a novel view does not
have), and the seconds the reprojection took per view.

Usage::

    python benchmarks/bench_reproject.py --run /tmp/clone/results/demo [--run ...]
        [--tolerances 0.03,0.05,0.1] [--angles 4,8,16,90] [--out benchmarks/results/reproject.md]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from machine import cpu_name, load_average

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
OUT = REPO / "benchmarks" / "results" / "reproject.md"


def score_run(run: Path, settings: list[tuple[float, float]], work: Path) -> list[dict]:
    """Per setting and held-out view: the three restorations' PSNR and the reprojection's
    seconds."""
    import torch

    from seathru.io.cameras import read_cameras
    from seathru.io.evaluation import truth_evaluation
    from seathru.io.model import load_model
    from seathru.io.water import read_water
    from seathru.nerf import reproject
    from seathru.nerf.inference import frame_renderer
    from seathru.steps.render import render_dataset

    torch.set_num_threads(2)
    cameras = read_cameras(run / "poses" / "cameras.json")
    model_render = frame_renderer(load_model(run / "train" / "model.pt", torch.device("cpu")))
    cache: dict[str, dict] = {}

    def render_fn(frame, downscale: int) -> dict:   # each view rendered once for every setting
        if frame.name not in cache:
            cache[frame.name] = model_render(frame, downscale)
        return cache[frame.name]

    seconds: list[float] = []
    timed = reproject.restored_with_detail

    def timing(*args, **kwargs):
        start = time.perf_counter()
        result = timed(*args, **kwargs)
        seconds.append(time.perf_counter() - start)
        return result

    water = read_water(run / "train" / "water.json", missing_ok=True)
    rows = []
    reproject.restored_with_detail = timing
    try:
        for tolerance, angle in settings:
            out = work / f"{run.name}_{tolerance:g}_{angle:g}"
            seconds.clear()
            render_dataset(render_fn, cameras, out, {"path_frames": 0, "photos": {
                "restore": "all", "reproject_tolerance": tolerance, "reproject_angle": angle}})
            views = [{"view": f.name} for f in sorted(cameras.split("test"), key=lambda f: f.name)]
            truth_evaluation(run / "simulate" / "truth", out, cameras, views, water)
            label = f"{run.parents[1].name}/{run.name}"   # <clone>/results/<dataset>
            rows += [{"run": label, "setting": (tolerance, angle), "seconds": s, **view}
                     for view, s in zip(views, seconds)]
    finally:
        reproject.restored_with_detail = timed
    return rows


def table(rows: list[dict]) -> list[str]:
    lines = ["| run | tolerance | angle (deg) | reprojected, per view (all / covered) | "
             "reprojected, mean | restored render, mean | held-out photograph restored, mean | "
             "s / view |", "|---|---|---|---|---|---|---|---|"]
    for key in dict.fromkeys((r["run"], r["setting"]) for r in rows):
        part = [r for r in rows if (r["run"], r["setting"]) == key]

        def mean(column: str) -> str:
            return (f"{np.mean([r[column] for r in part]):.2f} / "
                    f"{np.mean([r[column + '_covered'] for r in part]):.2f}")

        views = ", ".join(f"{r['reprojected_restored_psnr_linear']:.2f} / "
                          f"{r['reprojected_restored_psnr_linear_covered']:.2f}" for r in part)
        lines.append(f"| {key[0]} | {key[1][0]:g} | {key[1][1]:g} | {views} | "
                     f"{mean('reprojected_restored_psnr_linear')} | "
                     f"{mean('restored_psnr_linear')} | {mean('photo_restored_psnr_linear')} | "
                     f"{np.mean([r['seconds'] for r in part]):.2f} |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, action="append", required=True)
    parser.add_argument("--tolerances", default="0.03,0.05,0.1")
    parser.add_argument("--angles", default="4,8,16,90")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    tolerances = [float(v) for v in args.tolerances.split(",")]
    angles = [float(v) for v in args.angles.split(",")]
    settings = [(t, 8.0) for t in tolerances] + [(0.05, a) for a in angles if a != 8.0]
    before = load_average()
    with tempfile.TemporaryDirectory() as work:
        rows = [row for run in args.run for row in score_run(run, settings, Path(work))]
    lines = ["# Held-out views restored with the training photographs' detail reprojected "
             "(`benchmarks/bench_reproject.py`)", "",
             f"Device: {cpu_name()}; load average before/after: {before} / {load_average()}. "
             f"Runs: {', '.join(str(r) for r in args.run)}. PSNR (dB, linear) against the clean "
             "truth as the evaluate step scores it, all pixels / the pixels two or more training "
             "views see; the held-out photograph restored is what a novel view does not have.",
             "", *table(rows), ""]
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
