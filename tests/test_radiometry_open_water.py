"""Tests for seathru.radiometry.open_water: open water found in dive photographs."""

from __future__ import annotations

import numpy as np

from seathru.radiometry.open_water import open_water_mask

WATER = np.array([0.04, 0.2, 0.3])


def _dive(rng: np.random.Generator, water_rows: int, shape=(96, 128)) -> np.ndarray:
    image = rng.uniform(0.05, 0.8, size=(*shape, 3))                      # textured reef
    image[:water_rows] = WATER + rng.normal(0.0, 0.002, size=(water_rows, shape[1], 3))
    return image


def test_smooth_water_at_the_top_is_found_and_the_reef_is_not():
    rng = np.random.default_rng(0)
    image = _dive(rng, 32)
    mask = open_water_mask(image, block=8)
    assert mask[:24].mean() > 0.95           # the water, but for the blocks at its lower edge
    assert mask[40:].mean() == 0.0            # texture below
    assert 0.2 < mask.mean() < 0.3


def test_a_smooth_patch_inside_the_scene_is_not_open_water():
    rng = np.random.default_rng(1)
    image = _dive(rng, 0)
    image[40:72, 40:88] = [0.5, 0.45, 0.3]   # flat sand surrounded by reef
    assert not open_water_mask(image, block=8).any()


def test_masked_pixels_are_never_open_water():
    rng = np.random.default_rng(2)
    image = _dive(rng, 32)
    valid = np.ones(image.shape[:2], dtype=bool)
    valid[:, :64] = False
    mask = open_water_mask(image, block=8, valid=valid)
    assert not mask[:, :64].any() and mask[:16, 72:].all()


def test_tiny_images_have_no_open_water():
    assert not open_water_mask(np.zeros((8, 8, 3)), block=8).any()


def test_black_sky_is_no_open_water():
    # clear water (or air at night) leaves the region above a reef black: no veiling light
    rng = np.random.default_rng(3)
    image = _dive(rng, 32)
    image[:32] = rng.normal(0.0, 1e-5, size=(32, image.shape[1], 3)).clip(0.0)
    assert not open_water_mask(image, block=8).any()
    image[:32] = 0.0
    assert not open_water_mask(image, block=8).any()
