"""The simulate step's output folder: a dive's photos and its ground truth (file contract).

Layout (``README`` below is written into every folder, with the dive's values)::

    raw/<name>.dng            camera raw: 16-bit RGGB mosaic, DNG 1.4 tags in the main IFD
    jpeg/<name>.jpg           the same photo as an 8-bit sRGB JPEG (camera-like rendering,
                              the exposure and lens in its EXIF as a camera records them)
    truth/clean/<name>.tiff   clean linear radiance J, float32 (H, W, 3)
    truth/water/<name>.tiff   linear water image I before the sensor, float32 (H, W, 3)
    truth/depth/<name>.tiff   range z in metres, float32 (H, W); +inf where open water
    truth/cameras.json        cameras (seathru-cameras/1); images point to truth/water/
    truth/water.json          medium parameters of the image formation model
    truth/sensor.json         sensor parameters and per-image exposure
    truth/scene.json          scene geometry (seabed formula, objects, light, path)

Open-water pixels (no surface along the ray) have range ``+inf``, clean radiance 0 and water
image ``c_med``; cameras.json's near/far come from the finite ranges only. Images are named
``dive_0000``, ``dive_0001``, ... The writers here take ``seathru.sim.dive`` objects.
Readers: ``seathru.io.cameras.read_cameras`` (cameras.json), ``seathru.io.water.read_truth_water``
(water.json), ``seathru.io.evaluation.read_truth_image`` (truth images), ``seathru.io.dng`` (raw
files).

``truth/sparse/`` is not written by the simulation: :func:`write_truth_sparse_model` adds a
COLMAP model of points on the true surfaces there, which training on ``truth/cameras.json``
then uses as it uses COLMAP's points beside a poses step's cameras (the water benchmark).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from seathru.errors import PipelineError
from seathru.geometry.intrinsics import focal_35mm_from_px
from seathru.io.atomic import write_json, write_text
from seathru.io.cameras import CameraSet, Frame, write_cameras
from seathru.io.dng import write_dng
from seathru.io.images import read_image, write_camera_jpeg, write_float_tiff
from seathru.sim.dive import DivePlan, DiveSpec, SimulatedView
from seathru.sim.sensor import Pinhole, SensorConfig, jpeg_gain

NAME_PREFIX = "dive_"
# the layout table of this module's docstring, also written into every folder's README
LAYOUT = __doc__.split("::\n\n", 1)[1].split("\n\n", 1)[0] + "\n"
NEAR_FAR_MARGIN = 0.05  # cameras.json near/far = (1 -+ margin) * min/max finite range
JPEG_QUALITY = 95
TRUTH_KINDS = ("clean", "water", "depth")
SPARSE_DIR = "sparse"   # beside truth/cameras.json, as seathru.io.tracks looks for it


def view_names(views: int) -> list[str]:
    """``dive_0000``, ``dive_0001``, ... (sorted order is capture order)."""
    return [f"{NAME_PREFIX}{i:04d}" for i in range(views)]


def is_simulation(folder: str | os.PathLike) -> bool:
    """Whether ``folder`` holds an earlier simulate output (its truth camera file)."""
    return (Path(folder) / "truth" / "cameras.json").exists()


def check_replaceable(out: str | os.PathLike) -> None:
    """Refuse an output folder that exists and is neither empty nor an earlier simulation (it
    would be replaced)."""
    out = Path(out)
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not is_simulation(out))):
        raise PipelineError(f"--out {out}: exists and is not an earlier simulate output; "
                            "choose an empty or new folder (it would be replaced)")


def view_range_limits(range_m: np.ndarray) -> tuple[float, float]:
    """(min, max) finite range of a view in metres (open water, ``inf`` or NaN, left out);
    (0.1, 10) when it sees only open water."""
    finite = range_m[np.isfinite(range_m)]
    if not finite.size:
        return 0.1, 10.0
    return float(finite.min()), float(finite.max())


def truth_frame(name: str, camera: Pinhole, c2w: np.ndarray, range_m: np.ndarray,
                split: str) -> Frame:
    """The view's entry of ``truth/cameras.json``: near/far are the finite range bounds widened
    by :data:`NEAR_FAR_MARGIN`."""
    near, far = view_range_limits(range_m)
    return Frame(name=name, image=f"water/{name}.tiff", width=camera.width, height=camera.height,
                 fx=camera.fx, fy=camera.fy, cx=camera.cx, cy=camera.cy,
                 c2w=[[float(v) for v in row] for row in c2w],
                 near=(1.0 - NEAR_FAR_MARGIN) * near, far=(1.0 + NEAR_FAR_MARGIN) * far,
                 split=split)


def write_view(root: Path, name: str, view: SimulatedView, sensor: SensorConfig,
               camera: Pinhole) -> None:
    """The view's raw DNG, camera JPEG and truth images (clean, water, depth) under ``root``;
    the DNG records ``camera``'s 35 mm equivalent focal length in whole millimetres, as a
    camera's EXIF does."""
    root = Path(root)
    exposure = view.exposure
    write_dng(root / "raw" / f"{name}.dng", view.raw, black_level=sensor.black_level,
              white_level=sensor.white_level, exposure_time_s=exposure.exposure_time_s,
              iso=exposure.iso, f_number=exposure.f_number, cfa_pattern=sensor.cfa_pattern,
              focal_length_35mm=round(focal_35mm_from_px(camera.fx, camera.width,
                                                         camera.height)))
    write_camera_jpeg(root / "jpeg" / f"{name}.jpg", view.jpeg, JPEG_QUALITY,
                      exposure_time_s=exposure.exposure_time_s, iso=exposure.iso,
                      f_number=exposure.f_number, focal_length_35mm=round(focal_35mm_from_px(
                          camera.fx, camera.width, camera.height)), chroma=sensor.jpeg_chroma)
    for kind, image in zip(TRUTH_KINDS, (view.clean, view.water, view.range_m)):
        write_float_tiff(root / "truth" / kind / f"{name}.tiff", image)


