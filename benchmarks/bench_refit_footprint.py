"""Which surface pixels bias the water refit on exact ranges (a script).

The refit (``seathru.nerf.water_fit``: surface data grouped in 0.02 m voxels, brightness
weights, dark-pixel bound, as in training) on a simulated dive's own noise-free renders and
exact ranges, with every surface pixel and without the pixels whose true range varies across
their neighbourhood: a ``window`` x ``window`` block spanning more than ``spread`` in log range.
A wide window with a small spread takes out the seabed seen at a grazing angle, whose pixels'
footprints stretch over a range of distances; a narrow one with a large spread only the
occlusion edges. Errors against the simulator's water, per channel.

    python benchmarks/bench_refit_footprint.py [--dives survey_default,...] [--work DIR]

Dives are the water benchmark's (``bench_water.simulate``; made where missing in ``--work``).
Writes benchmarks/results/refit_footprint.md.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from machine import cpu_name

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
RESULTS = REPO / "benchmarks" / "results" / "refit_footprint.md"
KEYS = ("sigma_attn", "sigma_bs", "c_med")
NEIGHBOURHOODS = ((5, 0.05), (3, 0.1))


def dive_pixels(truth: Path, per_view: int, seed: int = 0):
    """Sampled pixels of the training views: origins, directions, ranges (inf: open water),
    colours, and per neighbourhood of ``NEIGHBOURHOODS`` whether the range varies across it."""
    from scipy import ndimage

    from seathru.io.cameras import read_cameras
    from seathru.io.evaluation import read_truth_image
    from seathru.nerf.rays import frame_rays

    rng = np.random.default_rng(seed)
    columns: dict[str, list] = {"origins": [], "directions": [], "ranges": [], "rgb": []}
    varied: list[list[np.ndarray]] = [[] for _ in NEIGHBOURHOODS]
    for frame in read_cameras(truth / "cameras.json").split("train"):
        origins, directions = frame_rays(frame)
        depth = read_truth_image(truth, "depth", frame.name)
        depth = depth[..., 0] if depth.ndim == 3 else depth
        image = read_truth_image(truth, "water", frame.name)[..., :3]
        log_range = np.log(np.where(np.isfinite(depth), depth, 1e4))
        pick = rng.choice(depth.size, min(per_view, depth.size), replace=False)
        columns["origins"].append(origins[pick].double())
        columns["directions"].append(directions[pick].double())
        columns["ranges"].append(torch.from_numpy(depth.reshape(-1)[pick].astype(np.float64)))
        columns["rgb"].append(torch.from_numpy(image.reshape(-1, 3)[pick].astype(np.float64)))
        for index, (window, spread) in enumerate(NEIGHBOURHOODS):
            span = ndimage.maximum_filter(log_range, window) \
                - ndimage.minimum_filter(log_range, window)
            varied[index].append((span > spread).reshape(-1)[pick])
    return ({k: torch.cat(v) for k, v in columns.items()},
            [torch.from_numpy(np.concatenate(v)) for v in varied])


def refit_errors(pixels: dict, keep, truth: dict) -> dict[str, list[float]]:
    from seathru.nerf import water_fit, water_surfaces

    water = ~torch.isfinite(pixels["ranges"])
    depth = torch.where(water, torch.nan, pixels["ranges"])
    data = water_surfaces.surface_data(pixels["origins"][keep], pixels["directions"][keep],
                                  pixels["rgb"][keep], depth[keep], (~water).double()[keep],
                                  0.02, 0.9, open_water_opacity=0.5, open_water=water[keep])
    fit = water_fit.fit_water(data.ranges, data.observed, data.ids, data.groups,
                              {"sigma_attn": 0.2, "sigma_bs": 0.2, "c_med": 0.2},
                              dark=data.dark)
    return {k: [100 * (v / t - 1) for v, t in zip(getattr(fit, k), truth[k])] for k in KEYS}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dives", default="survey_default,survey_coastal_3c,survey_turbid")
    parser.add_argument("--per-view", type=int, default=8000)
    parser.add_argument("--views", type=int, default=16)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    from bench_water import simulate
    from seathru.io.water import read_truth_water

    torch.set_num_threads(1)
    started = time.perf_counter()
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_footprint_"))
    lines = ["# Which surface pixels bias the water refit on exact ranges "
             "(`benchmarks/bench_refit_footprint.py`)", "",
             f"The refit on the simulator's noise-free renders and exact ranges ({args.views} "
             f"views at {args.width}x{args.height}, {args.per_view} pixels a view, voxels of "
             "0.02 m, brightness weights and dark-pixel bound); errors per channel (R, G, B) "
             "against the simulator's water, with every surface pixel and without those whose "
             "window x window neighbourhood spans more than the given share in range.", "",
             "| dive | surface pixels used | sigma_attn error | sigma_bs error | c_med error |",
             "|---|---|---|---|---|"]
    for dive in args.dives.split(","):
        path, water = dive.split("_", 1)
        truth = simulate(work, path, water, args) / "truth"
        true_water = read_truth_water(truth / "water.json").as_dict()
        pixels, varied = dive_pixels(truth, args.per_view, args.seed)
        surface = torch.isfinite(pixels["ranges"])
        cases = [("all", torch.ones_like(surface))] + [
            (f"without {100 * float(v[surface].double().mean()):.0f}% ({w}x{w}, {100 * s:g}%)",
             ~v | ~surface) for (w, s), v in zip(NEIGHBOURHOODS, varied)]
        for name, keep in cases:
            errors = refit_errors(pixels, keep, true_water)
            lines.append(f"| {dive} | {name} | " + " | ".join(
                ", ".join(f"{e:+.1f}%" for e in errors[k]) for k in KEYS) + " |")
            print(lines[-1], flush=True)
    lines += ["", f"Machine: {cpu_name()}; one thread; {time.strftime('%Y-%m-%d')}; "
              f"{(time.perf_counter() - started) / 60:.1f} min in all."]
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
