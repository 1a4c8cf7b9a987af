"""The training loop: Adam with warm-up and decay, coarse-to-fine grids, medium model selection,
a NaN/Inf guard, held-out evaluation, checkpoints. No file I/O: the step passes callbacks.

Progress. Training stops at ``config.step_limit`` steps or after ``config.max_minutes``,
whichever comes first (by default only the time budget limits it), and every schedule
(learning-rate decay, grid upsampling, the medium decision) follows ``progress = max(step /
step_limit, elapsed / budget)``, so a run cut short by its time budget still decays its learning
rate and reaches the finest grid: the model adapts to the machine it runs on.
``elapsed`` is training time: the held-out evaluations for the log are not counted (they are
also left out of ``wall_time_s`` in the log), the medium trial and checkpoints are.

Medium (``medium.mode=auto``) and view-dependent colour: ``seathru.nerf.selection``; the water
refitted on the model's surfaces: ``seathru.nerf.water_refit``. Losses: the paper's
reconstruction loss on linear data, its transmittance prior, mip-NeRF 360's distortion loss
(keeps each ray's object weight in one compact surface, so fog in the object field does not
stand in for water).
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
from typing import Callable

import torch

from seathru.errors import PipelineError
from seathru.nerf.config import TrainConfig, resolve_batch_rays
from seathru.nerf.losses import (distortion_loss, mse, psnr_from_mse, reconstruction_loss,
                                 sparse_depth_loss, total_variation_3d, transmittance_prior)
from seathru.nerf.model import SeaThruModel
from seathru.nerf.rays import RayBatch, RayDataset
from seathru.nerf.medium import DIRECTIONAL_MODES
from seathru.nerf.selection import ModelSelection
from seathru.nerf.water_refit import WaterRefitting

CHECKPOINT_FORMAT = "seathru-train-checkpoint/1"


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


class Trainer(ModelSelection, WaterRefitting):
    """The training loop over a model and its rays; the model choices are
    ``seathru.nerf.selection.ModelSelection``'s, the water refits
    ``seathru.nerf.water_refit.WaterRefitting``'s."""

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
        self._medium_decision_at = self.medium_decision_progress()
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

    # -------------------------------------------------------------------- loop
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

        def clock() -> float:
            """Training seconds so far (held-out evaluations for the log left out)."""
            return base_elapsed + (time.perf_counter() - run_start - self._eval_seconds)

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
            self.elapsed_s = clock()
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
                self.elapsed_s = clock()
                self._skip_refits_passed_meanwhile()
            if self.view_selection is None and progress >= c.field.view_select_at:
                self.view_selection = self.select_view_dependence()
                self._say(f"step {self.step}: view-dependent colour "
                          f"{self.view_selection['chosen']}: {self.view_selection['reason']}")
            if self.selection is None and progress >= self._medium_decision_at:
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

            self.elapsed_s = clock()
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

        self.elapsed_s = clock()
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
