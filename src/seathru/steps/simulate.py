"""Simulate a dive: a synthetic underwater scene with known ground truth (the demo dataset).

Renders a procedural seabed with textured balls, boxes and rocks along a dive camera path
(``orbit`` around the centre, ``transect`` over the seabed, or ``survey`` across a reef slope
with open water above its crest), applies the SeaThru water model (a named preset, the Jerlov
water types among them, or custom coefficients) and a raw sensor model, and writes raw DNGs,
camera-like JPEGs and the ground truth (clean images, water images, ranges, cameras, water and
sensor parameters) into ``--out``, atomically:
the folder appears complete or not at all. ``--out/README.md`` documents every file
(``seathru.io.truth``); the simulation itself is ``seathru.sim.dive``.
"""

from __future__ import annotations

import argparse
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from seathru import settings
from seathru.io import truth
from seathru.io.atomic import atomic_dir
from seathru.io.cameras import every_nth_split
from seathru.io.textures import load_sample_textures
from seathru.settings import setting
from seathru.sim import dive
from seathru.sim.dive import CameraPath
from seathru.sim.sensor import SensorConfig
from seathru.sim.water import WaterPreset, water_params

log = logging.getLogger(__name__)


@dataclass
class Settings:
    """Synthetic dive: views, image size, camera path, water and sensor sampling."""

    views: int = setting(24, help="number of images")
    width: int = setting(320, help="image width, pixels (even)")
    height: int = setting(240, help="image height, pixels (even)")
    path: CameraPath = setting("orbit", help="camera path: circle the centre object, no open "
                                             "water (orbit); swim over the seabed looking down "
                                             "(transect); swim along a reef slope looking "
                                             "across it, 0.5-50 m ranges and open water above "
                                             "the crest (survey)")
    water: WaterPreset = setting("default", help="water preset: default (coastal blue-green), "
                                                 "clear (no water), turbid (green, murky), or a "
                                                 "Jerlov type from clear oceanic (oceanic_i) to "
                                                 "turbid coastal (coastal_9c)")
    water_scale: float = setting(1.0, help="multiply the preset's sigma_attn and sigma_bs "
                                           "(turbidity)")
    sigma_attn: list[float] | None = setting(None, length=3, help="override the attenuation "
                                             "coefficients (red green blue), 1/m")
    sigma_bs: list[float] | None = setting(None, length=3, help="override the backscatter "
                                           "coefficients (red green blue), 1/m")
    c_med: list[float] | None = setting(None, length=3, help="override the medium (veiling "
                                        "light) colour (red green blue), linear")
    seed: int = setting(0, help="random seed")
    fov_deg: float = setting(65.0, help="horizontal field of view, degrees")
    supersample: int = setting(2, help="s x s rays per pixel for antialiasing")
    seabed_amplitude: float = setting(0.08, help="seabed undulation amplitude, m (0 = flat)")
    workers: int = setting(1, help="processes rendering views in parallel (the output does "
                                   "not depend on it)")
    test_every: int = setting(8, help="every n-th image (sorted names, starting with the "
                                      "first) is a test image (0 = none)")
    jpeg_white_balance: Literal["none", "auto"] = setting(
        "none", help="the camera JPEGs' white balance: none, or auto (the camera's, frame by "
                     "frame, grey world: ingest.images=jpeg trains on them)")
    jpeg_chroma: Literal["4:2:0", "4:4:4"] = setting(
        "4:2:0", help="the camera JPEGs' chroma sampling: 4:2:0 (colour at half resolution, "
                      "as cameras write it) or 4:4:4 (every pixel)")

    def dive_spec(self) -> dive.DiveSpec:
        """The resolved simulation (raises ValueError naming a bad setting)."""
        water = water_params(self.water, self.water_scale, self.sigma_attn, self.sigma_bs,
                             self.c_med)
        return dive.DiveSpec(views=self.views, width=self.width, height=self.height,
                             path=self.path, water=water, seed=self.seed, fov_deg=self.fov_deg,
                             supersample=self.supersample,
                             seabed_amplitude=self.seabed_amplitude,
                             sensor=SensorConfig(jpeg_white_balance=self.jpeg_white_balance,
                                                 jpeg_chroma=self.jpeg_chroma))

    def validate(self) -> None:
        self.dive_spec()
        if self.workers < 1:
            raise ValueError(f"workers: need at least 1, got {self.workers}")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, type=Path,
                        help="output folder (created or replaced atomically)")
    settings.add_arguments(parser, Settings)


def run(args: argparse.Namespace) -> None:
    simulate(args.out, settings.from_namespace(Settings, args))


def simulate(out: str | Path, cfg: Settings) -> dict:
    """Render the dataset into ``out`` (atomically). Returns a summary dict.

    Deterministic given ``cfg`` (the seed included), whatever ``cfg.workers``.
    """
    out, spec = Path(out), cfg.dive_spec()
    truth.check_replaceable(out)
    start = time.perf_counter()
    plan = dive.plan_dive(spec, load_sample_textures())
    names = truth.view_names(spec.views)
    splits = every_nth_split(names, cfg.test_every)
    log.info("simulate: %d %s views at %dx%d, water %s, metered radiance %.4f", spec.views,
             spec.path, spec.width, spec.height, spec.water.preset, plan.metered_radiance)
    frames = []
    open_water_pixels = 0
    with atomic_dir(out) as tmp:
        for i, (name, view) in enumerate(zip(names, dive.render_views(spec, plan, cfg.workers))):
            truth.write_view(tmp, name, view, spec.sensor, plan.camera)
            frames.append(truth.truth_frame(name, plan.camera, view.c2w, view.range_m,
                                            splits[name]))
            open_water_pixels += int(np.count_nonzero(~np.isfinite(view.range_m)))
            log.info("view %d/%d %s: range %.2f-%.2f m, exposure %.5f s (%+.2f EV)", i + 1,
                     spec.views, name, *truth.view_range_limits(view.range_m),
                     view.exposure.exposure_time_s, view.exposure.ev_offset)
        truth.write_records(tmp, spec, plan, frames, cfg.test_every, open_water_pixels)
    elapsed = time.perf_counter() - start
    log.info("simulate: wrote %d views to %s in %.1f s", spec.views, out, elapsed)
    return {"out": str(out), "views": spec.views, "seconds": elapsed,
            "open_water_pixels": open_water_pixels, "dn_per_unit": plan.dn_per_unit}
