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
    """Per setting and held-out view: the three restorations' PSNR (the render step at each
    setting, ``bench_restored_photo.scored_photo_settings``) and the reprojection's seconds."""
    from bench_restored_photo import scored_photo_settings
    from seathru.nerf import reproject

    seconds: list[float] = []
    timed = reproject.restored_and_support

    def timing(*args, **kwargs):   # the render step calls it once per held-out view
        start = time.perf_counter()
        result = timed(*args, **kwargs)
        seconds.append(time.perf_counter() - start)
        return result

    photos = [{"restore": "all", "reproject_tolerance": tolerance, "reproject_angle": angle}
              for tolerance, angle in settings]
    reproject.restored_and_support = timing
    try:
        scored = scored_photo_settings(run, photos, work)
    finally:
        reproject.restored_and_support = timed
    label = f"{run.parents[1].name}/{run.name}"   # <clone>/results/<dataset>
    views = [view for per_setting in scored for view in per_setting]
    keys = [setting for setting, per_setting in zip(settings, scored) for _ in per_setting]
    return [{"run": label, "setting": setting, "seconds": s, **view}
            for setting, view, s in zip(keys, views, seconds)]


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
