"""The water on a real dive: the medium decision, open water left empty, colour along tracks.

Reads finished workflow runs of a real dive (default: the d3_reef runs of
``benchmarks/bench_frontier.py`` in ``/tmp/bench_frontier``) and writes
``benchmarks/results/reef.md``, per run:

- the medium chosen and the evidence (``train/selection.json``);
- open water: the share of the held-out pixels that show open water in the photograph
  (``seathru.radiometry.open_water``) and the share of those the model renders with object
  opacity below 0.1 (``render/test/<view>/opacity.tiff``; goal: at least 90%);
- the slope of log colour against range along COLMAP tracks in the input images and in the
  restored renders, each observation's colour the mean over its window
  (``seathru.io.tracks.window_samples``; ``evaluate/summary.json`` ``track_colour_slope``
  where the evaluate step wrote it; goal: the restored slope at least 70% smaller);
- held-out PSNR;
- the same reduction for the nearest 90% of the tracks and for the farthest 10% (by each
  track's median range): the far tracks' ranges spread the most, so they weigh most in the
  pooled slope, and there the restoration divides by the smallest transmittance;
- fog in front of the tracked surfaces: the object opacity each track observation's ray gathers
  before 0.8 of its COLMAP point's range (``seathru.io.tracks.opacity_in_front``), mean over
  all observations and over the farthest quarter. The restored view renders the object field
  alone, so fog there is part of the restored colour, the more the longer the range.

Usage::

    python benchmarks/bench_reef.py [--work /tmp/bench_frontier] [--dataset d3_reef]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from seathru.io.cameras import read_cameras  # noqa: E402
from seathru.io.images import read_image  # noqa: E402
from seathru.radiometry.linearise import resize_area  # noqa: E402
from seathru.radiometry.open_water import open_water_mask  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "reef.md"
EMPTY_OPACITY = 0.1


def open_water_scores(run: Path, cameras_path: Path) -> dict:
    cameras = read_cameras(cameras_path)
    water = empty = pixels = 0
    for frame in cameras.split("test"):
        opacity_path = run / "render" / "test" / frame.name / "opacity.tiff"
        if not opacity_path.is_file():
            continue
        opacity = read_image(opacity_path)
        opacity = opacity[..., 0] if opacity.ndim == 3 else opacity
        photo = read_image(cameras.image_path(frame))[..., :3]
        if photo.shape[:2] != opacity.shape:
            photo = resize_area(photo, (opacity.shape[1], opacity.shape[0]))
        mask = open_water_mask(photo)
        water += int(mask.sum())
        empty += int((opacity[mask] < EMPTY_OPACITY).sum())
        pixels += mask.size
    return {"open_water_share": water / pixels if pixels else float("nan"),
            "empty_share": empty / water if water else float("nan")}


def track_scores(run: Path, cameras_path: Path) -> dict:
    """Fog in front of the tracked surfaces, the slope reduction of the nearest 90% of tracks
    against the farthest 10% (by each track's median range), and the share of the input's
    slope the full render (with water) follows, over all tracks."""
    import torch

    from seathru.eval.report_tracks import followed_share
    from seathru.eval.track_slope import colour_slope_summary, far_tracks
    from seathru.io.model import load_model
    from seathru.io.tracks import (SPARSE_DIR, opacity_in_front, rendered_colours,
                                   track_observations, track_windows)

    cameras = read_cameras(cameras_path)
    model_path = run / "train" / "model.pt"
    if not (cameras.root / SPARSE_DIR).is_dir() or not model_path.is_file():
        return {"fog_all": None, "fog_far": None, "reduction_near": None, "reduction_far": None,
                "reproduced": None, "followed": None}
    torch.set_num_threads(1)
    obs = track_observations(cameras, cameras.root / SPARSE_DIR)
    windows = track_windows(cameras, obs)
    observed = windows.observed
    model = load_model(model_path)
    with torch.no_grad():
        fog = opacity_in_front(model, cameras, obs)
        rendered = rendered_colours(model, cameras, obs, windows)
    far = obs.ranges >= np.quantile(obs.ranges, 0.75)
    far_track = far_tracks(obs.track_ids, obs.ranges)
    scores = {}
    for name, keep in (("near", ~far_track), ("far", far_track),
                       ("all", np.ones(len(obs.rows), bool))):
        summary = colour_slope_summary(obs.track_ids[keep], obs.ranges[keep],
                                       observed[keep], rendered["restored"][keep],
                                       rendered["rgb"][keep])
        scores[f"reduction_{name}"] = summary.get("reduction")
        if name == "all":
            scores["reproduced"] = summary.get("reproduced")
            scores["followed"] = followed_share(
                *(list(zip(summary[key]["slope"], summary[key]["stderr"]))
                  for key in ("input", "rendered")))
    return {"fog_all": float(fog.mean()), "fog_far": float(fog[far].mean()), **scores}


def describe(run: Path, cameras_path: Path) -> dict:
    selection = json.loads((run / "train" / "selection.json").read_text())
    summary_path = run / "evaluate" / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    stats = selection.get("statistics", {})
    return {"run": run.name, "chosen": selection.get("final_mode", selection.get("chosen")),
            "capacity": (selection.get("capacity") or {}).get("chosen"),
            "evidence": stats.get("evidence_of_water", []),
            **open_water_scores(run, cameras_path), **track_scores(run, cameras_path),
            "psnr": (summary.get("means") or {}).get("psnr_linear"),
            "tracks": summary.get("track_colour_slope")}


def _fmt(value, digits=2, scale=1.0) -> str:
    try:
        return f"{float(value) * scale:.{digits}f}"
    except (TypeError, ValueError):
        return "—"


def _percentages(values) -> str:
    return ", ".join(_fmt(v, 0, 100) + "%" for v in values) if values else "—"


def _photographs(tracks: dict | None) -> str:
    """The restored photographs' slope reduction: all tracks per channel and overall, nearest
    90% and farthest 10% overall; a dash where the evaluate step did not measure it."""
    parts = [((tracks or {}).get(name) or {}).get("photographs") or {}
             for name in ("all_views", "near_tracks", "far_tracks")]
    if not parts[0]:
        return "—"
    overall = [_fmt(p.get("reduction_overall"), 0, 100) + "%" for p in parts]
    return (f"{_percentages(parts[0].get('reduction'))} ({overall[0]}) / {overall[1]} / "
            f"{overall[2]}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=Path("/tmp/bench_frontier"))
    parser.add_argument("--dataset", default="d3_reef")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    results = args.work / "results"
    cameras = results / args.dataset / "poses" / "cameras.json"
    runs = sorted(p for p in results.iterdir()
                  if p.name == args.dataset or p.name.startswith(f"{args.dataset}+"))
    rows = [describe(run, cameras) for run in runs if (run / "train" / "selection.json").is_file()]
    lines = [f"# The water on a real dive (`benchmarks/bench_reef.py`): {args.dataset}", "",
             f"Runs read from `{results}` (written by `benchmarks/bench_frontier.py`: same "
             "poses, each preset trained for its budget on a 2-core CPU). Open water: held-out "
             "pixels that show open water in the photograph (smooth, reaching the top of the "
             f"frame); empty: rendered with object opacity below {EMPTY_OPACITY:g} (goal >= "
             "90%). Track slope: change of log colour per unit of range (COLMAP's) along "
             "COLMAP tracks, input photographs vs restored renders, each observation's colour "
             "the mean over a window 2% of the image width across at the track's median range, "
             "scaled by median range / range (`seathru.io.tracks.window_samples`: the same patch "
             "of surface in every view; from session 25) (goal: >= 70% smaller). Fog: "
             "object opacity in front of the tracked surfaces (before 0.8 of the point's "
             "range), all observations / the farthest quarter. Reduction by range: the nearest "
             "90% of tracks / the farthest 10% (each track's median range). Followed: the full "
             "render's slope (with water) as a share of the input's, all tracks, per channel and "
             "(in brackets) pooled over the channels whose input slope is twice its standard "
             "error, as the report judges it: a model that "
             "does not follow the input's slope takes it out of the restored render whether or "
             "not it removed the water. Restored photographs: the render step's "
             "`photos/<view>.tiff` (the photographs with the water taken out through the model, "
             "`seathru.radiometry.restore`) against the input, over the same windows "
             "(`evaluate/summary.json`): "
             "reduction over all tracks (R, G, B; overall) / nearest 90% / farthest 10% "
             "(overall).", "",
             "| run | capacity | medium | open water (% of pixels) | of it empty (%) | "
             "held-out PSNR (dB) | track slope input (R, G, B) | restored | reduction | fog (%) | "
             "reduction, nearest 90% / farthest 10% of tracks | followed by the full render | "
             "restored photographs: reduction |",
             "|---" * 13 + "|"]
    for row in rows:
        tracks = (row["tracks"] or {}).get("all_views") or {}
        input_slope, restored_slope = (
            ", ".join(_fmt(v) for v in tracks.get(part, {}).get("slope", [])) or "—"
            for part in ("input", "restored"))
        lines.append(
            f"| {row['run']} | {row['capacity'] or '—'} | {row['chosen']} | "
            f"{_fmt(row['open_water_share'], 1, 100)} | {_fmt(row['empty_share'], 1, 100)} | "
            f"{_fmt(row['psnr'])} | {input_slope} | {restored_slope} | "
            f"{_percentages(tracks.get('reduction'))} | "
            f"{_fmt(row['fog_all'], 1, 100)} / {_fmt(row['fog_far'], 1, 100)} | "
            f"{_percentages(row['reduction_near'])} / {_percentages(row['reduction_far'])} | "
            f"{_percentages(row['reproduced'])} ({_fmt(row['followed'], 0, 100)}%) | "
            f"{_photographs(row['tracks'])} |")
    lines += ["", "Evidence of water per run (selection.json):", ""]
    lines += [f"- {row['run']}: {'; '.join(row['evidence']) or 'none'}" for row in rows]
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
