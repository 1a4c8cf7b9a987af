"""Water benchmark: fitted water against the truth over waters x dive geometries (a script).

For every water preset and camera path (orbit: the hard case with no open water; transect;
survey: open water in every frame) a small dive is simulated and trained on its TRUE cameras
(so the water, not COLMAP, is what is measured), with the sparse cloud COLMAP would give
replaced by points on the true surfaces (``seathru.io.truth.write_truth_sparse_model``: the
sparse-depth loss and the track cue work as in the pipeline; ``--no-sparse`` leaves them out), twice, side by side: with the image cues
(the veiling light started at the smoothest image regions' colour, the water refitted on the
model's own surfaces with open-water rays and the dark-pixel bound: ``train.medium.*``) and
without them (``refit_at=[]``, ``veiling_light_init=false``). Per parameter and channel: the fitted value, its 95% interval, the truth;
whether the interval holds the truth; whether a parameter outside 5% was flagged as not
determined; restored-vs-clean PSNR (linear) on the held-out views, beside the full render's.
Beside water.json's intervals, the robust ones (``water_uncertainty.robust_halfwidths``) recomputed on
the final model's surfaces with the function's defaults (``bench_water_intervals.assess_model``:
without the train step's allowances for range error, grouping and the 1% floor), around the
trained value widened by its distance to that surface fit. The held-out photographs restored
through the model's render (``seathru.radiometry.restore``, the render step's default gain) are
scored beside the restored render: the photograph is the truth with water taken through the
simulator's sensor again (Poisson-Gaussian noise at the view's exposure, RGGB mosaic, bilinear
demosaicing, back to radiance), as noisy as the dive's raw files.

    python benchmarks/bench_water.py [--views 16 --width 160 --height 120] [--minutes 3]
        [--waters default,turbid,...] [--paths orbit,transect,survey] [--jobs 2]
        [--train-args '--field.view-dependent-colour off']
    python benchmarks/bench_water.py --rewrite benchmarks/results/water.json

Writes benchmarks/results/water.md (and water.json with every number); ``--rewrite`` writes the
tables again from a json of an earlier run, without training. Three minutes a run is the demo's
budget (about 45 min for the 27 runs on 2 cores); 0.75 min is a quick look (12 min), at which
the water is far from converged (survey medians of the error 32-53% against 3-22% at 3 min on
this VM, 2026-12-02).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from machine import cpu_name, load_average

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
RESULTS = REPO / "benchmarks" / "results" / "water.md"
KEYS = ("sigma_attn", "sigma_bs", "c_med")
# scored as the evaluate step scores the demo (seathru.eval.truth.view_truth_metrics: open water
# left out; "covered": the pixels two or more training views see)
SCORES = {"restored_psnr": "restored_psnr_linear", "full_psnr": "full_vs_clean_psnr_linear",
          "restored_psnr_covered": "restored_psnr_linear_covered",
          "covered_share": "covered_share",
          "photo_psnr": "photo_restored_psnr_linear",
          "photo_psnr_covered": "photo_restored_psnr_linear_covered"}
VARIANTS = {"cues": [], "no cues": ["--medium.refit-at", "--no-medium.veiling-light-init"]}


def simulate(root: Path, path: str, water: str, args) -> Path:
    from seathru.io.truth import write_truth_sparse_model
    from seathru.steps.simulate import Settings, simulate as run_simulation

    out = root / f"{path}_{water}"
    if not (out / "truth" / "cameras.json").exists():
        run_simulation(out, Settings(views=args.views, width=args.width, height=args.height,
                                     path=path, water=water, seed=args.seed, workers=1))
    if args.sparse and not (out / "truth" / "sparse").is_dir():
        write_truth_sparse_model(out, seed=args.seed)
    return out


def train(sim: Path, variant: str, args) -> Path:
    out = sim / ("train_" + variant.replace(" ", "_"))
    if not (out / "water.json").exists():
        command = [sys.executable, "-m", "seathru.cli", "train", "--cameras",
                   str(sim / "truth" / "cameras.json"), "--out", str(out), "--checkpoint-dir",
                   str(out.parent / f"ckpt_{out.name}"), "--threads", "1", "--no-progress",
                   "--max-minutes", str(args.minutes), "--seed", str(args.seed),
                   *VARIANTS[variant], *args.train_args.split()]
        done = subprocess.run(command, capture_output=True, text=True)
        (out.parent / f"{out.name}.log").write_text(done.stdout + done.stderr)
        if done.returncode != 0:
            raise RuntimeError(f"training {sim.name} ({variant}) failed:\n{done.stderr[-2000:]}")
    return out


def held_out_views(sim: Path, model):
    """Per held-out view of a dive on its true cameras: ``(frame, render, scoring, photo)``:
    the model's render (``render_frame``), the arguments of
    ``seathru.eval.truth.view_truth_metrics`` but the restored photograph (true range and
    coverage, as the evaluate step scores the demo), and the view's sensor photograph
    (:func:`sensor_photo`)."""
    from seathru.eval.truth import training_view_coverage
    from seathru.io.cameras import read_cameras
    from seathru.io.images import read_image
    from seathru.nerf.inference import render_frame

    cameras = read_cameras(sim / "truth" / "cameras.json")
    training = [(f, _truth_range(sim, f, cameras.scale)) for f in cameras.split("train")]
    for frame in sorted(cameras.split("test"), key=lambda f: f.name):
        rendered = render_frame(model, frame)
        view_range = _truth_range(sim, frame, cameras.scale)
        water = read_image(sim / "truth" / "water" / f"{frame.name}.tiff")
        scoring = dict(full=rendered["rgb"], restored=rendered["restored"],
                       depth=rendered["depth"], water=water,
                       clean=read_image(sim / "truth" / "clean" / f"{frame.name}.tiff"),
                       truth_depth=np.where(np.isfinite(view_range) & (view_range > 0),
                                            view_range / cameras.scale, np.inf),
                       gain=np.ones(3), metres_per_unit=1.0 / cameras.scale,
                       covered=training_view_coverage(frame, view_range, training) >= 2)
        yield frame, rendered, scoring, sensor_photo(sim, frame.name, water)


def measure(sim: Path, out: Path) -> dict:
    import torch

    from seathru.eval.truth import view_truth_metrics
    from seathru.io.model import load_model
    from seathru.io.water import read_truth_water, read_water
    from seathru.radiometry.restore import restore_photograph

    torch.set_num_threads(1)
    truth = read_truth_water(sim / "truth" / "water.json").as_dict()
    report = read_water(out / "water.json")
    fitted = report.per_source_unit.as_dict()
    interval = (report.to_dict().get("uncertainty") or {}).get("interval95")
    determined = (report.uncertainty or {}).get("determined")
    model = load_model(out / "model.pt")
    scores = [view_truth_metrics(**scoring, restored_photo=restore_photograph(photo, rendered))
              for _, rendered, scoring, photo in held_out_views(sim, model)]
    selection = json.loads((out / "selection.json").read_text())
    from bench_water_intervals import assess_model

    robust = assess_model(sim, out)
    params = []
    for key in KEYS:
        for channel in range(3):
            t, f = truth[key][channel], fitted[key][channel]
            lo, hi = interval[key][channel] if interval else (None, None)
            params.append({
                "parameter": key, "channel": "RGB"[channel], "truth": t, "fitted": f,
                "relative_error": abs(f - t) / t if t > 0 else None,
                "interval": [lo, hi],
                "contains_truth": None if lo is None else bool(lo <= t <= (hi if hi is not None
                                                                           else np.inf)),
                "determined": None if determined is None else determined[key][channel],
                **_robust(robust, key, channel, report.scale, t)})
    return {"medium": selection.get("final_mode"), "params": params,
            **{key: float(np.nanmean([score[column] for score in scores]))
               for key, column in SCORES.items()}}


def sensor_photo(sim: Path, name: str, water: np.ndarray, seed: int = 0) -> np.ndarray:
    """The view's image with water as the simulator's sensor records it, in radiance units:
    Poisson-Gaussian noise at the view's exposure (truth/sensor.json), RGGB mosaic, bilinear
    demosaicing, black level removed, divided by the exposure's DN per unit radiance."""
    from dataclasses import fields

    from seathru.sim import sensor

    info = json.loads((sim / "truth" / "sensor.json").read_text())
    config = sensor.SensorConfig(**{f.name: info[f.name] for f in fields(sensor.SensorConfig)})
    view = info["images"][name]
    exposure = sensor.Exposure(view["exposure_time_s"], view["iso"], view["f_number"],
                               view["ev_offset"])
    signal = sensor.expected_signal(water, exposure, info["dn_per_unit"])
    rng = np.random.default_rng([seed, int(name.rsplit("_", 1)[-1])])
    raw = sensor.capture_raw(sensor.mosaic_rggb(signal), exposure.iso, config, rng)
    value = sensor.demosaic_bilinear(raw).astype(np.float64) - config.black_level
    per_unit = exposure.exposure_time_s * exposure.iso / 100.0 * info["dn_per_unit"]
    return (value / per_unit).astype(np.float32)


