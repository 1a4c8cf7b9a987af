"""The trials that choose the model during training: water or none (``medium.mode=auto``),
view-dependent object colour or not (``field.view_dependent_colour=auto``).

Each trial is a race (:meth:`ModelSelection._race`): from the same state the model trains on
for the same few steps on the same batches under each choice, and each is measured on training
rays held out from the start. The simpler model wins unless the other is better by a margin;
for the water, the images' own evidence of water decides ties
(:meth:`ModelSelection.select_medium`).

:class:`ModelSelection` is a part of ``seathru.nerf.training.Trainer`` (a mixin): it uses the
trainer's model, optimiser, batch generator and held-out rays.
"""

from __future__ import annotations

import copy
import math
from typing import Callable

import torch

from seathru.nerf.losses import mse, psnr_from_mse


class ModelSelection:
    """The trainer's races between model choices, on its held-out training rays."""

    def _probe_psnr(self) -> float:
        rendered = self.render_batch(self.probe)
        return psnr_from_mse(float(mse(rendered["rgb"], self.probe.rgb)))

    def _state(self) -> dict:
        return {"model": {k: v.detach().clone() for k, v in self.model.state_dict().items()},
                "optimizer": copy.deepcopy(self.optimizer.state_dict()),
                "generator": self.generator.get_state(), "step": self.step}

    def _restore(self, state: dict) -> None:
        self.model.load_state_dict_resizing(state["model"])
        self.optimizer = self._build_optimizer()
        self.optimizer.load_state_dict(copy.deepcopy(state["optimizer"]))
        self.generator.set_state(state["generator"])
        self.step = state["step"]
        self.model.refresh_occupancy()

    def _trial_steps(self, share: float) -> int:
        """Steps of one trial: ``share`` of the steps the run will make (10 to 500)."""
        c = self.config
        budget = c.max_minutes * 60.0 if c.max_minutes and c.max_minutes > 0 else math.inf
        rate = self.step / max(self.elapsed_s, 1e-6)
        horizon = min(c.step_limit, rate * budget)
        return int(min(500, max(10, share * horizon)))

    def _race(self, setups: dict[str, Callable[[], None]], trial: int
              ) -> tuple[dict[str, float], dict[str, dict]]:
        """Train ``trial`` steps from the current state under each setup in turn, on the same
        batches (the batch generator is restored with the state), and measure each on the
        held-out training rays. Returns the PSNR and the end state per setup name (all but the
        last's: the model is left where the last one ended)."""
        start = self._state()
        results, ends = {}, {}
        previous = None
        for name, setup in setups.items():
            if previous is not None:
                ends[previous] = self._state()
                self._restore(start)
            previous = name
            setup()
            self._train_trial(trial)
            results[name] = self._probe_psnr()
        return results, ends

    def _train_trial(self, trial: int) -> None:
        """``trial`` optimisation steps at the learning rate of the current progress."""
        progress = self._progress()
        for _ in range(trial):
            self._set_lr(progress)
            if self._optimise_once() is not None:
                self.step += 1

    def select_view_dependence(self) -> dict:
        """``field.view_dependent_colour=auto``: object colour with or without the view
        direction, the simpler unless the views ask for more.

        The grid field trains without it until ``field.view_select_at``: while the water is
        refitted, a view-dependent colour would stand in for it (looking across a survey, the
        direction goes with the range; the clearer waters of the water benchmark ended 2-3 dB
        worse restored when it was on from the start). Then the model trains on for the same
        few steps on the same batches without and with it (``field.view_trial_share`` of the
        run each; the direction's weights start at zero, so both start from the same colours)
        and the two are compared on the held-out training rays. It is kept only when it does
        better by ``field.view_margin_db``: it costs the SH of every colour sample, and where
        the surfaces look the same from every side it can only fit noise or stand in for
        errors of the geometry or the water.
        """
        c = self.config
        decoder = self.model.field.decoder
        trial = self._trial_steps(c.field.view_trial_share)
        from_step = self.step
        results, ends = self._race({"off": lambda: decoder.set_view_enabled(False),
                                    "on": lambda: decoder.set_view_enabled(True)}, trial)
        gain = results["on"] - results["off"]
        chosen = "on" if gain > c.field.view_margin_db else "off"
        if chosen == "off":
            self._restore(ends["off"])
        self._take_snapshot()
        verdict = (f"better by {gain:.2f} dB > {c.field.view_margin_db:g} dB: kept"
                   if chosen == "on" else
                   f"not better by more than {c.field.view_margin_db:g} dB ({gain:+.2f} dB): "
                   "colour without the view direction")
        return {"requested": "auto", "chosen": chosen, "decided_at_step": from_step,
                "trial_steps": trial, "validation_psnr_off": results["off"],
                "validation_psnr_on": results["on"], "margin_db": c.field.view_margin_db,
                "reason": (f"trained {trial} steps with and without view-dependent colour from "
                           f"step {from_step}: on {len(self.probe)} held-out training rays "
                           f"{results['on']:.2f} dB with it, {results['off']:.2f} dB without; "
                           f"{verdict}")}

    def image_evidence_of_water(self) -> list[str]:
        """What the photographs themselves show of water, known before training: open water
        (smooth regions reaching the top of the frame) and the input colour changing with range
        along the COLMAP tracks; one sentence each."""
        c = self.config
        image_water = float(self.model.scene.get("open_water_image_share", 0.0))
        tracks = self.model.scene.get("track_colour_change") or {}
        fading = [abs(t) > c.medium.auto_track_t and abs(change) > c.medium.auto_track_change
                  for t, change in zip(tracks.get("t", []),
                                       tracks.get("change_over_median_range", []))]
        return [text for present, text in (
            (image_water > c.medium.auto_open_water_share,
             f"{100 * image_water:.1f}% of the training pixels are open water (smooth regions "
             "reaching the top of the frame)"),
            (any(fading),
             "along {} COLMAP tracks the input colour changes with range by {} over the median "
             "range (log colour, R G B)".format(tracks.get("tracks"), ", ".join(
                 f"{100 * v:+.0f}%" for v in tracks.get("change_over_median_range", [])))),
        ) if present]

    def medium_decision_progress(self) -> float:
        """When ``medium.mode=auto`` decides: ``auto_select_at``, or
        ``auto_select_at_no_image_evidence`` where the photographs show no water
        (:meth:`image_evidence_of_water`) and no water is the likelier answer, which then
        keeps more of the budget to recover from the switch (:meth:`select_medium`)."""
        c = self.config.medium
        if self.image_evidence_of_water():
            return c.auto_select_at
        return min(c.auto_select_at, c.auto_select_at_no_image_evidence)

    def _backscatter_in_front_share(self, rendered: dict, hit: torch.Tensor) -> float:
        """The water's backscatter between the camera and the surfaces the probe rays meet,
        as a share of their colour (max over channels; 0 where no ray meets a surface)."""
        if not bool(hit.any()):
            return 0.0
        with torch.no_grad():
            directions = self.probe.directions[hit.to(self.probe.directions.device)]
            _, sigma_bs, c_med = self.model.medium(directions.to(self.device))
        depth = rendered["depth_median"][hit].to(sigma_bs.device)[:, None]
        front = c_med * -torch.expm1(-sigma_bs * depth)
        colour = rendered["rgb"][hit].to(front.device).mean(0).clamp_min(1e-6)
        return float((front.mean(0) / colour).max())

    def select_medium(self) -> dict:
        """``medium.mode=auto``: no water (plain NeRF) or the water the run started with, the
        simplest that the training views support.

        The water has been trained so far: ``global``, or ``veiling`` (veiling light by view
        direction) where the open water of the training images changes colour with direction
        (``seathru.nerf.model.initial_medium_mode``). If what it adds to the images is
        negligible (backscatter below ``auto_backscatter_share`` of the image and attenuation
        over the median scene depth below ``auto_attenuation``) the water is switched off at
        once. Otherwise both models train on from here for the same few steps on the same
        batches (``auto_trial_share`` of the run each) and are compared on held-out training
        rays, where the images show evidence of water: open water in the photographs
        (smooth regions reaching the top of the frame, ``seathru.radiometry.open_water``) or in
        the model (rays that meet no surface; both above ``auto_open_water_share``, and only
        where the veiling light is visible: ``auto_veiling_brightness``), a density wall at the
        far bound standing in for it, the input colour changing with range along the COLMAP
        tracks (``seathru.io.tracks.input_colour_change``), attenuation the surfaces seen
        over a range of distances determine (``assess_water``; made only when nothing else
        shows water, as it costs seconds of the budget), or a fitted water whose
        backscatter is a large share of the image (``auto_backscatter_evidence``), and of it in
        front of the surfaces the rays meet (``auto_backscatter_in_front_evidence``: a
        half-trained scene's fog behind its surfaces is no water). With such evidence the water
        stays unless no water is better by ``auto_margin_db``. Without it there is no water and
        no race: the race starts from the model trained with the water, whose object colours
        were learnt under it and are each off by the attenuation once it is switched off. With
        ``auto_race_without_evidence`` the race is run anyway and the water must be better by
        ``auto_margin_no_evidence_db``, also after no water has trained a second trial. The
        paper's fully view-dependent water is never picked automatically: it can also absorb
        errors of a half-trained scene; ask for it with ``medium.mode=view``.
        """
        c = self.config
        rendered = self.render_batch(self.probe)
        water = self.model.water_parameters()
        mean_rgb = rendered["rgb"].mean(0).clamp_min(1e-6)
        backscatter_share = float((rendered["backscatter"].mean(0) / mean_rgb).max())
        hit = rendered["opacity"] > 0.5
        if bool(hit.any()):
            depth = float(torch.quantile(rendered["depth"][hit].float(), 0.5))
        else:
            depth = float(self.model.scene.get("typical_range", 1.0))
        front_share = self._backscatter_in_front_share(rendered, hit)
        attenuation = 1.0 - math.exp(-max(water["sigma_attn"]) * depth)
        # open water: rays that meet no surface AND whose pixel is the veiling light itself; an
        # empty ray whose pixel differs (textured seabed explained by water) is no evidence
        c_med = torch.tensor(water["c_med"], device=rendered["rgb"].device)
        observed = self.probe.rgb.to(c_med.device)
        matches = ((observed - c_med).abs() / c_med.clamp_min(0.02)).amax(-1) < 0.15
        # black "open water" is no veiling light: clear water, air, a black background
        def visible(colour: torch.Tensor) -> bool:
            return float(colour.mean()) >= c.medium.auto_veiling_brightness * float(
                observed.mean())

        open_water = float(((rendered["opacity"] < 0.1) & matches).float().mean()) \
            if visible(c_med) else 0.0
        far = self.model.ray_interval(self.probe.near, self.probe.far)[1].to(
            rendered["depth_median"].device)
        walled = (rendered["opacity"] > 0.5) & (rendered["depth_median"] > 0.95 * far)
        wall = float(walled.float().mean()) \
            if bool(walled.any()) and visible(observed[walled]) else 0.0
        image_water = float(self.model.scene.get("open_water_image_share", 0.0))
        tracks = self.model.scene.get("track_colour_change") or {}
        evidence = [*self.image_evidence_of_water(), *(text for present, text in (
            (open_water > c.medium.auto_open_water_share,
             f"{100 * open_water:.1f}% of the rays meet no surface and show the veiling light "
             "(open water)"),
            (wall > c.medium.auto_open_water_share,
             f"{100 * wall:.1f}% of the rays end in a density wall at the far bound"),
            (backscatter_share >= c.medium.auto_backscatter_evidence
             and front_share >= c.medium.auto_backscatter_in_front_evidence,
             f"the fitted water's backscatter makes up {100 * backscatter_share:.0f}% of the "
             f"image, {100 * front_share:.0f}% in front of the surfaces"),
        ) if present)]
        # The surface fit costs seconds of the budget (12 s of a 90-s demo run) and can only
        # add evidence: it is made when nothing else shows water, where it decides.
        surface_attenuation, surface_lower, determined = None, None, None
        if not evidence:
            surface_attenuation, surface_lower, determined = self._surface_fading(depth)
            # at the lower end of the fit's interval: a half-formed scene's surfaces are darker
            # seen from further away (clear toy orbits: up to 42%, its lower end 0-5%)
            if (determined or surface_lower >= c.medium.auto_surface_fading) \
                    and surface_attenuation > 2 * c.medium.auto_attenuation:
                evidence.append(f"surfaces seen over a range of distances fade by "
                                f"{100 * surface_attenuation:.0f}% over the median depth"
                                + (" (attenuation determined)" if determined else
                                   f" (at least {100 * surface_lower:.0f}%)"))
        stats = {"backscatter_share": backscatter_share,
                 "backscatter_in_front_share": front_share, "attenuation_over_depth": attenuation,
                 "scene_depth_median": depth, "object_hit_share": float(hit.float().mean()),
                 "open_water_share": open_water, "open_water_image_share": image_water,
                 "track_colour_change": tracks or None,
                 "far_wall_share": wall,
                 "surface_attenuation_over_depth": surface_attenuation,
                 "surface_attenuation_over_depth_lower": surface_lower,
                 "attenuation_determined": determined, "evidence_of_water": evidence,
                 "fitted_global": water, "validation_rays": len(self.probe)}
        thresholds = {"backscatter_share": c.medium.auto_backscatter_share,
                      "attenuation_over_depth": c.medium.auto_attenuation,
                      "open_water_share": c.medium.auto_open_water_share,
                      "margin_db": c.medium.auto_margin_db,
                      "margin_no_evidence_db": c.medium.auto_margin_no_evidence_db,
                      "backscatter_evidence": c.medium.auto_backscatter_evidence,
                      "backscatter_in_front_evidence":
                          c.medium.auto_backscatter_in_front_evidence,
                      "veiling_brightness": c.medium.auto_veiling_brightness}
        decided_at = {"decided_at_step": self.step, "decided_at_progress": self._progress()}
        water_mode = self.model.medium.mode   # global, or veiling where the open water asks
        if not evidence and backscatter_share < c.medium.auto_backscatter_share \
                and attenuation < c.medium.auto_attenuation:
            chosen = "off"
            reason = (f"fitted water is negligible: backscatter is {100 * backscatter_share:.2f}% "
                      f"of the image (< {100 * c.medium.auto_backscatter_share:g}%) and "
                      f"attenuation over the median scene depth ({depth:.3g}) is "
                      f"{100 * attenuation:.2f}% "
                      f"(< {100 * c.medium.auto_attenuation:g}%): clear water, plain NeRF")
            self.model.medium.set_mode(chosen)
        elif not evidence and not c.medium.auto_race_without_evidence:
            chosen = "off"
            reason = (f"no evidence of water: the images show no open water, far wall or fading "
                      f"with range, and the fitted water's backscatter makes up "
                      f"{100 * backscatter_share:.0f}% of the image, {100 * front_share:.0f}% in "
                      "front of the surfaces (evidence from "
                      f"{100 * c.medium.auto_backscatter_evidence:g}% and "
                      f"{100 * c.medium.auto_backscatter_in_front_evidence:g}%); a trial from a "
                      "model trained with the water would favour it: no water, plain NeRF")
            self.model.medium.set_mode(chosen)
        else:
            trial = self._trial_steps(c.medium.auto_trial_share)
            from_step = self.step
            results, ends = self._race({mode: (lambda m=mode: self.model.medium.set_mode(m))
                                        for mode in ("off", water_mode)}, trial)
            gain = results[water_mode] - results["off"]
            margin = c.medium.auto_margin_db if evidence \
                else c.medium.auto_margin_no_evidence_db
            recovered = None
            if not evidence and gain > margin:
                # one trial may not undo the switch (docs/water.md, "No water after the switch")
                ends[water_mode] = self._state()
                self._restore(ends["off"])
                self._train_trial(trial)
                recovered = self._probe_psnr()
                ends["off"] = self._state()
                gain = results[water_mode] - max(results["off"], recovered)
            chosen = water_mode if (gain > -margin if evidence else gain > margin) else "off"
            if chosen == "off":
                self._restore(ends["off"])
                self.model.medium.set_mode("off")
            elif recovered is not None:
                self._restore(ends[water_mode])
            stats.update({"trial_steps": trial, "validation_psnr_off": results["off"],
                          "validation_psnr_water": results[water_mode],
                          "validation_psnr_off_second_trial": recovered})
            if evidence:
                verdict = (f"kept: the images show water ({'; '.join(evidence)}) and no water "
                           f"is not better by more than {margin:g} dB ({gain:+.2f} dB for the "
                           "water)" if chosen != "off" else
                           f"dropped despite signs of water ({'; '.join(evidence)}): no water "
                           f"is better by {-gain:.2f} dB > {margin:g} dB")
            else:
                verdict = (f"better by {gain:.2f} dB > {margin:g} dB: one {water_mode} medium"
                           if chosen != "off" else
                           f"not better by more than {margin:g} dB ({gain:+.2f} dB) and the "
                           "images show no open water, far wall or fading with range: no "
                           "water, plain NeRF")
            second = "" if recovered is None else (
                f" ({recovered:.2f} dB after {trial} more steps to adapt to the switch)")
            reason = (f"trained {trial} steps with and without water from step "
                      f"{from_step}: on {len(self.probe)} held-out training rays the water "
                      f"model ({water_mode}) reaches {results[water_mode]:.2f} dB, no water "
                      f"{results['off']:.2f} dB{second}; the water is {verdict} (it made up "
                      f"{100 * backscatter_share:.1f}% of the image as backscatter, attenuation "
                      f"{100 * attenuation:.1f}% over the median depth {depth:.3g})")
        self.model.medium.to(self.device)
        self._take_snapshot()
        return {"requested": "auto", "chosen": chosen, "reason": reason,
                "candidates": ["off", water_mode], **decided_at,
                "statistics": stats, "thresholds": thresholds}
