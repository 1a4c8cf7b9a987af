"""The water refit on one trained model's pixels, with and without the processing blur taken out.

A diagnostic, not a test. For workflow runs of simulated dives (``RUN`` = ``results/<dataset>``
with ``simulate/``, ``poses/``, ``train/model.pt`` and ``evaluate/summary.json``), the refit of
the training step (``water_surfaces.surface_data`` and ``fit_water``, no dark-pixel bound) is run on
the same pixels of every training view, the model's surfaces at the simulator's true range, with
the observed colour from:

- the run's training images as they are, and deconvolved by their frames' ``blur_px``
  (``seathru.radiometry.deblur``; runs whose cameras.json predates it get the LINEAR demosaic's
  and the bilinear undistortion's blur), and by 0.8 and 1.2 times that (how much a wrong blur
  costs);
- the simulator's noise-free image with water, mapped onto the camera frames as the poses step
  maps the training images (only the undistortion's blur), as it is and deconvolved by that.

Everything but the observed colour is held. Usage::

    python benchmarks/bench_refit_deblur.py results/demo [RUN ...] \\
        --out benchmarks/results/refit_deblur.md
"""

from __future__ import annotations

import argparse
import platform
import sys
from pathlib import Path

import numpy as np
import torch

from bench_refit_decoding import trained_run
from bench_refit_true_depth import true_ranges
from machine import cpu_name

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from seathru.io.cameras import read_cameras  # noqa: E402
from seathru.io.images import read_image  # noqa: E402
from seathru.io.stored_views import source_cameras, stored_image_on_frame  # noqa: E402
from seathru.io.training import read_frame  # noqa: E402
from seathru.nerf import water_fit, water_surfaces  # noqa: E402
from seathru.nerf.rays import frame_rays  # noqa: E402
from seathru.radiometry.deblur import deblurred, processing_blur  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "refit_deblur.md"


def pixels(run: Path, per_view: int, seed: int = 0):
    """Per training view: rays, true range and the picked pixels of each image source."""
    cameras = read_cameras(run / "poses" / "cameras.json")
    truth = run / "simulate" / "truth"
    truth_frames = {f.name: f for f in read_cameras(truth / "cameras.json").frames}
    candidates = source_cameras(cameras)
    rng = np.random.default_rng(seed)
    views = []
    for frame in cameras.split("train"):
        origins, directions = frame_rays(frame)
        ranges = true_ranges(frame, truth_frames[frame.name],
                             truth / "depth" / f"{frame.name}.tiff")
        pick = rng.choice(len(ranges), per_view, replace=False)
        training = read_frame(cameras, frame)[0][..., :3]
        noise_free = stored_image_on_frame(read_image(truth / "water" / f"{frame.name}.tiff")
                                           [..., :3], frame, candidates)
        views.append({"frame": frame, "origins": origins[pick].double(),
                      "directions": directions[pick].double(), "true": ranges[pick],
                      "pick": pick, "training": training, "noise_free": noise_free})
    return views


def refit(views, model, scale: float, truth: dict, source: str, blur_of) -> dict[str, list]:
    """Errors (%, R G B) of the refit on ``source`` images deconvolved by ``blur_of(frame)``."""
    origins = torch.cat([v["origins"] for v in views])
    directions = torch.cat([v["directions"] for v in views])
    true = torch.from_numpy(np.concatenate([v["true"] for v in views]))
    observed = []
    for view in views:
        image = view[source]
        blur = blur_of(view["frame"])
        if blur is not None and max(blur) > 0:
            image = deblurred(image, blur)
        observed.append(torch.from_numpy(image.reshape(-1, 3)[view["pick"]].astype(np.float64)))
    observed = torch.cat(observed)
    observed = torch.where(torch.isfinite(observed), observed, 0.0)
    open_water = ~torch.isfinite(true)
    diagonal = float(torch.linalg.norm(model.box.box_max - model.box.box_min))
    data = water_surfaces.surface_data(origins, directions, observed,
                                  torch.where(open_water, torch.nan, true / scale),
                                  (~open_water).double(), 0.005 * diagonal, 0.9,
                                  open_water_opacity=0.5, open_water=open_water)
    fit = water_fit.fit_water(data.ranges, data.observed, data.ids, data.groups,
                              model.water_parameters(), 300, model.medium.colour_max)
    return {key: [100 * (value / scale / t - 1) for value, t in zip(getattr(fit, key), truth[key])]
            for key in ("sigma_attn", "sigma_bs")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--per-view", type=int, default=3200)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    torch.set_num_threads(2)
    lines = ["# The water refit with the processing blur taken out "
             "(`benchmarks/bench_refit_deblur.py`)", "",
             f"Device: {cpu_name()}, torch {torch.__version__}, Python "
             f"{platform.python_version()}. Per run: {args.per_view} pixels of every training "
             "view, the same for every row, at the simulator's true range; the refit of the "
             "training step (started at the model's water, no dark-pixel bound). Errors "
             "against the true water, %, R, G, B.", "",
             "| run | observed colour | deconvolved by (sigma px, R G B) | sigma_attn error | "
             "sigma_bs error |", "|---|---|---|---|---|"]
    pipeline = processing_blur("LINEAR", 1.0, "linear")
    undistortion = processing_blur(None, 1.0, "linear")
    for run in args.runs:
        scale, truth, model = trained_run(run)
        views = pixels(run, args.per_view)

        def recorded(frame, factor=1.0):
            blur = frame.blur_px if frame.blur_px is not None else pipeline
            return [factor * b for b in blur]

        rows = [("training images", "none", "training", lambda f: None),
                ("training images", "the frame's blur_px", "training", recorded),
                ("training images", "0.8 x blur_px", "training", lambda f: recorded(f, 0.8)),
                ("training images", "1.2 x blur_px", "training", lambda f: recorded(f, 1.2)),
                ("noise-free image", "none", "noise_free", lambda f: None),
                ("noise-free image", "the undistortion's", "noise_free",
                 lambda f: undistortion)]
        for label, by, source, blur_of in rows:
            errors = refit(views, model, scale, truth, source, blur_of)
            shown = by if blur_of(views[0]["frame"]) is None else \
                f"{by} ({', '.join(f'{b:.2f}' for b in blur_of(views[0]['frame']))})"
            cells = [", ".join(f"{e:+.0f}" for e in errors[k]) for k in ("sigma_attn", "sigma_bs")]
            lines.append(f"| {run.name} | {label} | {shown} | {cells[0]} | {cells[1]} |")
            print(lines[-1], flush=True)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
