"""Pinhole camera and raw sensor model of the simulated dive camera.

Camera: ideal pinhole, OpenCV axes (x right, y down, z forward), the centre of pixel (u, v) at
(u + 0.5, v + 0.5), principal point at the image centre, square pixels.

Sensor (all values in DN, digital numbers):
- the camera's colour space is linear sRGB (identity colour matrix from linear sRGB to camera
  RGB), so the mosaic samples the scene's linear RGB radiance directly;
- expected signal above black: ``radiance * exposure_time * (iso / 100) * dn_per_unit``, where
  ``dn_per_unit`` (DN per unit radiance per second at ISO 100) is the radiometric calibration;
- RGGB Bayer mosaic: R at (even row, even column), G at (even, odd) and (odd, even), B at
  (odd, odd);
- Poisson-Gaussian noise: the signal is ``signal / gain`` electrons, Poisson distributed, with
  ``gain = gain_iso100 * iso / 100`` DN per electron; plus Gaussian read noise of
  ``read_noise_dn`` DN. Variance in DN: ``gain * signal + read_noise_dn**2``;
- the black level is added, values are rounded to integers (``bit_depth``-bit container) and
  clipped to ``[0, white_level]`` (the sensor saturates at the white level).

Camera JPEG (:func:`develop_jpeg`): the bilinearly demosaiced raw, normalised like a raw
decoder, times one gain for the whole dive (:func:`jpeg_gain`), clipped and sRGB encoded; like a
camera JPEG it keeps each image's exposure and noise. White balance (``jpeg_white_balance``):
none, or the camera's automatic one, frame by frame (:func:`auto_white_balance_gains`), which
no file records.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from seathru.radiometry.colour import linear_to_srgb

JPEG_WHITE = 0.85  # the metered radiance at nominal exposure maps to this linear JPEG value


@dataclass(frozen=True)
class Pinhole:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_fov(cls, width: int, height: int, fov_deg: float) -> "Pinhole":
        """Square pixels, principal point at the centre, ``fov_deg`` the horizontal field."""
        f = 0.5 * width / math.tan(math.radians(fov_deg) / 2.0)
        return cls(width, height, f, f, width / 2.0, height / 2.0)


def pixel_rays(camera: Pinhole, c2w: np.ndarray, supersample: int = 1
               ) -> tuple[np.ndarray, np.ndarray]:
    """World-space rays of every pixel.

    ``supersample`` s puts an s x s grid of subsamples in each pixel (at ``(i + 0.5) / s``);
    s = 1 is the pixel centre. Returns the camera centre (3,) and unit directions
    (H, W, s * s, 3), float64.
    """
    s = int(supersample)
    offsets = (np.arange(s) + 0.5) / s
    u = np.arange(camera.width)[:, None] + offsets[None, :]   # (W, s)
    v = np.arange(camera.height)[:, None] + offsets[None, :]  # (H, s)
    x = (u - camera.cx) / camera.fx
    y = (v - camera.cy) / camera.fy
    # (H, W, s_v, s_u)
    xx = np.broadcast_to(x[None, :, None, :], (camera.height, camera.width, s, s))
    yy = np.broadcast_to(y[:, None, :, None], (camera.height, camera.width, s, s))
    d_cam = np.stack([xx, yy, np.ones_like(xx)], axis=-1).reshape(camera.height, camera.width,
                                                                   s * s, 3)
    d_cam = d_cam / np.linalg.norm(d_cam, axis=-1, keepdims=True)
    rotation = np.asarray(c2w, np.float64)[:3, :3]
    return np.asarray(c2w, np.float64)[:3, 3].copy(), d_cam @ rotation.T


@dataclass(frozen=True)
class SensorConfig:
    black_level: int = 512
    white_level: int = 15000
    bit_depth: int = 14
    cfa_pattern: str = "RGGB"
    gain_iso100: float = 0.25    # DN per electron at ISO 100
    read_noise_dn: float = 3.0   # standard deviation, DN
    iso: int = 400
    f_number: float = 2.8
    nominal_exposure_s: float = 1.0 / 125.0
    exposure_jitter_ev: float = 0.5  # exposure time varies uniformly within +-this many stops
    metering_fraction: float = 0.7   # metered radiance at nominal exposure -> this of the range
    jpeg_white_balance: str = "none"  # none | auto (per frame: auto_white_balance_gains)
    jpeg_chroma: str = "4:2:0"  # the JPEG's chroma sampling: 4:2:0 as cameras, or 4:4:4

    @property
    def range_dn(self) -> int:
        return self.white_level - self.black_level

    def gain(self, iso: float) -> float:
        return self.gain_iso100 * iso / 100.0

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Exposure:
    exposure_time_s: float
    iso: int
    f_number: float
    ev_offset: float  # log2(exposure_time / nominal exposure time)


def plan_exposures(config: SensorConfig, views: int, rng: np.random.Generator
                   ) -> list[Exposure]:
    """Per-image exposure: the nominal time scaled by a random ``2 ** U(-j, j)`` (j = jitter),
    rounded to whole microseconds so the DNG's rational ExposureTime stores it exactly."""
    offsets = rng.uniform(-config.exposure_jitter_ev, config.exposure_jitter_ev, views)
    exposures = []
    for ev in offsets:
        time_s = round(config.nominal_exposure_s * 2.0 ** float(ev) * 1e6) / 1e6
        exposures.append(Exposure(time_s, config.iso, config.f_number,
                                  math.log2(time_s / config.nominal_exposure_s)))
    return exposures