def _truth_range(sim: Path, frame, scale: float) -> np.ndarray:
    """The true range of a view in the camera file's units; inf where it sees open water."""
    from seathru.io.images import read_image

    depth = read_image(sim / "truth" / "depth" / f"{frame.name}.tiff").astype(np.float64)
    depth = depth[..., 0] if depth.ndim == 3 else depth
    return np.where(np.isfinite(depth) & (depth > 0), depth * scale, np.inf)


def _robust(record: dict, key: str, channel: int, scale: float, truth: float) -> dict:
    """The robust interval of one parameter, per source unit, around the trained value."""
    if "skipped" in record:     # no surfaces to fit on: open, as water.json writes it
        return {"robust_interval": [0.0, None], "robust_contains_truth": True,
                "robust_determined": False}
    factor = scale if key != "c_med" else 1.0
    trained, fit = record["trained"][key][channel], record["surface_fit"][key][channel]
    half = record["robust"][key][channel] + abs(trained - fit)
    low, high = max(0.0, (trained - half) * factor), (trained + half) * factor
    return {"robust_interval": [low, high if np.isfinite(high) else None],
            "robust_contains_truth": bool(low <= truth <= high),
            "robust_determined": record["robust_determined"][key][channel]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=16)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--minutes", type=float, default=3.0, help="training time per run")
    parser.add_argument("--waters", default="", help="comma-separated presets (default: all "
                                                     "with water)")
    parser.add_argument("--paths", default="orbit,transect,survey")
    parser.add_argument("--variants", default="cues,no cues")
    parser.add_argument("--no-cues-waters", default="default,coastal_3c",
                        help="waters also trained without the cues ('all' for every water)")
    parser.add_argument("--jobs", type=int, default=2, help="trainings in parallel")
    parser.add_argument("--train-args", default="",
                        help="extra train flags for every run, e.g. "
                             "'--field.view-dependent-colour off'")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sparse", action=argparse.BooleanOptionalAction, default=True,
                        help="write truth/sparse (points on the true surfaces) beside the true "
                             "cameras, as COLMAP's points are beside the poses step's")
    parser.add_argument("--work", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--rewrite", type=Path, default=None,
                        help="a water.json of an earlier run: write its tables again")
    args = parser.parse_args()
    if args.rewrite is not None:
        saved = json.loads(args.rewrite.read_text())
        if isinstance(saved, list):     # written before the settings were kept with the rows
            saved = {"rows": saved}
        for key, value in saved.get("settings", {}).items():
            setattr(args, key, value)
        write_results(saved["rows"], args, saved.get("seconds", float("nan")),
                      saved.get("machine"))
        return
    from seathru.sim.water import PRESETS

    waters = [w for w in (args.waters.split(",") if args.waters else PRESETS) if w != "clear"]
    paths = args.paths.split(",")
    variants = args.variants.split(",")
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_water_"))
    started = time.time()
    sims = {(p, w): simulate(work, p, w, args) for p in paths for w in waters}
    compare = set(waters) if args.no_cues_waters == "all" else set(args.no_cues_waters.split(","))
    jobs = [(key, variant) for key in sims for variant in variants
            if variant != "no cues" or key[1] in compare]
    with ThreadPoolExecutor(args.jobs) as pool:
        outs = list(pool.map(lambda job: train(sims[job[0]], job[1], args), jobs))
    rows = []
    for (key, variant), out in zip(jobs, outs):
        result = measure(sims[key], out)
        rows.append({"path": key[0], "water": key[1], "variant": variant, **result})
        print(key, variant, f"restored {result['restored_psnr']:.2f} dB", flush=True)
    write_results(rows, args, time.time() - started)


