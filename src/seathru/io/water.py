"""Water parameter files: the train step's fitted ``water.json`` and the simulator's truth.

``train/water.json`` (format ``seathru-water/1``; files written before the format key existed are
read too)::

    {"format": "seathru-water/1",
     "mode": "global",                  # off | global | veiling | view (the medium model)
     "units": "...",                    # how to read the numbers
     "scale": 0.15,                     # normalised units per source unit (camera file)
     "sigma_attn": [r, g, b],           # 1/(source unit) = normalised * scale
     "sigma_bs": [r, g, b],             # 1/(source unit)
     "c_med": [r, g, b],                # linear radiance of the training images
     "normalised": {"sigma_attn", "sigma_bs", "c_med"},   # 1/(normalised unit): the source
     "per_source_unit": {"sigma_attn", "sigma_bs"},
     # where the camera file knows the source's metric scale (poses.metres_per_unit; the
     # simulator's own cameras): the coefficients in 1/m, and their 95% intervals
     "metres_per_source_unit": m, "per_metre": {"sigma_attn", "sigma_bs", "interval95"},
     # modes "view" and "veiling" only: the values above are means over training rays, and
     "note": "...", "normalised_min": {...}, "min": {...}, "normalised_max": {...}, "max": {...}}

With a global medium, ``uncertainty`` says how well the views determine each number::

     "uncertainty": {"method": "...", "interval95": {"sigma_attn": [[lo, hi] x 3], ...},
                     "determined": {"sigma_attn": [bool x 3], ...},   # half-width <= 25%,
                         # and its part from what the images cannot tell apart <= 5%
                     "surface_fit": {...},       # the water fit on the model's own surfaces
                     "normalised": {"halfwidth95": {...}, "surface_fit": {...},
                                    "ambiguity95": {...}},   # that part (files since session
                                                             # 47; absent: not judged on it)
                     "pixels": int, "groups": int,
                     "not_assessed": "...",      # only where there were no surfaces to fit
                                                 # on: every interval open, nothing determined
                     "open_water_below_horizon": {"least_surface_range": z, "note": "..."}}
                         # only where the photographs' open water all looks below the horizon:
                         # the intervals allow for seabed from range z (source units) behind it

(per-source units like the top level; ``hi`` is null where the views do not bound it).

The ``normalised`` section (and, for view-dependent water, ``normalised_min`` / ``_max``) and
``scale`` are the data; every per-source-unit number is derived from them on writing.

``simulate/truth/water.json`` (written by the simulate step): ``sigma_attn``, ``sigma_bs``
(1/m), ``c_med``, ``units``, ``preset``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any, Mapping

from seathru.errors import PipelineError
from seathru.io.atomic import write_json
from seathru.io.jsonfile import read_json
from seathru.nerf.water_interval import DETERMINED_MAX_RELATIVE, interval_halfwidth

WATER_FORMAT = "seathru-water/1"
WATER_KEYS = ("sigma_attn", "sigma_bs", "c_med")
SIGMA_KEYS = ("sigma_attn", "sigma_bs")
UNITS = ("sigma_attn and sigma_bs: 1/(source unit) = normalised value * scale (metres for "
         "simulated data); c_med: linear radiance of the training images")
VIEW_NOTE = ("direction-dependent water (mode view: all of it; veiling: the veiling light c_med): "
             "values are the mean over training rays; min and max over the same rays")
MODES = ("off", "global", "view", "veiling")
DIRECTIONAL = ("view", "veiling")   # water (or its veiling light) that depends on direction
BELOW_HORIZON_NOTE = (
    "the photographs' open water looks below the horizon (seathru.geometry.upright; less than a "
    "fifth of it above): it may be seabed beyond the surfaces the views show, whose colour "
    "still holds some of its own light; the intervals allow for such a surface from "
    "least_surface_range on")
UNCERTAINTY_METHOD = (
    "95% prediction intervals around the trained value: a water fit on the model's own "
    "surfaces (seathru.nerf.water_uncertainty.robust_halfwidths) gives a cluster-robust "
    "statistical half-width plus a systematic one from how much parts of the data (near/far, "
    "the two sides of the scene, without open water, without the dark-pixel bound, other voxel "
    "groupings, noisier depth) disagree and how far the surfaces pull c_med from the open "
    "water's colour, or, with no open water in view, how much of the veiling light lies beyond "
    "the farthest surfaces; the interval is widened by the trained value's distance to that "
    "fit. A parameter whose interval reaches more than 25% of its value either side is not "
    "determined by the views, nor one whose interval the alternatives the images cannot tell "
    "apart (the veiling light beyond the farthest surfaces, open water that may be far "
    "seabed) widen by more than medium.determined_ambiguity (5%) of its value: "
    "normalised.ambiguity95")


@dataclass(frozen=True)
class WaterValues:
    """Per-channel (R, G, B) water parameters in one unit system."""

    sigma_attn: tuple[float, float, float]
    sigma_bs: tuple[float, float, float]
    c_med: tuple[float, float, float]

    @classmethod
    def from_mapping(cls, data: Any, where: str) -> WaterValues:
        """From ``{"sigma_attn": [3], "sigma_bs": [3], "c_med": [3]}``; ValueError naming
        ``where`` and the key when a value is missing or not three numbers."""
        if not isinstance(data, Mapping):
            raise ValueError(f"{where} is not an object")
        return cls(**{key: _triple(data.get(key), f"{where}.{key}") for key in WATER_KEYS})

    def as_dict(self) -> dict[str, list[float]]:
        return {key: list(getattr(self, key)) for key in WATER_KEYS}

    def scaled(self, sigma_factor: float) -> WaterValues:
        """The coefficients multiplied by ``sigma_factor`` (a change of length unit); c_med
        unchanged."""
        return WaterValues(*(tuple(float(v) * sigma_factor for v in getattr(self, key))
                             for key in SIGMA_KEYS), self.c_med)


def _triple(value: Any, where: str) -> tuple[float, float, float]:
    if (not isinstance(value, (list, tuple)) or len(value) != 3
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
        raise ValueError(f"{where} must be a list of 3 numbers, found {value!r}")
    return tuple(float(v) for v in value)


@dataclass(frozen=True)
class WaterReport:
    """The trained model's water (``train/water.json``).

    Attributes:
        mode: the medium model, ``off``, ``global`` or ``view``.
        scale: normalised scene units per source unit (the camera file's ``scale``).
        normalised: coefficients per normalised unit; for ``view``, means over training rays.
        normalised_min, normalised_max: ``view`` only, extremes over the same rays.
        metres_per_source_unit: the camera file's metric scale, where known.
    """

    mode: str
    scale: float
    normalised: WaterValues
    normalised_min: WaterValues | None = None
    normalised_max: WaterValues | None = None
    uncertainty: Mapping[str, Any] | None = None
    metres_per_source_unit: float | None = None
    format: str = WATER_FORMAT

    @classmethod
    def from_parameters(cls, params: Mapping[str, Any], scale: float,
                        assessment: Mapping[str, Any] | None = None,
                        metres_per_source_unit: float | None = None) -> WaterReport:
        """From ``SeaThruModel.water_parameters(directions)``: ``mode``, ``sigma_attn``,
        ``sigma_bs``, ``c_med`` (lists of 3, normalised units) and, for ``view``, ``min`` and
        ``max`` dicts of the same keys.

        Example::

            report = WaterReport.from_parameters(model.water_parameters(directions),
                                                 float(cameras.scale))
            write_water(out / "water.json", report)
        """
        bounds = {}
        if params["mode"] in DIRECTIONAL:
            bounds = {f"normalised_{b}": WaterValues.from_mapping(params[b], b)
                      for b in ("min", "max")}
        uncertainty = None
        if assessment and "skipped" in assessment and params["mode"] in ("global", "veiling"):
            # no surfaces to check the water on (turbid water hiding them, an unconverged
            # model): nothing is known to be determined, and saying so is the honest answer
            trained = WaterValues.from_mapping(params, "parameters").as_dict()
            uncertainty = {"halfwidth95": {k: [math.inf] * 3 for k in WATER_KEYS},
                           "determined": {k: [False] * 3 for k in WATER_KEYS},
                           "surface_fit": {k: [float(v) for v in trained[k]]
                                           for k in WATER_KEYS},
                           "pixels": 0, "groups": 0,
                           "not_assessed": str(assessment["skipped"])}
        elif assessment and "halfwidth95" in assessment:
            uncertainty = {"halfwidth95": {k: [float(v) for v in assessment["halfwidth95"][k]]
                                           for k in WATER_KEYS},
                           "determined": {k: [bool(v) for v in assessment["determined"][k]]
                                          for k in WATER_KEYS},
                           "surface_fit": {k: [float(v) for v in assessment["surface_fit"][k]]
                                           for k in WATER_KEYS},
                           "pixels": int(assessment["pixels"]),
                           "groups": int(assessment["groups"])}
            if assessment.get("ambiguity95") is not None:
                uncertainty["ambiguity95"] = {k: [float(v) for v in assessment["ambiguity95"][k]]
                                              for k in WATER_KEYS}
            if assessment.get("open_water_beyond") is not None:
                uncertainty["open_water_beyond"] = float(assessment["open_water_beyond"])
        return cls(mode=str(params["mode"]), scale=float(scale),
                   normalised=WaterValues.from_mapping(params, "parameters"), **bounds,
                   uncertainty=uncertainty, metres_per_source_unit=metres_per_source_unit)

    @property
    def per_source_unit(self) -> WaterValues:
        """Coefficients per unit of the source reconstruction (metres for simulated data)."""
        return self.normalised.scaled(self.scale)

    def to_dict(self) -> dict[str, Any]:
        """The file's JSON layout (see the module docstring)."""
        source = self.per_source_unit
        data: dict[str, Any] = {
            "format": self.format, "mode": self.mode, "units": UNITS, "scale": self.scale,
            "sigma_attn": list(source.sigma_attn), "sigma_bs": list(source.sigma_bs),
            "c_med": list(self.normalised.c_med),
            "normalised": self.normalised.as_dict(),
            "per_source_unit": {k: v for k, v in source.as_dict().items() if k in SIGMA_KEYS},
        }
        if self.uncertainty:
            data["uncertainty"] = self._uncertainty_dict()
        if self.metres_per_source_unit:
            data["metres_per_source_unit"] = self.metres_per_source_unit
            data["per_metre"] = self._per_metre(data)
        if self.mode in DIRECTIONAL and self.normalised_min and self.normalised_max:
            data["note"] = VIEW_NOTE
            for bound, values in (("min", self.normalised_min), ("max", self.normalised_max)):
                data[f"normalised_{bound}"] = values.as_dict()
                data[bound] = values.scaled(self.scale).as_dict()
        return data

    def _per_metre(self, data: Mapping[str, Any]) -> dict[str, Any]:
        """The coefficients (and their intervals) of ``data`` divided by the metric scale."""
        m = self.metres_per_source_unit
        per = {k: [v / m for v in data["per_source_unit"][k]] for k in SIGMA_KEYS}
        if "uncertainty" in data:
            per["interval95"] = {k: [[None if v is None else v / m for v in pair]
                                     for pair in data["uncertainty"]["interval95"][k]]
                                 for k in SIGMA_KEYS}
        return per

    def _uncertainty_dict(self) -> dict[str, Any]:
        u = self.uncertainty
        factor = {"sigma_attn": self.scale, "sigma_bs": self.scale, "c_med": 1.0}
        centre = self.normalised.as_dict()
        interval, surface = {}, {}
        for key in WATER_KEYS:
            f = factor[key]
            widths = [interval_halfwidth(c, g, h) for c, h, g in
                      zip(centre[key], u["halfwidth95"][key], u["surface_fit"][key])]
            interval[key] = [[max(0.0, (c - w) * f), (c + w) * f] if math.isfinite(w)
                             else [0.0, None] for c, w in zip(centre[key], widths)]
            surface[key] = [v * f for v in u["surface_fit"][key]]
        return {"method": UNCERTAINTY_METHOD, "interval95": interval,
                "determined": u["determined"], "surface_fit": surface,
                "normalised": {"halfwidth95": {k: [v if math.isfinite(v) else None
                                                   for v in u["halfwidth95"][k]]
                                               for k in WATER_KEYS},
                               "surface_fit": u["surface_fit"],
                               **({"ambiguity95": u["ambiguity95"]}
                                  if u.get("ambiguity95") else {})},
                "pixels": u["pixels"], "groups": u["groups"],
                **({"not_assessed": u["not_assessed"]} if u.get("not_assessed") else {}),
                **({"open_water_below_horizon": {
                    "least_surface_range": u["open_water_beyond"] / self.scale,
                    "note": BELOW_HORIZON_NOTE}} if u.get("open_water_beyond") else {})}

    def undetermined_message(self) -> str | None:
        """What the train step warns about the water the views do not determine, or None."""
        if not self.undetermined:
            return None
        not_assessed = (self.uncertainty or {}).get("not_assessed")
        if not_assessed:
            return (f"the water could not be checked on the model's own surfaces "
                    f"({not_assessed}): none of its values is known to be determined by the "
                    "views, and the restored images rest on them")
        u = self.uncertainty or {}
        below = "the photographs' open water looks below the horizon: it may be far seabed, " \
            "not the veiling light" if u.get("open_water_beyond") else ""
        wide, ambiguous = self._undetermined_by_reason()
        parts = [f"{', '.join(wide)} (95% interval wider than "
                 f"+-{DETERMINED_MAX_RELATIVE:.0%})"] if wide else []
        if ambiguous:
            alternative = below or "the veiling light beyond the farthest surfaces, which no " \
                "open water in view shows"
            parts.append(", ".join(f"{name} (up to {share:.0%})" for name, share in ambiguous)
                         + f", moved by what the images cannot tell ({alternative})")
        note = f" ({below})" if below and not ambiguous else ""
        return (f"the views do not determine the water's {'; '.join(parts)}{note}: the "
                "restored images rest on them")

    def _undetermined_by_reason(self) -> tuple[list[str], list[tuple[str, float]]]:
        """The undetermined values whose interval is wider than ``DETERMINED_MAX_RELATIVE`` of
        them, and the others with the share of their value that what the images cannot tell
        apart moves them."""
        u, centre = self.uncertainty or {}, self.normalised.as_dict()
        wide, ambiguous = [], []
        for key in WATER_KEYS:
            for i, ok in enumerate(u.get("determined", {}).get(key, [])):
                if ok:
                    continue
                name, value = f"{key}[{'RGB'[i]}]", abs(centre[key][i])
                width = interval_halfwidth(centre[key][i], u["surface_fit"][key][i],
                                           u["halfwidth95"][key][i])
                share = u.get("ambiguity95", {}).get(key, [0.0] * 3)[i] / value \
                    if value > 0 else math.inf
                if math.isfinite(width) and width <= DETERMINED_MAX_RELATIVE * value and share > 0:
                    ambiguous.append((name, share))
                else:
                    wide.append(name)
        return wide, ambiguous

    @property
    def undetermined(self) -> list[str]:
        """``parameter[channel]`` names the images do not determine (empty if not assessed)."""
        if not self.uncertainty:
            return []
        return [f"{key}[{'RGB'[i]}]" for key in WATER_KEYS
                for i, ok in enumerate(self.uncertainty["determined"][key]) if not ok]

    @classmethod
    def from_dict(cls, data: Any, source: str = "water.json") -> WaterReport:
        """Parse the JSON layout; PipelineError naming ``source`` when it is malformed."""
        try:
            if not isinstance(data, Mapping):
                raise ValueError("expected a JSON object")
            version = data.get("format", WATER_FORMAT)
            if version != WATER_FORMAT:
                raise ValueError(f"expected format {WATER_FORMAT!r}, found {version!r}")
            mode = data.get("mode")
            if mode not in MODES:
                raise ValueError(f"mode must be one of {', '.join(MODES)}, found {mode!r}")
            scale = data.get("scale")
            if isinstance(scale, bool) or not isinstance(scale, (int, float)) or scale <= 0:
                raise ValueError(f"scale must be a positive number, found {scale!r}")
            bounds = {f"normalised_{b}": WaterValues.from_mapping(data[f"normalised_{b}"],
                                                                  f"normalised_{b}")
                      for b in ("min", "max") if f"normalised_{b}" in data}
            uncertainty = None
            if isinstance(data.get("uncertainty"), Mapping):
                u = data["uncertainty"]
                uncertainty = {
                    "halfwidth95": {k: [math.inf if v is None else float(v) for v in
                                        u["normalised"]["halfwidth95"][k]] for k in WATER_KEYS},
                    "determined": {k: [bool(v) for v in u["determined"][k]] for k in WATER_KEYS},
                    "surface_fit": {k: [float(v) for v in u["normalised"]["surface_fit"][k]]
                                    for k in WATER_KEYS},
                    "pixels": int(u["pixels"]), "groups": int(u["groups"])}
                if isinstance(u["normalised"].get("ambiguity95"), Mapping):
                    uncertainty["ambiguity95"] = {
                        k: [float(v) for v in u["normalised"]["ambiguity95"][k]]
                        for k in WATER_KEYS}
                if u.get("not_assessed"):
                    uncertainty["not_assessed"] = str(u["not_assessed"])
                below = u.get("open_water_below_horizon")
                if isinstance(below, Mapping) and below.get("least_surface_range") is not None:
                    uncertainty["open_water_beyond"] = \
                        float(below["least_surface_range"]) * float(scale)
            metres = data.get("metres_per_source_unit")
            if metres is not None and (isinstance(metres, bool) or
                                       not isinstance(metres, (int, float)) or metres <= 0):
                raise ValueError(f"metres_per_source_unit must be a positive number, found "
                                 f"{metres!r}")
            return cls(mode=mode, scale=float(scale),
                       normalised=WaterValues.from_mapping(data.get("normalised"), "normalised"),
                       **bounds, uncertainty=uncertainty,
                       metres_per_source_unit=None if metres is None else float(metres))
        except (ValueError, KeyError, TypeError) as exc:
            raise PipelineError(f"{source}: not a valid water file ({exc}); re-run the 'train' "
                                "step") from None


def write_water(path: str | os.PathLike, report: WaterReport) -> None:
    """Write ``water.json`` atomically."""
    write_json(path, report.to_dict())


def read_water(path: str | os.PathLike, *, missing_ok: bool = False) -> WaterReport | None:
    """Read a train step's ``water.json``; None when it is missing and ``missing_ok``.

    Raises:
        PipelineError: naming the file when it is missing (unless ``missing_ok``), not JSON or
        malformed.
    """
    data = read_json(path, missing_ok=missing_ok, hint="run the 'train' step")
    return None if data is None else WaterReport.from_dict(data, str(path))


def read_truth_water(path: str | os.PathLike) -> WaterValues:
    """The simulator's true water (``truth/water.json``), coefficients in 1/m.

    Raises:
        PipelineError: naming the file when it is missing, not JSON or malformed.
    """
    data = read_json(path, hint="truth water parameters are written by the 'simulate' step; "
                                "re-run it")
    try:
        return WaterValues.from_mapping(data, "truth")
    except ValueError as exc:
        raise PipelineError(f"{path}: not a valid truth water file ({exc}); re-run the "
                            "'simulate' step") from None
