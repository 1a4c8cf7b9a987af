"""A whole simulated dive: scene, camera path, exposures and every view's images.

:func:`plan_dive` fixes everything the views share (scene, poses, camera, the radiometric
calibration from an auto-exposure metering pass, per-image exposures and noise seeds);
:func:`render_views` then synthesises each view: clean radiance and range by ray casting, the
water image (the water acts on each subsample ray at its own range, then the pixel averages
them, as a sensor pixel integrates its footprint), the noisy raw mosaic and the camera JPEG.
The random streams are split from one ``numpy.random.SeedSequence(seed)`` (scene, path,
exposures, noise; the noise stream once more per view), so the dive is deterministic given the
spec, whatever the number of worker processes. Pure numpy, no file I/O (``seathru.io.truth``
writes a dive to disk).
"""

from __future__ import annotations

import concurrent.futures
import multiprocessing
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from seathru.sim import reef
from seathru.sim import scene as scene_mod
from seathru.sim.camera_paths import orbit_path, transect_path
from seathru.sim.shapes import Seabed
from seathru.sim import sensor as sensor_mod
from seathru.sim.water import WaterParams, water_image


CameraPath = Literal["orbit", "transect", "survey"]  # the keys of CAMERA_PATHS
# Each path's poses over its scene (see build_scene): the orbit circles the demo's objects
# (no open water: the hard case for the water fit), the transect looks down on them while
# swimming over, the survey looks across a reef slope with open water above the crest.
CAMERA_PATHS: dict[CameraPath, Callable[[scene_mod.Scene, int, np.random.Generator],
                                        np.ndarray]] = {
    "orbit": orbit_path, "transect": transect_path,
    "survey": reef.survey_path}


def build_scene(path: CameraPath, textures_srgb: Mapping[str, np.ndarray] | None, seed: int,
                seabed_amplitude: float) -> scene_mod.Scene:
    """The scene a camera path looks at: the reef slope for ``survey``
    (:func:`seathru.sim.reef.build_reef_scene`), the demo's patch of seabed otherwise
    (:func:`seathru.sim.scene.build_dive_scene`)."""
    if path == "survey":
        return reef.build_reef_scene(textures_srgb, seed, seabed_amplitude)
    return scene_mod.build_dive_scene(textures_srgb, seed=seed,
                                      seabed=Seabed(amplitude=seabed_amplitude))


@dataclass(frozen=True)
class DiveSpec:
    """What to simulate, resolved (water coefficients, not a preset name).

    Raises ``ValueError`` naming the field when a value is out of range.
    """

    views: int
    width: int
    height: int
    path: CameraPath
    water: WaterParams
    seed: int
    fov_deg: float
    supersample: int
    seabed_amplitude: float
    sensor: sensor_mod.SensorConfig = field(default_factory=sensor_mod.SensorConfig)

    def __post_init__(self) -> None:
        if self.views < 1:
            raise ValueError(f"views: need at least 1 image, got {self.views}")
        for name, value in (("width", self.width), ("height", self.height)):
            if value < 8 or value % 2:
                raise ValueError(f"{name}: need an even number of pixels >= 8 (whole 2x2 Bayer "
                                 f"cells), got {value}")
        if self.path not in CAMERA_PATHS:
            raise ValueError(f"path: unknown camera path {self.path!r}; use "
                             f"{', '.join(CAMERA_PATHS)}")
        if not 10.0 <= self.fov_deg <= 150.0:
            raise ValueError(f"fov_deg: expected 10 to 150 degrees, got {self.fov_deg}")
        if not 1 <= self.supersample <= 8:
            raise ValueError(f"supersample: expected 1 to 8, got {self.supersample}")
        if not 0.0 <= self.seabed_amplitude <= 0.5:
            raise ValueError(f"seabed_amplitude: expected 0 to 0.5 m, got "
                             f"{self.seabed_amplitude}")


@dataclass
class DivePlan:
    """Everything the views of a dive share."""

    scene: scene_mod.Scene
    poses: np.ndarray                       # (V, 4, 4) camera-to-world, metres
    camera: sensor_mod.Pinhole
    metered_radiance: float                 # auto-exposure reading of the water images
    dn_per_unit: float                      # radiometric calibration from that reading
    exposures: list[sensor_mod.Exposure]    # (V,)
    noise_seeds: list[np.random.SeedSequence]  # (V,) one raw-noise stream per view


@dataclass
class SimulatedView:
    """One view: ``clean`` J and ``water`` I (H, W, 3) float32 linear radiance, ``range_m``
    (H, W) float32 (``+inf`` where no surface is seen: open water, where J is 0 and I is
    ``c_med``), ``raw`` (H, W) uint16 RGGB mosaic and ``jpeg`` (H, W, 3) sRGB-encoded float32
    in [0, 1]."""

    c2w: np.ndarray
    exposure: sensor_mod.Exposure
    clean: np.ndarray
    range_m: np.ndarray
    water: np.ndarray
    raw: np.ndarray
    jpeg: np.ndarray


