"""Every setting of the model and its training, as nested typed sections.

``TrainConfig`` is the train step's ``Settings``: its flags (``seathru train --help``), the
``train:`` section of config/config.yaml and the sheet's ``train.<section>.<key>`` options all
derive from these dataclasses (``seathru.settings``). Defaults are the fast CPU model; the paper
baseline is ``field.kind=mlp``, ``sampler.kind=hierarchical``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Literal

from seathru import settings
from seathru.settings import section, setting


@dataclass
class FieldConfig:
    """Object field: a density voxel grid and tri-plane colour, refined coarse to fine in stages."""

    kind: Literal["grid", "mlp"] = setting(
        "grid", help="grid (fast voxel density + tri-plane colour) or mlp (the paper's PE MLP)")
    density_res: list[int] = setting(default_factory=lambda: [96, 128, 160],
                                     help="density grid cells along the longest axis, per stage")
    plane_res: list[int] = setting(default_factory=lambda: [128, 256, 384],
                                   help="finest tri-plane resolution, per stage")
    stage_starts: list[float] = setting(default_factory=lambda: [0.08, 0.25],
                                        help="training progress at which stages 2, 3, ... start")
    plane_coarse_res: int = setting(48, help="resolution of the coarse tri-plane level")
    density_coarse_res: int = setting(32, help="resolution of the coarse density level")
    plane_channels: int = setting(8, help="feature channels per tri-plane")
    decoder_hidden: int = setting(32, help="width of the colour decoder")
    view_dependent_colour: Literal["auto", "on", "off"] = setting(
        "auto", help="object colour depends on view direction: on, off, or auto (grid field: "
                     "trained without it until field.view_select_at, then switched on only if "
                     "a trial with it does better than one without on held-out training rays "
                     "by field.view_margin_db; the MLP field: on)")
    view_select_at: float = setting(
        0.1, help="auto: progress at which view-dependent colour is decided (later, the rest "
                  "of the model has already made up for it with floaters and a short trial "
                  "cannot show what it adds: a tint of +-30% with direction gained 0.48-0.66 "
                  "dB at 0.1, 0.02-0.37 dB at 0.3; benchmarks/results/view_trial.md)")
    view_trial_share: float = setting(0.05, help="auto: share of the run each view-dependence "
                                                 "trial trains")
    view_margin_db: float = setting(
        0.5, help="auto: view-dependent colour is kept when it does better than without by "
                  "more than this (a half-trained model also uses the direction for what it "
                  "has not yet fit otherwise: Lambertian simulated dives gained up to 0.47 dB "
                  "in 45-s runs; fern -0.02 dB)")
    colour_max: float = setting(1.5, help="largest object colour (raised to 2x the 99.9th "
                                          "percentile of the training images)")
    init_opacity: float = setting(0.05, help="initial object opacity across the scene box")
    min_views: int = setting(2, help="density is only learnt where this many views look")
    mlp_width: int = setting(256, help="MLP field: hidden width")
    mlp_depth: int = setting(8, help="MLP field: hidden layers")


@dataclass
class SamplerConfig:
    """Where along each ray the object field is evaluated."""

    kind: Literal["occupancy", "hierarchical"] = setting(
        "occupancy", help="occupancy (density-grid histogram) or hierarchical (the paper's "
                          "coarse + fine)")
    far_factor: float = setting(
        1.0, help="the object field is sampled up to this multiple of each camera's far bound "
                  "(cameras.json: from the sparse points the image sees, and far hazy seabed "
                  "has few of them; beyond it the water is integrated in closed form); 0 = "
                  "auto: 3 where the photographs show open water whose veiling light is the "
                  "same in every direction (the water starts global), else 1. 3 on the demo: "
                  "restored photographs +0.5..+1.0 dB, held-out views -0.6..-0.9 dB "
                  "(benchmarks/results/far_factor_photos.md)")
    samples_per_ray: int = setting(16, help="object samples per ray (occupancy sampler)")
    candidates_linear: int = setting(64, help="candidate bins linear in the scene box")
    candidates_disparity: int = setting(16, help="candidate bins linear in 1/t beyond the box")
    uniform_mix: float = setting(0.1, help="final share of uniformly placed samples")
    uniform_mix_start: float = setting(1.0, help="share of uniform samples at the start")
    uniform_mix_until: float = setting(0.3, help="progress by which the share has fallen to "
                                                 "uniform_mix")
    occupancy_dilate: int = setting(1, help="dilation of the cached occupancy grid (cells)")
    occupancy_lookup: Literal["exact", "grid"] = setting(
        "exact", help="density lookup for the candidates: exact (trilinear) or grid (cached, "
                      "faster, less accurate)")
    occupancy_refresh_every: int = setting(8, help="steps between cached occupancy refreshes")
    colour_weight_threshold: float = setting(1e-4, help="colour is decoded only for samples "
                                                        "weighing more than this")
    coarse_samples: int = setting(128, help="hierarchical sampler: coarse samples per ray")
    fine_samples: int = setting(32, help="hierarchical sampler: fine samples per ray")


@dataclass
class MediumConfig:
    """The water: attenuation, backscatter and veiling light per colour channel."""

    mode: Literal["auto", "off", "global", "veiling", "view"] = setting(
        "auto", help="auto (the simplest model the images support), off (clear water / air), "
                     "global (one water per scene), veiling (global attenuation and "
                     "backscatter, veiling light by view direction: open water brighter "
                     "towards the surface), view (all of the water by view direction, as the "
                     "paper)")
    sigma_init: float = setting(0.0, help="initial attenuation and backscatter per normalised "
                                          "unit; 0 = 0.5 / typical range")
    render_method: Literal["exact", "paper"] = setting(
        "exact", help="exact (closed-form integral) or paper (the paper's discretisation)")
    water_before: bool = setting(True, help="integrate the water before the first sample")
    water_after: bool = setting(True, help="integrate the water after the last sample")
    veiling_light_init: bool = setting(True, help="start the veiling light c_med at the colour "
                                                  "of the smoothest image regions (open water, "
                                                  "far haze) instead of the mean image colour")
    refit_at: list[float] = setting(
        default_factory=lambda: [0.15, 0.4, 0.7, 0.9],
        help="training progress at which the water is refitted to the images on the model's "
             "own depth (variable projection); empty = never")
    hold_refitted: bool = setting(
        True, help="water values a refit determined are held there for the rest of the run "
                   "(trained on, they drift as fog in the object field stands in for the "
                   "water); false = they train on from the refitted value")
    hold_max_relative: float = setting(
        0.25, help="a refitted value is held only if its 95% half-width is below this share of "
                   "it (a loosely determined value trains on with the geometry)")
    refit_rays: int = setting(65536, help="training rays rendered for a water refit")
    refit_opacity: float = setting(0.9, help="a refit uses rays whose object opacity exceeds "
                                             "this (surfaces, not fog or open water)")
    refit_grouping: Literal["points", "voxels"] = setting(
        "voxels", help="refit: pixels are grouped by the voxel their surface point falls in "
                       "(voxels: refit_rays random pixels) or by the surface point they see "
                       "(points: a quarter of refit_rays find surface points, whose pixel in "
                       "every view that sees them is taken; closer on exact geometry, no "
                       "better on the demo, docs/water.md)")
    refit_trim: float = setting(
        3.5, help="refits and the final water assessment fit twice, the second time without "
                  "surface pixels whose residual lies more than this many robust standard "
                  "deviations from the median (surfaces placed at the wrong range: simulated "
                  "surveys' green and blue attenuation 10-15 points high with them, "
                  "docs/water.md; without the sparse-depth loss it neither gains nor loses "
                  "on six simulated surveys, but lowers green and blue attenuation on "
                  "some); 0 = fit once on every pixel")
    refit_deblur: bool = setting(
        True, help="refits and the final water assessment use the training images with the "
                   "blur of the pipeline's own demosaic and undistortion deconvolved (each "
                   "frame's blur_px in cameras.json; the model still trains on the images as "
                   "they are)")
    refit_voxel: float = setting(0.005, help="refit: surface points are grouped in voxels of "
                                             "this share of the scene box diagonal (voxel "
                                             "grouping, and the intervals' regrouping)")
    interval_range_error: float = setting(
        0.05, help="relative error of the model's depth that water.json's intervals allow for "
                   "(the fit is redone on ranges with this much more error and the move widens "
                   "the intervals; 3-5% on the demo against the true depth; 0 = exact depth)")
    interval_voxel_factors: list[float] = setting(
        default_factory=lambda: [0.5, 2.0],
        help="water.json's intervals also allow for the move of the fit when the surface "
             "pixels are grouped in voxels this many times refit_voxel (where the model places "
             "surfaces inconsistently between views the water depends on the grouping); "
             "empty = not")
    interval_unseen_veiling: bool = setting(
        True, help="without open water in view, water.json's intervals also allow for the "
                   "veiling light beyond the farthest surfaces, which only the curvature of "
                   "their backscatter with range shows, and for the attenuation's move with "
                   "it (transects, orbits; docs/water.md)")
    determined_ambiguity: float = setting(
        0.05, help="water.json flags a value as not determined by the views when the part of "
                   "its 95% interval that comes from what the images cannot tell apart (the "
                   "veiling light beyond the farthest surfaces with no open water in view; "
                   "open water that may be far seabed) exceeds this share of it, however "
                   "narrow the interval (the water benchmark's 5% goal); 1 = judged on the "
                   "interval's width alone (25%)")
    interval_floor: float = setting(
        0.01, help="least 95% half-width of each water value in water.json, as a share of it: "
                   "what the image values themselves are known to (black level, "
                   "linearisation); open water alone gives c_med to 0.01%")
    open_water_opacity: float = setting(
        0.1, help="rays below this object opacity meet no surface: their pixel is the veiling "
                  "light; with open water in the photographs (seathru.radiometry.open_water), "
                  "the rays they show as open water are taken instead, whatever the model's "
                  "opacity (0 = do not use open water)")
    horizon_margin: float = setting(
        5.0, help="open water in the photographs that looks more than this many degrees below "
                  "the horizon (the vertical the cameras imply: seathru.geometry.upright) may "
                  "be far seabed: where enough open water looks above it, only that pins "
                  "c_med; where none does, water.json's intervals allow for a surface behind "
                  "it (simulated orbits: all of their 'open water' was seabed 6-11 m away, "
                  "10-23% off the veiling light); negative = the horizon is not used")
    open_water_from: float = setting(
        1.1, help="where the photographs show no open water in view: progress from which "
                  "refits take the model's empty rays as open water (above 1, the default: "
                  "never; such rays are mostly holes in unfinished surfaces, whose colour put "
                  "c_med up to 6x off on simulated transects with an interval of +-10%); the "
                  "photographs' open water is used from the first refit")
    open_water_surfaces_from: float = setting(
        0.6, help="progress from which refits and the final water assessment take a pixel of "
                  "the photographs' open water that the model renders as an opaque surface "
                  "short of open_water_surface_share of the far bound as that surface, not "
                  "as the veiling light (turbid water's far seabed is smooth and fills the "
                  "top of the frame; the model, converged, places it); above 1 = never")
    open_water_surface_share: float = setting(
        0.9, help="see open_water_surfaces_from: nearer than this share of a ray's far bound "
                  "(the density a model puts at its far bound in real open water is not a "
                  "surface)")
    dark_pixel_bound: bool = setting(True, help="refits keep the backscatter below the darkest "
                                                "pixels at each range (Sea-thru's dark-pixel "
                                                "estimate)")
    balance_brightness: bool = setting(
        True, help="refits weight each surface voxel by its inverse clean colour, so that bright "
                   "surfaces do not set the attenuation alone (false: every pixel alike)")
    refit_noise_term: bool = setting(
        True, help="refits add back what fitting each surface voxel's clean colour takes out of "
                   "its residuals, the pull of texture that fades with range (docs/water.md, "
                   "\"The refit adds the term back\"; false: plain least squares)")
    refit_max_relative: float = setting(
        1.0, help="a refitted value replaces the current one only if its 95% half-width is "
                  "below this share of it (and the fit did not run to the edge of the "
                  "parameter space)")
    refit_steps: int = setting(300, help="most L-BFGS iterations of a water refit")
    auto_select_at: float = setting(0.8, help="auto: progress at which the model is chosen")
    auto_select_at_no_image_evidence: float = setting(
        0.4, help="auto: the same where the photographs show no open water and no colour "
                  "change with range along the COLMAP tracks (air, clear water): chosen late, "
                  "no water has too little of the budget left to recover from the switch "
                  "(fern: the train step's held-out PSNR 19.97 dB at 0.8, 20.54 at 0.4, "
                  "21.30 without water throughout; benchmarks/results/medium_decision_fern.md)")
    auto_trial_share: float = setting(0.05, help="auto: share of the run each trial trains")
    auto_margin_db: float = setting(0.5, help="auto: with evidence of water in the images, no "
                                              "water must beat the water by this many dB on "
                                              "held-out rays to be chosen")
    auto_race_without_evidence: bool = setting(
        False, help="auto: race the water against no water also where nothing shows water "
                    "(it must then win by auto_margin_no_evidence_db); off: no evidence, no "
                    "water (the race starts from a model trained with the water and favours it: "
                    "docs/water.md, \"No evidence, no water\")")
    auto_margin_no_evidence_db: float = setting(
        3.0, help="auto: with auto_race_without_evidence, the water must beat no water by this "
                  "many dB (a water model also fits what a half-trained scene gets wrong: fern, "
                  "in air, gained 1.7 dB from it)")
    auto_backscatter_evidence: float = setting(
        0.3, help="auto: a fitted water whose backscatter makes up this share of the image is "
                  "evidence of water (a scattering medium; 61-67% on the simulated surveys and "
                  "the default-water orbit, 15% on the clearest oceanic orbit, whose tracks "
                  "show its water; 20% for the water model fern, in air, trained)")
    auto_backscatter_in_front_evidence: float = setting(
        0.2, help="auto: ... and at least this share in front of the surfaces the rays meet (a "
                  "half-trained scene's fog behind its surfaces is no water: 6-15% in front on "
                  "toy clear-water scenes, 28-59% in the default water)")
    auto_surface_fading: float = setting(
        0.25, help="auto: a water fit on the model's own surfaces (independent of the trained "
                   "water) whose attenuation fades the colour by this share over the median "
                   "depth at its 95% interval's lower end is evidence of water even when not "
                   "determined (oceanic I orbits: 35-65%; clear toy orbits 0-5%, up to 42% by "
                   "the fit itself; fern 0%)")
    auto_veiling_brightness: float = setting(
        0.1, help="auto: open water is evidence of water only where it is at least this share "
                  "of the images' brightness (black open water shows no veiling light: clear "
                  "water, air or a black background)")
    auto_open_water_share: float = setting(0.05, help="auto: share of rays meeting no surface "
                                                      "(or a wall at the far bound) that counts "
                                                      "as open water in view")
    auto_backscatter_share: float = setting(0.01, help="auto: backscatter below this share of "
                                                       "the image is negligible")
    auto_attenuation: float = setting(0.02, help="auto: attenuation over the scene depth below "
                                                 "this is negligible")
    auto_track_t: float = setting(5.0, help="auto: the input colour's slope against range "
                                            "along COLMAP tracks counts as evidence of water "
                                            "when it is this many standard errors from 0 ...")
    auto_track_change: float = setting(
        0.2, help="auto: ... and changes the colour by more than this share over the median "
                  "range (measured over the tracks' windows: 35-50% in green and blue on "
                  "d3_reef, -69% in red on the survey demo, 10-11% on a simulated orbit in "
                  "clear water)")
    auto_veiling_spread: float = setting(
        0.1, help="auto: the water starts as veiling (else global) when the open water's "
                  "colour changes with view direction by more than this share of its "
                  "brightness (the spread of a linear fit of colour on direction over the "
                  "training images; measured 0.27 on d3_reef, 0.045 on the uniform water of "
                  "the survey demo, 0.004-0.05 on the other simulated surveys)")


@dataclass
class LossConfig:
    """Loss terms and their weights."""

    transmittance_prior_weight: float = setting(1e-4, help="weight of -log P(T_obj), pushing "
                                                           "object transmittance to 0 or 1")
    transmittance_prior_start: float = setting(0.0, help="progress at which the prior starts "
                                                         "(ramped in over 0.1)")
    open_water_weight: float = setting(
        0.05, help="weight of the object opacity of rays whose pixel is open water (smooth, "
                   "reaching the top of the frame: seathru.radiometry.open_water), while the "
                   "water's veiling light depends on direction (veiling, view) and open water "
                   "is more than medium.auto_open_water_share of the training pixels: open "
                   "water is the water's own colour, not a surface; 0 = off")
    distortion_weight: float = setting(0.01, help="weight of the distortion loss")
    sparse_depth_weight: float = setting(
        0.1, help="weight of the depth loss on rays towards COLMAP's sparse points (points seen "
                  "by 3+ training views): the relative error of the rendered expected depth, "
                  "which also clears fog in front of them (docs/water.md); 0 = off")
    sparse_depth_rays: int = setting(256, help="sparse-depth rays added to each step's batch")
    density_tv_weight: float = setting(0.0, help="weight of total variation on the density grid")
    recon_eps: float = setting(1e-3, help="eps of the relative reconstruction loss")


@dataclass
class OptimConfig:
    """Adam with warm-up and decay."""

    lr: float = setting(0.05, help="base learning rate of the feature grids")
    density_lr_scale: float = setting(4.0, help="density grid learning rate / lr")
    network_lr_scale: float = setting(0.1, help="decoder / MLP learning rate / lr")
    view_lr_scale: float = setting(
        1.0, help="colour decoder's view-direction weights learning rate / lr (they start at "
                  "zero and must show what they add within a short trial: "
                  "field.view_dependent_colour=auto)")
    medium_lr_scale: float = setting(1.0, help="water parameters' learning rate / lr")
    warmup_steps: int = setting(30, help="linear warm-up steps")
    lr_final_ratio: float = setting(0.05, help="final learning rate / initial")


# the step limit of a run without a time budget (``TrainConfig.steps`` 0)
DEFAULT_STEPS = 6000
# Settings that do not change the model being trained: a resumed run may change them.
RUNTIME_KEYS = ("max_minutes", "log_every", "checkpoint_every", "eval_rays", "snapshot_every",
                "nan_max_retries", "device", "progress", "quality_snapshot_first_s",
                "quality_snapshot_downscale")


@dataclass
class TrainConfig:
    """Training of the SeaThru-NeRF model: object field, sampler, water, losses, optimiser and
    the run's budget. Stops at ``steps`` or after ``max_minutes``, whichever comes first."""

    preset: Literal["auto", "fast", "balanced", "quality", "paper"] = setting(
        "auto", help="named settings beneath the explicit ones: auto (the capacity level "
                     "the scene and the budget can use: fast, balanced or quality; "
                     "seathru.nerf.capacity), fast (smaller grids, fewer samples), balanced "
                     "(the defaults), quality (finer grids, more samples), paper (the "
                     "paper-faithful configuration: PE MLP, hierarchical 128+32 samples, "
                     "view-dependent water)")
    field: FieldConfig = section(FieldConfig)
    sampler: SamplerConfig = section(SamplerConfig)
    medium: MediumConfig = section(MediumConfig)
    loss: LossConfig = section(LossConfig)
    optim: OptimConfig = section(OptimConfig)
    glare: Literal["auto", "off"] = setting(
        "auto", help="auto: where the same surfaces are brighter in the photographs that show "
                     "them next to the open water (fitted along COLMAP tracks beside range; "
                     "veiling glare in the port or local tone mapping, not the water), train "
                     "on the photographs divided by that brightening "
                     "(seathru.radiometry.glare); off: the photographs as they are")
    frame_colour: Literal["auto", "off"] = setting(
        "auto", help="auto: where the training photographs' colour casts differ from frame to "
                     "frame beyond what the points and their ranges explain along COLMAP "
                     "tracks (a camera's auto white balance), train on each brought to the "
                     "median frame's (seathru.eval.track_slope.frame_colour_offsets; never for "
                     "camera RAW, which ingest develops with one white balance); off: as "
                     "they are")
    steps: int = setting(0, help="maximum optimisation steps; 0: no step limit under a time "
                                 "budget (max_minutes decides), 6000 without one")
    passes: float = setting(0.0, help="training budget as passes over the training pixels: "
                                      "sets steps to passes x pixels / batch_rays (0 = use "
                                      "steps); max_minutes still applies")
    max_minutes: float = setting(3.0, help="wall-time budget in minutes; training stops "
                                           "gracefully and writes its outputs (0 = no limit)")
    batch_rays: int | None = setting(None, help="rays per step; automatic: 1024 on CPU, 4096 on "
                                                "CUDA (benchmarks/results/training_h200*.md)")
    seed: int = setting(0, help="random seed")
    device: str = setting("auto", help="auto | cpu | cuda[:N]")
    eval_rays: int = setting(4096, help="held-out test pixels for the PSNR in the log")
    log_every: int = setting(50, help="steps between train_log rows")
    checkpoint_every: int = setting(500, help="steps between checkpoints (0 = only at the end)")
    snapshot_every: int = setting(50, help="steps between in-memory snapshots (NaN rollback)")
    quality_snapshot_first_s: float = setting(
        5.0, help="the model is measured on whole held-out images after this many seconds of "
                  "training, then at twice the time each time, and at the end (quality against "
                  "time: train/snapshots.csv); 0 = never")
    quality_snapshot_downscale: int = setting(4, help="held-out images are measured at this "
                                                      "downscale in the snapshots")
    nan_max_retries: int = setting(5, help="rollbacks after NaN/Inf before giving up")
    progress: bool = setting(True, help="show a progress bar")

    def to_dict(self) -> dict:
        return settings.to_dict(self)


    @classmethod
    def from_dict(cls, data: dict) -> "TrainConfig":
        """From a nested dict (model.pt, checkpoints) or the flat dict of seathru-model/1."""
        if not any(isinstance(v, dict) for v in data.values()):
            data = _nest_flat_v1(data)
        return settings.from_mapping(cls, data)


    def identity(self) -> dict:
        """The settings that must match for a checkpoint to be resumed."""
        return {k: v for k, v in settings.flatten(self.to_dict()).items()
                if k not in RUNTIME_KEYS}

    @property
    def step_limit(self) -> float:
        """The most optimisation steps the run makes: ``steps``; with ``steps`` 0, none under a
        time budget (``inf``: the budget decides) and :data:`DEFAULT_STEPS` without one."""
        if self.steps > 0:
            return float(self.steps)
        return math.inf if self.max_minutes and self.max_minutes > 0 else float(DEFAULT_STEPS)

    def validate(self) -> None:
        f, s = self.field, self.sampler
        if f.kind == "mlp" and s.kind == "occupancy":
            raise ValueError("the MLP field has no density grid: use sampler.kind=hierarchical")
        if len(f.density_res) != len(f.plane_res) or \
                len(f.stage_starts) != len(f.density_res) - 1:
            raise ValueError("field.density_res and field.plane_res need one entry per stage and "
                             "field.stage_starts one per stage after the first")
        if self.passes < 0:
            raise ValueError(f"passes must be >= 0, got {self.passes}")
        if self.steps < 0:
            raise ValueError(f"steps must be >= 0, got {self.steps}")
        for name, value in (("sampler.samples_per_ray", s.samples_per_ray),
                            ("batch_rays", self.batch_rays or 1)):
            if value < 1:
                raise ValueError(f"{name} must be >= 1, got {value}")
        if s.far_factor != 0 and s.far_factor < 1:
            raise ValueError(f"sampler.far_factor must be 0 (auto) or >= 1, got "
                             f"{s.far_factor}")
        if self.optim.lr <= 0:
            raise ValueError(f"optim.lr must be > 0, got {self.optim.lr}")


