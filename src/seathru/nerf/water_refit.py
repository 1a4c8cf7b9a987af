"""The water refitted during training, and the final assessment of how well the views
determine it.

Early in training the water settles wherever it started and fog in the object field makes up for
the rest; on the surfaces the model already places well, the same surface seen at several ranges
pins the water down. At ``medium.refit_at`` the trainer fits the global water to the training
images on the model's own geometry (variable projection: ``seathru.nerf.water_fit``), keeps the
values the views determine (:func:`refit_acceptance`) and holds them for the rest of the run
(``medium.hold_refitted``). At the end :meth:`WaterRefitting.assess_water` fits the final
surfaces again and gives each value its interval (``seathru.nerf.water_uncertainty``).

:class:`WaterRefitting` is a part of ``seathru.nerf.training.Trainer`` (a mixin): it uses the
trainer's model, data, optimiser and configuration.
"""

from __future__ import annotations

import math
import time
from typing import Sequence

import torch

from seathru.nerf.water_fit import WaterFit, fit_surfaces
from seathru.nerf.water_surfaces import SurfaceData, correspondence_rays, surface_data
from seathru.nerf.water_uncertainty import (WaterUncertainty, ambiguity_halfwidths,
                                            far_surface_range, interval_determined,
                                            laplace_halfwidths, robust_halfwidths)

WATER_KEYS = ("sigma_attn", "sigma_bs", "c_med")


