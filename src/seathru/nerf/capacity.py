"""Model capacity that fits the scene and the budget (``train.preset=auto``).

A voxel or tri-plane cell finer than the footprint of one pixel learns nothing the images hold,
and a model the budget cannot show its data to at least about once converges to less than a
smaller one would in the same time. ``auto`` therefore takes the largest of the capacity levels
(the ``fast``, ``balanced`` and ``quality`` presets) that

1. the scene can use: its finest tri-plane is not finer than the scene's footprint resolution
   (cells along the scene box's longest axis for one cell per pixel at the median distance of
   the cameras from the box centre), and
2. the budget can train: the rays it will see (the time budget at the level's typical step
   time on this kind of device, or the step limit, whichever is smaller) cover the training
   pixels at least ``MIN_PASSES`` times.

The smallest level is taken when no level meets both.

When the budget shows the data to the chosen level ``MIN_PASSES`` times, its colour planes
then follow the scene: the finest is the largest of ``PLANE_LADDER`` within
``PLANE_FOOTPRINT_FACTOR`` times the footprint resolution (surfaces nearer than the box centre
have finer footprints than that median), never coarser than the level's own, and the middle
stage lies halfway between the first and the finest on a log scale. Finer planes cost about
1.3x the step time (their gradients and Adam's moments are dense); below that many passes
they bought nothing (d3_reef at 0.8 passes).

Only settings still at their defaults are changed: an explicit ``field.plane_res`` or
``sampler.samples_per_ray`` is kept. The choice and its evidence go to ``selection.json``
(``capacity``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from seathru import settings
from seathru.nerf.config import TRAIN_PRESETS, TrainConfig

LEVELS = ("fast", "balanced", "quality")

# Training step time (s) of each level at its final stage with 1024 rays, by device type:
# benchmarks/results/profile.md (CPU, 2 threads: 35, 49, 90 ms on the demo). CUDA steps cost
# about the same for every level at these sizes (benchmarks/results/training_h200*.md).
STEP_SECONDS = {"cpu": {"fast": 0.035, "balanced": 0.049, "quality": 0.090},
                "cuda": {"fast": 0.015, "balanced": 0.016, "quality": 0.019}}
REFERENCE_BATCH = 1024
# On the demo (3 min, 2 CPU threads) fast (3.3 expected passes) ended 0.6 dB above balanced
# (2.4 passes) and quality (1.3 passes) on the held-out views, and reached balanced's final
# PSNR in less than half the time: benchmarks/results/frontier.md.
MIN_PASSES = 3.0
# Finest colour planes by footprint. On the demo (footprint 676 cells, 3 min, 2 CPU threads)
# 768 instead of 256 gained +0.9..+1.5 dB held-out and +0.2..+0.6 dB restored vs clean, two
# runs each side by side, at 1.3-1.4x the step time; 512 lay between; on d3_reef (0.8 passes)
# nothing: benchmarks/results/planes.md.
PLANE_LADDER = (256, 384, 512, 768)
PLANE_FOOTPRINT_FACTOR = 1.2


@dataclass
class SceneMeasure:
    """What the capacity choice reads of a scene."""

    train_pixels: int          # valid training pixels
    images: int
    width: int                 # median image size
    height: int
    footprint_res: float       # cells along the box's longest axis for one cell per pixel


def measure_scene(frames, box_min, box_max, train_pixels: int) -> SceneMeasure:
    """The scene's size in pixels and data.

    Args:
        frames: the training frames (``c2w`` (4, 4), ``fx``, ``width``, ``height``).
        box_min, box_max: the scene box (3,), in the cameras' units.
        train_pixels: the number of valid training pixels.

    Returns:
        the measure; ``footprint_res`` is ``longest box side * focal / distance`` with the
        median focal length (pixels) and median camera distance from the box centre.

    Example::

        measure = measure_scene(frames, scene["box_min"], scene["box_max"], len(data))
    """
    lo, hi = np.asarray(box_min, float), np.asarray(box_max, float)
    centre = 0.5 * (lo + hi)
    distance = float(np.median([np.linalg.norm(np.asarray(f.c2w_array)[:3, 3] - centre)
                                for f in frames]))
    focal = float(np.median([f.fx for f in frames]))
    longest = float((hi - lo).max())
    return SceneMeasure(train_pixels=int(train_pixels), images=len(frames),
                        width=int(np.median([f.width for f in frames])),
                        height=int(np.median([f.height for f in frames])),
                        footprint_res=longest * focal / max(distance, 1e-9))


def _level_settings(level: str) -> dict[str, Any]:
    """The flattened settings of a capacity level (its preset over the defaults)."""
    config = settings.from_mapping(TrainConfig, {"preset": level})
    keys = settings.flatten(TRAIN_PRESETS["quality"]).keys() | \
        settings.flatten(TRAIN_PRESETS["fast"]).keys()
    flat = settings.flatten(config.to_dict())
    return {k: flat[k] for k in keys}


def expected_rays(config: TrainConfig, level: str, device_type: str) -> float:
    """Rays the run will train on at ``level``: the step limit and the time budget's steps."""
    batch = config.batch_rays or REFERENCE_BATCH
    steps = config.step_limit
    if config.max_minutes and config.max_minutes > 0:
        step_s = STEP_SECONDS.get(device_type, STEP_SECONDS["cpu"])[level]
        step_s *= max(1.0, batch / REFERENCE_BATCH) if device_type == "cpu" else 1.0
        steps = min(steps, config.max_minutes * 60.0 / step_s)
    return steps * batch


