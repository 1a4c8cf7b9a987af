"""Tests for seathru.radiometry.glare: the brightening next to the open water, its fit along
tracks (seathru.io.tracks) and the photographs without it (seathru.io.training)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from seathru.io import tracks as tracks_io
from seathru.io.cameras import CameraSet, Frame
from seathru.io.images import write_float_tiff
from seathru.io.training import read_frame_images
from seathru.radiometry.linearise import resize_area
from seathru.radiometry.glare import (GlareCorrection, brighter_near_open_water, glare_gain,
                                      open_water_distance, photograph_gain)
from seathru.radiometry.open_water import open_water_mask

CORRECTION = GlareCorrection(coefficient=-0.3, near=0.05, reference=0.2, far=0.5)


def test_distance_is_the_nearest_open_water_pixel_as_a_share_of_the_width():
    rng = np.random.default_rng(0)
    water = rng.random((12, 20)) < 0.05
    water[0, 0] = True
    distance = open_water_distance(water)
    wet = np.argwhere(water)
    for row, col in np.ndindex(water.shape):
        nearest = np.sqrt(((wet - [row, col]) ** 2).sum(1)).min()
        assert distance[row, col] == pytest.approx(nearest / 20)
    assert np.isinf(open_water_distance(np.zeros((4, 5), bool))).all()


@settings(max_examples=50, deadline=None)
@given(distance=st.floats(1e-6, 10.0), coefficient=st.floats(-1.0, 1.0))
def test_gain_follows_the_power_of_distance_within_the_fitted_range(distance, coefficient):
    correction = GlareCorrection(coefficient, 0.05, 0.2, 0.5)
    clipped = min(max(distance, 0.05), 0.5)
    expected = (clipped / 0.2) ** (coefficient * min(distance / 0.05, 1.0))
    assert float(glare_gain(np.array(distance), correction)) == pytest.approx(expected,
                                                                             rel=1e-12)


def test_open_water_keeps_its_value_and_a_frame_without_any_counts_as_far():
    assert float(glare_gain(np.array(0.0), CORRECTION)) == 1.0
    assert float(glare_gain(np.array(np.inf), CORRECTION)) == pytest.approx(
        (0.5 / 0.2) ** -0.3)
    assert float(glare_gain(np.array(0.2), CORRECTION)) == pytest.approx(1.0)
    # brighter next to the water: from the fit's nearest distance on the gain falls with
    # distance; nearer, it goes to 1 without a step at the water's edge
    gains = glare_gain(np.array([0.05, 0.1, 0.3, 0.5, 0.9]), CORRECTION)
    assert gains[-1] == gains[-2] and np.all(np.diff(gains[:-1]) < 0)
    edge = glare_gain(np.linspace(0.0, 0.05, 11), CORRECTION)
    assert np.all(np.diff(edge) > 0) and np.max(np.diff(edge)) < 0.05 * edge[-1]


def test_a_photographs_gain_follows_the_open_water_it_shows_on_its_valid_pixels():
    rng = np.random.default_rng(1)
    photograph = rng.uniform(0.05, 0.8, (32, 40, 3))
    photograph[:16] = (0.05, 0.3, 0.5)
    water = open_water_mask(photograph)
    assert water[:8].all() and not water[16:].any()
    gain = photograph_gain(photograph, CORRECTION)
    assert np.allclose(gain, glare_gain(open_water_distance(water), CORRECTION), rtol=1e-12)
    assert np.all(gain[water] == 1.0) and not np.allclose(gain[16:], 1.0, rtol=1e-3)
    valid = np.ones((32, 40), bool)
    valid[:, :16] = False                                  # masked pixels are never water
    masked = photograph_gain(photograph, CORRECTION, valid)
    assert np.allclose(masked, glare_gain(open_water_distance(
        open_water_mask(photograph, valid=valid)), CORRECTION))
    assert not np.allclose(masked[:8, :16], 1.0)


@pytest.mark.parametrize("coefficient, stderr, expected", [
    ([-0.33, -0.32, -0.28], [0.01, 0.01, 0.01], True),      # d3_reef
    ([-0.33, -0.32, 0.0], [0.01, 0.01, 0.01], True),        # two channels are enough
    ([-0.33, 0.0, 0.0], [0.01, 0.01, 0.01], False),         # one is not
    ([-0.33, -0.32, -0.28], [0.1, 0.1, 0.1], False),        # loose: 3 standard errors
    ([-0.05, -0.05, -0.05], [0.001, 0.001, 0.001], False),  # significant but small
    ([0.3, 0.3, 0.3], [0.01, 0.01, 0.01], False),           # darker near the water
    ([None, float("nan"), -0.3], [0.01, 0.01, 0.01], False),
])
def test_the_rule_needs_two_channels_clearly_brighter_near_the_water(coefficient, stderr,
                                                                     expected):
    assert brighter_near_open_water(coefficient, stderr) is expected


def _observations(rng: np.random.Generator, coefficient: float, tracks: int = 300,
                  per_track: int = 5, width: int = 400):
    """Tracks seen at several ranges and distances to the open water: colour
    ``J exp(slope * range) (clip(d) / 0.2) ** coefficient`` with a little noise."""
    ids = np.repeat(np.arange(tracks), per_track)
    ranges = rng.uniform(1.0, 5.0, ids.size)
    share = rng.uniform(0.02, 0.8, ids.size)
    share[rng.random(ids.size) < 0.05] = np.inf                    # frames without open water
    clean = rng.uniform(0.05, 0.6, (tracks, 3))[ids]
    slope = np.array([-0.1, 0.0, 0.05])
    near, far = np.percentile(share[np.isfinite(share)], [5, 95])
    clipped = np.clip(np.where(np.isfinite(share), share, far), near, far)
    colour = (clean * np.exp(slope * ranges[:, None]) * (clipped[:, None] / 0.2) ** coefficient
              * np.exp(0.01 * rng.standard_normal(clean.shape)))
    frames = np.zeros(ids.size, np.int64)
    obs = SimpleNamespace(track_ids=ids, ranges=ranges, frames=frames)
    windows = SimpleNamespace(observed=colour, open_water_distance=share * width)
    cameras = SimpleNamespace(frames=[SimpleNamespace(width=width)])
    return cameras, obs, windows, slope


@pytest.mark.parametrize("coefficient", [-0.3, -0.15])
def test_the_track_fit_recovers_a_planted_brightening_beside_range(coefficient):
    cameras, obs, windows, slope = _observations(np.random.default_rng(2), coefficient)
    fit = tracks_io._glare_fit(cameras, obs, windows, np.ones(obs.ranges.size, bool))
    assert fit["coefficient"] == pytest.approx([coefficient] * 3, abs=0.01)
    assert fit["slope"] == pytest.approx(slope, abs=0.01)
    assert fit["brighter"] and fit["near"] < fit["reference"] < fit["far"]
    correction = tracks_io.glare_correction({"near_open_water": fit})
    assert correction.coefficient == pytest.approx(coefficient, abs=0.01)


def test_no_correction_without_a_brightening_or_without_open_water():
    cameras, obs, windows, _ = _observations(np.random.default_rng(3), 0.0)
    fit = tracks_io._glare_fit(cameras, obs, windows, np.ones(obs.ranges.size, bool))
    assert fit["coefficient"] == pytest.approx([0.0] * 3, abs=0.01) and not fit["brighter"]
    assert tracks_io.glare_correction({"near_open_water": fit}) is None
    assert tracks_io.glare_correction(None) is None
    windows.open_water_distance[:] = np.inf
    assert tracks_io._glare_fit(cameras, obs, windows, np.ones(obs.ranges.size, bool)) is None


def test_training_images_are_read_without_the_glare(tmp_path):
    """A photograph of a reef under smooth open water, read with the correction: divided by
    its gain around the open water the photograph itself shows; the water keeps its value."""
    rng = np.random.default_rng(4)
    height, width = 48, 64
    rows, cols = np.mgrid[0:height, 0:width]
    photographed = (0.1 + 0.4 * ((rows // 8 + cols // 8) % 2)[..., None]
                    + rng.uniform(0.0, 0.05, (height, width, 3)))
    photographed[:16] = (0.05, 0.3, 0.5)
    water = open_water_mask(photographed)
    assert water[:8].all() and not water[16:].any()
    (tmp_path / "images").mkdir()
    write_float_tiff(tmp_path / "images" / "v.tiff", photographed.astype(np.float32))
    frame = Frame(name="v", image="images/v.tiff", width=width, height=height, fx=50.0,
                  fy=50.0, cx=32.0, cy=24.0, c2w=np.eye(4).tolist(), near=0.1, far=5.0,
                  split="train")
    cameras = CameraSet(frames=[frame], near=0.1, far=5.0, root=tmp_path)
    (plain,), _ = read_frame_images(cameras, [frame])
    (corrected,), _ = read_frame_images(cameras, [frame], CORRECTION)
    gain = glare_gain(open_water_distance(water), CORRECTION)
    assert np.allclose(plain, photographed, atol=1e-6)
    assert np.allclose(corrected, photographed / gain[..., None], rtol=1e-5)
    assert np.allclose(corrected[water], plain[water])
    assert (np.abs(corrected / plain - 1) > 0.1)[~water].mean() > 0.5
    assert corrected.dtype == plain.dtype


def test_the_model_file_carries_the_correction_to_the_render_and_evaluate_steps(tmp_path):
    """model.pt records the correction the photographs were trained with; the render and
    evaluate steps read the photographs without it (seathru.io.renders)."""
    import torch

    from seathru.io.renders import photograph_glare, read_view_photograph

    torch.save({"config": {}, "glare": CORRECTION.to_dict()}, tmp_path / "model.pt")
    assert photograph_glare(tmp_path / "model.pt") == CORRECTION
    torch.save({"config": {}, "glare": None}, tmp_path / "plain.pt")
    torch.save({"config": {}}, tmp_path / "older.pt")
    assert photograph_glare(tmp_path / "plain.pt") is None
    assert photograph_glare(tmp_path / "older.pt") is None
    assert photograph_glare(tmp_path / "absent.pt") is None

    rng = np.random.default_rng(5)
    image = rng.uniform(0.1, 0.6, (32, 48, 3)).astype(np.float32)
    image[:16] = (0.05, 0.3, 0.5)
    (tmp_path / "images").mkdir()
    write_float_tiff(tmp_path / "images" / "v.tiff", image)
    frame = Frame(name="v", image="images/v.tiff", width=48, height=32, fx=40.0, fy=40.0,
                  cx=24.0, cy=16.0, c2w=np.eye(4).tolist(), near=0.1, far=5.0, split="test")
    cameras = CameraSet(frames=[frame], near=0.1, far=5.0, root=tmp_path)
    expected = image / photograph_gain(image, CORRECTION)[..., None]
    photograph, gain = read_view_photograph(cameras, frame, CORRECTION)
    assert np.allclose(photograph / gain[..., None], expected, rtol=1e-5)
    assert np.allclose(photograph, image)
    assert read_view_photograph(cameras, frame)[1] is None
    assert not np.allclose(expected, image, rtol=0.05)


def test_held_out_renders_get_the_glare_back_and_their_photograph_loses_it():
    """The render step compares a held-out view's full render with the photograph as it is, so
    the image formation gets the gain back; the restored render does not, and the restored
    photograph starts from the photograph without it."""
    from seathru.io.renders import split_glare

    rng = np.random.default_rng(6)
    photograph = rng.uniform(0.1, 0.6, (32, 48, 3))
    photograph[:16] = (0.05, 0.3, 0.5)
    images = {key: rng.uniform(0.0, 1.0, (32, 48, 3))
              for key in ("rgb", "direct", "backscatter", "restored")}
    images["depth"] = rng.uniform(1.0, 2.0, (32, 48))
    gain = glare_gain(open_water_distance(open_water_mask(photograph)), CORRECTION)
    assert not np.allclose(gain, 1.0)
    clean, recorded = split_glare(photograph, images, gain)
    assert np.allclose(clean, photograph / gain[..., None])
    for key in ("rgb", "direct", "backscatter"):
        assert np.allclose(recorded[key], images[key] * gain[..., None])
    assert recorded["restored"] is images["restored"] and recorded["depth"] is images["depth"]
    same, untouched = split_glare(photograph, images, None)
    assert same is photograph and untouched == images
    assert split_glare(None, images, gain) == (None, images)


def test_a_held_out_view_finds_its_open_water_on_the_pixels_its_mask_keeps(tmp_path):
    """The gain taken out of a held-out photograph is the one the train step divides it by:
    open water outside the frame's mask file does not count (the undistorted border, a
    diver's light), so the render step's gain matches the training's."""
    from seathru.io.images import write_mask
    from seathru.io.renders import read_view_photograph, split_glare

    rng = np.random.default_rng(7)
    image = rng.uniform(0.1, 0.6, (32, 48, 3)).astype(np.float32)
    image[:10] = (0.05, 0.3, 0.5)          # open water the mask keeps
    image[:, 40:] = (0.05, 0.3, 0.5)       # and a strip it leaves out
    mask = np.ones((32, 48), np.uint8) * 255
    mask[:, 40:] = 0
    (tmp_path / "images").mkdir()
    (tmp_path / "masks").mkdir()
    write_float_tiff(tmp_path / "images" / "v.tiff", image)
    write_mask(tmp_path / "masks" / "v.png", mask)
    frame = Frame(name="v", image="images/v.tiff", mask="masks/v.png", width=48, height=32,
                  fx=40.0, fy=40.0, cx=24.0, cy=16.0, c2w=np.eye(4).tolist(), near=0.1,
                  far=5.0, split="test")
    cameras = CameraSet(frames=[frame], near=0.1, far=5.0, root=tmp_path)
    photograph, gain = read_view_photograph(cameras, frame, CORRECTION)
    assert np.allclose(photograph, image)
    (trained,), _ = read_frame_images(cameras, [frame], CORRECTION)
    assert np.allclose(photograph / gain[..., None], trained, rtol=1e-5)
    small, small_gain = read_view_photograph(cameras, frame, CORRECTION, (24, 16))
    assert small.shape == (16, 24, 3) and small_gain.shape == (16, 24)
    assert np.allclose(split_glare(small, {}, small_gain)[0],
                       resize_area(image, (24, 16)) / resize_area(gain, (24, 16))[..., None])
    unmasked = photograph_gain(image, CORRECTION)
    assert np.abs(gain / unmasked - 1)[:, 20:40].max() > 0.05
    assert read_view_photograph(cameras, frame)[1] is None
