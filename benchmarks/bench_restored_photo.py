"""Restored photographs against the restored render, per setting, on simulated runs.

For finished workflow runs of simulated datasets (``results/<dataset>``: ``poses/cameras.json``,
``train/model.pt``, ``simulate/truth``), the held-out views are rendered with their photographs
restored through the render (``seathru.radiometry.restore``) at each pair of ``--gains``
(``render.photos.max_gain``) and ``--detail-scales`` (``render.photos.detail_scale``), and scored against the clean truth exactly as the evaluate step does
(``seathru.io.evaluation.truth_evaluation``: one colour gain, open water left out, "covered" =
pixels two or more training views see). The photographs are the pipeline's own (ingested from
the simulated raw files: sensor noise, demosaicing, white balance), so the largest gain trades
the detail the model misses against the noise it magnifies, and the detail scale the colour the
model misses against a colour its water does not reproduce (which only a real dive shows:
``bench_reef.py``).

Usage::

    python benchmarks/bench_restored_photo.py --run /tmp/clone/results/demo [--run ...]
        [--gains 1,2,3,5,10] [--detail-scales 0,0.05] [--out benchmarks/results/restored_photo.md]
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
OUT = REPO / "benchmarks" / "results" / "restored_photo.md"


def score_run(run: Path, settings: list[tuple[float, float]], work: Path) -> list[dict]:
    """Per setting and held-out view: the restored render's and the restored photograph's
    PSNR."""
    import torch

    from seathru.io.cameras import read_cameras
    from seathru.io.evaluation import truth_evaluation
    from seathru.io.model import load_model
    from seathru.io.water import read_water
    from seathru.nerf.inference import frame_renderer
    from seathru.steps.render import render_dataset

    torch.set_num_threads(2)
    cameras = read_cameras(run / "poses" / "cameras.json")
    render_fn = frame_renderer(load_model(run / "train" / "model.pt", torch.device("cpu")))
    water = read_water(run / "train" / "water.json", missing_ok=True)
    rows = []
    for setting in settings:
        out = work / f"{run.name}_{setting[0]:g}_{setting[1]:g}"
        render_dataset(render_fn, cameras, out, {"path_frames": 0, "photos": {
            "restore": "test", "max_gain": setting[0], "detail_scale": setting[1]}})
        views = [{"view": f.name} for f in sorted(cameras.split("test"), key=lambda f: f.name)]
        truth_evaluation(run / "simulate" / "truth", out, cameras, views, water)
        rows += [{"run": run.name, "setting": setting, **view} for view in views]
    return rows


def write_results(rows: list[dict], settings: list[tuple[float, float]], out: Path,
                  seconds: float) -> None:
    lines = ["# Restored photographs (`benchmarks/bench_restored_photo.py`)", "",
             "PSNR (linear, dB) against the clean truth on the held-out views, as the evaluate "
             "step scores them: the model's restored render, and the view's photograph "
             "restored through the render, per largest gain (`render.photos.max_gain`) and "
             "detail scale (`render.photos.detail_scale`, 0: the whole residual); all pixels "
             "with a surface / covered (two or more training views see them).", "",
             "| run | view | restored render | "
             + " | ".join(f"photo, gain {g:g}, detail {d:g}" for g, d in settings) + " |",
             "|---|---|---|" + "---|" * len(settings)]
    keyed = {(r["run"], r["view"], r["setting"]): r for r in rows}
    for run, view in dict.fromkeys((r["run"], r["view"]) for r in rows):
        first = keyed[(run, view, settings[0])]
        cells = [f"{first['restored_psnr_linear']:.2f} / "
                 f"{first['restored_psnr_linear_covered']:.2f}"]
        for setting in settings:
            r = keyed[(run, view, setting)]
            cells.append(f"{r['photo_restored_psnr_linear']:.2f} / "
                         f"{r['photo_restored_psnr_linear_covered']:.2f}")
        lines.append(f"| {run} | {view} | " + " | ".join(cells) + " |")
    means = ["| mean | | " + " / ".join(
        f"{np.mean([r[c] for r in rows if r['setting'] == settings[0]]):.2f}"
        for c in ("restored_psnr_linear", "restored_psnr_linear_covered"))]
    for setting in settings:
        means.append(" / ".join(
            f"{np.mean([r[c] for r in rows if r['setting'] == setting]):.2f}"
            for c in ("photo_restored_psnr_linear", "photo_restored_psnr_linear_covered")))
    lines += [" | ".join(means) + " |", "",
              f"Machine: {cpu_name()}; load {load_average()}; {time.strftime('%Y-%m-%d')}; "
              f"{seconds:.0f} s.", ""]
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines))
    print("\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, action="append", required=True,
                        help="results/<dataset> of a finished simulated workflow run")
    parser.add_argument("--gains", default="1,2,3,5,10")
    parser.add_argument("--detail-scales", default="0,0.05")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    settings = [(float(g), float(d)) for d in args.detail_scales.split(",")
                for g in args.gains.split(",")]
    started = time.time()
    with tempfile.TemporaryDirectory(prefix="bench_restored_photo_") as work:
        rows = [row for run in args.run for row in score_run(run.resolve(), settings,
                                                             Path(work))]
    write_results(rows, settings, args.out, time.time() - started)


if __name__ == "__main__":
    main()
