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
``--real-run``).

``--water-dive`` takes a dive of ``bench_water.py``'s work folder instead (``<work>/survey_<water>``:
true cameras, ``train_cues/model.pt``), whose photographs are the truth with water taken through
the simulator's sensor again (``bench_water.sensor_photo``), scored as that benchmark scores
them, and also what limits them: the exact restoration of the sensor photograph with the true
water and range, and the noise-free image restored through the model.
``--real-run`` takes a workflow run of a real dive (``results/d3_reef``): every photograph
is restored at each setting and the slope of log colour against range along the COLMAP tracks is
compared with the input's, both averaged over the evaluate step's window
(``seathru.io.tracks.restored_photo_colours``), over all tracks, the nearest 90% and the farthest
10%.

Usage::

    python benchmarks/bench_restored_photo.py --run /tmp/clone/results/demo [--run ...]
        [--water-dive /tmp/bw/survey_default ...] [--real-run /tmp/reef/results/d3_reef]
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


def scored_photo_settings(run: Path, photos: list[dict], work: Path) -> list[list[dict]]:
    """The render step on a finished simulated run at each of ``photos`` (``render.photos``
    settings), every view rendered once for all of them, the held-out views scored as the
    evaluate step scores them (``truth_evaluation``): per setting, a row per held-out view."""
    import torch

    from seathru.io.cameras import read_cameras
    from seathru.io.evaluation import truth_evaluation
    from seathru.io.model import load_model
    from seathru.io.water import read_water
    from seathru.nerf.inference import frame_renderer
    from seathru.steps.render import render_dataset

    torch.set_num_threads(2)
    cameras = read_cameras(run / "poses" / "cameras.json")
    model_render = frame_renderer(load_model(run / "train" / "model.pt", torch.device("cpu")))
    renders: dict[tuple[str, int], dict] = {}

    def render_fn(frame, downscale: int) -> dict:
        if (frame.name, downscale) not in renders:
            renders[frame.name, downscale] = model_render(frame, downscale)
        return renders[frame.name, downscale]

    water = read_water(run / "train" / "water.json", missing_ok=True)
    scored = []
    for index, setting in enumerate(photos):
        out = work / f"{run.name}_{index}"
        render_dataset(render_fn, cameras, out, {"path_frames": 0, "photos": setting})
        views = [{"view": f.name} for f in sorted(cameras.split("test"), key=lambda f: f.name)]
        truth_evaluation(run / "simulate" / "truth", out, cameras, views, water)
        scored.append(views)
    return scored


def score_run(run: Path, settings: list[tuple[float, float]], work: Path) -> list[dict]:
    """Per setting and held-out view: the restored render's and the restored photograph's
    PSNR."""
    photos = [{"restore": "test", "max_gain": gain, "detail_scale": scale}
              for gain, scale in settings]
    return [{"run": run.name, "setting": setting, **view}
            for setting, views in zip(settings, scored_photo_settings(run, photos, work))
            for view in views]


