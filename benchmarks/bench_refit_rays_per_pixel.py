"""Does the water refit's bias come from the rays a pixel averages? (a script)

The refit (``seathru.nerf.water_fit``) on the simulator's exact pixels: a survey's own
noise-free images with water and true ranges, 0.054 m voxels, the open water as the image
shows it. Two questions, each answered side by side on the same dive:

- one ray a pixel (``supersample`` 1) against the usual 2 x 2 rays, and the 2 x 2 pixels without
  those whose rays' ranges spread by more than 2% or 0.5% (``fit_surfaces`` with the training's
  trim, dark-pixel bound and brightness weights);
- the 2 x 2 pixels fitted with their mean range (as the refit does) against each ray's own range
  in the transmission and the backscatter, ``mean_k exp(-sigma z_k)`` (``fit_water``, 2,000 open
  water pixels at ``c_med``; the refit's residuals are patched for the second arm only).

    python benchmarks/bench_refit_rays_per_pixel.py [--waters default,coastal_3c]

Writes benchmarks/results/refit_rays_per_pixel.md. About 3 min a water on 2 CPU cores.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from machine import cpu_name

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
RESULTS = REPO / "benchmarks" / "results" / "refit_rays_per_pixel.md"
VOXEL = 0.054
START = {"sigma_attn": 0.3, "sigma_bs": 0.3, "c_med": 0.3}
OPEN_WATER_PIXELS = 2000


def survey_rays(water: str, supersample: int):
    """Every pixel of a 10-view survey at 160x120: centre-ray origins and directions, mean
    range (inf: open water), the rays' ranges (pixels, rays), their spread relative to the mean,
    the image with water and the clean image (the mean of the rays' clean radiance)."""
    from seathru.io.textures import load_sample_textures
    from seathru.sim import dive as dive_mod
    from seathru.sim import scene as scene_mod
    from seathru.sim import sensor
    from seathru.sim.water import water_params

    spec = dive_mod.DiveSpec(views=10, width=160, height=120, path="survey",
                             water=water_params(water), seed=0, fov_deg=65.0,
                             supersample=supersample, seabed_amplitude=0.08)
    plan = dive_mod.plan_dive(spec, load_sample_textures())
    parts: dict[str, list[np.ndarray]] = {k: [] for k in
                                          ("origins", "dirs", "range", "rays", "spread", "image",
                                           "clean")}
    for c2w in plan.poses:
        origin, dirs = sensor.pixel_rays(plan.camera, c2w, supersample)
        radiance, ranges = scene_mod.render_subsamples(plan.scene, origin, dirs)
        clean, mean_range = scene_mod.pixel_means(radiance, ranges)
        centre_origin, centre_dirs = sensor.pixel_rays(plan.camera, c2w, 1)
        with np.errstate(invalid="ignore"):
            spread = (ranges.max(axis=2) - ranges.min(axis=2)) / mean_range
        parts["dirs"].append(centre_dirs.reshape(-1, 3))
        parts["origins"].append(np.broadcast_to(centre_origin, parts["dirs"][-1].shape))
        parts["range"].append(mean_range.reshape(-1).astype(np.float64))
        parts["rays"].append(ranges.reshape(-1, supersample * supersample))
        parts["spread"].append(np.nan_to_num(spread.reshape(-1), nan=0.0))
        parts["image"].append(dive_mod.subsampled_water_image(radiance, ranges, spec.water)
                              .reshape(-1, 3).astype(np.float64))
        parts["clean"].append(clean.reshape(-1, 3).astype(np.float64))
    return spec.water, {k: np.concatenate(v) for k, v in parts.items()}


def errors(fit, truth) -> str:
    return "; ".join(
        ", ".join(f"{100 * (a / b - 1):+.1f}" for a, b in zip(getattr(fit, k), getattr(truth, k)))
        for k in ("sigma_attn", "sigma_bs", "c_med"))


def by_footprint(water: str) -> list[str]:
    from seathru.nerf.water_fit import fit_surfaces
    from seathru.nerf.water_surfaces import surface_data

    rows = []
    for supersample in (1, 2):
        truth, px = survey_rays(water, supersample)
        surface = np.isfinite(px["range"])
        for label, keep in (("every pixel", np.ones_like(surface)),
                            ("rays' ranges within 2%", px["spread"] < 0.02),
                            ("rays' ranges within 0.5%", px["spread"] < 0.005)):
            if supersample == 1 and label != "every pixel":
                continue  # one ray: no spread
            use = keep | ~surface
            origins, dirs, ranges, image = (torch.from_numpy(np.ascontiguousarray(px[k][use]))
                                            for k in ("origins", "dirs", "range", "image"))
            open_water = ~torch.isfinite(ranges)
            data = surface_data(origins, dirs, image, torch.where(open_water, torch.nan, ranges),
                                (~open_water).double(), VOXEL, 0.9, open_water_opacity=0.5,
                                open_water=open_water)
            fit, _ = fit_surfaces(data, START, trim=3.5)
            rows.append(f"| {water} | {supersample} x {supersample} | {label} | "
                        f"{keep[surface].mean():.2f} | {errors(fit, truth)} |")
            print(rows[-1], flush=True)
    return rows


def by_ray_ranges(water: str) -> list[str]:
    import seathru.nerf.water_fit as water_fit
    import seathru.nerf.water_surfaces as water_surfaces

    truth, px = survey_rays(water, 2)
    surface = np.isfinite(px["range"])
    points = px["origins"][surface] + px["dirs"][surface] * px["range"][surface, None]
    ids, groups = water_surfaces.voxel_groups(torch.from_numpy(points), VOXEL)
    veiling = torch.tensor(truth.c_med, dtype=torch.float64).repeat(OPEN_WATER_PIXELS, 1)
    observed = torch.cat([torch.from_numpy(px["image"][surface]), veiling])
    ids = torch.cat([ids, torch.full((OPEN_WATER_PIXELS,), groups)])
    rays = torch.from_numpy(px["rays"][surface].astype(np.float64))
    far = torch.full((OPEN_WATER_PIXELS,), float("inf"), dtype=torch.float64)
    plain = water_fit.projected_residuals

    def per_ray(sigma_attn, sigma_bs, c_med, ranges, observed, ids, groups, weights=None):
        if ranges.ndim == 1:
            return plain(sigma_attn, sigma_bs, c_med, ranges, observed, ids, groups, weights)
        ranges = ranges.clamp_max(1e6)
        attenuation = torch.exp(-sigma_attn * ranges[:, :, None]).mean(1)
        backscatter = c_med * (1.0 - torch.exp(-sigma_bs * ranges[:, :, None]).mean(1))
        num = observed.new_zeros(groups, 3).index_add_(0, ids,
                                                       attenuation * (observed - backscatter))
        den = observed.new_zeros(groups, 3).index_add_(0, ids, attenuation * attenuation)
        clean = (num / den.clamp_min(1e-12)).clamp_min(0.0)
        residuals = observed - clean[ids] * attenuation - backscatter
        if weights is not None:
            residuals = residuals * weights.sqrt()[ids]
        return residuals, clean, ranges.mean(1)

    rows = []
    arms = (("the pixel's mean range", torch.cat([rays.mean(1), far])),
            ("each ray's own range", torch.cat([rays, far[:, None].expand(-1, rays.shape[1])])))
    for label, ranges in arms:
        water_fit.projected_residuals = per_ray
        try:
            fit = water_fit.fit_water(ranges, observed, ids, groups + 1, START)
        finally:
            water_fit.projected_residuals = plain
        rows.append(f"| {water} | {label} | {errors(fit, truth)} |")
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--waters", default="default,coastal_3c")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    torch.set_num_threads(2)
    started = time.time()
    waters = args.waters.split(",")
    footprint = [row for water in waters for row in by_footprint(water)]
    ray_ranges = [row for water in waters for row in by_ray_ranges(water)]
    lines = ["# The rays a pixel averages and the water refit (`benchmarks/"
             "bench_refit_rays_per_pixel.py`)", "",
             "A 10-view survey at 160x120 (seed 0), the simulator's noise-free images with water "
             "and true ranges, voxels of 0.054 m; errors against the simulator's water "
             "(%: `sigma_attn` R, G, B; `sigma_bs`; `c_med`).", "",
             "## One ray a pixel against 2 x 2 (`fit_surfaces`, as the training refits)", "",
             "| water | rays a pixel | pixels | share of surface pixels kept | error (%) |",
             "|---|---|---|---|---|", *footprint, "",
             "## The 2 x 2 pixels with their mean range or each ray's own (`fit_water`)", "",
             "| water | ranges in the fit | error (%) |", "|---|---|---|", *ray_ranges, "",
             f"Machine: {cpu_name()}; {time.strftime('%Y-%m-%d')}; "
             f"{(time.time() - started) / 60:.0f} min in all.", ""]
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