def _summary(rows: list[dict], variant: str) -> str:
    params = [p for r in rows if r["variant"] == variant for p in r["params"]]
    within = [p for p in params if p["relative_error"] is not None]
    close = sum(p["relative_error"] <= 0.05 for p in within)
    covered = [p["contains_truth"] for p in params if p["contains_truth"] is not None]
    off = [p for p in within if p["relative_error"] > 0.05 and p["determined"] is not None]
    flagged = sum(not p["determined"] for p in off)
    robust = [p.get("robust_contains_truth") for p in params
              if p.get("robust_contains_truth") is not None]
    robust_off = [p for p in within if p["relative_error"] > 0.05
                  and p.get("robust_determined") is not None]
    robust_flagged = sum(not p["robust_determined"] for p in robust_off)
    restored = [r["restored_psnr"] for r in rows if r["variant"] == variant]
    return (f"**{variant}**: {close}/{len(within)} parameters within 5% of the truth; "
            f"water.json's intervals hold the truth in {sum(covered)}/{len(covered)} fits"
            f" ({100 * sum(covered) / max(1, len(covered)):.0f}%), the robust ones in "
            f"{sum(robust)}/{len(robust)} ({100 * sum(robust) / max(1, len(robust)):.0f}%); of "
            f"the parameters more than 5% off, {flagged}/{len(off)} are flagged as not "
            f"determined by water.json, {robust_flagged}/{len(robust_off)} by the robust "
            f"intervals; restored vs clean "
            f"{np.median(restored):.1f} dB median ({min(restored):.1f}-{max(restored):.1f})"
            + _photo_summary([r for r in rows if r["variant"] == variant]) + ".")