def score_water_dive(sim: Path, settings: list[tuple[float, float]]
                     ) -> tuple[list[dict], list[dict]]:
    """As :func:`score_run`, on a dive of ``bench_water.py`` (true cameras, sensor photos),
    scored as that benchmark scores it (``bench_water.held_out_views``); and, per held-out view,
    what limits its restored photographs: the sensor photograph restored exactly (Sea-thru's
    ``(I - B) / T`` with the true water and the true range: no model error left, only the
    sensor's noise divided by the transmission), and the noise-free image with water restored
    through the model at the default settings (no noise, only the model's error).

    Returns:
        the rows per view and setting, and the bounds per view (:func:`bound_lines`).
    """
    import torch

    from bench_restored_error import restore
    from bench_water import held_out_views
    from seathru.eval.truth import view_truth_metrics
    from seathru.io.model import load_model
    from seathru.io.water import read_truth_water
    from seathru.radiometry.restore import restore_photograph

    torch.set_num_threads(2)
    truth = read_truth_water(sim / "truth" / "water.json")
    rows, bounds = [], []
    for frame, rendered, scoring, photo in held_out_views(
            sim, load_model(sim / "train_cues" / "model.pt")):
        for setting in settings:
            rows.append({"run": sim.name, "setting": setting, "view": frame.name,
                         **view_truth_metrics(**scoring, restored_photo=restore_photograph(
                             photo, rendered, *setting))})
        ranges = np.where(np.isfinite(scoring["truth_depth"]), scoring["truth_depth"], 0.0)
        exact = restore(photo, ranges, truth.sigma_attn, truth.sigma_bs, truth.c_med)
        bound = {"run": sim.name, "view": frame.name}
        for key, image in (("exact", exact),
                           ("noise_free", restore_photograph(scoring["water"], rendered))):
            scores = view_truth_metrics(**scoring, restored_photo=image)
            bound[key] = (scores["photo_restored_psnr_linear"],
                          scores["photo_restored_psnr_linear_covered"])
        bounds.append(bound)
    return rows, bounds


def bound_lines(rows: list[dict]) -> list[str]:
    if not rows:
        return []
    lines = ["", "What limits the photographs (all / covered, dB): the "
             "sensor photograph restored exactly with the true water and the true range (only "
             "its noise, divided by the transmission, is left), and the noise-free image with "
             "water restored through the model at the default settings (only the model's "
             "error is left).", "", "| run | view | exact water and range, sensor photograph "
             "| model, noise-free image |", "|---|---|---|---|"]
    pair = (lambda v: f"{v[0]:.2f} / {v[1]:.2f}")
    for r in rows:
        lines.append(f"| {r['run']} | {r['view']} | {pair(r['exact'])} | "
                     f"{pair(r['noise_free'])} |")
    mean = (lambda key: pair(np.nanmean([r[key] for r in rows], axis=0)))
    return lines + [f"| mean | | {mean('exact')} | {mean('noise_free')} |"]


def score_real_run(run: Path, settings: list[tuple[float, float]], work: Path) -> list[dict]:
    """Per setting: the restored photographs' track-slope reduction (all, near, far tracks)."""
    import torch

    from seathru.eval.track_slope import colour_slope_summary, far_tracks
    from seathru.io import tracks
    from seathru.io.cameras import read_cameras
    from seathru.io.model import load_model
    from seathru.nerf.inference import frame_renderer
    from seathru.steps.render import render_dataset

    torch.set_num_threads(2)
    cameras = read_cameras(run / "poses" / "cameras.json")
    obs = tracks.track_observations(cameras, cameras.root / tracks.SPARSE_DIR)
    far = far_tracks(obs.track_ids, obs.ranges)
    render_fn = frame_renderer(load_model(run / "train" / "model.pt", torch.device("cpu")))
    rows = []
    for setting in settings:
        out = work / f"{run.name}_{setting[0]:g}_{setting[1]:g}"
        render_dataset(render_fn, cameras, out, {"path_frames": 0, "photos": {
            "restore": "all", "max_gain": setting[0], "detail_scale": setting[1]}})
        source, photo = tracks.restored_photo_colours(out, cameras, obs)
        row = {"run": run.name, "setting": setting}
        for name, keep in (("all", np.ones(len(far), bool)), ("near", ~far), ("far", far)):
            summary = colour_slope_summary(obs.track_ids[keep], obs.ranges[keep], source[keep],
                                           photo[keep])
            row[name] = {key: summary[key] for key in ("reduction", "reduction_overall")}
            row[name]["input"], row[name]["restored"] = (summary[key]["slope"]
                                                         for key in ("input", "restored"))
        rows.append(row)
    return rows


