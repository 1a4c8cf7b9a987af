"""Tests for seathru.nerf.capacity: the capacity ``train.preset=auto`` chooses for a scene."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from seathru import settings
from seathru.io.cameras import CameraSet, Frame
from seathru.nerf.capacity import (LEVELS, PLANE_FOOTPRINT_FACTOR, PLANE_LADDER, SceneMeasure,
                                   choose_capacity, expected_rays, measure_scene,
                                   planes_for_footprint, steps_for_passes)
from seathru.nerf.config import DEFAULT_STEPS, TrainConfig
from seathru.nerf.prepare import prepare_run


def _frame(name: str, centre, focal: float = 100.0, size=(64, 48)) -> Frame:
    c2w = np.eye(4)
    c2w[:3, 3] = centre
    return Frame(name=name, image=f"{name}.png", width=size[0], height=size[1], fx=focal,
                 fy=focal, cx=size[0] / 2, cy=size[1] / 2, c2w=c2w.tolist(), near=0.1, far=4.0)


def _config(**overrides) -> TrainConfig:
    return settings.from_mapping(TrainConfig, {"batch_rays": 1024, **overrides})


def test_footprint_is_box_side_times_focal_over_distance():
    frames = [_frame(f"f{i}", [0.0, 0.0, d]) for i, d in enumerate((2.0, 3.0, 4.0))]
    measure = measure_scene(frames, [-0.5, -0.25, -0.1], [0.5, 0.25, 0.1], 1000)
    assert measure.footprint_res == pytest.approx(1.0 * 100.0 / 3.0)   # median distance 3
    assert (measure.images, measure.width, measure.height) == (3, 64, 48)


def _measure(footprint: float, pixels: int) -> SceneMeasure:
    return SceneMeasure(train_pixels=pixels, images=10, width=320, height=240,
                        footprint_res=footprint)


def test_a_large_budget_on_a_large_scene_takes_the_largest_level():
    config, record = choose_capacity(_config(max_minutes=0, steps=100000),
                                     _measure(2000, 10**6), "cpu")
    assert record["chosen"] == LEVELS[-1]
    quality = settings.from_mapping(TrainConfig, {"preset": "quality"})
    assert config.field.plane_res[0] == quality.field.plane_res[0]
    assert config.field.plane_res[-1] == max(PLANE_LADDER) > quality.field.plane_res[-1]
    assert config.field.density_res == quality.field.density_res
    assert config.sampler.samples_per_ray == quality.sampler.samples_per_ray
    assert config.preset == "auto"


def test_a_budget_below_one_pass_takes_the_smallest_level():
    config, record = choose_capacity(_config(max_minutes=1.0), _measure(2000, 10**8), "cpu")
    assert record["chosen"] == LEVELS[0]
    assert all(not level["fits_budget"] for level in record["levels"].values())
    fast = settings.from_mapping(TrainConfig, {"preset": "fast"})
    assert config.field.density_res == fast.field.density_res


def test_a_scene_smaller_than_the_planes_keeps_them_coarse():
    budget = _config(max_minutes=0, steps=100000)
    planes = {level: entry["finest_plane"] for level, entry in
              choose_capacity(budget, _measure(10**4, 10**5), "cpu")[1]["levels"].items()}
    between = 0.5 * (planes["balanced"] + planes["quality"])
    assert choose_capacity(budget, _measure(between, 10**5), "cpu")[1]["chosen"] == "balanced"
    # a scene finer than no level's planes still gets the smallest level, not none
    assert choose_capacity(budget, _measure(10, 10**5), "cpu")[1]["chosen"] == LEVELS[0]


def test_colour_planes_follow_the_footprint_when_the_budget_fits_the_level():
    fast = settings.from_mapping(TrainConfig, {"preset": "fast"}).field.plane_res
    budget = _config(max_minutes=1.0)
    pixels = int(expected_rays(budget, "fast", "cpu") / 3.5)   # fast fits, balanced does not
    for footprint in (100.0, 300.0, 400.0, 676.0, 5000.0):
        config, record = choose_capacity(budget, _measure(footprint, pixels), "cpu")
        assert record["chosen"] == "fast" and record["levels"]["fast"]["fits_budget"]
        planes = config.field.plane_res
        usable = [p for p in PLANE_LADDER if p <= PLANE_FOOTPRINT_FACTOR * footprint]
        assert planes[-1] == max(usable + [fast[-1]])
        assert planes[0] == fast[0] and planes == sorted(planes)
        assert all(new >= old for new, old in zip(planes, fast))
        assert record["changed"]["field.plane_res"] == planes
        assert "/".join(map(str, planes)) in record["reason"]


def test_a_budget_that_does_not_fit_the_level_keeps_its_planes():
    fast = settings.from_mapping(TrainConfig, {"preset": "fast"}).field.plane_res
    config, record = choose_capacity(_config(max_minutes=1.0), _measure(5000.0, 10**8), "cpu")
    assert not record["levels"]["fast"]["fits_budget"]
    assert config.field.plane_res == fast


def test_planes_for_footprint_keeps_what_is_already_fine_enough():
    assert planes_for_footprint([96, 192, 256], 100.0) == [96, 192, 256]
    assert planes_for_footprint([192, 384, 512], 500.0) == [192, 384, 512]
    assert planes_for_footprint([96, 192, 256], 676.0) == [96, 256, 768]
    assert planes_for_footprint([128, 256], 900.0) == [128, 768]   # two stages: no middle


def test_explicit_settings_are_kept_and_named():
    config, record = choose_capacity(
        _config(max_minutes=0, steps=100000, sampler={"samples_per_ray": 20}),
        _measure(2000, 10**6), "cpu")
    assert config.sampler.samples_per_ray == 20
    assert "sampler.samples_per_ray" in record["kept_explicit"]
    assert "sampler.samples_per_ray" not in record["changed"]
    planes = [64, 128, 200]
    config, record = choose_capacity(
        _config(max_minutes=0, steps=100000, field={"plane_res": planes}),
        _measure(2000, 10**6), "cpu")
    assert config.field.plane_res == planes and "field.plane_res" in record["kept_explicit"]


def test_named_presets_are_left_alone():
    config = _config(preset="balanced", max_minutes=0, steps=100000)
    same, record = choose_capacity(config, _measure(2000, 10**6), "cpu")
    assert same == config and record == {"requested": "balanced", "chosen": "balanced"}


def test_expected_rays_follow_the_tighter_of_steps_and_time():
    assert expected_rays(_config(max_minutes=0, steps=500), "fast", "cpu") == 500 * 1024
    by_time = expected_rays(_config(max_minutes=1.0, steps=10**9), "fast", "cpu")
    slower = expected_rays(_config(max_minutes=1.0, steps=10**9), "quality", "cpu")
    assert 0 < slower < by_time < 10**9 * 1024


def test_by_default_the_time_budget_alone_sets_the_expected_rays():
    """steps 0 (the default) puts no step limit under a budget: fifteen minutes on a CPU plan
    five times the rays of three (with a 6000-step limit a real dive given 15 min planned
    0.9 passes and stopped after about 5.5 min)."""
    three, fifteen = (expected_rays(_config(max_minutes=m), "fast", "cpu") for m in (3.0, 15.0))
    assert fifteen == pytest.approx(5 * three)
    assert fifteen > 6000 * 1024
    assert expected_rays(_config(max_minutes=0), "fast", "cpu") == DEFAULT_STEPS * 1024


def test_passes_become_steps():
    assert steps_for_passes(2.0, 10_000, 1000) == 20
    assert steps_for_passes(0.01, 10_000, 1000) == 1


def test_prepare_run_turns_passes_into_steps_and_records_the_capacity():
    rng = np.random.default_rng(0)
    frames = [_frame(f"f{i}", [0.3 * i - 0.3, 0.0, 2.0]) for i in range(3)]
    for frame in frames:   # look down -z at the origin: the OpenGL camera convention
        frame.c2w[2][2] = 1.0
    cameras = CameraSet(frames=frames, near=0.1, far=4.0)
    images = [rng.uniform(0, 1, (48, 64, 3)).astype(np.float32) for _ in frames]
    config = _config(passes=2.0, max_minutes=0, steps=10)
    run = prepare_run(config, cameras, frames, images, [None] * 3, device="cpu")
    assert run.config.steps == steps_for_passes(2.0, 3 * 64 * 48, 1024)
    assert run.capacity["requested"] == "auto" and run.capacity["chosen"] in LEVELS
    assert run.capacity["scene"]["train_pixels"] == 3 * 64 * 48
    assert torch.isfinite(run.model.field.density.raw).all()
