"""The water refit on one trained model's pixels, the observed colour decoded each way.

A diagnostic, not a test. For a workflow run of a simulated dive (``RUN`` = ``results/<dataset>``
with ``simulate/``, ``poses/``, ``train/model.pt`` and ``evaluate/summary.json``), the dive's
RAW files are ingested once per decoding (LibRaw demosaics, and 2x2 binning upsampled back), each
decoded image is mapped onto the run's camera frames as the poses step maps the training images
(``seathru.io.stored_views.stored_image_on_frame``), and the refit of the training step
(``water_surfaces.surface_data`` and ``fit_water``, no dark-pixel bound) is run on the same pixels of
every training view: the model's surfaces, at the simulator's true range and at the model's
depth. Everything but the observed colour is held, so what moves between rows is the decoding's.
The simulator's noise-free image with water gives the reference row. Usage::

    python benchmarks/bench_refit_decoding.py results/demo [RUN ...] \\
        --out benchmarks/results/refit_decoding.md

Writes a markdown table of ``sigma_attn`` / ``sigma_bs`` errors against the truth, per channel.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
import torch

from bench_refit_true_depth import true_ranges
from machine import cpu_name

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from seathru.io.cameras import read_cameras  # noqa: E402
from seathru.io.images import read_image  # noqa: E402
from seathru.io.model import load_model  # noqa: E402
from seathru.io.stored_views import source_cameras, stored_image_on_frame  # noqa: E402
from seathru.io.water import read_truth_water  # noqa: E402
from seathru.nerf import water_fit, water_surfaces  # noqa: E402
from seathru.nerf.rays import frame_rays  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "refit_decoding.md"
DECODINGS = ("AHD", "PPG", "DCB", "AAHD", "VNG", "DHT", "LINEAR", "half")
#: the dive's camera JPEGs instead of its RAW files: as simulated (4:2:0), and simulated again
#: with the colour at full resolution (the same seed and settings: the same raw, JPEGs at 4:4:4)
JPEG_DECODINGS = ("jpeg_420", "jpeg_444")


def _seathru(*arguments: str) -> None:
    subprocess.run([sys.executable, "-m", "seathru.cli", *arguments], check=True,
                   capture_output=True, env={**os.environ, "PYTHONPATH": str(REPO / "src")})


def ingest(simulated: Path, out: Path, decoding: str) -> Path:
    """The linear folder of the simulated dive ingested with ``decoding`` (a demosaic of its
    RAW files, ``half``, or one of :data:`JPEG_DECODINGS`)."""
    if decoding in JPEG_DECODINGS:
        if decoding == "jpeg_444":
            simulated = _simulated_again(simulated, out / "simulate", "--jpeg-chroma", "4:4:4")
        _seathru("ingest", "--input", str(simulated), "--subdir", "jpeg", "--out",
                 str(out / "ingest"), "--workers", "2")
        return out / "ingest" / "linear"
    flags = ["--half-size"] if decoding == "half" else ["--demosaic", decoding]
    _seathru("ingest", "--input", str(simulated / "raw"), "--out", str(out), "--workers", "2",
             *flags)
    return out / "linear"


def _simulated_again(simulated: Path, out: Path, *flags: str) -> Path:
    """The dive of ``simulated`` simulated again into ``out`` with ``flags`` (from its recorded
    scene and water; the raw mosaics checked to be the same)."""
    import rawpy

    scene = json.loads((simulated / "truth" / "scene.json").read_text())
    water = json.loads((simulated / "truth" / "water.json").read_text())
    raws = sorted((simulated / "raw").glob("*.dng"))
    height, width = read_image(simulated / "truth" / "depth" / f"{raws[0].stem}.tiff").shape[:2]
    _seathru("simulate", "--out", str(out), "--views", str(len(raws)), "--width", str(width),
             "--height", str(height), "--path", scene["path"], "--seed", str(scene["seed"]),
             "--fov-deg", str(scene["fov_deg"]), "--supersample", str(scene["supersample"]),
             "--water", water["preset"].split("+")[0], "--sigma-attn",
             *map(str, water["sigma_attn"]), "--sigma-bs", *map(str, water["sigma_bs"]),
             "--c-med", *map(str, water["c_med"]), "--workers", "2", *flags)
    for path in (raws[0], raws[-1]):
        with rawpy.imread(str(path)) as mine, rawpy.imread(str(out / "raw" / path.name)) as new:
            if not np.array_equal(mine.raw_image_visible, new.raw_image_visible):
                raise SystemExit(f"{simulated}: simulated again, {path.name} differs (a "
                                 "setting the truth folder does not record?)")
    return out


def decoded_image(linear: Path, name: str, half: bool) -> np.ndarray:
    image = read_image(linear / f"{name}.tiff")[..., :3]
    if half:  # back to the sensor's size, where the frame mapping starts
        image = cv2.resize(image, (image.shape[1] * 2, image.shape[0] * 2),
                           interpolation=cv2.INTER_LINEAR)
    return image


def observations(run: Path, model, folders: dict[str, Path], per_view: int, seed: int = 0):
    """Rays, model depth and opacity, true range and, per decoding and ``truth``, the observed
    colour of ``per_view`` pixels of every training view."""
    cameras = read_cameras(run / "poses" / "cameras.json")
    truth = run / "simulate" / "truth"
    truth_frames = {f.name: f for f in read_cameras(truth / "cameras.json").frames}
    candidates = source_cameras(cameras)
    rng = np.random.default_rng(seed)
    parts: dict[str, list] = {k: [] for k in ("origins", "directions", "model", "opacity", "true")}
    colours: dict[str, list] = {k: [] for k in [*folders, "truth"]}
    for frame in cameras.split("train"):
        origins, directions = frame_rays(frame)
        ranges = true_ranges(frame, truth_frames[frame.name],
                             truth / "depth" / f"{frame.name}.tiff")
        pick = rng.choice(len(ranges), per_view, replace=False)
        index = torch.from_numpy(pick)
        with torch.no_grad():
            render = model(origins[index], directions[index], torch.full((per_view,), frame.near),
                           torch.full((per_view,), frame.far)).render
        parts["origins"].append(origins[index].double())
        parts["directions"].append(directions[index].double())
        parts["model"].append(render.depth_median.double())
        parts["opacity"].append(render.opacity.double())
        parts["true"].append(torch.from_numpy(ranges[pick]))
        sources = {name: decoded_image(folder, frame.name, name == "half")
                   for name, folder in folders.items()}
        sources["truth"] = read_image(truth / "water" / f"{frame.name}.tiff")[..., :3]
        for name, image in sources.items():
            mapped = stored_image_on_frame(image, frame, candidates).reshape(-1, 3)[pick]
            colours[name].append(torch.from_numpy(mapped.astype(np.float64)))
    return ({k: torch.cat(v) for k, v in parts.items()},
            {k: torch.cat(v) for k, v in colours.items()})


def trained_run(run: Path):
    """A workflow run's metric scale (evaluate step), true water (by name) and trained model
    (CPU, eval mode)."""
    summary = json.loads((run / "evaluate" / "summary.json").read_text())
    scale = float(summary["truth"]["metric_scale"]["scale"])
    truth = read_truth_water(run / "simulate" / "truth" / "water.json").as_dict()
    model = load_model(run / "train" / "model.pt", torch.device("cpu"))
    model.eval()
    return scale, truth, model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--decodings", nargs="+", default=list(DECODINGS),
                        help=f"demosaics, half, or {', '.join(JPEG_DECODINGS)}")
    parser.add_argument("--per-view", type=int, default=3200)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    torch.set_num_threads(1)
    lines = ["# The water refit on one model's pixels, decoded each way "
             "(`benchmarks/bench_refit_decoding.py`)", "",
             f"Device: {cpu_name()}, 1 thread, torch {torch.__version__}, Python "
             f"{platform.python_version()}. Per run: {args.per_view} pixels of every training "
             "view, the same for every row; the observed colour from the dive's RAW files "
             "ingested with each decoding (`half`: 2x2 binning, upsampled back) or the "
             "simulator's noise-free image with water, mapped onto the camera frames as the "
             "poses step maps the training images; the refit of the training step (started at "
             "the model's water, no dark-pixel bound) at the true range and at the model's "
             "depth. Errors against the true water, %, R, G, B.", "",
             "| run | observed colour | range | sigma_attn error | sigma_bs error |",
             "|---|---|---|---|---|"]
    for run in args.runs:
        scale, truth, model = trained_run(run)
        with tempfile.TemporaryDirectory(prefix="refit_decoding_") as work:
            folders = {name: ingest(run / "simulate", Path(work) / name, name)
                       for name in args.decodings}
            rays, colours = observations(run, model, folders, args.per_view)
        open_water = ~torch.isfinite(rays["true"])
        depths = {"true": (torch.where(open_water, torch.nan, rays["true"] / scale),
                           (~open_water).double()),
                  "model": (rays["model"], rays["opacity"])}
        diagonal = float(torch.linalg.norm(model.box.box_max - model.box.box_min))
        defined = torch.isfinite(colours["truth"]).all(-1)
        for name, observed in colours.items():
            observed = torch.where(defined[:, None], observed, colours[args.decodings[0]]) \
                if name == "truth" else observed
            for depth_name, (depth, opacity) in depths.items():
                data = water_surfaces.surface_data(rays["origins"], rays["directions"], observed,
                                              depth, opacity, 0.005 * diagonal, 0.9,
                                              open_water_opacity=0.5, open_water=open_water)
                fit = water_fit.fit_water(data.ranges, data.observed, data.ids, data.groups,
                                          model.water_parameters(), 300,
                                          model.medium.colour_max)
                errors = [", ".join(f"{100 * (value / scale / true - 1):+.0f}" for value, true
                                    in zip(getattr(fit, key), truth[key]))
                          for key in ("sigma_attn", "sigma_bs")]
                shown = "noise-free image" if name == "truth" else name
                lines.append(f"| {run.name} | {shown} | {depth_name} | {errors[0]} | "
                             f"{errors[1]} |")
                print(lines[-1], flush=True)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