def real_lines(rows: list[dict]) -> list[str]:
    if not rows:
        return []
    lines = ["", "Real dives: the slope of log colour against range along the COLMAP tracks, "
             "input and restored photographs averaged over the evaluate step's window, and the "
             "share of the input's slope removed (overall: 1 - sum |restored| / sum |input|).",
             "", "| run | max_gain, detail_scale | input slope (R, G, B) | restored photographs "
             "| removed, all tracks (R, G, B; overall) | nearest 90% | farthest 10% |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        slope = (lambda v: ", ".join(f"{x:.3f}" for x in v))
        share = (lambda v: f"{100 * v:.0f}%")
        lines.append(f"| {r['run']} | {r['setting'][0]:g}, {r['setting'][1]:g} | "
                     f"{slope(r['all']['input'])} | {slope(r['all']['restored'])} | "
                     + ", ".join(share(v) for v in r["all"]["reduction"])
                     + f" ({share(r['all']['reduction_overall'])}) | "
                     f"{share(r['near']['reduction_overall'])} | "
                     f"{share(r['far']['reduction_overall'])} |")
    return lines


def psnr_lines(rows: list[dict], settings: list[tuple[float, float]]) -> list[str]:
    if not rows:
        return []
    lines = ["PSNR (linear, dB) against the clean truth on the held-out views, as the evaluate "
             "step scores them: the model's restored render, and the view's photograph "
             "restored through the render, per largest gain (`render.photos.max_gain`) and "
             "detail scale (`render.photos.detail_scale`, 0: the whole residual); all pixels "
             "with a surface / covered (two or more training views see them).", "",
             "| run | view | restored render | "
             + " | ".join(f"photo, gain {g:g}, detail {d:g}" for g, d in settings) + " |",
             "|---|---|---|" + "---|" * len(settings)]
    keyed = {(r["run"], r["view"], r["setting"]): r for r in rows}
    pair = (lambda r, prefix: f"{r[prefix]:.2f} / {r[prefix + '_covered']:.2f}")
    for run, view in dict.fromkeys((r["run"], r["view"]) for r in rows):
        cells = [pair(keyed[(run, view, settings[0])], "restored_psnr_linear")]
        cells += [pair(keyed[(run, view, s)], "photo_restored_psnr_linear") for s in settings]
        lines.append(f"| {run} | {view} | " + " | ".join(cells) + " |")
    mean = (lambda setting, prefix: " / ".join(
        f"{np.nanmean([r[c] for r in rows if r['setting'] == setting]):.2f}"
        for c in (prefix, prefix + "_covered")))
    return lines + ["| mean | | " + " | ".join(
        [mean(settings[0], "restored_psnr_linear")]
        + [mean(s, "photo_restored_psnr_linear") for s in settings]) + " |"]


def write_results(rows: list[dict], settings: list[tuple[float, float]], out: Path,
                  seconds: float, real: list[dict] | None = None,
                  bounds: list[dict] | None = None) -> None:
    lines = ["# Restored photographs (`benchmarks/bench_restored_photo.py`)", "",
             *psnr_lines(rows, settings), *bound_lines(bounds or []), *real_lines(real or []),
             "",
             f"Machine: {cpu_name()}; load {load_average()}; {time.strftime('%Y-%m-%d')}; "
             f"{seconds:.0f} s.", ""]
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines))
    print("\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, action="append", default=[],
                        help="results/<dataset> of a finished simulated workflow run")
    parser.add_argument("--water-dive", type=Path, action="append", default=[],
                        help="a trained dive of bench_water.py's work folder")
    parser.add_argument("--real-run", type=Path, action="append", default=[],
                        help="results/<dataset> of a finished workflow run of a real dive")
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
        bounds = []
        for sim in args.water_dive:
            dive_rows, dive_bounds = score_water_dive(sim.resolve(), settings)
            rows += dive_rows
            bounds += dive_bounds
        real = [row for run in args.real_run for row in score_real_run(run.resolve(), settings,
                                                                        Path(work))]
    write_results(rows, settings, args.out, time.time() - started, real, bounds)


if __name__ == "__main__":
    main()