def _photo_summary(rows: list[dict]) -> str:
    photo = [r["photo_psnr"] for r in rows if np.isfinite(r.get("photo_psnr", np.nan))]
    if not photo:
        return ""
    return (f", the photographs restored through the model {np.median(photo):.1f} dB median "
            f"({min(photo):.1f}-{max(photo):.1f})")


def _by_path(rows: list[dict], variant: str) -> list[str]:
    """Per camera path: parameters within 5%, and the median error (signed) per parameter."""
    lines = []
    for path in dict.fromkeys(r["path"] for r in rows):
        params = [p for r in rows if r["variant"] == variant and r["path"] == path
                  for p in r["params"] if p["relative_error"] is not None]
        if not params:
            continue
        close = sum(p["relative_error"] <= 0.05 for p in params)
        medians = []
        for key in KEYS:
            errors = [p["fitted"] / p["truth"] - 1 for p in params if p["parameter"] == key]
            medians.append(f"`{key}` {100 * np.median(np.abs(errors)):.0f}% "
                           f"({100 * np.median(errors):+.0f}%)")
        restored = [r.get("restored_psnr_covered", np.nan) for r in rows
                     if r["variant"] == variant and r["path"] == path]
        photo = [r.get("photo_psnr_covered", np.nan) for r in rows
                 if r["variant"] == variant and r["path"] == path]
        lines.append(f"  - {path}: {close}/{len(params)} within 5%; median error (signed): "
                     + ", ".join(medians)
                     + f"; restored vs clean on covered pixels {np.nanmedian(restored):.1f} dB "
                       "median"
                     + (f", restored photographs {np.nanmedian(photo):.1f} dB"
                        if np.isfinite(photo).any() else ""))
    return lines