_V1_RENAMED = {"field": "field.kind", "sampler": "sampler.kind", "medium": "medium.mode",
               "medium_sigma_init": "medium.sigma_init"}


def _nest_flat_v1(flat: dict[str, Any]) -> dict[str, Any]:
    """The flat ModelConfig dict of seathru-model/1 files as nested sections; unknown keys of
    old files are dropped."""
    sections = {name: {f.name for f in dataclasses.fields(cls)}
                for name, cls in _SECTION_TYPES.items()}
    top = {f.name for f in dataclasses.fields(TrainConfig)} - set(sections)
    dotted = {}
    for key, value in flat.items():
        if key in _V1_RENAMED:
            dotted[_V1_RENAMED[key]] = value
            continue
        owner = next((name for name, keys in sections.items() if key in keys), None)
        if owner is not None:
            dotted[f"{owner}.{key}"] = value
        elif key in top:
            dotted[key] = value
    return settings.nest(dotted)


_SECTION_TYPES = {"field": FieldConfig, "sampler": SamplerConfig, "medium": MediumConfig,
                  "loss": LossConfig, "optim": OptimConfig}


# Rays per step when batch_rays is automatic. On an H200 1024 rays ran 64 steps/s and 4096 rays
# 52 steps/s (4x the rays for 20% fewer steps), reaching the paper configuration's PSNR 22x
# instead of 15x sooner; on CPU the step time grows with the batch.
CPU_BATCH_RAYS = 1024
GPU_BATCH_RAYS = 4096


