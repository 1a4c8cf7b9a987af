"""Simulate a dive: a synthetic underwater scene with known ground truth (the demo dataset).

Renders a procedural seabed with textured balls, boxes and rocks along a dive camera path
(``orbit`` around the centre or ``transect`` over the seabed), applies the SeaThru water model
and a raw sensor model, and writes raw DNGs, camera-like JPEGs and the ground truth (clean
images, water images, ranges, cameras, water and sensor parameters) into ``--out``, atomically:
the folder appears complete or not at all. ``--out/README.md`` documents every file.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import contextlib
import logging
import multiprocessing
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from seathru.sim import scene as scene_mod
from seathru.sim import sensor as sensor_mod
from seathru.radiometry.colour import linear_to_srgb
from seathru.sim.water import PRESETS, WaterParams, water_image, water_params
from seathru.errors import PipelineError
from seathru.io.atomic import atomic_dir, write_json, write_text
from seathru.io.cameras import CameraSet, Frame, every_nth_split, write_cameras
from seathru.io.dng import write_dng
from seathru.io.images import write_8bit, write_float_tiff

log = logging.getLogger(__name__)

NAME_PREFIX = "dive_"
NEAR_FAR_MARGIN = 0.05  # cameras.json near/far = (1 -+ margin) * min/max finite range
JPEG_QUALITY = 95
JPEG_WHITE = 0.85  # the metered radiance at nominal exposure maps to this linear JPEG value

# Texture name -> (file in skimage/data, crop rows, crop columns). Only files that ship inside
# the scikit-image wheel; a missing file falls back to procedural noise.
SKIMAGE_TEXTURES = {
    "seabed_a": ("gravel.png", None),
    "seabed_b": ("moon.png", None),
    "algae": ("grass.png", None),
    "rock": ("moon.png", None),
    "gravel": ("gravel.png", None),
    "coffee": ("coffee.png", None),
    "astronaut": ("astronaut.png", None),
    "coral": ("retina.jpg", (slice(350, 1050), slice(350, 1050))),
    "cat": ("chelsea.png", None),
    "rocket": ("rocket.jpg", None),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, type=Path,
                        help="output folder (created or replaced atomically)")
    parser.add_argument("--views", type=int, default=24, help="number of images (default 24)")
    parser.add_argument("--width", type=int, default=320, help="image width, pixels (even)")
    parser.add_argument("--height", type=int, default=240, help="image height, pixels (even)")
    parser.add_argument("--path", choices=("orbit", "transect"), default="orbit",
                        help="camera path: circle the centre object, or swim over the seabed")
    parser.add_argument("--water", choices=tuple(PRESETS), default="default",
                        help="water preset (default: coastal blue-green)")
    parser.add_argument("--water-scale", type=float, default=1.0,
                        help="multiply the preset's sigma_attn and sigma_bs (turbidity)")
    parser.add_argument("--sigma-attn", type=float, nargs=3, metavar=("R", "G", "B"),
                        help="override the attenuation coefficients, 1/m")
    parser.add_argument("--sigma-bs", type=float, nargs=3, metavar=("R", "G", "B"),
                        help="override the backscatter coefficients, 1/m")
    parser.add_argument("--c-med", type=float, nargs=3, metavar=("R", "G", "B"),
                        help="override the medium (veiling light) colour, linear")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--fov-deg", type=float, default=65.0,
                        help="horizontal field of view, degrees (default 65)")
    parser.add_argument("--supersample", type=int, default=2,
                        help="s x s rays per pixel for antialiasing (default 2)")
    parser.add_argument("--seabed-amplitude", type=float, default=0.08,
                        help="seabed undulation amplitude, m (0 = flat)")
    parser.add_argument("--workers", type=int, default=1,
                        help="processes rendering views in parallel (default 1; the output does "
                             "not depend on it)")
    parser.add_argument("--test-every", type=int, default=8,
                        help="every n-th image (sorted names, starting with the first) is a test "
                             "image (default 8; 0 = none)")


@dataclass
class SimulationOptions:
    views: int = 24
    width: int = 320
    height: int = 240
    path: str = "orbit"
    water: WaterParams = field(default_factory=lambda: water_params("default"))
    seed: int = 0
    fov_deg: float = 65.0
    supersample: int = 2
    seabed_amplitude: float = 0.08
    test_every: int = 8
    workers: int = 1
    sensor: sensor_mod.SensorConfig = field(default_factory=sensor_mod.SensorConfig)


def run(args: argparse.Namespace) -> None:
    water = water_params(args.water, args.water_scale, args.sigma_attn, args.sigma_bs, args.c_med)
    options = SimulationOptions(views=args.views, width=args.width, height=args.height,
                                path=args.path, water=water, seed=args.seed,
                                fov_deg=args.fov_deg, supersample=args.supersample,
                                seabed_amplitude=args.seabed_amplitude,
                                test_every=args.test_every, workers=args.workers)
    simulate(args.out, options)


def _validate(out: Path, options: SimulationOptions) -> None:
    if options.views < 1:
        raise PipelineError(f"--views: need at least 1 image, got {options.views}")
    for name, value in (("--width", options.width), ("--height", options.height)):
        if value < 8 or value % 2:
            raise PipelineError(f"{name}: need an even number of pixels >= 8 (whole 2x2 Bayer "
                                f"cells), got {value}")
    if not 10.0 <= options.fov_deg <= 150.0:
        raise PipelineError(f"--fov-deg: expected 10 to 150 degrees, got {options.fov_deg}")
    if options.workers < 1:
        raise PipelineError(f"--workers: need at least 1, got {options.workers}")
    if not 1 <= options.supersample <= 8:
        raise PipelineError(f"--supersample: expected 1 to 8, got {options.supersample}")
    if not 0.0 <= options.seabed_amplitude <= 0.5:
        raise PipelineError(f"--seabed-amplitude: expected 0 to 0.5 m, got "
                            f"{options.seabed_amplitude}")
    if out.exists() and (not out.is_dir() or (any(out.iterdir())
                                             and not (out / "truth" / "cameras.json").exists())):
        raise PipelineError(f"--out {out}: exists and is not an earlier simulate output; "
                            "choose an empty or new folder (it would be replaced)")


def load_sample_textures() -> dict[str, np.ndarray]:
    """sRGB ``uint8`` textures from the sample images shipped inside scikit-image (no download);
    names whose file is absent are left out (the scene then uses procedural noise)."""
    import skimage.data

    data_dir = Path(skimage.data.__file__).parent
    textures = {}
    for name, (filename, crop) in SKIMAGE_TEXTURES.items():
        image = cv2.imread(str(data_dir / filename), cv2.IMREAD_COLOR)
        if image is None:
            log.warning("texture %s: %s not found in %s, using procedural noise", name, filename,
                        data_dir)
            continue
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
        textures[name] = image[crop] if crop is not None else image
    return textures


def _camera_path(scene: scene_mod.Scene, options: SimulationOptions,
                 rng: np.random.Generator) -> np.ndarray:
    if options.path == "orbit":
        return scene_mod.orbit_path(scene, options.views, rng)
    if options.path == "transect":
        return scene_mod.transect_path(scene, options.views, rng)
    raise PipelineError(f"--path: unknown camera path {options.path!r}; use orbit or transect")


def _meter(scene: scene_mod.Scene, poses: np.ndarray, options: SimulationOptions) -> float:
    """Auto-exposure metering on a cheap low-resolution pass over all views: the 99th
    percentile of the brightest channel of the water image."""
    small = sensor_mod.Pinhole.from_fov(max(16, options.width // 8), max(12, options.height // 8),
                                        options.fov_deg)
    values = []
    for c2w in poses:
        origin, dirs = sensor_mod.pixel_rays(small, c2w, 1)
        clean, rng_m = scene_mod.render_view(scene, origin, dirs)
        values.append(water_image(clean, rng_m, options.water).max(axis=2).ravel())
    return float(np.percentile(np.concatenate(values), 99.0))


@dataclass
class _ViewJob:
    """Everything one view needs; module-level so worker processes can receive it once."""

    scene: scene_mod.Scene
    camera: sensor_mod.Pinhole
    options: SimulationOptions
    dn_per_unit: float


_JOB: _ViewJob | None = None


def _init_worker(job: _ViewJob) -> None:
    global _JOB
    _JOB = job


def _render_one(c2w: np.ndarray, exposure: sensor_mod.Exposure,
                noise_seed: np.random.SeedSequence) -> tuple[np.ndarray, ...]:
    """Clean image, range, water image and raw mosaic of one view."""
    job = _JOB
    assert job is not None
    origin, dirs = sensor_mod.pixel_rays(job.camera, c2w, job.options.supersample)
    clean, rng_m = scene_mod.render_view(job.scene, origin, dirs)
    water = water_image(clean, rng_m, job.options.water)
    signal = sensor_mod.expected_signal(water, exposure, job.dn_per_unit)
    raw = sensor_mod.capture_raw(sensor_mod.mosaic_rggb(signal), exposure.iso,
                                 job.options.sensor, np.random.default_rng(noise_seed))
    return clean, rng_m, water, raw


def simulate(out: str | Path, options: SimulationOptions) -> dict:
    """Render the dataset into ``out`` (atomically). Returns a summary dict.

    Deterministic given ``options`` (the seed included), whatever ``options.workers``.
    """
    out = Path(out)
    _validate(out, options)
    start = time.perf_counter()
    scene_seed, path_seed, exposure_seed, noise_seed = np.random.SeedSequence(
        options.seed).spawn(4)
    scene = scene_mod.build_scene(
        load_sample_textures(), seed=int(scene_seed.generate_state(1)[0]),
        seabed=scene_mod.Seabed(amplitude=options.seabed_amplitude))
    poses = _camera_path(scene, options, np.random.default_rng(path_seed))
    camera = sensor_mod.Pinhole.from_fov(options.width, options.height, options.fov_deg)
    config = options.sensor
    metered = _meter(scene, poses, options)
    dn_per_unit = sensor_mod.calibrate_dn_per_unit(config, metered)
    exposures = sensor_mod.plan_exposures(config, options.views, np.random.default_rng(
        exposure_seed))
    noise_seeds = noise_seed.spawn(options.views)
    jpeg_gain = JPEG_WHITE / config.metering_fraction
    names = [f"{NAME_PREFIX}{i:04d}" for i in range(options.views)]
    splits = every_nth_split(names, options.test_every)
    log.info("simulate: %d %s views at %dx%d, water %s, metered radiance %.4f",
             options.views, options.path, options.width, options.height, options.water.preset,
             metered)

    job = _ViewJob(scene, camera, options, dn_per_unit)
    frames = []
    open_water_pixels = 0
    with contextlib.ExitStack() as stack:
        if options.workers > 1:
            # "spawn": forking after OpenCV has started its thread pool is not safe everywhere.
            pool = stack.enter_context(concurrent.futures.ProcessPoolExecutor(
                max_workers=options.workers, mp_context=multiprocessing.get_context("spawn"),
                initializer=_init_worker, initargs=(job,)))
            results = pool.map(_render_one, poses, exposures, noise_seeds)
        else:
            _init_worker(job)
            results = map(_render_one, poses, exposures, noise_seeds)
        tmp = stack.enter_context(atomic_dir(out))
        for i, (name, c2w, exposure, result) in enumerate(zip(names, poses, exposures,
                                                              results)):
            clean, rng_m, water, raw = result
            write_dng(tmp / "raw" / f"{name}.dng", raw, black_level=config.black_level,
                      white_level=config.white_level, exposure_time_s=exposure.exposure_time_s,
                      iso=exposure.iso, f_number=exposure.f_number,
                      cfa_pattern=config.cfa_pattern)
            developed = sensor_mod.normalise_raw(sensor_mod.demosaic_bilinear(raw), config)
            write_8bit(tmp / "jpeg" / f"{name}.jpg",
                       linear_to_srgb(np.clip(jpeg_gain * developed, 0.0, 1.0)), JPEG_QUALITY)
            write_float_tiff(tmp / "truth" / "clean" / f"{name}.tiff", clean)
            write_float_tiff(tmp / "truth" / "water" / f"{name}.tiff", water)
            write_float_tiff(tmp / "truth" / "depth" / f"{name}.tiff", rng_m)
            finite = rng_m[np.isfinite(rng_m)]
            open_water_pixels += int(rng_m.size - finite.size)
            near = float(finite.min()) if finite.size else 0.1
            far = float(finite.max()) if finite.size else 10.0
            frames.append(Frame(
                name=name, image=f"water/{name}.tiff", width=camera.width, height=camera.height,
                fx=camera.fx, fy=camera.fy, cx=camera.cx, cy=camera.cy,
                c2w=[[float(v) for v in row] for row in c2w],
                near=(1.0 - NEAR_FAR_MARGIN) * near, far=(1.0 + NEAR_FAR_MARGIN) * far,
                split=splits[name]))
            log.info("view %d/%d %s: range %.2f-%.2f m, exposure %.5f s (%+.2f EV)", i + 1,
                     options.views, name, near, far, exposure.exposure_time_s,
                     exposure.ev_offset)
        cameras = CameraSet(frames=frames, near=min(f.near for f in frames),
                            far=max(f.far for f in frames), centre=[0.0, 0.0, 0.0], scale=1.0,
                            source="simulated")
        write_cameras(tmp / "truth" / "cameras.json", cameras)
        write_json(tmp / "truth" / "water.json", options.water.to_dict())
        write_json(tmp / "truth" / "sensor.json", _sensor_record(
            config, dn_per_unit, metered, jpeg_gain, names, exposures))
        scene_record = scene.describe()
        scene_record.update({"path": options.path, "seed": options.seed,
                             "fov_deg": options.fov_deg, "supersample": options.supersample,
                             "open_water_pixels": open_water_pixels})
        write_json(tmp / "truth" / "scene.json", scene_record)
        write_text(tmp / "README.md", _readme(options, config))
    elapsed = time.perf_counter() - start
    log.info("simulate: wrote %d views to %s in %.1f s", options.views, out, elapsed)
    return {"out": str(out), "views": options.views, "seconds": elapsed,
            "open_water_pixels": open_water_pixels, "dn_per_unit": dn_per_unit}


def _sensor_record(config: sensor_mod.SensorConfig, dn_per_unit: float, metered: float,
                   jpeg_gain: float, names: list[str],
                   exposures: list[sensor_mod.Exposure]) -> dict:
    record = config.to_dict()
    record.update({
        "bayer": "RGGB: R at (even row, even column), B at (odd row, odd column)",
        "camera_colour_space": "linear sRGB (identity colour matrix)",
        "dn_per_unit": dn_per_unit,
        "metered_radiance": metered,
        "signal_model": ("raw = clip(round(black_level + gain * Poisson(S / gain) + "
                         "Normal(0, read_noise_dn)), 0, white_level) with S = I_channel * "
                         "exposure_time_s * iso / 100 * dn_per_unit and gain = gain_iso100 * "
                         "iso / 100 (DN per electron)"),
        "jpeg": {"gain": jpeg_gain, "quality": JPEG_QUALITY,
                 "model": ("jpeg = sRGB(clip(gain * (demosaic_bilinear(raw) - black_level) / "
                           "(white_level - black_level), 0, 1)), 8 bit; no white balance")},
        "images": {name: {"exposure_time_s": e.exposure_time_s, "iso": e.iso,
                          "f_number": e.f_number, "ev_offset": e.ev_offset}
                   for name, e in zip(names, exposures)},
    })
    return record


def _readme(options: SimulationOptions, config: sensor_mod.SensorConfig) -> str:
    water = options.water
    return f"""# Simulated dive (seathru simulate)