def write_records(root: Path, spec: DiveSpec, plan: DivePlan, frames: list[Frame],
                  test_every: int, open_water_pixels: int) -> None:
    """``truth/cameras.json``, ``water.json``, ``sensor.json``, ``scene.json`` and
    ``README.md`` of a dive whose views are ``frames``."""
    root = Path(root)
    cameras = CameraSet(frames=frames, near=min(f.near for f in frames),
                        far=max(f.far for f in frames), centre=[0.0, 0.0, 0.0], scale=1.0,
                        source="simulated", metres_per_source_unit=1.0)
    write_cameras(root / "truth" / "cameras.json", cameras)
    write_json(root / "truth" / "water.json", spec.water.to_dict())
    write_json(root / "truth" / "sensor.json", sensor_record(
        spec.sensor, plan, [f.name for f in frames]))
    scene = plan.scene.describe()
    scene.update({"path": spec.path, "seed": spec.seed, "fov_deg": spec.fov_deg,
                  "supersample": spec.supersample, "open_water_pixels": open_water_pixels})
    write_json(root / "truth" / "scene.json", scene)
    write_text(root / "README.md", readme(spec, test_every))


def sensor_record(config: SensorConfig, plan: DivePlan, names: list[str]) -> dict:
    """The content of ``truth/sensor.json``."""
    record = config.to_dict()
    record.update({
        "bayer": "RGGB: R at (even row, even column), B at (odd row, odd column)",
        "camera_colour_space": "linear sRGB (identity colour matrix)",
        "dn_per_unit": plan.dn_per_unit,
        "metered_radiance": plan.metered_radiance,
        "signal_model": ("raw = clip(round(black_level + gain * Poisson(S / gain) + "
                         "Normal(0, read_noise_dn)), 0, white_level) with S = I_channel * "
                         "exposure_time_s * iso / 100 * dn_per_unit and gain = gain_iso100 * "
                         "iso / 100 (DN per electron)"),
        "jpeg": {"gain": jpeg_gain(config), "quality": JPEG_QUALITY,
                 "chroma": config.jpeg_chroma,
                 "model": ("jpeg = sRGB(clip(gain * (demosaic_bilinear(raw) - black_level) / "
                           "(white_level - black_level) * wb, 0, 1)), 8 bit; wb = 1, or "
                           "with jpeg_white_balance auto the frame's grey-world gains "
                           "(seathru.sim.sensor.auto_white_balance_gains)")},
        "images": {name: {"exposure_time_s": e.exposure_time_s, "iso": e.iso,
                          "f_number": e.f_number, "ev_offset": e.ev_offset}
                   for name, e in zip(names, plan.exposures)},
    })
    return record


