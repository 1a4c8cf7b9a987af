"""Tests for seathru.nerf.prepare: the first guess of the veiling light from the images."""

from __future__ import annotations

import numpy as np
import pytest
import torch

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


def _frames(count: int, size=(64, 48)):
    from seathru.io.cameras import Frame

    frames = []
    for i in range(count):
        c2w = np.eye(4)
        c2w[:3, 3] = [0.3 * i - 0.3, 0.0, 2.0]
        frames.append(Frame(name=f"f{i}", image=f"f{i}.png", width=size[0], height=size[1],
                            fx=60.0, fy=60.0, cx=size[0] / 2, cy=size[1] / 2, c2w=c2w.tolist(),
                            near=0.1, far=4.0))
    return frames


def test_open_water_pixels_reach_the_rays_and_the_scene():
    from seathru import settings
    from seathru.io.cameras import CameraSet
    from seathru.nerf.config import TrainConfig
    from seathru.nerf.prepare import prepare_run

    rng = np.random.default_rng(3)
    frames = _frames(3)
    images = [_dive_image(rng, 16)[:48, :64] for _ in frames]      # 16 of 48 rows open water
    masks = [None, None, np.ones((48, 64), bool)]
    masks[2][:, :32] = False                                          # half of one frame masked
    config = settings.from_mapping(TrainConfig, {"batch_rays": 256, "max_minutes": 0})
    run = prepare_run(config, CameraSet(frames=frames, near=0.1, far=4.0), frames, images,
                      masks)
    flags = run.data.open_water
    assert flags is not None and len(flags) == len(run.data)
    # the blocks at the water's lower edge border on reef: between a sixth and a third
    assert 1 / 6 - 1e-6 < float(flags.float().mean()) < 1 / 3 + 1e-6
    assert run.model.scene["open_water_image_share"] == pytest.approx(
        float(flags.double().mean()), abs=1e-9)
    batch = run.data.sample(64, torch.Generator().manual_seed(0))
    assert batch.open_water is not None and batch.open_water.shape == (64,)
    # the water refits use the flags too, with or without the open-water loss
    off = settings.from_mapping(TrainConfig, {"batch_rays": 256, "max_minutes": 0,
                                              "loss": {"open_water_weight": 0.0}})
    assert prepare_run(off, CameraSet(frames=frames, near=0.1, far=4.0), frames, images,
                       masks).data.open_water is not None
    reef = [_dive_image(rng, 0)[:48, :64] for _ in frames]            # no open water in view
    assert prepare_run(off, CameraSet(frames=frames, near=0.1, far=4.0), frames, reef,
                       masks).data.open_water is None


def test_open_water_brighter_upwards_has_a_direction_spread_and_uniform_water_none():
    from seathru.nerf.prepare import open_water_direction_spread
    from seathru.nerf.rays import frame_rays

    frames = _frames(2)
    masks = [np.ones((48, 64), bool), np.ones((48, 64), bool)]
    rng = np.random.default_rng(5)
    uniform = [WATER + rng.normal(0, 0.002, (48, 64, 3)) for _ in frames]
    graded = []
    for frame in frames:
        up = frame_rays(frame)[1].numpy().reshape(48, 64, 3)[..., 1]   # +y: up in the world
        graded.append(WATER * (1.0 + 0.8 * up[..., None]))
    flat = open_water_direction_spread(frames, uniform, masks)
    assert flat < 0.02
    assert open_water_direction_spread(frames, graded, masks) > 5 * flat
    assert open_water_direction_spread(frames, uniform, [np.zeros((48, 64), bool)] * 2) == 0.0