def choose_capacity(config: TrainConfig, measure: SceneMeasure, device_type: str
                    ) -> tuple[TrainConfig, dict]:
    """The config with the capacity ``auto`` chooses, and the choice with its evidence.

    Args:
        config: resolved training settings (``batch_rays`` set, ``steps`` final).
        measure: :func:`measure_scene` of the training frames.
        device_type: ``cpu`` or ``cuda``.

    Returns:
        the config (unchanged unless ``config.preset == "auto"``) and a record for
        ``selection.json``: the level, the settings it changed, and per level the finest
        plane, the expected passes and whether the scene and the budget allow it.
    """
    if config.preset != "auto":
        return config, {"requested": config.preset, "chosen": config.preset}
    defaults = settings.flatten(TrainConfig().to_dict())
    current = settings.flatten(config.to_dict())
    evidence = {}
    chosen = LEVELS[0]
    for level in LEVELS:
        plane = max(_level_settings(level)["field.plane_res"])
        passes = expected_rays(config, level, device_type) / max(1, measure.train_pixels)
        fits_scene = plane <= measure.footprint_res or level == LEVELS[0]
        fits_budget = passes >= MIN_PASSES
        evidence[level] = {"finest_plane": plane, "expected_passes": round(passes, 2),
                           "fits_scene": bool(fits_scene), "fits_budget": bool(fits_budget)}
        if fits_scene and fits_budget:
            chosen = level
    target = _level_settings(chosen)
    if evidence[chosen]["fits_budget"]:
        target["field.plane_res"] = planes_for_footprint(target["field.plane_res"],
                                                         measure.footprint_res)
    changed = {k: v for k, v in target.items()
               if current[k] == defaults[k] and v != current[k]}
    kept = sorted(k for k, v in target.items()
                  if current[k] != defaults[k] and v != current[k])
    flat = {**current, **changed}
    new = settings.from_mapping(TrainConfig, {**settings.nest(flat), "preset": "auto"})
    record = {
        "requested": "auto", "chosen": chosen, "changed": changed, "kept_explicit": kept,
        "scene": dataclasses.asdict(measure), "device_type": device_type,
        "min_passes": MIN_PASSES, "levels": evidence,
        "reason": _reason(chosen, measure, evidence[chosen],
                          settings.nest(flat)["field"]["plane_res"]),
    }
    return new, record


def planes_for_footprint(plane_res: list[int], footprint_res: float) -> list[int]:
    """The per-stage plane resolutions with the finest raised to what the scene can use.

    Args:
        plane_res: a level's plane resolution per stage (first to finest).
        footprint_res: :attr:`SceneMeasure.footprint_res`.

    Returns:
        ``plane_res`` with its finest entry the largest of ``PLANE_LADDER`` not above
        ``PLANE_FOOTPRINT_FACTOR * footprint_res`` when that is finer, and a middle stage (if
        any) at the geometric mean of the first and the finest (a multiple of 32), never
        coarser than before; unchanged otherwise.

    Example::

        planes_for_footprint([96, 192, 256], 676.0)   # -> [96, 256, 768]
    """
    finest = max([p for p in PLANE_LADDER if p <= PLANE_FOOTPRINT_FACTOR * footprint_res],
                 default=0)
    if finest <= plane_res[-1]:
        return list(plane_res)
    planes = [*plane_res[:-1], finest]
    if len(planes) == 3:
        planes[1] = max(planes[1], 32 * round(math.sqrt(planes[0] * finest) / 32))
    return planes


def _reason(level: str, measure: SceneMeasure, evidence: dict, planes: list[int]) -> str:
    return (f"{level}: about {evidence['expected_passes']:.1f} passes over the "
            f"{measure.train_pixels:,} training pixels in the budget (a larger level needs "
            f">= {MIN_PASSES:g} passes and a scene it can resolve); colour planes "
            f"{'/'.join(map(str, planes))} for a scene of {measure.footprint_res:.0f} pixel "
            "footprints across")


def steps_for_passes(passes: float, train_pixels: int, batch_rays: int) -> int:
    """Optimisation steps of ``passes`` passes over ``train_pixels`` at ``batch_rays`` a step."""
    return max(1, math.ceil(passes * train_pixels / batch_rays))