class WaterRefitting:
    """The trainer's water refits (:meth:`refit_water`), the values they hold
    (:meth:`_hold_refitted_water`) and the final assessment (:meth:`assess_water`)."""

    def _hold_refitted_water(self) -> None:
        """Zero the gradient of the water values the latest refit determined to within
        ``medium.hold_max_relative`` (``medium.hold_refitted``).

        Trained on through the NeRF, the water drifts from its surface fit as fog in the object
        field stands in for it (on the survey demo, attenuation from within 3% of the truth at
        the last refit to 23-44% low at the end of the run); the surface fit is not biased that
        way. In veiling mode the directional veiling light keeps training.
        """
        if not self.config.medium.hold_refitted:
            return
        medium = self.model.medium
        key = (len(self.water_refits), medium.mode)
        if self._held_water is None or self._held_water[0] != key:
            self._held_water = (key, self._held_water_flags(medium.mode))
        for param, flags in zip(medium.global_parameters(), self._held_water[1]):
            if param.grad is not None and flags is not None:
                param.grad[flags.to(param.grad.device)] = 0.0

    def _held_water_flags(self, mode: str) -> list[torch.Tensor | None]:
        """Per water key, (3,) bool of the values held (None: none), from the latest refit."""
        fitted = [r for r in self.water_refits if r.get("accepted")]
        if not fitted:
            return [None] * len(WATER_KEYS)
        last, limit = fitted[-1], self.config.medium.hold_max_relative
        flags = []
        for key in WATER_KEYS:
            held = [bool(ok and half <= limit * abs(value)) for ok, half, value in zip(
                last["accepted"][key], last["halfwidth95"][key], last["after"][key])]
            if key == "c_med" and mode == "veiling":
                held = [False] * 3
            flags.append(torch.tensor(held) if any(held) else None)
        return flags

    def _surface_fading(self, depth: float) -> tuple[float, float, bool]:
        """How much the surfaces seen over a range of distances fade over ``depth`` by their
        own water fit (``assess_water``): by its attenuation and by the lower end of its 95%
        interval (the channel fading most each), and whether their attenuation is
        determined."""
        assessment = self.assess_water() or {}
        determined = all(assessment.get("fit_determined", {}).get("sigma_attn", [False]))
        attenuation = assessment.get("surface_fit", {}).get("sigma_attn", [0.0])
        halfwidth = assessment.get("halfwidth95", {}).get("sigma_attn", [math.inf] * len(
            attenuation))
        lowest = max(max(value - width, 0.0) for value, width in zip(attenuation, halfwidth))
        return (1.0 - math.exp(-max(attenuation) * depth), 1.0 - math.exp(-lowest * depth),
                determined)

    @torch.no_grad()
    def _surface_data(self, seed: int, voxel_factors: Sequence[float] = (1.0,)
                      ) -> list[SurfaceData | str]:
        """Surface data of one set of rendered training rays, grouped at ``medium.refit_voxel``
        times each of ``voxel_factors``."""
        c, model = self.config, self.model
        point_ids = None
        if c.medium.refit_grouping == "points":
            found = correspondence_rays(self.data, self.render_batch, c.medium.refit_rays // 4,
                                        c.medium.refit_rays, seed, c.medium.refit_opacity,
                                        deblurred=c.medium.refit_deblur)
            rays, depth, opacity, point_ids = (found.rays, found.depth, found.opacity,
                                               found.point_ids)
        else:
            rays = self.data.fixed_subset(c.medium.refit_rays, seed, c.medium.refit_deblur)
            rendered = self.render_batch(rays)
            depth, opacity = rendered["depth_median"], rendered["opacity"]
        diagonal = float(torch.linalg.norm(model.box.box_max - model.box.box_min))
        progress = self._progress()
        open_water = refit_open_water_opacity(c.medium, rays.open_water is not None, progress)
        below = below_horizon(rays.directions, model.scene.get("up"), c.medium.horizon_margin)
        within = c.medium.open_water_surface_share * rays.far.reshape(-1) \
            if progress >= c.medium.open_water_surfaces_from else None
        # the first grouping is the refit's own; other factors regroup the same pixels by voxel
        return [surface_data(rays.origins, rays.directions, rays.rgb, depth, opacity,
                             factor * c.medium.refit_voxel * diagonal, c.medium.refit_opacity,
                             open_water_opacity=open_water, open_water=rays.open_water,
                             below_horizon=below, point_ids=point_ids if i == 0 else None,
                             open_water_surface_within=within)
                for i, factor in enumerate(voxel_factors)]

    def _fit_surfaces(self, data: SurfaceData, start: dict) -> tuple[WaterFit, SurfaceData]:
        return medium_surface_fit(data, start, self.config.medium, self.model.medium.colour_max)

    def _skip_refits_passed_meanwhile(self) -> None:
        """Record the refit points training passed while the last refit ran as skipped.

        Progress follows the clock, so a refit that takes longer than the gap to the next
        point (a short budget, a slow machine) would otherwise be followed by the next one
        step after step, each on the same geometry, spending the budget on refits
        (docs/water.md, "The fits stop where the loss stops moving").
        """
        progress = self._progress()
        due = sum(1 for at in self.config.medium.refit_at if progress >= at)
        while len(self.water_refits) < due:
            self.water_refits.append({"step": self.step, "progress": round(progress, 4),
                                      "skipped": "passed while the refit before it ran"})

    @torch.no_grad()
    def refit_water(self) -> dict:
        """Refit the global water to the training images on the model's own geometry.

        Early in training the water settles wherever it started and fog in the object field
        makes up for the rest; on surfaces the model already places well (opacity above
        ``medium.refit_opacity``), the same surface seen at several ranges pins the water
        down (``seathru.nerf.water_fit``). The fitted values replace the medium's and its
        optimiser state is reset. Returns a record of what was done (for selection.json;
        ``colours`` says whether the pixels' colours had the processing blur taken out).
        """
        model = self.model
        record = {"step": self.step, "progress": round(self._progress(), 4),
                  "colours": "deblurred" if self.config.medium.refit_deblur and
                  self.data.deblurred_rgb is not None else "as trained"}
        if model.medium.mode not in ("global", "veiling"):
            return {**record, "skipped": f"medium mode is {model.medium.mode}"}
        started = time.perf_counter()
        data = self._surface_data(self.config.seed + 5 + len(self.water_refits))[0]
        if isinstance(data, str):
            return {**record, "skipped": data}
        before = model.water_parameters()
        offered = len(data.ranges)
        fit, data = self._fit_surfaces(data, before)
        spread = laplace_halfwidths(fit, data.ranges, data.observed, data.ids, data.groups)
        accepted = refit_acceptance(fit, spread, before, model.medium.colour_max,
                                    self.config.medium.refit_max_relative)
        after = {k: [f if ok else b for f, b, ok in zip(getattr(fit, k), before[k],
                                                        accepted[k])] for k in WATER_KEYS}
        if model.medium.mode == "veiling":   # one c_med does not describe it: keep it
            after["c_med"] = before["c_med"]
        model.medium.set_global(after["sigma_attn"], after["sigma_bs"],
                                after["c_med"] if model.medium.mode == "global" else None)
        for param in model.medium.global_parameters():
            self.optimizer.state.pop(param, None)
        record.update({"pixels": fit.pixels, "left_out": offered - len(data.ranges),
                       "groups": fit.groups, "seconds":
                       round(time.perf_counter() - started, 2),
                       "before": {k: before[k] for k in WATER_KEYS},
                       "fitted": {k: getattr(fit, k) for k in WATER_KEYS},
                       "halfwidth95": spread.halfwidth, "accepted": accepted, "after": after})
        kept = sum(not ok for values in accepted.values() for ok in values)
        note = f"; {kept} of 9 values left as they were: the views do not determine them" \
            if kept else ""
        self._say(f"step {self.step}: water refitted on {fit.pixels} surface pixels: "
                  f"sigma_attn {_fmt(before['sigma_attn'])} -> {_fmt(after['sigma_attn'])}, "
                  f"sigma_bs {_fmt(before['sigma_bs'])} -> {_fmt(after['sigma_bs'])}, c_med "
                  f"{_fmt(before['c_med'])} -> {_fmt(after['c_med'])} (normalised{note})")
        return record

    @torch.no_grad()
    def assess_water(self, trained: dict | None = None) -> dict | None:
        """How well the images determine the trained water: a fit on the final geometry's
        surfaces and its robust 95% half-widths (``water_uncertainty.robust_halfwidths``:
        statistical and systematic parts), normalised units; ``determined`` judges the
        interval around the ``trained`` values (``water_uncertainty.interval_determined``;
        default: the model's water) and its part from what the images cannot tell apart
        (``ambiguity95``, against ``medium.determined_ambiguity``), ``fit_determined`` the
        surface fit's own half-widths. None when the medium is neither
        global nor veiling (whose c_med is the mean over directions) or there are too few
        surface pixels."""
        model = self.model
        if model.medium.mode not in ("global", "veiling"):
            return None
        medium = self.config.medium
        data, *regrouped = self._surface_data(
            self.config.seed + 97, (1.0, *medium.interval_voxel_factors))
        if isinstance(data, str):
            return {"skipped": data}
        offered = len(data.ranges)
        fit, data = self._fit_surfaces(data, model.water_parameters())
        spread, beyond = assessment_spread(fit, data, regrouped, medium,
                                           model.medium.colour_max)
        ambiguity = ambiguity_halfwidths(spread)
        return {"surface_fit": {k: getattr(fit, k) for k in WATER_KEYS},
                "halfwidth95": spread.halfwidth, "fit_determined": spread.determined,
                "determined": interval_determined(
                    trained or model.water_parameters(), fit, spread.halfwidth,
                    ambiguity=ambiguity, max_ambiguity=medium.determined_ambiguity),
                "ambiguity95": ambiguity,
                "pixels": fit.pixels, "left_out": offered - len(data.ranges),
                "groups": fit.groups,
                "effective_samples": spread.effective_samples,
                **({"open_water_beyond": beyond} if beyond is not None else {})}