def test_direction_spread_drawn_frame_by_frame_is_the_fit_on_the_pooled_draw():
    """Gathering the drawn open-water pixels frame by frame gives the fit of drawing from all
    of them pooled (the straightforward way, which holds every open-water pixel at once)."""
    from seathru.nerf.prepare import open_water_direction_spread
    from seathru.nerf.rays import frame_rays

    frames = _frames(3)
    rng = np.random.default_rng(11)
    images = [rng.random((48, 64, 3)) for _ in frames]
    masks = [rng.random((48, 64)) > 0.4, np.zeros((48, 64), bool), rng.random((48, 64)) > 0.7]

    def pooled(max_pixels, seed=0):
        dirs = np.concatenate([frame_rays(f)[1].numpy()[m.reshape(-1)]
                               for f, m in zip(frames, masks)])
        rgb = np.concatenate([i.reshape(-1, 3)[m.reshape(-1)] for i, m in zip(images, masks)])
        if len(dirs) > max_pixels:
            pick = np.random.default_rng(seed).choice(len(dirs), max_pixels, replace=False)
            dirs, rgb = dirs[pick], rgb[pick]
        design = np.concatenate([np.ones((len(dirs), 1)), dirs], axis=1)
        predicted = design @ np.linalg.lstsq(design, rgb, rcond=None)[0]
        return float(np.linalg.norm(predicted.std(0)) / np.linalg.norm(rgb.mean(0)))

    for max_pixels in (500, 10_000):
        assert open_water_direction_spread(frames, images, masks, max_pixels) == \
            pytest.approx(pooled(max_pixels), rel=1e-12)


def test_uniform_clear_water_with_a_dark_red_channel_has_no_direction_spread():
    """Clear blue water extinguishes red (c_med 0.016 on the oceanic II survey): the red
    channel's noise, and a faint tint towards the hazy seabed, must not read as a veiling light
    that changes with direction (the spread is a share of the whole colour's brightness)."""
    from seathru.nerf.config import MediumConfig
    from seathru.nerf.prepare import open_water_direction_spread
    from seathru.nerf.rays import frame_rays

    frames = _frames(2)
    masks = [np.ones((48, 64), bool), np.ones((48, 64), bool)]
    rng = np.random.default_rng(7)
    blue_water = np.array([0.016, 0.11, 0.25])
    images = []
    for frame in frames:
        down = -frame_rays(frame)[1].numpy().reshape(48, 64, 3)[..., 1]
        red_tint = np.zeros((48, 64, 3))
        red_tint[..., 0] = 0.01 * down         # red changes with direction, G and B do not
        images.append(blue_water + red_tint + rng.normal(0, 0.002, (48, 64, 3)))
    spread = open_water_direction_spread(frames, images, masks)
    assert spread < MediumConfig().auto_veiling_spread / 3
    # the premise: red alone varies by more than the threshold's share of its own level
    red_share = float(np.max([np.std(im[..., 0]) for im in images]) / blue_water[0])
    assert red_share > MediumConfig().auto_veiling_spread


def test_the_water_fit_gets_deblurred_colours_only_where_a_blur_is_recorded_and_wanted():
    import dataclasses

    import cv2

    from seathru import settings
    from seathru.io.cameras import CameraSet
    from seathru.nerf.config import TrainConfig
    from seathru.nerf.prepare import prepare_run

    rng = np.random.default_rng(5)
    # reef texture with a photograph's spectrum (white noise softened), then the blur
    sharp = [cv2.GaussianBlur(_dive_image(rng, 16)[:48, :64], (0, 0), 1.0) for _ in range(3)]
    images = [cv2.GaussianBlur(image, (0, 0), 0.9) for image in sharp]
    config = settings.from_mapping(TrainConfig, {"batch_rays": 256, "max_minutes": 0})
    blurred = [dataclasses.replace(f, blur_px=[0.9, 0.9, 0.9]) for f in _frames(3)]

    def run(frames, **medium):
        chosen = settings.from_mapping(TrainConfig, {"batch_rays": 256, "max_minutes": 0,
                                                     "medium": medium}) if medium else config
        return prepare_run(chosen, CameraSet(frames=frames, near=0.1, far=4.0), frames,
                           images, [None] * 3).data

    data = run(blurred)
    assert data.deblurred_rgb is not None
    truth = torch.from_numpy(np.concatenate([image.reshape(-1, 3) for image in sharp]))
    truth = truth[data.pixel_ids].to(data.rgb)
    # the fit's colours are nearer the unblurred images than the training colours are
    assert float((data.deblurred_rgb - truth).abs().mean()) < \
        0.8 * float((data.rgb - truth).abs().mean())
    assert run(blurred, refit_deblur=False).deblurred_rgb is None
    assert run(blurred, mode="off").deblurred_rgb is None
    assert run(_frames(3)).deblurred_rgb is None                      # no blur recorded
