"""The SeaThru-NeRF model: object field + water medium + sampler + medium-aware renderer.

Default (``field="grid"``, ``sampler="occupancy"``): per ray, 64 + 16 candidate bins (linear in
the scene box, 1/t beyond) are weighted by the field's own density, 16 contiguous intervals are
drawn from that histogram, the density grid gives sigma at their midpoints, the tri-plane
colour is decoded only where a sample's weight matters, and ``render_seathru`` integrates
objects and water in closed form (water before, between and after the intervals). The paper
baseline (``field="mlp"``, ``sampler="hierarchical"``) uses a PE MLP with 128 + 32 samples.

``SeaThruModel(config, scene)`` renders rays (``forward``); ``from_checkpoint`` rebuilds it from
``model.pt`` or a training checkpoint (the dict ``torch.load(path, weights_only=True)`` returns);
``water_parameters`` gives the fitted water in normalised units.

``scene`` is a plain dict (it goes into ``model.pt``)::

    {"box_min": [3], "box_max": [3],        # scene box, normalised units (rays.covisible_box)
     "near": float, "far": float,           # camera file bounds
     "typical_range": float,                # a representative camera-to-scene distance
     "normalisation": {"centre": [3], "scale": float}}
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn
from torch.profiler import record_function

from seathru.nerf.config import TrainConfig
from seathru.nerf.fields import GridField, MLPField, SceneBox
from seathru.nerf.medium import DIRECTIONAL_MODES, Medium
from seathru.nerf.rays import ray_box_intersect
from seathru.nerf.rendering import RayRender, render_seathru
from seathru.nerf.sampler import (candidate_edges, lookup_nearest, merge_edges,
                                  normalised_distance, occupancy_weights, sample_pdf,
                                  stratified_edges)

MODEL_FORMAT = "seathru-model/2"  # /2: nested config sections; /1 files still load


@dataclass
class ModelOutput:
    render: RayRender               # the final rendering
    t_edges: Tensor                 # (R, S+1)
    s_edges: Tensor | None = None   # (R, S+1) normalised ray coordinate of the edges
    coarse: RayRender | None = None  # hierarchical sampler: the coarse pass


def initial_medium_mode(config: TrainConfig, scene: dict | None = None) -> str:
    """The medium a run starts with: ``auto`` starts ``veiling`` where the training images'
    open water changes colour with view direction (``scene["open_water_direction_spread"]``
    above ``medium.auto_veiling_spread``), else ``global``."""
    if config.medium.mode != "auto":
        return config.medium.mode
    spread = float((scene or {}).get("open_water_direction_spread", 0.0))
    return "veiling" if spread > config.medium.auto_veiling_spread else "global"


#: ``sampler.far_factor`` auto where the photographs show open water of one colour
AUTO_FAR_FACTOR = 3.0


def far_bound_choice(config: TrainConfig, scene: dict | None = None) -> dict[str, Any]:
    """How far along each ray the object field is sampled, as a multiple of the camera's far
    bound: ``sampler.far_factor``, or with 0 (auto) :data:`AUTO_FAR_FACTOR` where the training
    photographs show open water (``scene["open_water_image_share"]`` above
    ``medium.auto_open_water_share``) and the water starts ``global``
    (:func:`initial_medium_mode`), else 1.

    Why: the far bound comes from the sparse points, and the far hazy seabed that recedes into
    open water has few of them, so the object field puts that seabed in front of the bound and
    the restoration divides it by too little water. Sampled to 3x the bound, the demo's
    restored photographs gain 0.5-1.0 dB, but its held-out views lose 0.6-0.9 dB on their near
    surfaces (benchmarks/results/far_factor_photos.md), so auto is not the default. Where the
    veiling light changes with direction (``veiling``; d3_reef) the object field beyond the
    bound fills the open water; without open water in view the bound already holds the scene.

    Returns:
        ``{"requested", "chosen", "reason"}`` (selection.json's ``far_factor``).

    Example::

        far_bound_choice(config, {"open_water_image_share": 0.22,
                                  "open_water_direction_spread": 0.045})["chosen"]   # 3.0
    """
    requested = float(config.sampler.far_factor)
    if requested:
        return {"requested": requested, "chosen": requested,
                "reason": f"sampler.far_factor {requested:g} (0: auto)"}
    scene = scene or {}
    share = float(scene.get("open_water_image_share", 0.0))
    mode = initial_medium_mode(config, scene)
    if share <= config.medium.auto_open_water_share:
        chosen, why = 1.0, (f"{100 * share:.1f}% of the training pixels are open water: the "
                            f"sparse points bound the scene")
    elif mode == "off":
        chosen, why = 1.0, "no water model (medium.mode off): no veiling light to go by"
    elif mode != "global":
        chosen, why = 1.0, (f"the water starts {mode} (its veiling light changes with "
                            f"direction): beyond the bound the object field would fill the "
                            f"open water")
    else:
        chosen, why = AUTO_FAR_FACTOR, (f"{100 * share:.1f}% of the training pixels are open "
                                        f"water of one colour: far seabed may lie beyond the "
                                        f"sparse points")
    return {"requested": "auto", "chosen": chosen, "reason": why}


def _replace_parameter(root: nn.Module, name: str, value: Tensor) -> nn.Parameter:
    *path, attr = name.split(".")
    parent = root
    for part in path:
        parent = parent[int(part)] if part.isdigit() else getattr(parent, part)
    new = nn.Parameter(value.detach().clone().contiguous(), requires_grad=True)
    if attr.isdigit():
        parent[int(attr)] = new
    else:
        setattr(parent, attr, new)
    return new


class SeaThruModel(nn.Module):
    def __init__(self, config: TrainConfig, scene: dict):
        super().__init__()
        config.validate()
        self.config = config
        self.scene = {k: v for k, v in scene.items()}
        self.box = SceneBox(scene["box_min"], scene["box_max"])
        extent = (self.box.box_max - self.box.box_min).tolist()
        typical = float(scene.get("typical_range") or max(extent))
        if config.field.kind == "grid":
            diagonal = math.sqrt(sum(e * e for e in extent))
            init_density = -math.log(1.0 - config.field.init_opacity) / diagonal
            self.field = GridField(extent, config.field.density_res[0], config.field.plane_res[0],
                                   config.field.plane_coarse_res, config.field.plane_channels,
                                   config.field.decoder_hidden, config.field.view_dependent_colour,
                                   config.field.colour_max, init_density, config.field.density_coarse_res)
        else:
            # the paper's MLP is view-dependent unless told otherwise: no trial for it
            self.field = MLPField(config.field.mlp_width, config.field.mlp_depth, colour_max=config.field.colour_max,
                                  view_dependent=config.field.view_dependent_colour != "off")
        sigma_init = config.medium.sigma_init or 0.5 / typical
        c_med = scene.get("c_med_init", [0.1, 0.2, 0.3])
        if config.field.kind == "grid":
            self.field.decoder.init_colour(c_med)
        self.medium = Medium(initial_medium_mode(config, scene), sigma_init, c_med, config.field.colour_max)
        self.far_bound = far_bound_choice(config, scene)
        self.register_buffer("stage", torch.tensor(0))
        self._occupancy: Tensor | None = None
        self.uniform_mix = config.sampler.uniform_mix  # the trainer anneals it

    def set_progress(self, progress: float) -> None:
        """Training progress in [0, 1]: anneals the share of uniformly placed samples."""
        c = self.config
        fade = min(1.0, progress / c.sampler.uniform_mix_until) if c.sampler.uniform_mix_until > 0 else 1.0
        self.uniform_mix = c.sampler.uniform_mix_start + (c.sampler.uniform_mix - c.sampler.uniform_mix_start) * fade

    # ------------------------------------------------------------------ construction / io
    @classmethod
    def from_checkpoint(cls, ckpt: dict, device="cpu") -> "SeaThruModel":
        """Rebuild from ``model.pt`` ({"format", "config", "state_dict", "scene"}) or from a
        training checkpoint ({"config", "model", "scene", ...})."""
        if "state_dict" in ckpt:
            state = ckpt["state_dict"]
        elif "model" in ckpt:
            state = ckpt["model"]
        else:
            raise ValueError("checkpoint has neither 'state_dict' nor 'model'")
        model = cls(TrainConfig.from_dict(ckpt["config"]), ckpt["scene"])
        model.load_state_dict_resizing(state)
        model.to(device)
        model.eval()
        return model

    def export(self) -> dict:
        """The ``model.pt`` dict (loadable with ``torch.load(weights_only=True)``)."""
        return {"format": MODEL_FORMAT, "config": self.config.to_dict(),
                "state_dict": {k: v.detach().cpu() for k, v in self.state_dict().items()},
                "scene": self.scene}

    def load_state_dict_resizing(self, state: dict) -> None:
        """load_state_dict after giving grid parameters the shapes found in ``state``."""
        own = dict(self.named_parameters())
        state = _split_decoder_view_columns(state, own)
        for name, value in state.items():
            if name in own and tuple(own[name].shape) != tuple(value.shape):
                _replace_parameter(self, name, torch.empty(value.shape, dtype=own[name].dtype,
                                                           device=own[name].device))
        self.load_state_dict(state)
        self._occupancy = None

    # ------------------------------------------------------------------ coarse to fine
    def stage_for_progress(self, progress: float) -> int:
        return sum(1 for start in self.config.field.stage_starts if progress >= start)

    def set_stage(self, stage: int) -> dict[str, tuple[nn.Parameter, nn.Parameter]]:
        """Resample the grids to ``stage``'s resolution; returns {name: (old, new) parameter}."""
        if stage == int(self.stage):
            return {}
        if self.config.field.kind != "grid":
            self.stage.fill_(stage)
            return {}
        values = self.field.resize(self.config.field.density_res[stage], self.config.field.plane_res[stage])
        own = dict(self.named_parameters())
        swapped = {}
        for short, value in values.items():
            name = f"field.{short}"
            swapped[name] = (own[name], _replace_parameter(self, name, value))
        self.stage.fill_(stage)
        self._occupancy = None
        return swapped

    # ------------------------------------------------------------------ rendering
    def refresh_occupancy(self) -> None:
        """Recompute the cached occupancy grid (``occupancy_lookup="grid"`` only)."""
        if self.config.field.kind == "grid" and self.config.sampler.occupancy_lookup == "grid":
            self._occupancy = self.field.occupancy_density(self.config.sampler.occupancy_dilate)
        else:
            self._occupancy = None

    def _split_distance(self, origins: Tensor, dirs: Tensor, near: Tensor) -> Tensor:
        t_in, t_out = ray_box_intersect(origins, dirs, self.box.box_min, self.box.box_max)
        return torch.where(t_out >= torch.maximum(t_in, near), t_out, near)

    def ray_interval(self, near: Tensor, far: Tensor) -> tuple[Tensor, Tensor]:
        """Where the object field is sampled along rays with the cameras' bounds ``near``,
        ``far`` (R,): from ``near`` to ``far`` times the far factor (:func:`far_bound_choice`;
        the water before and after is integrated in closed form either way)."""
        return near, far * self.far_bound["chosen"]

    def forward(self, origins: Tensor, dirs: Tensor, near: Tensor, far: Tensor,
                generator: torch.Generator | None = None) -> ModelOutput:
        """Render rays: origins, dirs (R, 3) (unit), near, far (R,). ``generator``: jitter the
        samples (training); None: deterministic."""
        sigma_attn, sigma_bs, c_med = self.medium(dirs)
        # the candidates are linear up to the box's exit but never past the camera's own far
        # bound, whatever the far factor: beyond it they go linear in 1/t, so a widened
        # interval does not thin the candidates on the near surfaces
        t_split = torch.minimum(self._split_distance(origins, dirs, near), far)
        near, far = self.ray_interval(near, far)
        if self.config.sampler.kind == "occupancy":
            return self._forward_occupancy(origins, dirs, near, far, t_split, generator,
                                           (sigma_attn, sigma_bs, c_med))
        return self._forward_hierarchical(origins, dirs, near, far, t_split, generator,
                                          (sigma_attn, sigma_bs, c_med))

    def _jitter(self, rays: int, count: int, generator, device) -> Tensor | None:
        if generator is None or count <= 0:
            return None
        return torch.rand(rays, count, generator=generator).to(device)

    def _render(self, sigma, rgb, t_edges, water) -> RayRender:
        c = self.config
        return render_seathru(sigma, rgb, t_edges, *water, method=c.medium.render_method,
                              water_before=c.medium.water_before, water_after=c.medium.water_after)

    def _forward_occupancy(self, origins, dirs, near, far, t_split, generator, water):
        c = self.config
        rays, samples = origins.shape[0], c.sampler.samples_per_ray
        with torch.no_grad(), record_function("seathru.sample"):
            candidates = candidate_edges(near, far, t_split, c.sampler.candidates_linear,
                                         c.sampler.candidates_disparity)
            mids = 0.5 * (candidates[:, 1:] + candidates[:, :-1])
            g = self.box.to_grid(origins[:, None, :] + dirs[:, None, :] * mids[..., None])
            if c.sampler.occupancy_lookup == "exact":
                density = self.field.density_at(g.reshape(-1, 3)).reshape(mids.shape)
            else:
                if self._occupancy is None or self._occupancy.device != origins.device:
                    self.refresh_occupancy()
                density = lookup_nearest(self._occupancy, g)
            weights = occupancy_weights(candidates, density)
            jitter = self._jitter(rays, samples - 1, generator, origins.device)
            mix = self.uniform_mix if self.training else c.sampler.uniform_mix
            t_edges = sample_pdf(candidates, weights, samples, mix, jitter)
            deltas = t_edges[:, 1:] - t_edges[:, :-1]
            mids = t_edges[:, :-1] + 0.5 * deltas
            g = self.box.to_grid((origins[:, None, :] + dirs[:, None, :] * mids[..., None])
                                 .reshape(-1, 3))
        with record_function("seathru.density"):
            sigma = self.field.density_at(g).reshape(rays, samples)
        with torch.no_grad():
            w = occupancy_weights(t_edges, sigma.detach())
            keep = (w.reshape(-1) > c.sampler.colour_weight_threshold).nonzero().squeeze(-1)
        with record_function("seathru.colour"):
            view = None
            if self.field.uses_view:
                view = dirs[:, None, :].expand(rays, samples, 3).reshape(-1, 3)[keep]
            colours = self.field.colour_at(g[keep], view)
            rgb = colours.new_zeros(rays * samples, 3).index_copy(0, keep, colours)
        with record_function("seathru.render"):
            render = self._render(sigma, rgb.reshape(rays, samples, 3), t_edges, water)
        share = c.sampler.candidates_linear / (c.sampler.candidates_linear + c.sampler.candidates_disparity)
        s_edges = normalised_distance(t_edges, near, far, t_split, share) \
            if self.training else None
        return ModelOutput(render=render, t_edges=t_edges, s_edges=s_edges)

    def _field_all(self, t_edges, origins, dirs):
        rays, samples = t_edges.shape[0], t_edges.shape[1] - 1
        mids = 0.5 * (t_edges[:, 1:] + t_edges[:, :-1])
        points = origins[:, None, :] + dirs[:, None, :] * mids[..., None]
        g = self.box.to_grid(points.reshape(-1, 3))
        view = dirs[:, None, :].expand(rays, samples, 3).reshape(-1, 3)
        sigma, rgb = self.field.density_and_colour(g, view)
        return sigma.reshape(rays, samples), rgb.reshape(rays, samples, 3)

    def _forward_hierarchical(self, origins, dirs, near, far, t_split, generator, water):
        c = self.config
        rays = origins.shape[0]
        n_disp = max(1, c.sampler.coarse_samples // 4)
        with torch.no_grad():
            coarse_edges = candidate_edges(near, far, t_split, c.sampler.coarse_samples - n_disp, n_disp)
            coarse_edges = stratified_edges(coarse_edges, self._jitter(
                rays, c.sampler.coarse_samples - 1, generator, origins.device))
        sigma, rgb = self._field_all(coarse_edges, origins, dirs)
        coarse = self._render(sigma, rgb, coarse_edges, water)
        with torch.no_grad():
            fine = sample_pdf(coarse_edges, coarse.weights.detach(), c.sampler.fine_samples, 0.0,
                              self._jitter(rays, c.sampler.fine_samples - 1, generator, origins.device))
            t_edges = merge_edges(coarse_edges, fine)
        sigma, rgb = self._field_all(t_edges, origins, dirs)
        return ModelOutput(render=self._render(sigma, rgb, t_edges, water), t_edges=t_edges,
                           coarse=coarse)

    # ------------------------------------------------------------------ water
    @torch.no_grad()
    def water_parameters(self, directions: Tensor | None = None) -> dict[str, Any]:
        """Fitted water in normalised units: {"mode", "sigma_attn", "sigma_bs", "c_med"} (lists
        of 3). View-dependent mode: the mean over ``directions`` (R, 3) (or over a fixed sphere
        of directions if None), with "min" and "max" dicts."""
        mode = self.medium.mode
        if directions is None:
            directions = _fibonacci_sphere(512, self.medium.raw_attn.device)
        if mode not in DIRECTIONAL_MODES:
            directions = directions[:1]
        directions = directions.to(self.medium.raw_attn.device)
        attn, bs, colour = self.medium(directions)
        values = {"sigma_attn": attn, "sigma_bs": bs, "c_med": colour}
        result: dict[str, Any] = {"mode": mode}
        result.update({k: [float(x) for x in v.mean(0)] for k, v in values.items()})
        if mode in DIRECTIONAL_MODES:
            result["min"] = {k: [float(x) for x in v.amin(0)] for k, v in values.items()}
            result["max"] = {k: [float(x) for x in v.amax(0)] for k, v in values.items()}
        return result


def _fibonacci_sphere(count: int, device) -> Tensor:
    i = torch.arange(count, dtype=torch.float32, device=device) + 0.5
    z = 1.0 - 2.0 * i / count
    r = torch.sqrt(1.0 - z * z)
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)


def scene_from_frames(frames, near: float, far: float, centre, scale: float, mean_rgb=None,
                min_fraction: float = 0.5) -> dict:
    """The ``scene`` dict of a model from the training frames of a camera file.

    The box is where most cameras look (``rays.covisible_box``); ``typical_range`` (twice the
    median frame near bound) sets the initial water coefficients; ``mean_rgb`` (the training
    images' mean colour) the initial veiling light; ``up`` (``seathru.geometry.upright``) the
    vertical, which tells open water above the horizon from far seabed below it.
    """
    import numpy as np

    from seathru.geometry.upright import estimate_up
    from seathru.nerf.rays import covisible_box

    box_min, box_max = covisible_box(frames, min_fraction=min_fraction)
    typical = 2.0 * float(np.median([f.near for f in frames]))
    scene = {"box_min": [float(v) for v in box_min], "box_max": [float(v) for v in box_max],
             "near": float(near), "far": float(far), "typical_range": typical,
             "normalisation": {"centre": [float(v) for v in centre], "scale": float(scale)}}
    if len(frames):
        up = estimate_up(np.stack([f.c2w_array for f in frames]))
        scene["up"] = None if up is None else list(up.vector)
        scene["up_method"] = "cameras disagree" if up is None else up.method
    if mean_rgb is not None:
        scene["c_med_init"] = [float(v) for v in mean_rgb]
    return scene


def _split_decoder_view_columns(state: dict, own: dict) -> dict:
    """Models saved before the decoder had its own ``view`` layer kept the direction's weights
    as the last 16 columns of the first layer: split them into the current layout."""
    first, view = "field.decoder.net.0.weight", "field.decoder.view.weight"
    if view in own and view not in state and first in state and first in own \
            and state[first].shape[1] == own[first].shape[1] + own[view].shape[1]:
        state = dict(state)
        weight = state[first]
        state[first], state[view] = weight[:, :own[first].shape[1]], \
            weight[:, own[first].shape[1]:]
    return state