def subsampled_water_image(radiance: np.ndarray, range_m: np.ndarray, water: WaterParams
                          ) -> np.ndarray:
    """The image with water (H, W, 3) float32 of subsamples (``radiance`` (H, W, S, 3), ``range``
    (H, W, S), as :func:`seathru.sim.scene.render_subsamples` gives them): the water acts on each
    subsample at its own range, then the pixel takes their mean. Applying it once at the
    pixel's mean range instead would give a pixel that spans ranges more backscatter and less
    direct light than its rays bring (both are convex or concave in range), which no per-ray
    model such as the trained renderer can reproduce."""
    # float32 subsamples, as the clean image and range map are stored: one subsample a pixel
    # gives exactly ``water_image(clean, range)``
    rays = water_image(radiance.astype(np.float32), range_m.astype(np.float32), water)
    return rays.astype(np.float64).mean(axis=2).astype(np.float32)


def meter(scene: scene_mod.Scene, poses: np.ndarray, spec: DiveSpec) -> float:
    """Auto-exposure metering on a cheap low-resolution pass over all views: the 99th
    percentile of the brightest channel of the water image."""
    small = sensor_mod.Pinhole.from_fov(max(16, spec.width // 8), max(12, spec.height // 8),
                                        spec.fov_deg)
    values = []
    for c2w in poses:
        origin, dirs = sensor_mod.pixel_rays(small, c2w, 1)
        values.append(subsampled_water_image(*scene_mod.render_subsamples(scene, origin, dirs),
                                             spec.water).max(axis=2).ravel())
    return float(np.percentile(np.concatenate(values), 99.0))


def plan_dive(spec: DiveSpec, textures_srgb: Mapping[str, np.ndarray] | None = None) -> DivePlan:
    """The scene, camera path, calibration and exposures of a dive.

    Args:
        spec: what to simulate.
        textures_srgb: sRGB ``uint8`` texture images by name (see
            :func:`build_scene`); missing ones get procedural noise.

    Returns:
        the plan; deterministic given ``spec`` and the textures.

    Example::

        plan = plan_dive(DiveSpec(4, 32, 24, "orbit", water_params(), 0, 65.0, 1, 0.08))
    """
    scene_seed, path_seed, exposure_seed, noise_seed = np.random.SeedSequence(
        spec.seed).spawn(4)
    scene = build_scene(spec.path, textures_srgb, int(scene_seed.generate_state(1)[0]),
                        spec.seabed_amplitude)
    poses = CAMERA_PATHS[spec.path](scene, spec.views, np.random.default_rng(path_seed))
    metered = meter(scene, poses, spec)
    return DivePlan(
        scene=scene, poses=poses,
        camera=sensor_mod.Pinhole.from_fov(spec.width, spec.height, spec.fov_deg),
        metered_radiance=metered,
        dn_per_unit=sensor_mod.calibrate_dn_per_unit(spec.sensor, metered),
        exposures=sensor_mod.plan_exposures(spec.sensor, spec.views,
                                            np.random.default_rng(exposure_seed)),
        noise_seeds=noise_seed.spawn(spec.views))


@dataclass
class _ViewJob:
    """What every view needs; module-level so worker processes receive it once."""

    spec: DiveSpec
    plan: DivePlan


_JOB: _ViewJob | None = None


def _init_worker(job: _ViewJob) -> None:
    global _JOB
    _JOB = job


def _render_one(index: int) -> SimulatedView:
    job = _JOB
    assert job is not None
    spec, plan = job.spec, job.plan
    c2w, exposure = plan.poses[index], plan.exposures[index]
    origin, dirs = sensor_mod.pixel_rays(plan.camera, c2w, spec.supersample)
    radiance, ranges = scene_mod.render_subsamples(plan.scene, origin, dirs)
    clean, range_m = scene_mod.pixel_means(radiance, ranges)
    water = subsampled_water_image(radiance, ranges, spec.water)
    signal = sensor_mod.expected_signal(water, exposure, plan.dn_per_unit)
    raw = sensor_mod.capture_raw(sensor_mod.mosaic_rggb(signal), exposure.iso, spec.sensor,
                                 np.random.default_rng(plan.noise_seeds[index]))
    return SimulatedView(c2w, exposure, clean, range_m, water, raw,
                         sensor_mod.develop_jpeg(raw, spec.sensor))


def render_views(spec: DiveSpec, plan: DivePlan, workers: int = 1) -> Iterator[SimulatedView]:
    """Every view of the dive, in order, one at a time (``workers`` processes compute them
    ahead; the result does not depend on their number).

    Example::

        for view in render_views(spec, plan_dive(spec), workers=2): ...
    """
    job = _ViewJob(spec, plan)
    if workers <= 1:
        _init_worker(job)
        yield from map(_render_one, range(spec.views))
        return
    # "spawn": forking after OpenCV has started its thread pool is not safe everywhere.
    with concurrent.futures.ProcessPoolExecutor(
            max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
            initializer=_init_worker, initargs=(job,)) as pool:
        yield from pool.map(_render_one, range(spec.views))