def medium_surface_fit(data: SurfaceData, start: dict, medium, colour_max: float
                       ) -> tuple[WaterFit, SurfaceData]:
    """The water fitted to ``data`` from ``start`` with the ``medium`` config's refit
    settings, and the pixels it used (``water_fit.fit_surfaces``)."""
    return fit_surfaces(data, start, medium.refit_steps, colour_max, medium.dark_pixel_bound,
                        medium.balance_brightness, medium.refit_trim, medium.refit_noise_term)


def assessment_spread(fit: WaterFit, data: SurfaceData, regrouped: Sequence[SurfaceData | str],
                      medium, colour_max: float) -> tuple[WaterUncertainty, float | None]:
    """The final assessment's robust 95% half-widths of ``fit`` on ``data`` (the pixels it
    used) with the ``medium`` config's interval settings, the same pixels ``regrouped`` at
    other voxel sizes (reasons, str, are left out); and the least range of seabed the open
    water may be, where it looks below the horizon (else None)."""
    beyond = far_surface_range(data.ranges) if data.open_water_below_horizon else None
    spread = robust_halfwidths(fit, data.ranges, data.observed, data.ids, data.groups,
                               colour_max=colour_max, open_water_beyond=beyond,
                               unseen_veiling=medium.interval_unseen_veiling,
                               dark=data.dark if medium.dark_pixel_bound else None,
                               range_error=medium.interval_range_error,
                               min_relative=medium.interval_floor,
                               regrouped=[(d.ranges, d.observed, d.ids, d.groups)
                                          for d in regrouped if not isinstance(d, str)])
    return spread, beyond


def below_horizon(directions: torch.Tensor, up, margin_deg: float) -> torch.Tensor | None:
    """(R,) bool: the unit ``directions`` (R, 3) that look more than ``margin_deg`` below the
    horizon of the vertical ``up`` (3 floats, or None: not known, as in models saved before
    the scene kept it); None where the horizon is not used (negative margin)."""
    if up is None or margin_deg < 0:
        return None
    vertical = torch.as_tensor(up, dtype=directions.dtype, device=directions.device)
    return directions @ vertical < -math.sin(math.radians(margin_deg))


def refit_open_water_opacity(medium, from_images: bool, progress: float) -> float:
    """The ``open_water_opacity`` a water fit at ``progress`` passes to
    ``water_surfaces.surface_data`` (0: no open water): the photographs' open water needs no
    converged model; the model's empty rays count only from ``medium.open_water_from``."""
    return medium.open_water_opacity if from_images or progress >= medium.open_water_from \
        else 0.0


def refit_acceptance(fit, spread, before: dict, colour_max: float,
                     max_relative: float) -> dict[str, list[bool]]:
    """Which refitted values replace the current ones: those the views determine.

    A value is kept out when its 95% half-width exceeds ``max_relative`` of it, or when the fit
    ran to the edge of the parameter space (a coefficient collapsing below 1% of its current
    value, a veiling light at 95% of ``colour_max``): there the curvature says nothing and the
    fit has traded the water for the surfaces' colours.
    """
    accepted = {}
    for key in WATER_KEYS:
        flags = []
        for value, half, current in zip(getattr(fit, key), spread.halfwidth[key], before[key]):
            edge = value >= 0.95 * colour_max if key == "c_med" else value < 0.01 * current
            flags.append(bool(half <= max_relative * abs(value) and not edge))
        accepted[key] = flags
    return accepted


def _fmt(values) -> str:
    return "(" + ", ".join(f"{v:.3g}" for v in values) + ")"