{options.views} views, {options.width}x{options.height} pixels, path `{options.path}`,
water preset `{water.preset}`, seed {options.seed}, horizontal field of view
{options.fov_deg} deg, {options.supersample}x{options.supersample} rays per pixel.
Units: metres; world z up, seabed near z = 0. Images are named `{NAME_PREFIX}0000`,
`{NAME_PREFIX}0001`, ...

## Layout

    raw/<name>.dng            camera raw: 16-bit RGGB mosaic, DNG 1.4 tags in the main IFD
    jpeg/<name>.jpg           the same photo as an 8-bit sRGB JPEG (camera-like rendering)
    truth/clean/<name>.tiff   clean linear radiance J, float32 (H, W, 3)
    truth/water/<name>.tiff   linear water image I before the sensor, float32 (H, W, 3)
    truth/depth/<name>.tiff   range z in metres, float32 (H, W)
    truth/cameras.json        cameras (seathru-cameras/1); images point to truth/water/
    truth/water.json          medium parameters of the image formation model
    truth/sensor.json         sensor parameters and per-image exposure
    truth/scene.json          scene geometry (seabed formula, objects, light, path)

## Ground truth

- **Range** `z` is the Euclidean distance from the camera centre to the surface along
  the pixel's ray (not the z-depth). With s x s supersampling, a pixel's clean radiance
  and range are the *means* over its subsamples. A pixel where any subsample sees no
  surface (open water to infinity) has NaN range and NaN clean radiance; its water
  image is `c_med`.
