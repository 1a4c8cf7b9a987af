"""Tests for seathru.nerf.prepare: the first guess of the veiling light from the images."""

from __future__ import annotations

import numpy as np

from seathru.nerf.prepare import veiling_light_estimate

WATER = np.array([0.05, 0.22, 0.31], dtype=np.float32)


def _dive_image(rng: np.random.Generator, open_rows: int) -> np.ndarray:
    image = rng.uniform(0.0, 0.8, size=(96, 128, 3)).astype(np.float32)   # textured reef
    image[:open_rows] = WATER + rng.normal(0, 0.004, size=(open_rows, 128, 3))
    return image


def test_the_smoothest_regions_give_the_veiling_light_not_the_mean_colour():
    rng = np.random.default_rng(0)
    images = [_dive_image(rng, rows) for rows in (16, 24, 32)]
    estimate = np.array(veiling_light_estimate(images))
    assert np.allclose(estimate, WATER, atol=0.01), estimate
    mean = np.mean([im.reshape(-1, 3).mean(0) for im in images], axis=0)
    assert np.abs(mean - WATER).max() > 0.1           # the old start was far off


def test_masked_pixels_are_left_out():
    rng = np.random.default_rng(1)
    image = _dive_image(rng, 24)
    image[40:60] = [1.0, 0.0, 0.0]                    # a flat clipped band, invalid
    mask = np.ones(image.shape[:2], dtype=bool)
    mask[40:60] = False
    estimate = np.array(veiling_light_estimate([image], [mask]))
    assert np.allclose(estimate, WATER, atol=0.01), estimate
    assert veiling_light_estimate([np.zeros((4, 4, 3), np.float32)]) is None


def test_smooth_regions_of_many_colours_are_no_veiling_light():
    rng = np.random.default_rng(2)
    images = []
    for _ in range(3):
        image = rng.uniform(0.0, 0.8, size=(96, 128, 3)).astype(np.float32)
        for row in range(0, 96, 16):          # flat patches of different colours: clear water
            image[row:row + 8, :64] = rng.uniform(0.1, 0.9, size=3)
        images.append(image)
    assert veiling_light_estimate(images) is None