def resolve_batch_rays(config: TrainConfig, device_type: str) -> TrainConfig:
    """``config`` with an automatic ``batch_rays`` set for the device type (``cpu``, ``cuda``)."""
    if config.batch_rays is not None:
        return config
    rays = GPU_BATCH_RAYS if device_type == "cuda" else CPU_BATCH_RAYS
    return dataclasses.replace(config, batch_rays=rays)


# Named training settings (``train.preset``): the explicit settings of a dataset win over them.
# fast/balanced/quality are the capacity levels ``auto`` chooses among (seathru.nerf.capacity;
# measured against each other on the demo and d3_reef: benchmarks/results/frontier.md). paper
# is the paper-faithful configuration (Levy et al. 2023): PE MLP 8x256, hierarchical 128 + 32
# samples, view-dependent water and colour, the paper's discretisation with no water beyond
# the samples, Adam at 5e-4; the baseline of benchmarks/bench_training.py.
TRAIN_PRESETS: dict[str, dict] = {
    "auto": {},  # resolved per scene: seathru.nerf.capacity
    "fast": {"field": {"density_res": [64, 96, 128], "plane_res": [96, 192, 256],
                       "plane_channels": 6},
             "sampler": {"samples_per_ray": 12, "candidates_linear": 48}},
    "balanced": {},
    "quality": {"field": {"density_res": [128, 176, 224], "plane_res": [192, 384, 512],
                          "plane_channels": 12},
                "sampler": {"samples_per_ray": 24, "candidates_linear": 96,
                            "candidates_disparity": 24}},
    "paper": {
        "field": {"kind": "mlp", "view_dependent_colour": "on", "min_views": 0},
        "sampler": {"kind": "hierarchical", "coarse_samples": 128, "fine_samples": 32},
        "medium": {"mode": "view", "render_method": "paper", "water_before": False,
                   "water_after": False},
        "loss": {"transmittance_prior_weight": 1e-4, "distortion_weight": 0.0,
                 "open_water_weight": 0.0, "sparse_depth_weight": 0.0},
        "optim": {"lr": 5e-4, "network_lr_scale": 1.0, "medium_lr_scale": 1.0},
        "batch_rays": 1024,
    },
}
# read by seathru.settings.from_mapping (a class attribute, not a setting)
TrainConfig.PRESETS = TRAIN_PRESETS