- **Water image**, exact per pixel and channel (computed in float64 from the stored
  clean image and range, then stored as float32):
  `I = J * exp(-sigma_attn * z) + c_med * (1 - exp(-sigma_bs * z))` with
  sigma_attn = {list(water.sigma_attn)} /m, sigma_bs = {list(water.sigma_bs)} /m,
  c_med = {list(water.c_med)} (truth/water.json).
- **Cameras**: pinhole, OpenCV axes (x right, y down, z forward), pixel centres at
  +0.5, normalisation centre 0 and scale 1 (units are metres). A frame's `near`/`far`
  are its minimum/maximum finite range times {1 - NEAR_FAR_MARGIN:.2f}/{1 + NEAR_FAR_MARGIN:.2f};
  the scene-wide values are their min/max. In sorted name order, image 0, n, 2n, ...
  (n = {options.test_every}) are `test`, the others `train`.

## Sensor

The camera's colour space is linear sRGB (identity colour matrix). Noise-free signal
above black, in DN: `S = I * exposure_time_s * iso / 100 * dn_per_unit`, sampled
through an RGGB Bayer mosaic, with Poisson shot noise (gain {config.gain_iso100} DN per
electron at ISO 100, proportional to ISO) and Gaussian read noise
({config.read_noise_dn} DN); black level {config.black_level} added, rounded, clipped to
[0, {config.white_level}] (white level; {config.bit_depth}-bit data). Exposure time varies
per image by up to +-{config.exposure_jitter_ev} EV around {config.nominal_exposure_s:.6f} s;
ISO {config.iso}, f/{config.f_number}. A raw decoder without white balance or colour
conversion returns `(raw - black) / (white - black) ~= clip(S / (white - black), 0, 1)`.
ExposureTime, ISOSpeedRatings and FNumber are in the DNG's main IFD.

The JPEG is the bilinearly demosaiced raw, normalised the same way, times one gain for
the whole set (truth/sensor.json, `jpeg`), clipped and sRGB encoded, with no white
balance: like a camera JPEG it keeps each image's exposure and noise.
"""