def readme(spec: DiveSpec, test_every: int) -> str:
    """The folder's ``README.md``: layout, ground-truth definitions and the sensor model."""
    water, config = spec.water, spec.sensor
    white_balance = ("no white balance" if config.jpeg_white_balance == "none" else
                     "the camera's automatic white balance, frame by frame (grey world, "
                     "recorded nowhere)")
    return f"""# Simulated dive (seathru simulate)

{spec.views} views, {spec.width}x{spec.height} pixels, path `{spec.path}`,
water preset `{water.preset}`, seed {spec.seed}, horizontal field of view
{spec.fov_deg} deg, {spec.supersample}x{spec.supersample} rays per pixel.
Units: metres; world z up, seabed near z = 0. Images are named `{NAME_PREFIX}0000`,
`{NAME_PREFIX}0001`, ...

## Layout

{LAYOUT}
## Ground truth

- **Range** `z` is the Euclidean distance from the camera centre to the surface along
  the pixel's ray (not the z-depth). With s x s supersampling, a pixel's clean radiance
  and range are the *means* over its subsamples.
- **Open water**: a pixel where any subsample sees no surface (water to infinity, e.g.
  above the reef crest of the `survey` path) has range `+inf` (IEEE infinity in the
  float32 TIFF), clean radiance `0` (no surface to restore: leave these pixels out when
  scoring a restoration). Where every subsample sees open water the water image is
  exactly `c_med`, the limit of the formula below as z -> inf; at the open water's edge
  it mixes `c_med` with the surface's rays. Readers should select surfaces with
  `isfinite(range)`.
- **Water image**: the formula acts on each subsample ray at its own range, then the
  pixel takes the mean, as a sensor pixel integrates its footprint (computed in float64
  from the float32 subsamples, stored as float32):
  `I = J * exp(-sigma_attn * z) + c_med * (1 - exp(-sigma_bs * z))` with
  sigma_attn = {list(water.sigma_attn)} /m, sigma_bs = {list(water.sigma_bs)} /m,
  c_med = {list(water.c_med)} (truth/water.json). With one subsample a pixel this is the
  formula on the stored clean image and range exactly; with more, it holds at the stored
  means where the range and texture hardly change across the pixel (a pixel spanning an
  occluding edge is the mean of its near and far rays, not the water at its mean range).
- **Cameras**: pinhole, OpenCV axes (x right, y down, z forward), pixel centres at
  +0.5, normalisation centre 0 and scale 1 (units are metres). A frame's `near`/`far`
  are its minimum/maximum finite range times {1 - NEAR_FAR_MARGIN:.2f}/{1 + NEAR_FAR_MARGIN:.2f}
  (open water does not count: `far` stays finite); the scene-wide values are their
  min/max. In sorted name order, image 0, n, 2n, ... (n = {test_every}) are `test`, the
  others `train`.

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
ExposureTime, ISOSpeedRatings, FNumber and FocalLengthIn35mmFilm (by the image diagonal, whole
millimetres, as cameras record it) are in the DNG's main IFD.

The JPEG is the bilinearly demosaiced raw, normalised the same way, times one gain for
the whole set (truth/sensor.json, `jpeg`), clipped and sRGB encoded, with {white_balance},
its colour stored at {config.jpeg_chroma} chroma sampling:
like a camera JPEG it keeps each image's exposure and noise, and its EXIF records the
exposure and the 35 mm equivalent focal length.
"""


def write_truth_sparse_model(root: str | os.PathLike, per_view: int = 300, noise: float = 0.0,
                             seed: int = 0) -> Path:
    """A COLMAP model of points on the dive's true surfaces, ``truth/sparse/``, in place of the
    one structure from motion would give (``seathru.sim.sparse.truth_sparse_points``: every
    view draws ``per_view`` surface pixels; a point is kept with the two or more views that
    see it unhidden; ``noise`` is its relative position error). Written atomically; returns the
    folder.

    Raises:
        PipelineError: ``root`` is not a simulate output (names the missing file).
    """
    from seathru.io.atomic import atomic_dir
    from seathru.io.cameras import read_cameras
    from seathru.io.exports import colmap_reconstruction
    from seathru.sim.sparse import truth_sparse_points

    truth = Path(root) / "truth"
    if not (truth / "cameras.json").is_file():
        raise PipelineError(f"{truth / 'cameras.json'}: missing; pass a simulate output folder")
    cameras = read_cameras(truth / "cameras.json")
    ranges = [read_image(truth / "depth" / f"{frame.name}.tiff") for frame in cameras.frames]
    cloud = truth_sparse_points(cameras.frames, ranges, per_view=per_view, noise=noise,
                                seed=seed)
    model = colmap_reconstruction(cameras, {f.name: Path(f.image).name for f in cameras.frames},
                                  cloud.points, seen=cloud.seen)
    with atomic_dir(truth / SPARSE_DIR) as tmp:
        model.write(tmp)
    return truth / SPARSE_DIR
