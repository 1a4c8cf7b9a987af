"""The training loop: Adam with warm-up and decay, coarse-to-fine grids, medium model selection,
a NaN/Inf guard, held-out evaluation, checkpoints. No file I/O: the step passes callbacks.

Progress. Training stops at ``config.step_limit`` steps or after ``config.max_minutes``,
whichever comes first (by default only the time budget limits it), and every schedule
(learning-rate decay, grid upsampling, the medium decision) follows ``progress = max(step /
step_limit, elapsed / budget)``, so a run cut short by its time budget still decays its learning
rate and reaches the finest grid: the model adapts to the machine it runs on.
``elapsed`` is training time: the held-out evaluations for the log are not counted (they are
also left out of ``wall_time_s`` in the log), the medium trial and checkpoints are.

Medium (``medium.mode=auto``): see ``Trainer.select_medium``. Losses: the paper's reconstruction
loss on linear data, its transmittance prior, mip-NeRF 360's distortion loss (keeps each ray's
object weight in one compact surface, so fog in the object field does not stand in for water).
Density gradients are dropped where fewer than ``min_views`` training cameras look (what only
one camera sees is unconstrained and becomes floaters in front of it). CPU threads: the faster
of ``--threads`` and 1 is measured on real steps every few hundred steps (``ThreadTuner``).

NaN guard. A non-finite loss or gradient norm restores the last in-memory snapshot (taken every
``snapshot_every`` good steps), halves the learning rate and carries on; after
``nan_max_retries`` such rollbacks training stops with a ``PipelineError``.

Checkpoints (``checkpoint_state``) hold only tensors, dicts, lists, str, int, float, bool and
None, so ``torch.load(weights_only=True)`` reads them.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass
from typing import Callable, Sequence

import torch

from seathru.errors import PipelineError
from seathru.nerf.config import TrainConfig, resolve_batch_rays
from seathru.nerf.losses import (distortion_loss, mse, psnr_from_mse, reconstruction_loss,
                                 sparse_depth_loss, total_variation_3d, transmittance_prior)
from seathru.nerf.model import SeaThruModel
from seathru.nerf.rays import RayBatch, RayDataset
from seathru.nerf.medium import DIRECTIONAL_MODES
from seathru.nerf.water_fit import (SurfaceData, WaterFit, correspondence_rays, fit_surfaces,
                                    surface_data)
from seathru.nerf.water_uncertainty import (far_surface_range, interval_determined,
                                            laplace_halfwidths, robust_halfwidths)

CHECKPOINT_FORMAT = "seathru-train-checkpoint/1"
WATER_KEYS = ("sigma_attn", "sigma_bs", "c_med")


@dataclass
class TrainCallbacks:
    """Hooks the step passes in (all optional)."""

    progress: Callable[[int, dict], None] | None = None     # every step: (step, stats)
    log_row: Callable[[dict], None] | None = None           # each train_log row
    checkpoint: Callable[[dict], None] | None = None        # a checkpoint dict to store
    message: Callable[[str], None] | None = None            # human-readable events
    batch_hook: Callable[[int, RayBatch], RayBatch] | None = None  # tests: alter a batch
    # at log-spaced training times and at the end: (step, elapsed_s); its time is not counted
    quality_snapshot: Callable[[int, float], None] | None = None


@dataclass
class TrainResult:
    steps: int
    elapsed_s: float
    stopped_by: str                 # "steps" | "time"
    log: list[dict]
    selection: dict
    rollbacks: int
    final_test_psnr: float | None
    train_step_rate: float          # steps per second in this run
    rays_per_second: float


def log_spaced_steps(limit: float) -> set[int]:
    """1, 2, 3, 5, 7, 10, 20, 30, 50, 70, 100, ... up to ``limit`` (at most 7e9: a run without a
    step limit)."""
    limit = min(limit, 7e9)
    steps, decade = set(), 1
    while decade <= limit:
        for m in (1, 2, 3, 5, 7):
            if m * decade <= limit:
                steps.add(m * decade)
        decade *= 10
    return steps


def _adam(groups: list[dict]) -> torch.optim.Adam:
    try:
        return torch.optim.Adam(groups, betas=(0.9, 0.99), eps=1e-15, fused=True)
    except (RuntimeError, TypeError):
        return torch.optim.Adam(groups, betas=(0.9, 0.99), eps=1e-15)


class Trainer:
    def __init__(self, model: SeaThruModel, data: RayDataset, test: RayBatch | None = None,
                 callbacks: TrainCallbacks | None = None, device="cpu", frames=None):
        self.model = model
        model.config = resolve_batch_rays(model.config, torch.device(device).type)
        self.config: TrainConfig = model.config
        self.data = data
        self.test = test.to(device) if test is not None else None
        self.callbacks = callbacks or TrainCallbacks()
        self.device = torch.device(device)
        self.generator = torch.Generator().manual_seed(self.config.seed + 1)
        # Held-out training rays (never sampled): they judge the medium model (medium.mode=auto).
        self.probe = data.hold_out(max(256, min(self.config.eval_rays, len(data) // 20)),
                                   self.config.seed + 2)
        self.step = 0
        self.elapsed_s = 0.0
        self.lr_scale = 1.0
        self.rollbacks = 0
        self.log: list[dict] = []
        self.selection: dict | None = None
        self.water_refits: list[dict] = []
        self._held_water: tuple | None = None   # ((refits, mode), flags): _hold_refitted_water
        if self.config.medium.mode != "auto":
            self.selection = {"requested": self.config.medium.mode, "chosen": self.config.medium.mode,
                              "reason": "set explicitly (medium.mode)"}
        requested = self.config.field.view_dependent_colour
        self.view_selection: dict | None = None
        if not hasattr(model.field, "decoder") or not hasattr(model.field.decoder,
                                                               "view_enabled"):
            self.view_selection = {"requested": requested,
                                   "chosen": "off" if requested == "off" else "on",
                                   "reason": "set explicitly (field.view_dependent_colour)"
                                   if requested != "auto" else "the MLP field is view-dependent"}
        self.optimizer = self._build_optimizer()
        self._snapshot = None
        self._eval_steps = log_spaced_steps(self.config.step_limit)
        self._seen = self._seen_mask(frames)
        self._seen_cache: dict = {}
        self._threads = ThreadTuner(torch.get_num_threads()) if self.device.type == "cpu" \
            else None

    def _seen_mask(self, frames) -> torch.Tensor | None:
        """(1, 1, D, H, W) 1 where at least ``min_views`` training cameras see a grid vertex.

        Density elsewhere is seen by one camera only and can take any value that paints that
        camera's image (the floaters in front of it): its gradient is dropped.
        """
        c = self.config
        if frames is None or c.field.min_views <= 1 or c.field.kind != "grid":
            return None
        from seathru.nerf.fields import axis_resolution, grid_vertices
        from seathru.nerf.rays import view_counts

        dims = axis_resolution(max(c.field.density_res) // 2, self.model.field.extent)
        points = grid_vertices(self.model.box, dims)
        counts = view_counts(points.reshape(-1, 3).numpy(), frames)
        mask = torch.from_numpy(counts >= c.field.min_views).float().reshape(1, 1, *points.shape[:3])
        return mask.to(self.device)

    def _mask_density_gradients(self) -> None:
        if self._seen is None:
            return
        for param in self.model.field.grid_parameters():
            if param.grad is None:
                continue
            shape = tuple(param.shape[2:])
            if shape not in self._seen_cache:
                self._seen_cache[shape] = torch.nn.functional.interpolate(
                    self._seen, size=shape, mode="nearest")
            param.grad.mul_(self._seen_cache[shape])

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

    # -------------------------------------------------------------------- optimiser
    def _groups(self) -> list[dict]:
        c, m = self.config, self.model
        spec = [("density", m.field.grid_parameters(), c.optim.lr * c.optim.density_lr_scale),
                ("features", m.field.feature_parameters(), c.optim.lr),
                ("networks", m.field.network_parameters() + m.medium.network_parameters(),
                 c.optim.lr * c.optim.network_lr_scale),
                ("view", m.field.view_parameters(), c.optim.lr * c.optim.view_lr_scale),
                ("medium", m.medium.global_parameters(), c.optim.lr * c.optim.medium_lr_scale)]
        return [{"params": params, "lr": lr, "base_lr": lr, "name": name}
                for name, params, lr in spec if params]

    def _build_optimizer(self) -> torch.optim.Optimizer:
        return _adam(self._groups())

    def _swap_parameters(self, swapped: dict) -> None:
        """Coarse-to-fine: move Adam's moments to the resampled parameters (same resampling)."""
        for name, (old, new) in swapped.items():
            state = self.optimizer.state.pop(old, None)
            for group in self.optimizer.param_groups:
                group["params"] = [new if p is old else p for p in group["params"]]
            if state:
                resized = {}
                for key, value in state.items():
                    if torch.is_tensor(value) and value.shape == old.shape:
                        resized[key] = _resample_like(value, new.shape)
                    else:
                        resized[key] = value
                self.optimizer.state[new] = resized

    def _set_lr(self, progress: float) -> None:
        c = self.config
        warm = min(1.0, (self.step + 1) / max(1, c.optim.warmup_steps))
        decay = c.optim.lr_final_ratio ** min(1.0, progress)
        for group in self.optimizer.param_groups:
            group["lr"] = group["base_lr"] * warm * decay * self.lr_scale

    # -------------------------------------------------------------------- checkpoints
    def checkpoint_state(self) -> dict:
        rng = {"torch": torch.get_rng_state(), "batch": self.generator.get_state()}
        if torch.cuda.is_available():
            rng["cuda"] = torch.cuda.get_rng_state_all()
        return {"format": CHECKPOINT_FORMAT, "config": self.config.to_dict(),
                "scene": self.model.scene,
                "model": {k: v.detach().cpu() for k, v in self.model.state_dict().items()},
                "optimizer": _to_cpu(self.optimizer.state_dict()),
                "step": self.step, "elapsed_s": self.elapsed_s, "rng": rng,
                "log": [dict(row) for row in self.log], "lr_scale": self.lr_scale,
                "rollbacks": self.rollbacks,
                "selection": copy.deepcopy(self.selection),
                "view_selection": copy.deepcopy(self.view_selection),
                "water_refits": copy.deepcopy(self.water_refits)}

    def load_checkpoint(self, ckpt: dict) -> None:
        self.model.load_state_dict_resizing(ckpt["model"])
        self.model.to(self.device)
        self.optimizer = self._build_optimizer()
        self.optimizer.load_state_dict(ckpt["optimizer"])
        self.step = int(ckpt["step"])
        self.elapsed_s = float(ckpt["elapsed_s"])
        torch.set_rng_state(ckpt["rng"]["torch"])
        self.generator.set_state(ckpt["rng"]["batch"])
        if "cuda" in ckpt["rng"] and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(ckpt["rng"]["cuda"])
        self.log = [dict(row) for row in ckpt["log"]]
        self.lr_scale = float(ckpt["lr_scale"])
        self.rollbacks = int(ckpt["rollbacks"])
        self.selection = ckpt.get("selection")
        self.view_selection = ckpt.get("view_selection", self.view_selection)
        self.water_refits = list(ckpt.get("water_refits", []))

    # -------------------------------------------------------------------- guard
    def _take_snapshot(self) -> None:
        self._snapshot = {"model": {k: v.detach().clone() for k, v in
                                    self.model.state_dict().items()},
                          "optimizer": copy.deepcopy(self.optimizer.state_dict())}

    def _rollback(self, why: str) -> None:
        self.rollbacks += 1
        if self.rollbacks > self.config.nan_max_retries:
            raise PipelineError(
                f"training diverged: {why} at step {self.step}, {self.rollbacks} times despite "
                f"rolling back and lowering the learning rate (now {self.lr_scale:g} x optim.lr); "
                "lower train.optim.lr, or check the input images for NaN/Inf values")
        self.lr_scale *= 0.5
        if self._snapshot is not None:
            self.model.load_state_dict_resizing(self._snapshot["model"])
            self.optimizer = self._build_optimizer()
            self.optimizer.load_state_dict(copy.deepcopy(self._snapshot["optimizer"]))
        self.model.refresh_occupancy()
        self._say(f"step {self.step}: {why}; rolled back to the last good state, learning rate "
                  f"x{self.lr_scale:g} (rollback {self.rollbacks}/{self.config.nan_max_retries})")

    # -------------------------------------------------------------------- evaluation
    @torch.no_grad()
    def render_batch(self, rays: RayBatch, chunk: int = 8192) -> dict[str, torch.Tensor]:
        was_training = self.model.training
        self.model.eval()
        outs = {"rgb": [], "backscatter": [], "opacity": [], "depth": [], "depth_median": []}
        for start in range(0, len(rays), chunk):
            part = rays.subset(slice(start, start + chunk))
            r = self.model(part.origins, part.directions, part.near, part.far).render
            outs["rgb"].append(r.rgb)
            outs["backscatter"].append(r.backscatter)
            outs["opacity"].append(r.opacity)
            outs["depth"].append(r.depth_mean)
            outs["depth_median"].append(r.depth_median)
        self.model.train(was_training)
        return {k: torch.cat(v) for k, v in outs.items()}

    def test_psnr(self) -> float | None:
        if self.test is None or len(self.test) == 0:
            return None
        start = time.perf_counter()
        rendered = self.render_batch(self.test)
        value = psnr_from_mse(float(mse(rendered["rgb"], self.test.rgb)))
        self._eval_seconds = getattr(self, "_eval_seconds", 0.0) + time.perf_counter() - start
        return value

    # -------------------------------------------------------------------- medium selection
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
            progress = self._progress()
            for _ in range(trial):
                self._set_lr(progress)
                if self._optimise_once() is not None:
                    self.step += 1
            results[name] = self._probe_psnr()
        return results, ends

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
        rays. The images' own evidence of water decides ties: open water in the photographs
        (smooth regions reaching the top of the frame, ``seathru.radiometry.open_water``) or in
        the model (rays that meet no surface; both above ``auto_open_water_share``, and only
        where the veiling light is visible: ``auto_veiling_brightness``), a density wall at the
        far bound standing in for it, the input colour changing with range along the COLMAP
        tracks (``seathru.io.tracks.input_colour_change``), attenuation the surfaces seen
        over a range of distances determine (``assess_water``; made only when nothing else
        shows water, as it costs seconds of the budget), or a fitted water whose
        backscatter is a large share of the image (``auto_backscatter_evidence``). With such
        evidence the water stays unless no water is better by ``auto_margin_db``; without it,
        the water must be better by ``auto_margin_no_evidence_db``. The paper's fully
        view-dependent water is never picked automatically: it can also absorb errors of a
        half-trained scene; ask for it with ``medium.mode=view``.
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
        fading = [abs(t) > c.medium.auto_track_t and abs(change) > c.medium.auto_track_change
                  for t, change in zip(tracks.get("t", []),
                                       tracks.get("change_over_median_range", []))]
        evidence = [text for present, text in (
            (image_water > c.medium.auto_open_water_share,
             f"{100 * image_water:.1f}% of the training pixels are open water (smooth regions "
             "reaching the top of the frame)"),
            (any(fading),
             "along {} COLMAP tracks the input colour changes with range by {} over the median "
             "range (log colour, R G B)".format(tracks.get("tracks"), ", ".join(
                 f"{100 * v:+.0f}%" for v in tracks.get("change_over_median_range", [])))),
            (open_water > c.medium.auto_open_water_share,
             f"{100 * open_water:.1f}% of the rays meet no surface and show the veiling light "
             "(open water)"),
            (wall > c.medium.auto_open_water_share,
             f"{100 * wall:.1f}% of the rays end in a density wall at the far bound"),
            (backscatter_share >= c.medium.auto_backscatter_evidence,
             f"the fitted water's backscatter makes up {100 * backscatter_share:.0f}% of the "
             "image"),
        ) if present]
        # The surface fit costs seconds of the budget (12 s of a 90-s demo run) and can only
        # add evidence: it is made when nothing else shows water, where it decides.
        surface_attenuation, determined = None, None
        if not evidence:
            surface_attenuation, determined = self._surface_fading(depth)
            if (determined or surface_attenuation >= c.medium.auto_surface_fading) \
                    and surface_attenuation > 2 * c.medium.auto_attenuation:
                evidence.append(f"surfaces seen over a range of distances fade by "
                                f"{100 * surface_attenuation:.0f}% over the median depth"
                                + (" (attenuation determined)" if determined else ""))
        stats = {"backscatter_share": backscatter_share, "attenuation_over_depth": attenuation,
                 "scene_depth_median": depth, "object_hit_share": float(hit.float().mean()),
                 "open_water_share": open_water, "open_water_image_share": image_water,
                 "track_colour_change": tracks or None,
                 "far_wall_share": wall,
                 "surface_attenuation_over_depth": surface_attenuation,
                 "attenuation_determined": determined, "evidence_of_water": evidence,
                 "fitted_global": water, "validation_rays": len(self.probe)}
        thresholds = {"backscatter_share": c.medium.auto_backscatter_share,
                      "attenuation_over_depth": c.medium.auto_attenuation,
                      "open_water_share": c.medium.auto_open_water_share,
                      "margin_db": c.medium.auto_margin_db,
                      "margin_no_evidence_db": c.medium.auto_margin_no_evidence_db,
                      "veiling_brightness": c.medium.auto_veiling_brightness}
        decided_at = {"decided_at_step": self.step, "decided_at_progress": self._progress()}
        water_mode = self.model.medium.mode   # global, or veiling where the open water asks
        if not evidence and backscatter_share < c.medium.auto_backscatter_share \
                and attenuation < c.medium.auto_attenuation:
            chosen = "off"
            reason = (f"fitted water is negligible: backscatter is {100 * backscatter_share:.2f}% "
                      f"of the image (< {100 * c.medium.auto_backscatter_share:g}%) and attenuation "
                      f"over the median scene depth ({depth:.3g}) is {100 * attenuation:.2f}% "
                      f"(< {100 * c.medium.auto_attenuation:g}%): clear water, plain NeRF")
            self.model.medium.set_mode(chosen)
        else:
            trial = self._trial_steps(c.medium.auto_trial_share)
            from_step = self.step
            results, ends = self._race({mode: (lambda m=mode: self.model.medium.set_mode(m))
                                        for mode in ("off", water_mode)}, trial)
            gain = results[water_mode] - results["off"]
            margin = c.medium.auto_margin_db if evidence \
                else c.medium.auto_margin_no_evidence_db
            chosen = water_mode if (gain > -margin if evidence else gain > margin) else "off"
            if chosen == "off":
                self._restore(ends["off"])
                self.model.medium.set_mode("off")
            stats.update({"trial_steps": trial, "validation_psnr_off": results["off"],
                          "validation_psnr_water": results[water_mode]})
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
            reason = (f"trained {trial} steps with and without water from step "
                      f"{from_step}: on {len(self.probe)} held-out training rays the water "
                      f"model ({water_mode}) reaches {results[water_mode]:.2f} dB, no water "
                      f"{results['off']:.2f} dB; the water is {verdict} (it made up "
                      f"{100 * backscatter_share:.1f}% of the image as backscatter, attenuation "
                      f"{100 * attenuation:.1f}% over the median depth {depth:.3g})")
        self.model.medium.to(self.device)
        self._take_snapshot()
        return {"requested": "auto", "chosen": chosen, "reason": reason,
                "candidates": ["off", water_mode], **decided_at,
                "statistics": stats, "thresholds": thresholds}

    def _surface_fading(self, depth: float) -> tuple[float, bool]:
        """How much the surfaces seen over a range of distances fade over ``depth`` by their
        own water fit (``assess_water``), and whether their attenuation is determined."""
        assessment = self.assess_water() or {}
        determined = all(assessment.get("fit_determined", {}).get("sigma_attn", [False]))
        return 1.0 - math.exp(-max(assessment.get("surface_fit", {}).get(
            "sigma_attn", [0.0])) * depth), determined

    # -------------------------------------------------------------------- loop
    @torch.no_grad()
    def _surface_data(self, seed: int, voxel_factors: Sequence[float] = (1.0,)
                      ) -> list[SurfaceData | str]:
        """Surface data of one set of rendered training rays, grouped at ``medium.refit_voxel``
        times each of ``voxel_factors``."""
        c, model = self.config, self.model
        point_ids = None
        if c.medium.refit_grouping == "points":
            found = correspondence_rays(self.data, self.render_batch, c.medium.refit_rays // 4,
                                        c.medium.refit_rays, seed, c.medium.refit_opacity)
            rays, depth, opacity, point_ids = (found.rays, found.depth, found.opacity,
                                               found.point_ids)
        else:
            rays = self.data.fixed_subset(c.medium.refit_rays, seed)
            rendered = self.render_batch(rays)
            depth, opacity = rendered["depth_median"], rendered["opacity"]
        diagonal = float(torch.linalg.norm(model.box.box_max - model.box.box_min))
        open_water = refit_open_water_opacity(c.medium, rays.open_water is not None,
                                              self._progress())
        below = below_horizon(rays.directions, model.scene.get("up"), c.medium.horizon_margin)
        # the first grouping is the refit's own; other factors regroup the same pixels by voxel
        return [surface_data(rays.origins, rays.directions, rays.rgb, depth, opacity,
                             factor * c.medium.refit_voxel * diagonal, c.medium.refit_opacity,
                             open_water_opacity=open_water, open_water=rays.open_water,
                             below_horizon=below, point_ids=point_ids if i == 0 else None)
                for i, factor in enumerate(voxel_factors)]

    def _fit_surfaces(self, data: SurfaceData, start: dict) -> tuple[WaterFit, SurfaceData]:
        """The water fitted to ``data`` from ``start`` with the medium's refit settings, and
        the pixels it used (``water_fit.fit_surfaces``)."""
        medium = self.config.medium
        return fit_surfaces(data, start, medium.refit_steps, self.model.medium.colour_max,
                            medium.dark_pixel_bound, medium.balance_brightness,
                            medium.refit_trim)

    @torch.no_grad()
    def refit_water(self) -> dict:
        """Refit the global water to the training images on the model's own geometry.

        Early in training the water settles wherever it started and fog in the object field
        makes up for the rest; on surfaces the model already places well (opacity above
        ``medium.refit_opacity``), the same surface seen at several ranges pins the water
        down (``seathru.nerf.water_fit``). The fitted values replace the medium's and its
        optimiser state is reset. Returns a record of what was done (for selection.json).
        """
        model = self.model
        record = {"step": self.step, "progress": round(self._progress(), 4)}
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
        surfaces and its robust 95% half-widths (``water_uncertainty.robust_halfwidths``: statistical and
        systematic parts), normalised units; ``determined`` judges the interval around the
        ``trained`` values (``water_uncertainty.interval_determined``; default: the model's water),
        ``fit_determined`` the surface fit's own half-widths. None when the medium is neither
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
        beyond = far_surface_range(data.ranges) if data.open_water_below_horizon else None
        spread = robust_halfwidths(fit, data.ranges, data.observed, data.ids, data.groups,
                                   colour_max=model.medium.colour_max,
                                   open_water_beyond=beyond,
                                   dark=data.dark if medium.dark_pixel_bound else None,
                                   range_error=medium.interval_range_error,
                                   min_relative=medium.interval_floor,
                                   regrouped=[(d.ranges, d.observed, d.ids, d.groups)
                                              for d in regrouped if not isinstance(d, str)])
        return {"surface_fit": {k: getattr(fit, k) for k in WATER_KEYS},
                "halfwidth95": spread.halfwidth, "fit_determined": spread.determined,
                "determined": interval_determined(trained or model.water_parameters(), fit,
                                                  spread.halfwidth),
                "pixels": fit.pixels, "left_out": offered - len(data.ranges),
                "groups": fit.groups,
                "effective_samples": spread.effective_samples,
                **({"open_water_beyond": beyond} if beyond is not None else {})}

    def _progress(self) -> float:
        c = self.config
        budget = c.max_minutes * 60.0 if c.max_minutes and c.max_minutes > 0 else math.inf
        return max(self.step / c.step_limit, self.elapsed_s / budget)

    def _say(self, text: str) -> None:
        if self.callbacks.message:
            self.callbacks.message(text)

    def _loss(self, batch: RayBatch, depth: tuple[RayBatch, torch.Tensor] | None = None
              ) -> tuple[torch.Tensor, torch.Tensor, dict]:
        """The step's loss on ``batch``; ``depth``: sparse-depth rays and their ranges, rendered
        in the same pass (the colour losses see ``batch`` alone)."""
        c = self.config
        rays = batch if depth is None else _concatenated(batch, depth[0])
        out = self.model(rays.origins, rays.directions, rays.near, rays.far,
                         generator=self.generator)
        render, count = out.render, len(batch)
        recon = reconstruction_loss(render.rgb[:count], batch.rgb, c.loss.recon_eps)
        loss = recon
        if out.coarse is not None:
            loss = loss + reconstruction_loss(out.coarse.rgb[:count], batch.rgb,
                                              c.loss.recon_eps)
        if depth is not None:
            loss = loss + c.loss.sparse_depth_weight * sparse_depth_loss(
                render.depth_mean[count:], depth[1])
        ramp = min(1.0, max(0.0, (self._progress() - c.loss.transmittance_prior_start) / 0.1)) \
            if c.loss.transmittance_prior_start > 0 else 1.0
        if c.loss.transmittance_prior_weight > 0 and ramp > 0:
            loss = loss + ramp * c.loss.transmittance_prior_weight * transmittance_prior(
                render.transmittance[:, -1])
        # Only for water whose veiling light varies with direction: uniform open water is
        # already left empty by a global medium, and there the mask's border blocks (far, hazy
        # seabed) would be emptied wrongly (the demo lost 0.9 dB restored and 0.23 of depth
        # correlation); real open water is filled with floaters without it (d3_reef).
        if c.loss.open_water_weight > 0 and batch.open_water is not None \
                and self.model.medium.mode in DIRECTIONAL_MODES and bool(batch.open_water.any()):
            opacity = 1.0 - render.transmittance[:count, -1]
            loss = loss + c.loss.open_water_weight * opacity[batch.open_water].mean()
        if c.loss.distortion_weight > 0 and out.s_edges is not None:
            loss = loss + c.loss.distortion_weight * distortion_loss(render.weights, out.s_edges)
        if c.loss.density_tv_weight > 0 and c.field.kind == "grid":
            loss = loss + c.loss.density_tv_weight * total_variation_3d(
                self.model.field.density.raw, 8192, self.generator)
        return loss, mse(render.rgb[:count].detach(), batch.rgb), {}

    def run(self) -> TrainResult:
        c = self.config
        model = self.model
        model.train()
        budget = c.max_minutes * 60.0 if c.max_minutes and c.max_minutes > 0 else math.inf
        run_start = time.perf_counter()
        self._eval_seconds = 0.0  # held-out evaluation for the log: not training time
        base_elapsed, base_step = self.elapsed_s, self.step
        stopped_by = "steps"
        acc_loss = acc_mse = 0.0
        acc_n = 0
        # Resume: the stage follows the checkpoint's progress.
        swapped = model.set_stage(model.stage_for_progress(self._progress()))
        self._swap_parameters(swapped)
        model.refresh_occupancy()
        self._take_snapshot()
        last_test = None
        next_quality = c.quality_snapshot_first_s
        while 0 < next_quality <= self.elapsed_s:
            next_quality *= 2.0
        while self.step < c.step_limit:
            self.elapsed_s = base_elapsed + (time.perf_counter() - run_start - self._eval_seconds)
            if self.elapsed_s >= budget:
                stopped_by = "time"
                break
            progress = self._progress()
            stage = model.stage_for_progress(progress)
            if stage != int(model.stage):
                self._swap_parameters(model.set_stage(stage))
                model.refresh_occupancy()
                self._take_snapshot()
                if c.field.kind == "grid":
                    self._say(f"step {self.step}: grids upsampled to stage {stage} (density "
                              f"{c.field.density_res[stage]}, planes {c.field.plane_res[stage]})")
            refits_due = sum(1 for at in c.medium.refit_at if progress >= at)
            if len(self.water_refits) < refits_due:
                self.water_refits.append(self.refit_water())
                self._take_snapshot()
            if self.view_selection is None and progress >= c.field.view_select_at:
                self.view_selection = self.select_view_dependence()
                self._say(f"step {self.step}: view-dependent colour "
                          f"{self.view_selection['chosen']}: {self.view_selection['reason']}")
            if self.selection is None and progress >= c.medium.auto_select_at:
                self.selection = self.select_medium()
                self._say(f"step {self.step}: medium '{self.selection['chosen']}': "
                          f"{self.selection['reason']}")
            self._set_lr(progress)
            model.set_progress(progress)
            if self.step % c.sampler.occupancy_refresh_every == 0:
                model.refresh_occupancy()

            if self._threads is not None:
                self._threads.before_step()
            outcome = self._optimise_once()
            if outcome is None:
                continue
            loss, batch_mse = outcome
            self.step += 1
            if self._threads is not None:
                self._threads.after_step()
            loss_value, mse_value = float(loss.detach()), float(batch_mse)
            acc_loss += loss_value
            acc_mse += mse_value
            acc_n += 1
            if self.step % c.snapshot_every == 0:
                self._take_snapshot()

            self.elapsed_s = base_elapsed + (time.perf_counter() - run_start - self._eval_seconds)
            run_steps = self.step - base_step
            rate = run_steps / max(1e-9, time.perf_counter() - run_start)
            if self.callbacks.progress:
                self.callbacks.progress(self.step, {
                    "loss": loss_value, "psnr": psnr_from_mse(mse_value),
                    "rays_per_s": rate * c.batch_rays, "medium": model.medium.mode,
                    "progress": self._progress()})
            final = self.step >= c.step_limit
            is_eval = self.step in self._eval_steps or final
            if is_eval or self.step % c.log_every == 0:
                test = self.test_psnr() if is_eval else None
                last_test = test if test is not None else last_test
                self._append_log(acc_loss / acc_n, acc_mse / acc_n, test)
                acc_loss = acc_mse = 0.0
                acc_n = 0
            if c.checkpoint_every and self.step % c.checkpoint_every == 0 and not final:
                self._checkpoint()
            if 0 < next_quality <= self.elapsed_s and not final:
                self._quality_snapshot()
                while next_quality <= self.elapsed_s:
                    next_quality *= 2.0

        self.elapsed_s = base_elapsed + (time.perf_counter() - run_start - self._eval_seconds)
        if self.view_selection is None:
            self.view_selection = {"requested": "auto", "chosen": "off",
                                   "reason": "the run ended before field.view_select_at: "
                                             "colour without the view direction"}
        if self.selection is None:  # stopped before the decision point: decide now
            self.selection = self.select_medium()
            self._say(f"medium '{self.selection['chosen']}': {self.selection['reason']}")
        if not self.log or self.log[-1]["step"] != self.step or self.log[-1]["test_psnr"] is None:
            test = self.test_psnr()
            last_test = test
            if acc_n:
                self._append_log(acc_loss / acc_n, acc_mse / acc_n, test)
            elif self.log and self.log[-1]["step"] == self.step:
                self.log[-1]["test_psnr"] = test
            else:
                self._append_log(float("nan"), float("nan"), test)
        if c.quality_snapshot_first_s > 0:
            self._quality_snapshot()
        self._checkpoint()
        run_time = time.perf_counter() - run_start
        run_steps = self.step - base_step
        return TrainResult(steps=self.step, elapsed_s=self.elapsed_s, stopped_by=stopped_by,
                           log=self.log, selection=self.selection, rollbacks=self.rollbacks,
                           final_test_psnr=last_test,
                           train_step_rate=run_steps / max(run_time, 1e-9),
                           rays_per_second=run_steps * c.batch_rays / max(run_time, 1e-9))

    def _quality_snapshot(self) -> None:
        """Let the step measure the model on whole held-out images; not training time."""
        if self.callbacks.quality_snapshot is None:
            return
        start = time.perf_counter()
        self.callbacks.quality_snapshot(self.step, self.elapsed_s)
        self._eval_seconds = getattr(self, "_eval_seconds", 0.0) + time.perf_counter() - start

    def _optimise_once(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """One Adam step on a fresh batch; None if the NaN guard rolled back instead."""
        batch = self.data.sample(self.config.batch_rays, self.generator)
        if self.callbacks.batch_hook is not None:
            batch = self.callbacks.batch_hook(self.step, batch)
        depth = None
        if self.config.loss.sparse_depth_weight > 0 and self.data.depth_rays is not None:
            depth = self.data.depth_rays.sample(self.config.loss.sparse_depth_rays,
                                                self.generator)
        loss, batch_mse, _ = self._loss(batch, depth)
        if not bool(torch.isfinite(loss)):
            self._rollback("non-finite loss")
            return None
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self._mask_density_gradients()
        self._hold_refitted_water()
        params = [p for g in self.optimizer.param_groups for p in g["params"]
                  if p.grad is not None]
        grad_norm = torch.nn.utils.get_total_norm([p.grad for p in params])
        if not bool(torch.isfinite(grad_norm)):
            self._rollback("non-finite gradient")
            return None
        self.optimizer.step()
        return loss, batch_mse

    def _append_log(self, loss: float, batch_mse: float, test: float | None) -> None:
        row = {"step": self.step, "wall_time_s": round(self.elapsed_s, 3), "loss": loss,
               "train_psnr": psnr_from_mse(batch_mse) if batch_mse == batch_mse else None,
               "test_psnr": test}
        self.log.append(row)
        if self.callbacks.log_row:
            self.callbacks.log_row(row)

    def _checkpoint(self) -> None:
        if self.callbacks.checkpoint:
            self.callbacks.checkpoint(self.checkpoint_state())


class ThreadTuner:
    """Picks the faster of ``max_threads`` and 1 CPU thread, measured on real steps.

    On a shared machine two OpenMP threads can be several times slower than one (each parallel
    region waits for a core that someone else holds); on an idle one they are faster. Every
    ``period`` steps, ``probe`` steps run with each setting and the faster one is kept.
    """

    def __init__(self, max_threads: int, probe: int = 4, period: int = 300):
        self.options = [max_threads, 1] if max_threads > 1 else [max_threads]
        self.probe, self.period = probe, period
        self.count = 0
        self.times: dict[int, list[float]] = {}
        self.current = max_threads
        self._start = 0.0

    def _phase(self) -> int | None:
        position = self.count % self.period
        start = 3  # skip the first steps of a run (allocations, caches)
        if len(self.options) < 2 or not start <= position < start + 2 * self.probe:
            return None
        return self.options[(position - start) // self.probe]

    def before_step(self) -> None:
        threads = self._phase()
        if threads is not None and threads != torch.get_num_threads():
            torch.set_num_threads(threads)
        self._start = time.perf_counter()

    def after_step(self) -> None:
        threads = self._phase()
        if threads is not None:
            self.times.setdefault(threads, []).append(time.perf_counter() - self._start)
        self.count += 1
        if threads is not None and self._phase() is None:  # probe window over: choose
            best = min(self.options, key=lambda n: sorted(self.times.get(n, [math.inf]))[
                len(self.times.get(n, [0])) // 2])
            self.current = best
            torch.set_num_threads(best)
            self.times = {}


def _concatenated(a: RayBatch, b: RayBatch) -> RayBatch:
    """The rays of ``a`` then ``b`` in one batch (open-water flags where ``a`` has them)."""
    water = None
    if a.open_water is not None:
        water = torch.cat([a.open_water, b.open_water if b.open_water is not None
                           else torch.zeros(len(b), dtype=torch.bool, device=a.rgb.device)])
    return RayBatch(*(torch.cat([getattr(a, k), getattr(b, k)]) for k in
                      ("origins", "directions", "near", "far", "rgb")), water)


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
    ``water_fit.surface_data`` (0: no open water): the photographs' open water needs no
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


def _resample_like(value: torch.Tensor, shape) -> torch.Tensor:
    """Resample an optimiser moment to a parameter's new grid shape (corner aligned; a convex
    combination, so second moments stay non-negative)."""
    mode = "trilinear" if value.dim() == 5 else "bilinear"
    return torch.nn.functional.interpolate(value, size=tuple(shape[2:]), mode=mode,
                                           align_corners=True)


def _to_cpu(obj):
    if torch.is_tensor(obj):
        return obj.detach().cpu()
    if isinstance(obj, dict):
        return {k: _to_cpu(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_to_cpu(v) for v in obj]
    if isinstance(obj, tuple):
        return tuple(_to_cpu(v) for v in obj)
    return obj
