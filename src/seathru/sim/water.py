"""Underwater image formation (SeaThru / SeaThru-NeRF model), analytic per pixel and channel.

    I = J * exp(-sigma_attn * z) + c_med * (1 - exp(-sigma_bs * z))

``J`` clean linear radiance of the surface, ``z`` the range (metres along the ray), ``sigma_attn``
the attenuation of the direct signal and ``sigma_bs`` the backscatter coefficient (1/m), ``c_med``
the radiance of the medium at infinite range (backscatter saturation). A pixel that sees no
surface (open water: ``z`` is ``+inf``, or NaN) gets the limit of the formula, ``c_med``
exactly, whatever its ``J`` (the simulator stores ``J = 0`` there).

Presets (:data:`PRESETS`, red green blue):

- ``default``: coastal blue-green water chosen for the demo's orbit, where the diver is ~2.5-4 m
  from the seabed; at 3 m the direct signal keeps ~19 % red, ~47 % green, ~55 % blue and the
  backscatter is ~0.03 / 0.12 / 0.15: clearly underwater, objects keep contrast;
- ``clear``: no water (every coefficient zero), ``I == J`` exactly;
- ``turbid``: green, murky water: green transmission ~0.1 at 3.5 m (the orbit's seabed range),
  backscatter ~75 % saturated there; objects are faint (a hard case for SfM);
- the Jerlov water types, from the clearest oceanic water to turbid coastal water:
  ``oceanic_i``, ``oceanic_ib``, ``oceanic_ii``, ``oceanic_iii`` and ``coastal_1c``,
  ``coastal_3c``, ``coastal_5c``, ``coastal_7c``, ``coastal_9c``.

Where the Jerlov numbers come from: ``sigma_attn`` follows the diffuse attenuation spectra
``Kd(lambda)`` that define the Jerlov types (N. G. Jerlov, *Marine Optics*, 1976; the reference
spectra refitted by Solonenko & Mobley, "Inherent optical properties of Jerlov water types",
Applied Optics 54(17):5392, 2015), averaged roughly over camera bands (red 575-650 nm, green
500-575 nm, blue 425-500 nm) and rounded: a guide, not a measurement of any camera. The oceanic
types lose red fastest and blue slowest; with growing turbidity the coastal types lose blue
(dissolved matter) faster than green. ``sigma_bs`` and ``c_med`` are modelling choices guided by
the revised image formation model (Akkaynak & Treibitz, CVPR 2018): the veiling light builds up at
the rate of the wavelengths it consists of, the least attenuated within each band, so in clear
water ``sigma_bs`` is below ``sigma_attn`` (most in the red) and flatter across the channels; in
turbid coastal water scattering makes it build up faster in green. ``c_med`` goes from a dim
deep blue (oceanic I) to a brighter green-brown (coastal 9C), on the scale of the simulator's
radiance (lit surfaces ~0.1-0.4). Every preset but ``clear`` has three different coefficients
per quantity and ``sigma_bs != sigma_attn`` in every channel.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Sequence

import numpy as np

WaterPreset = Literal["default", "clear", "turbid", "oceanic_i", "oceanic_ib", "oceanic_ii",
                      "oceanic_iii", "coastal_1c", "coastal_3c", "coastal_5c", "coastal_7c",
                      "coastal_9c"]  # the keys of PRESETS


@dataclass(frozen=True)
class WaterParams:
    sigma_attn: tuple[float, float, float]
    sigma_bs: tuple[float, float, float]
    c_med: tuple[float, float, float]
    preset: str = "custom"

    def to_dict(self) -> dict:
        return {"sigma_attn": list(self.sigma_attn), "sigma_bs": list(self.sigma_bs),
                "c_med": list(self.c_med),
                "units": "1/m; distances are ranges along the ray in metres",
                "preset": self.preset}


PRESETS: dict[WaterPreset, WaterParams] = {
    "default": WaterParams((0.55, 0.25, 0.20), (0.45, 0.30, 0.25), (0.04, 0.20, 0.28), "default"),
    "clear": WaterParams((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), "clear"),
    "turbid": WaterParams((1.1, 0.66, 0.75), (0.5, 0.4, 0.4), (0.05, 0.22, 0.19), "turbid"),
    # Jerlov types: sigma_attn ~ band-averaged Kd (see the module docstring).
    "oceanic_i": WaterParams((0.25, 0.056, 0.022), (0.11, 0.045, 0.028), (0.01, 0.07, 0.22),
                             "oceanic_i"),
    "oceanic_ib": WaterParams((0.27, 0.067, 0.038), (0.13, 0.052, 0.047), (0.012, 0.09, 0.24),
                              "oceanic_ib"),
    "oceanic_ii": WaterParams((0.30, 0.088, 0.070), (0.16, 0.11, 0.085), (0.015, 0.11, 0.25),
                              "oceanic_ii"),
    "oceanic_iii": WaterParams((0.34, 0.12, 0.13), (0.20, 0.16, 0.11), (0.02, 0.14, 0.24),
                               "oceanic_iii"),
    "coastal_1c": WaterParams((0.37, 0.15, 0.25), (0.25, 0.21, 0.20), (0.03, 0.17, 0.22),
                              "coastal_1c"),
    "coastal_3c": WaterParams((0.45, 0.22, 0.38), (0.34, 0.30, 0.32), (0.04, 0.20, 0.19),
                              "coastal_3c"),
    "coastal_5c": WaterParams((0.55, 0.32, 0.56), (0.44, 0.42, 0.47), (0.06, 0.22, 0.16),
                              "coastal_5c"),
    "coastal_7c": WaterParams((0.70, 0.48, 0.85), (0.58, 0.62, 0.70), (0.08, 0.24, 0.13),
                              "coastal_7c"),
    "coastal_9c": WaterParams((0.95, 0.72, 1.30), (0.80, 0.92, 1.05), (0.12, 0.22, 0.09),
                              "coastal_9c"),
}


def _triple(name: str, values: Sequence[float] | None) -> tuple[float, float, float] | None:
    if values is None:
        return None
    values = tuple(float(v) for v in values)
    if len(values) != 3 or any(not np.isfinite(v) or v < 0.0 for v in values):
        raise ValueError(f"{name}: expected three finite values >= 0 (red green blue), got "
                         f"{list(values)}")
    return values  # type: ignore[return-value]


def water_params(preset: WaterPreset = "default", scale: float = 1.0,
                 sigma_attn: Sequence[float] | None = None,
                 sigma_bs: Sequence[float] | None = None,
                 c_med: Sequence[float] | None = None) -> WaterParams:
    """A preset, its coefficients multiplied by ``scale``, then any explicit per-channel
    override (overrides are taken as given, not scaled).

    Args:
        preset: one of :data:`PRESETS`.
        scale: turbidity factor on the preset's ``sigma_attn`` and ``sigma_bs``.
        sigma_attn, sigma_bs, c_med: (3,) red, green, blue overrides, or None.

    Returns:
        the parameters; ``preset`` is ``"<name>+custom"`` when anything was changed.

    Raises:
        ValueError: an unknown preset, or a negative or non-finite value (message names it).

    Example::

        water_params("default", scale=2.0).sigma_attn  # (1.1, 0.5, 0.4)
    """
    if preset not in PRESETS:
        raise ValueError(f"water: unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    if not np.isfinite(scale) or scale < 0.0:
        raise ValueError(f"water_scale: expected a finite value >= 0, got {scale}")
    base = PRESETS[preset]
    attn = _triple("sigma_attn", sigma_attn) or tuple(scale * v for v in base.sigma_attn)
    bs = _triple("sigma_bs", sigma_bs) or tuple(scale * v for v in base.sigma_bs)
    med = _triple("c_med", c_med) or base.c_med
    changed = scale != 1.0 or any(v is not None for v in (sigma_attn, sigma_bs, c_med))
    return WaterParams(attn, bs, med, f"{preset}+custom" if changed else preset)  # type: ignore


def water_image(clean: np.ndarray, range_m: np.ndarray, params: WaterParams) -> np.ndarray:
    """Water image I (H, W, 3) float32 from clean J (H, W, 3) and range z (H, W) in metres.

    Computed in float64. Open-water pixels (``range_m`` ``+inf`` or NaN) get ``c_med``, the limit
    of the formula as ``z -> inf``, whatever ``clean`` holds there: the result is finite wherever
    ``clean`` is finite on the surfaces.

    Example::

        water_image(np.zeros((1, 1, 3)), np.array([[np.inf]]), PRESETS["default"])  # c_med
    """
    z = np.asarray(range_m, np.float64)[..., None]
    j = np.asarray(clean, np.float64)
    attn = np.asarray(params.sigma_attn, np.float64)
    bs = np.asarray(params.sigma_bs, np.float64)
    med = np.asarray(params.c_med, np.float64)
    surface = np.isfinite(z)
    # Evaluate the formula only on surfaces: exp(-sigma * inf) * J would give NaN for J = inf
    # and 0 * inf for sigma = 0 (clear water).
    z_safe = np.where(surface, z, 0.0)
    j_safe = np.where(surface, j, 0.0)
    image = j_safe * np.exp(-attn * z_safe) + med * (1.0 - np.exp(-bs * z_safe))
    image = np.where(surface, image, med)
    return image.astype(np.float32)