def calibrate_dn_per_unit(config: SensorConfig, metered_radiance: float) -> float:
    """Radiometric calibration chosen like auto-exposure: ``metered_radiance`` (e.g. a high
    percentile of the scene radiance) at the nominal exposure fills ``metering_fraction`` of the
    raw range."""
    metered = max(float(metered_radiance), 1e-6)
    return (config.metering_fraction * config.range_dn
            / (metered * config.nominal_exposure_s * config.iso / 100.0))


def expected_signal(radiance: np.ndarray, exposure: Exposure, dn_per_unit: float) -> np.ndarray:
    """Noise-free signal above black in DN, same shape as ``radiance``."""
    return np.asarray(radiance, np.float64) * (exposure.exposure_time_s * exposure.iso / 100.0
                                               * dn_per_unit)


def mosaic_rggb(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) -> (H, W): the channel each RGGB photosite samples."""
    out = np.empty(rgb.shape[:2], dtype=rgb.dtype)
    out[0::2, 0::2] = rgb[0::2, 0::2, 0]
    out[0::2, 1::2] = rgb[0::2, 1::2, 1]
    out[1::2, 0::2] = rgb[1::2, 0::2, 1]
    out[1::2, 1::2] = rgb[1::2, 1::2, 2]
    return out


def cfa_channel(height: int, width: int) -> np.ndarray:
    """(H, W) index of the colour (0 R, 1 G, 2 B) each RGGB photosite samples."""
    channel = np.ones((height, width), dtype=np.int64)
    channel[0::2, 0::2] = 0
    channel[1::2, 1::2] = 2
    return channel


def noise_sigma_dn(signal_dn: np.ndarray, iso: float, config: SensorConfig) -> np.ndarray:
    """Standard deviation of the raw value (DN) around a noise-free signal above black."""
    return np.sqrt(config.gain(iso) * np.clip(signal_dn, 0.0, None) + config.read_noise_dn ** 2)


def capture_raw(signal_mosaic_dn: np.ndarray, iso: float, config: SensorConfig,
                rng: np.random.Generator) -> np.ndarray:
    """Noisy, quantised raw mosaic (H, W) ``uint16`` from the noise-free signal above black."""
    gain = config.gain(iso)
    electrons = rng.poisson(np.clip(signal_mosaic_dn, 0.0, None) / gain)
    value = electrons * gain + rng.normal(0.0, config.read_noise_dn, signal_mosaic_dn.shape)
    raw = np.round(value + config.black_level)
    return np.clip(raw, 0, min(config.white_level, 2 ** config.bit_depth - 1)).astype(np.uint16)


def normalise_raw(raw: np.ndarray, config: SensorConfig) -> np.ndarray:
    """(raw - black) / (white - black), float32, clipped to [0, 1] like a raw decoder."""
    value = (raw.astype(np.float32) - config.black_level) / config.range_dn
    return np.clip(value, 0.0, 1.0)


def demosaic_bilinear(raw: np.ndarray) -> np.ndarray:
    """RGGB ``uint16`` mosaic -> (H, W, 3) ``uint16`` by OpenCV's bilinear demosaicing."""
    return cv2.demosaicing(raw, cv2.COLOR_BayerRGGB2RGB)


def jpeg_gain(config: SensorConfig) -> float:
    """The camera JPEG's gain on normalised raw values: the metered radiance at nominal exposure
    (``metering_fraction`` of the raw range) maps to :data:`JPEG_WHITE`."""
    return JPEG_WHITE / config.metering_fraction


#: How far a camera's automatic white balance moves a channel against green (its colour
#: temperature range ends there: underwater it cannot undo the red fading at depth).
AUTO_WHITE_BALANCE_LIMIT = 4.0


def auto_white_balance_gains(developed: np.ndarray) -> np.ndarray:
    """A camera's automatic white balance of one frame: the grey-world gains that bring the
    frame's mean red and blue to its mean green, within :data:`AUTO_WHITE_BALANCE_LIMIT`.

    Args:
        developed: ``(H, W, 3)`` linear values of the frame.

    Returns:
        ``(3,)`` gains, green's 1.

    Example:
        >>> frame = np.ones((4, 4, 3)) * np.array([0.1, 0.4, 0.5])
        >>> auto_white_balance_gains(frame).round(2).tolist()
        [4.0, 1.0, 0.8]
    """
    means = np.maximum(np.asarray(developed, np.float64).reshape(-1, 3).mean(axis=0), 1e-9)
    return np.clip(means[1] / means, 1.0 / AUTO_WHITE_BALANCE_LIMIT, AUTO_WHITE_BALANCE_LIMIT)


def develop_jpeg(raw: np.ndarray, config: SensorConfig) -> np.ndarray:
    """The camera-like JPEG rendering of an RGGB mosaic, before 8-bit encoding.

    Args:
        raw: (H, W) ``uint16`` mosaic.
        config: the sensor (black and white level).

    Returns:
        (H, W, 3) sRGB-encoded float32 in [0, 1]:
        ``srgb(clip(jpeg_gain * wb * normalise_raw(demosaic_bilinear(raw)), 0, 1))``, ``wb``
        the frame's :func:`auto_white_balance_gains` where ``config.jpeg_white_balance`` is
        ``auto``, else 1.

    Example::

        jpeg = develop_jpeg(capture_raw(signal, 400, config, rng), config)
    """
    developed = normalise_raw(demosaic_bilinear(raw), config)
    if config.jpeg_white_balance == "auto":
        developed = developed * auto_white_balance_gains(developed).astype(np.float32)
    return linear_to_srgb(np.clip(jpeg_gain(config) * developed, 0.0, 1.0))