def write_results(rows: list[dict], args, seconds: float, machine: str | None = None) -> None:
    lines = ["# Water benchmark (`benchmarks/bench_water.py`)", "",
             f"Dives of {args.views} views at {args.width}x{args.height}, trained on their true "
             f"cameras for {args.minutes:g} min each (1 CPU thread each, {args.jobs} run(s) at a time); "
             "errors per channel (R, G, B); interval: 95% from water.json's uncertainty; "
             "`?` = flagged as not determined by the views (water.json); robust: "
             "`water_uncertainty.robust_halfwidths` recomputed on the final model's surfaces with its "
             "defaults (no allowance for range error, grouping or the 1% floor), around "
             "the trained value widened by its distance to that fit. Restored and full render "
             "against the clean truth as the evaluate step scores them: open water left out; "
             "covered: only the pixels two or more training views see. Photograph restored: the "
             "held-out photograph (the truth with water through the simulator's sensor: noise, "
             "mosaic, demosaicing) with the water removed through the model's render."
             + (f" Extra train flags: `{args.train_args}`." if args.train_args else ""), ""]
    for variant in dict.fromkeys(r["variant"] for r in rows):
        lines.append("- " + _summary(rows, variant))
        lines += _by_path(rows, variant)
    lines += ["", "| path | water | variant | medium | sigma_attn error | sigma_bs error | "
              "c_med error | truth in interval | truth in robust interval | "
              "restored / full vs clean (dB) | restored, covered (dB) | "
              "photograph restored, all / covered (dB) |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        cells = []
        for key in KEYS:
            ps = [p for p in r["params"] if p["parameter"] == key]
            cells.append(", ".join(
                ("n/a" if p["relative_error"] is None
                 else f"{100 * (p['fitted'] / p['truth'] - 1):+.0f}%")
                + ("?" if p["determined"] is False else "") for p in ps))
        covered = [p["contains_truth"] for p in r["params"] if p["contains_truth"] is not None]
        robust = [p.get("robust_contains_truth") for p in r["params"]
                  if p.get("robust_contains_truth") is not None]
        lines.append(f"| {r['path']} | {r['water']} | {r['variant']} | {r['medium']} | "
                     + " | ".join(cells) + f" | {sum(covered)}/{len(covered)} | "
                     f"{sum(robust)}/{len(robust)} | "
                     f"{r['restored_psnr']:.1f} / {r['full_psnr']:.1f} | "
                     f"{r.get('restored_psnr_covered', float('nan')):.1f} | "
                     f"{r.get('photo_psnr', float('nan')):.1f} / "
                     f"{r.get('photo_psnr_covered', float('nan')):.1f} |")
    machine = machine or (f"{cpu_name()}; load {load_average()}; {time.strftime('%Y-%m-%d')}; "
                          f"{seconds / 60:.0f} min in all")
    lines += ["", f"Machine: {machine}.", ""]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines))
    settings = {key: getattr(args, key) for key in ("views", "width", "height", "minutes",
                                                   "jobs", "train_args")}
    args.out.with_suffix(".json").write_text(json.dumps(
        {"settings": settings, "seconds": seconds, "machine": machine, "rows": rows}, indent=1))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
