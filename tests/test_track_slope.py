"""Tests for seathru.eval.track_slope (colour against range along SfM tracks) and
seathru.io.tracks (the tracks of the poses step's COLMAP model as colour observations)."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from seathru.eval.track_slope import (colour_slope_summary, far_tracks, frame_colour_offsets,
                                      slope_beside,
                                      slope_reduction, track_slope)
from seathru.io import tracks as tracks_io
from seathru.io.cameras import CameraSet, Frame
from seathru.io.images import write_float_tiff
from seathru.nerf.rays import camera_rays_np
from seathru.sim.camera_paths import look_at


def _tracks(rng: np.random.Generator, count: int, slope: np.ndarray, noise: float = 0.0,
            most: int = 6):
    """Observations of ``count`` points: log colour = the point's own + slope * range."""
    sizes = rng.integers(1, most + 1, count)
    ids = np.repeat(np.arange(count) * 7 + 3, sizes)          # ids need not be 0..n-1
    ranges = rng.uniform(1.0, 10.0, ids.size)
    own = rng.normal(-1.5, 0.8, (count, 3))
    log_colour = own[np.searchsorted(np.arange(count) * 7 + 3, ids)] + ranges[:, None] * slope
    log_colour += noise * rng.standard_normal(log_colour.shape)
    return ids, ranges, np.exp(log_colour), sizes


def _reference_slope(ids, ranges, values) -> np.ndarray:
    """Float64 least squares with one indicator column per track and a common slope."""
    _, index = np.unique(ids, return_inverse=True)
    design = np.zeros((ids.size, index.max() + 2))
    design[np.arange(ids.size), index] = 1.0
    design[:, -1] = ranges
    solution, *_ = np.linalg.lstsq(design, values, rcond=None)
    return solution[-1]


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2 ** 31), count=st.integers(5, 60),
       slope=st.lists(st.floats(-0.5, 0.5), min_size=3, max_size=3),
       noise=st.floats(0.0, 0.3))
def test_slope_is_the_fixed_effects_least_squares_slope(seed, count, slope, noise):
    rng = np.random.default_rng(seed)
    ids, ranges, colours, sizes = _tracks(rng, count, np.array(slope), noise)
    fit = track_slope(ids, ranges, colours)
    if (sizes >= 2).sum() == 0:
        assert fit.tracks == 0 and np.isnan(fit.slope).all()
        return
    reference = _reference_slope(ids, ranges, np.log(np.maximum(colours, 1e-3)))  # the floor
    np.testing.assert_allclose(fit.slope, reference, rtol=1e-7, atol=1e-10)
    assert fit.tracks == int((sizes >= 2).sum())
    assert fit.observations == int(sizes[sizes >= 2].sum())
    # on the colour itself, the same estimator
    np.testing.assert_allclose(track_slope(ids, ranges, colours, log=False).slope,
                               _reference_slope(ids, ranges, colours), rtol=1e-7, atol=1e-12)


def test_known_slope_is_recovered_and_its_error_is_honest():
    truth = np.array([-0.3, -0.1, 0.05])
    errors, stderrs = [], []
    for seed in range(40):
        ids, ranges, colours, _ = _tracks(np.random.default_rng(seed), 200, truth, noise=0.1)
        fit = track_slope(ids, ranges, colours)
        errors.append(fit.slope - truth)
        stderrs.append(fit.stderr)
    errors, stderrs = np.array(errors), np.array(stderrs)
    assert np.all(np.abs(errors.mean(0)) < 3 * errors.std(0) / np.sqrt(len(errors)) + 1e-4)
    # the cluster-robust standard error matches the spread of the estimates over draws
    ratio = np.median(stderrs, 0) / errors.std(0, ddof=1)
    assert np.all((ratio > 0.7) & (ratio < 1.4)), ratio


def test_range_independent_colour_has_zero_slope_and_full_reduction():
    ids, ranges, colours, _ = _tracks(np.random.default_rng(1), 100, np.zeros(3))
    assert np.allclose(track_slope(ids, ranges, colours).slope, 0.0, atol=1e-12)
    water = colours * np.exp(-np.array([0.4, 0.2, 0.1]) * ranges[:, None]) \
        + np.array([0.02, 0.1, 0.2]) * (1 - np.exp(-0.3 * ranges[:, None]))
    summary = colour_slope_summary(ids, ranges, water, colours)
    assert summary["input"]["slope"][0] < -0.1                 # red fades with range
    assert summary["reduction"] == pytest.approx([1.0, 1.0, 1.0], abs=1e-9)
    assert summary["reduction_overall"] == pytest.approx(1.0, abs=1e-9)
    assert summary["input"]["tracks"] == summary["restored"]["tracks"]


def test_the_full_renders_slope_says_how_much_of_the_input_it_follows():
    """A render that keeps half of the water's log slope follows half of the input's; one
    without water follows none, and its restored slope is zero whether or not water was
    removed."""
    ids, ranges, colours, _ = _tracks(np.random.default_rng(3), 100, np.zeros(3))
    beta = np.array([0.4, 0.2, 0.1])
    water = colours * np.exp(-beta * ranges[:, None])
    half = colours * np.exp(-0.5 * beta * ranges[:, None])
    summary = colour_slope_summary(ids, ranges, water, colours, rendered=half)
    assert summary["rendered"]["slope"] == pytest.approx(list(-0.5 * beta), abs=1e-9)
    assert summary["reproduced"] == pytest.approx([0.5, 0.5, 0.5], abs=1e-9)
    assert summary["rendered"]["tracks"] == summary["input"]["tracks"]
    flat = colour_slope_summary(ids, ranges, water, colours, rendered=colours)
    assert flat["reproduced"] == pytest.approx([0.0, 0.0, 0.0], abs=1e-9)
    assert flat["reduction_overall"] == pytest.approx(1.0, abs=1e-9)
    assert "rendered" not in colour_slope_summary(ids, ranges, water, colours)


def test_reduction_is_one_minus_the_ratio_of_absolute_slopes():
    reduction = slope_reduction([-0.2, 0.1, 0.0], [-0.05, -0.2, 0.1])
    assert reduction[0] == pytest.approx(0.75)
    assert reduction[1] == pytest.approx(-1.0)                 # worse than the input
    assert np.isnan(reduction[2])                              # no slope to reduce


def test_tracks_with_one_observation_or_one_range_are_left_out():
    ids = np.array([1, 2, 2, 3, 3, 3])
    ranges = np.array([1.0, 2.0, 2.0, 1.0, 2.0, 3.0])
    colours = np.exp(np.array([0.0, 5.0, 5.0, 0.1, 0.2, 0.3]))[:, None].repeat(3, 1)
    fit = track_slope(ids, ranges, colours)
    assert (fit.tracks, fit.observations) == (1, 3)
    assert fit.slope == pytest.approx([0.1, 0.1, 0.1])
    with pytest.raises(ValueError, match="disagree"):
        track_slope(ids, ranges[:-1], colours)


# ------------------------------------------------------------------- io: tracks as observations

def _scene(root: Path) -> tuple[CameraSet, np.ndarray]:
    """Three cameras around points near the origin (source units; centre and scale not
    trivial), their images in images/ (colour: the pixel's row, column, frame)."""
    centre, scale = np.array([0.5, -0.2, 0.1]), 0.4
    frames = []
    (root / "images").mkdir(parents=True)
    for index, eye in enumerate(([3.0, 0.0, 0.5], [0.0, 4.0, 0.3], [-2.5, -2.5, 0.8])):
        c2w = look_at(eye, [0.0, 0.0, 0.0])
        c2w[:3, 3] = (c2w[:3, 3] - centre) * scale
        name = f"v{index}"
        rows, cols = np.mgrid[0:60, 0:80].astype(np.float32)
        write_float_tiff(root / "images" / f"{name}.tiff",
                         np.stack([rows, cols, np.full_like(rows, index)], -1))
        frames.append(Frame(name=name, image=f"images/{name}.tiff", width=80, height=60,
                            fx=70.0, fy=70.0, cx=40.0, cy=30.0, c2w=c2w.tolist(), near=0.1,
                            far=5.0, split="test" if index == 1 else "train"))
    cameras = CameraSet(frames=frames, near=0.1, far=5.0, centre=centre.tolist(), scale=scale,
                        source="colmap", root=root)
    points = np.random.default_rng(0).uniform(-0.5, 0.5, (25, 3))
    return cameras, points


def _every_point_in_every_view(points: np.ndarray, monkeypatch) -> None:
    """A stand-in COLMAP model for :func:`_scene`: every point tracked in all three views."""
    model = SimpleNamespace(images={i + 1: SimpleNamespace(name=f"v{i}.png") for i in range(3)},
                            points3D={k: SimpleNamespace(xyz=p, track=SimpleNamespace(elements=[
                                SimpleNamespace(image_id=i) for i in (1, 2, 3)]))
                                for k, p in enumerate(points)})
    monkeypatch.setattr(tracks_io, "read_model", lambda path: model)


def _tracked_scene(tmp_path: Path, monkeypatch) -> tuple[CameraSet, tracks_io.TrackObservations]:
    """:func:`_scene` with every point tracked in every view, and its observations."""
    cameras, points = _scene(tmp_path)
    _every_point_in_every_view(points, monkeypatch)
    return cameras, tracks_io.track_observations(cameras, tmp_path / "sparse")


def test_track_observations_find_each_points_pixel_and_range(tmp_path, monkeypatch):
    cameras, points = _scene(tmp_path)
    images = {i + 1: SimpleNamespace(name=f"v{i}.png") for i in range(3)}
    images[9] = SimpleNamespace(name="not_in_the_camera_file.png")
    model = SimpleNamespace(images=images, points3D={
        100 + k: SimpleNamespace(xyz=p, track=SimpleNamespace(elements=[
            SimpleNamespace(image_id=i) for i in (1, 2, 3, 9)])) for k, p in enumerate(points)})
    monkeypatch.setattr(tracks_io, "read_model", lambda path: model)
    obs = tracks_io.track_observations(cameras, tmp_path / "sparse")
    assert len(obs.rows) > 40 and set(np.unique(obs.frames)) == {0, 1, 2}
    assert obs.held_out.sum() == (obs.frames == 1).sum()
    for row, col, frame_index, point_id, distance, colour in zip(
            obs.rows, obs.cols, obs.frames, obs.track_ids, obs.ranges, obs.observed):
        frame = cameras.frames[frame_index]
        point = points[point_id - 100]
        eye = frame.c2w_array[:3, 3] / cameras.scale + np.asarray(cameras.centre)
        assert distance == pytest.approx(np.linalg.norm(point - eye), rel=1e-9)
        assert tuple(colour) == (row, col, frame_index)          # the pixel's own value
        # the ray of that pixel (the model's own ray code) passes the point within a pixel
        origins, dirs = camera_rays_np(frame.c2w_array, frame.fx, frame.fy, frame.cx,
                                       frame.cy, frame.width, frame.height)
        ray = dirs[row * frame.width + col]
        normalised = (point - np.asarray(cameras.centre)) * cameras.scale
        offset = normalised - origins[0]
        miss = np.linalg.norm(offset - ray * (offset @ ray))
        assert miss <= np.linalg.norm(offset) / frame.fx * 0.75


def test_no_colmap_model_means_no_track_slope(tmp_path):
    cameras, _ = _scene(tmp_path)
    assert tracks_io.track_colour_slope(cameras, tmp_path / "model.pt") is None
    (tmp_path / "sparse").mkdir()
    result = tracks_io.track_colour_slope(cameras, tmp_path / "model.pt")
    assert result["source"] == "none" and "model" in result["reason"]


def test_rendered_colours_come_from_the_ray_of_each_observations_pixel(tmp_path, monkeypatch):
    """A stand-in model whose restored colour is its ray's direction (its full render the
    negated direction): each observation gets the direction of its own pixel's ray (the
    model's ray code as the reference)."""
    cameras, obs = _tracked_scene(tmp_path, monkeypatch)

    def render_rays(model, origins, directions, near, far, chunk=8192):
        return {"restored": directions.clone(), "rgb": -directions}

    monkeypatch.setattr("seathru.nerf.inference.render_rays", render_rays)
    colours = tracks_io.rendered_colours(None, cameras, obs)
    np.testing.assert_array_equal(colours["rgb"], -colours["restored"])
    for row, col, frame_index, colour in zip(obs.rows, obs.cols, obs.frames,
                                             colours["restored"]):
        frame = cameras.frames[frame_index]
        _, dirs = camera_rays_np(frame.c2w_array, frame.fx, frame.fy, frame.cx, frame.cy,
                                 frame.width, frame.height)
        np.testing.assert_allclose(colour, dirs[row * frame.width + col], atol=1e-6)


def test_restored_photo_colours_are_the_mean_over_each_observations_window(tmp_path, monkeypatch):
    """Photographs holding (row, col, frame) at each pixel, at full and at half size: the mean
    over a window of a linear ramp is the ramp at the window's centre, the observation's pixel
    centre in the photograph's own pixel coordinates."""
    cameras, obs = _tracked_scene(tmp_path, monkeypatch)
    points = tracks_io.window_samples(cameras, obs)
    half_side = np.abs(points - points.mean(1, keepdims=True)).max((1, 2))
    for shrink in (1, 2):
        renders = tmp_path / f"render{shrink}"
        for index, frame in enumerate(cameras.frames):
            height, width = frame.height // shrink, frame.width // shrink
            rows, cols = np.mgrid[0:height, 0:width]
            write_float_tiff(renders / "photos" / f"{frame.name}.tiff",
                             np.stack([rows, cols, np.full_like(rows, index)], -1)
                             .astype(np.float32))
        source, photo = tracks_io.restored_photo_colours(renders, cameras, obs)
        # windows inside the image (no sample clipped at its edge)
        inner = ((obs.rows + 0.5 - half_side >= 1) & (obs.rows + 0.5 + half_side <= 59)
                 & (obs.cols + 0.5 - half_side >= 1) & (obs.cols + 0.5 + half_side <= 79))
        assert inner.sum() > 20
        expected = np.stack([(obs.rows + 0.5) / shrink - 0.5, (obs.cols + 0.5) / shrink - 0.5,
                             obs.frames], -1)
        np.testing.assert_allclose(photo[inner], expected[inner], atol=1e-4)
        # the input images hold (row, col, frame) at full size: the same windows
        np.testing.assert_allclose(source[inner], (expected if shrink == 1 else np.stack(
            [obs.rows + 0.0, obs.cols + 0.0, obs.frames], -1))[inner], atol=1e-4)
        np.testing.assert_allclose(source, tracks_io.track_windows(cameras, obs).observed,
                                   atol=1e-6)
    (tmp_path / "render1" / "photos" / f"{cameras.frames[0].name}.tiff").unlink()
    assert tracks_io.restored_photo_colours(tmp_path / "render1", cameras, obs) is None


def test_window_spans_the_same_patch_of_surface_in_every_view(tmp_path, monkeypatch):
    """The window's side is TRACK_WINDOW of the frame's width at the track's median range and
    shrinks as 1 / range; its samples are a regular grid centred on the observation's pixel."""
    cameras, obs = _tracked_scene(tmp_path, monkeypatch)
    points = tracks_io.window_samples(cameras, obs, window=0.05, grid=4)
    assert points.shape == (len(obs.rows), 16, 2)
    xs, ys = points[..., 0], points[..., 1]
    clipped = (xs <= 0.5) | (xs >= 79.5) | (ys <= 0.5) | (ys >= 59.5)
    free = ~clipped.any(1)
    assert free.sum() > 20
    side = (xs.max(1) - xs.min(1)) * 4 / 3          # outer samples are 3/4 of the side apart
    np.testing.assert_allclose((ys.max(1) - ys.min(1))[free] * 4 / 3, side[free])
    np.testing.assert_allclose(xs.mean(1)[free], obs.cols[free] + 0.5)
    np.testing.assert_allclose(ys.mean(1)[free], obs.rows[free] + 0.5)
    for track in np.unique(obs.track_ids):
        mine = (obs.track_ids == track) & free
        footprint = side[mine] * obs.ranges[mine]       # side (pixels) x range: the patch
        median = np.median(obs.ranges[obs.track_ids == track])
        np.testing.assert_allclose(footprint, 0.05 * 80 * median, rtol=1e-9)


def test_windows_take_out_the_bias_of_a_blob_seen_at_different_ranges(
        tmp_path, monkeypatch):
    """A dark dot on a grey surface: seen far, its pixel averages the dot with the grey, so
    the pixel brightens with range though nothing else does. Over a window of the same patch
    of surface in every view, the colour does not change with range."""
    cameras, obs = _tracked_scene(tmp_path, monkeypatch)
    grey, dark, dot = 0.5, 0.05, 0.025    # the dot's radius: source units on the surface
    fine = 16                              # sub-samples a pixel side: the pixel's area average
    offsets = (np.arange(fine) + 0.5) / fine
    for index, frame in enumerate(cameras.frames):
        here = obs.frames == index
        image = np.full((frame.height, frame.width), grey)
        for row, col, distance in zip(obs.rows[here], obs.cols[here], obs.ranges[here]):
            radius = dot * frame.fx / distance             # pixels
            for r in range(max(row - 3, 0), min(row + 4, frame.height)):
                for c in range(max(col - 3, 0), min(col + 4, frame.width)):
                    inside = np.hypot(c + offsets[None] - col - 0.5,
                                      r + offsets[:, None] - row - 0.5) <= radius
                    image[r, c] = min(image[r, c], grey + inside.mean() * (dark - grey))
        write_float_tiff(tmp_path / "images" / f"{frame.name}.tiff",
                         np.repeat(image[..., None], 3, -1).astype(np.float32))
    pixel = np.stack([np.asarray(tracks_io.read_image(cameras.image_path(
        cameras.frames[f])))[r, c] for f, r, c in zip(obs.frames, obs.rows, obs.cols)])
    windowed = tracks_io.track_windows(cameras, obs, window=0.2, grid=9).observed
    at_pixel = track_slope(obs.track_ids, obs.ranges, pixel).slope
    over_window = track_slope(obs.track_ids, obs.ranges, windowed).slope
    assert (at_pixel > 0.1).all()
    np.testing.assert_array_less(np.abs(over_window), 0.25 * at_pixel)


def test_window_samples_on_invalid_pixels_are_left_out_of_every_mean(tmp_path, monkeypatch):
    """Samples on pixels outside the frame's mask (0.9) or not finite (undistortion's borders)
    count neither in the input's colour (0.25) nor in the renders' or photographs' means (the
    photograph is 9 where the input is not finite)."""
    cameras, obs = _tracked_scene(tmp_path, monkeypatch)
    (tmp_path / "masks").mkdir()
    for index, frame in enumerate(cameras.frames):
        image = np.full((frame.height, frame.width, 3), 0.25, np.float32)
        mask = np.ones((frame.height, frame.width), np.float32)
        # left of each observation's own column: masked out in odd columns, NaN in even ones
        for row, col in zip(obs.rows[obs.frames == index], obs.cols[obs.frames == index]):
            for c in range(max(col - 6, 0), col):
                if c % 2:
                    mask[max(row - 6, 0):row + 7, c] = 0.0
                    image[max(row - 6, 0):row + 7, c] = 0.9
                else:
                    image[max(row - 6, 0):row + 7, c] = np.nan
        mask[obs.rows[obs.frames == index], obs.cols[obs.frames == index]] = 1.0
        image[obs.rows[obs.frames == index], obs.cols[obs.frames == index]] = 0.25
        write_float_tiff(tmp_path / "images" / f"{frame.name}.tiff", image)
        write_float_tiff(tmp_path / "masks" / f"{frame.name}.tiff", mask)
        frame.mask = f"masks/{frame.name}.tiff"
        write_float_tiff(tmp_path / "render" / "photos" / f"{frame.name}.tiff",
                         np.where(np.isfinite(image), 0.5, 9.0).astype(np.float32))
    windows = tracks_io.track_windows(cameras, obs, window=0.1, grid=5)
    assert (~windows.valid).any() and windows.valid.any(1).all()
    np.testing.assert_allclose(windows.observed, 0.25, atol=1e-6)
    _, photo = tracks_io.restored_photo_colours(tmp_path / "render", cameras, obs, windows)
    np.testing.assert_allclose(photo, 0.5, atol=1e-6)

    def render_rays(model, origins, directions, near, far, chunk=8192):
        return {"restored": torch.ones(len(origins), 3), "rgb": torch.full((len(origins), 3),
                                                                          0.5)}

    monkeypatch.setattr("seathru.nerf.inference.render_rays", render_rays)
    rendered = tracks_io.rendered_colours(None, cameras, obs, windows)
    np.testing.assert_allclose(rendered["restored"], 1.0)
    # without the masks the masked-out pixels (0.9) count, the NaN ones still do not
    for frame in cameras.frames:
        frame.mask = None
    unmasked = tracks_io.track_windows(cameras, obs, window=0.1, grid=5)
    assert (unmasked.observed > 0.25 + 1e-3).any() and np.isfinite(unmasked.observed).all()


def test_opacity_in_front_stops_each_ray_short_of_its_points_range(tmp_path, monkeypatch):
    """A stand-in model whose opacity is the far bound it is given: each observation's ray ends
    at the share of its point's range, in the camera file's normalised units."""
    cameras, obs = _tracked_scene(tmp_path, monkeypatch)

    def render_rays(model, origins, directions, near, far, chunk=8192):
        return {"opacity": far.clone()}

    monkeypatch.setattr("seathru.nerf.inference.render_rays", render_rays)
    opacity = tracks_io.opacity_in_front(None, cameras, obs, share=0.7)
    np.testing.assert_allclose(opacity, 0.7 * obs.ranges * cameras.scale, rtol=1e-6)


def test_far_tracks_are_those_whose_median_range_is_in_the_top_tenth():
    rng = np.random.default_rng(3)
    ids = rng.permutation(np.repeat(np.arange(50), 5))
    centre = np.linspace(1.0, 30.0, 50)[ids]
    ranges = centre * rng.uniform(0.9, 1.1, ids.size)
    far = far_tracks(ids, ranges)
    medians = np.array([np.median(ranges[ids == k]) for k in range(50)])   # the reference
    expected = medians > np.quantile(medians, 0.9)
    assert expected.sum() == 5
    np.testing.assert_array_equal(far, expected[ids])
    np.testing.assert_array_equal(far_tracks(ids, ranges, share=0.5),
                                  (medians > np.quantile(medians, 0.5))[ids])
    assert far_tracks(ids[:0], ranges[:0]).size == 0
    with pytest.raises(ValueError, match="disagree"):
        far_tracks(ids, ranges[:-1])


def test_track_colour_slope_splits_the_tracks_into_near_and_far(tmp_path, monkeypatch):
    """Every observation falls in one of the two parts; the far part holds the tracks of
    :func:`far_tracks`."""
    cameras, obs = _tracked_scene(tmp_path, monkeypatch)
    (tmp_path / "sparse").mkdir()
    (tmp_path / "model.pt").write_bytes(b"stand-in")
    monkeypatch.setattr("seathru.io.model.load_model", lambda path, device=None: None)
    monkeypatch.setattr("seathru.nerf.inference.render_rays",
                        lambda model, origins, directions, near, far, chunk=8192:
                        {"restored": torch.ones(len(origins), 3),
                         "rgb": torch.full((len(origins), 3), 0.5)})
    renders = tmp_path / "render"
    result = tracks_io.track_colour_slope(cameras, tmp_path / "model.pt", min_tracks=1,
                                          renders=renders)
    assert "photographs" not in result["all_views"]     # the render step wrote none
    for frame in cameras.frames:   # restored photographs of one grey: no slope left
        write_float_tiff(renders / "photos" / f"{frame.name}.tiff",
                         np.full((frame.height, frame.width, 3), 0.4, np.float32))
    result = tracks_io.track_colour_slope(cameras, tmp_path / "model.pt", min_tracks=1,
                                          renders=renders)
    photographs = result["all_views"]["photographs"]
    assert photographs["restored"]["slope"] == pytest.approx([0.0] * 3, abs=1e-9)
    assert photographs["reduction_overall"] == pytest.approx(1.0)
    assert photographs["input"]["observations"] == len(obs.rows)
    far = far_tracks(obs.track_ids, obs.ranges)
    # a render that does not change with range follows none of the input's slope
    assert result["all_views"]["rendered"]["slope"] == pytest.approx([0.0] * 3, abs=1e-12)
    assert 0 < far.sum() < far.size
    assert result["near_tracks"]["input"]["observations"] == (~far).sum()
    assert result["far_tracks"]["input"]["observations"] == far.sum()
    assert result["all_views"]["input"]["observations"] == far.size


def test_depth_observations_keep_training_views_and_their_rays_end_at_the_points(
        tmp_path, monkeypatch):
    from seathru.nerf.rays import depth_rays

    cameras, points = _scene(tmp_path)
    _every_point_in_every_view(points, monkeypatch)
    (tmp_path / "sparse").mkdir()
    # two training views (v1 is held out): no point has three training views
    assert tracks_io.training_depth_observations(cameras) is None
    obs = tracks_io.training_depth_observations(cameras, min_views=2)
    assert set(np.unique(obs.frames)) == {0, 2} and not obs.held_out.any()
    rays = depth_rays(cameras.frames, obs.frames, obs.points, obs.observed)
    assert len(rays) == len(obs.frames)
    ends = rays.rays.origins + rays.rays.directions * rays.ranges[:, None]
    normalised = (points[obs.track_ids] - np.asarray(cameras.centre)) * cameras.scale
    np.testing.assert_allclose(ends.numpy(), normalised, atol=1e-5)
    np.testing.assert_allclose(rays.ranges.numpy(), obs.ranges * cameras.scale, rtol=1e-5)
    np.testing.assert_allclose(rays.rays.rgb.numpy(), obs.observed)
    # points beyond a frame's far bound are left out
    cameras.frames[0].far = 0.2
    fewer = depth_rays(cameras.frames, obs.frames, obs.points, obs.observed)
    assert len(fewer) == int((obs.frames == 2).sum())


def test_slope_beside_recovers_range_and_the_other_term_as_least_squares_does():
    """Log colour = the point's own + 0.05 range - 0.3 term (+ noise): the joint within-track
    fit recovers both, equals least squares on the within-centred design (the float64
    reference), and its standard errors cover the truth; alone, the range slope soaks up the
    term where the two vary together."""
    rng = np.random.default_rng(7)
    ids = np.repeat(np.arange(400), 5)
    ranges = rng.uniform(1.0, 6.0, ids.size)
    term = 0.5 * ranges + rng.normal(0.0, 1.0, ids.size)         # correlated with range
    own = rng.normal(-1.5, 0.5, (400, 3))[ids]
    truth_slope, truth_term = np.array([0.05, -0.02, 0.1]), np.array([-0.3, -0.3, -0.1])
    colours = np.exp(own + ranges[:, None] * truth_slope + term[:, None] * truth_term
                     + rng.normal(0.0, 0.02, (ids.size, 3)))
    fit = slope_beside(ids, ranges, colours, term)
    np.testing.assert_allclose(fit.slope, truth_slope, atol=4 * fit.stderr.max())
    np.testing.assert_allclose(fit.coefficient, truth_term, atol=4 * fit.coefficient_stderr.max())
    centred = lambda v: v - (np.bincount(ids, v) / np.bincount(ids))[ids]   # noqa: E731
    design = np.stack([centred(ranges), centred(term)], 1)
    for c in range(3):
        reference = np.linalg.lstsq(design, centred(np.log(colours[:, c])), rcond=None)[0]
        np.testing.assert_allclose([fit.slope[c], fit.coefficient[c]], reference, rtol=1e-9)
    alone = track_slope(ids, ranges, colours).slope
    assert abs(alone[0] - truth_slope[0]) > 0.1                      # the term leaks into it
    # a non-finite term leaves those observations out; a term equal to range cannot be told apart
    term_gaps = term.copy()
    term_gaps[:500] = np.inf
    assert slope_beside(ids, ranges, colours, term_gaps).observations == ids.size - 500
    assert slope_beside(ids, ranges, colours, 2.0 * ranges) is None


def test_windows_measure_the_distance_to_the_open_water_in_each_image(tmp_path, monkeypatch):
    """Frames whose top rows are smooth bright water above a textured reef: each observation's
    distance is that to the nearest open-water pixel (brute force as the reference); a frame
    without water gives inf, and no open water anywhere gives no near_open_water part."""
    cameras, obs = _tracked_scene(tmp_path, monkeypatch)
    rng = np.random.default_rng(3)
    water_rows = {0: 16, 1: 0, 2: 24}
    for index, frame in enumerate(cameras.frames):
        rows, cols = np.mgrid[0:frame.height, 0:frame.width]
        checker = ((rows // 8 + cols // 8) % 2).astype(np.float32)       # rough in 8x8 blocks
        image = (0.1 + 0.5 * checker[..., None]
                 + rng.uniform(0.0, 0.05, (frame.height, frame.width, 3))).astype(np.float32)
        image[:water_rows[index]] = (0.05, 0.3, 0.5)
        write_float_tiff(tmp_path / "images" / f"{frame.name}.tiff", image)
    from seathru.radiometry.open_water import open_water_mask

    assert tracks_io.track_windows(cameras, obs).open_water_distance is None
    windows = tracks_io.track_windows(cameras, obs, open_water=True)
    for index, frame in enumerate(cameras.frames):
        mask = open_water_mask(tracks_io.read_image(cameras.image_path(frame)))
        assert mask.any() == (water_rows[index] > 0)
        assert not mask[water_rows[index] + 8:].any()             # the reef is not water
        water = np.argwhere(mask)
        for k in np.flatnonzero(obs.frames == index):
            expected = np.inf if not water.size else np.sqrt(
                ((water - [obs.rows[k], obs.cols[k]]) ** 2).sum(1)).min()
            assert windows.open_water_distance[k] == pytest.approx(expected), k
    assert tracks_io._near_open_water(obs, windows) is not None
    # a restoration that keeps the input's colour removes nothing; one flat in range, all
    beside = tracks_io._near_open_water(obs, windows, {"same": windows.observed,
                                                       "flat": np.ones_like(windows.observed)})
    assert beside["same"]["slope"] == pytest.approx(beside["slope"])
    assert beside["same"]["reduction_overall"] == pytest.approx(0.0, abs=1e-9)
    assert beside["flat"]["reduction_overall"] == pytest.approx(1.0)
    windows.open_water_distance[:] = np.inf
    assert tracks_io._near_open_water(obs, windows) is None


def _tracks_in_water(frames: int = 14, points: int = 60, seed: int = 0):
    """Points seen by every frame at ranges 1-6 m through water (attenuation and backscatter
    per channel: the backscatter bends log colour against range), with photo noise."""
    rng = np.random.default_rng(seed)
    surface = rng.uniform(0.1, 0.8, (points, 3))
    ranges = rng.uniform(1.0, 6.0, (frames, points))
    sigma, backscatter, veil = np.array([0.5, 0.2, 0.15]), np.array([0.4, 0.3, 0.25]), \
        np.array([0.05, 0.2, 0.3])
    z = ranges[..., None]
    colours = surface[None] * np.exp(-sigma * z) + veil * (1 - np.exp(-backscatter * z))
    colours *= rng.lognormal(0.0, 0.01, colours.shape)
    ids = np.tile(np.arange(points), frames)
    frame_of = np.repeat(np.arange(frames), points)
    return ids, frame_of, ranges.reshape(-1), colours.reshape(-1, 3), rng


def test_frame_colour_offsets_find_a_per_frame_white_balance_and_nothing_without_one():
    ids, frame_of, ranges, colours, rng = _tracks_in_water()
    plain = frame_colour_offsets(ids, frame_of, ranges, colours)
    assert plain.spread.max() < 0.01 and not plain.varies
    exposure = rng.lognormal(0.0, 0.3, 14)                   # the same in every channel
    assert not frame_colour_offsets(ids, frame_of, ranges, colours * exposure[frame_of, None]
                                    ).varies
    balance = np.exp(rng.normal(0.0, 0.15, (14, 3)))         # red, green, blue gains a frame
    cast = frame_colour_offsets(ids, frame_of, ranges, colours * balance[frame_of])
    injected = np.log(balance[:, [0, 2]] / balance[:, [1]])
    injected -= np.median(injected, axis=0)
    assert cast.varies and list(cast.frames) == list(range(14))
    for ratio in range(2):
        assert np.corrcoef(cast.offsets[:, ratio], injected[:, ratio])[0, 1] > 0.99
    np.testing.assert_allclose(cast.offsets, injected - np.median(injected - cast.offsets, 0),
                               atol=0.03)   # the smooth range term takes a little of them


def _survey_tracks(frames: int = 24, points: int = 900, seed: int = 3):
    """A camera moving along a reef slope and looking across it, white-balancing every frame:
    its gains (red and blue against green) drift along the path as what it shows changes,
    and each point is seen from frames on either side of it. Returns the tracks and the
    injected offsets (log red / green, blue / green) against the median frame."""
    rng = np.random.default_rng(seed)
    along = rng.uniform(-3.0, frames * 0.5 + 3.0, points)
    across = rng.uniform(1.0, 8.0, points)
    surface = rng.uniform(0.1, 0.8, (points, 3))
    sigma, backscatter, veil = np.array([0.5, 0.2, 0.15]), np.array([0.4, 0.3, 0.25]), \
        np.array([0.05, 0.2, 0.3])
    drift = np.linspace(-0.2, 0.25, frames)
    balance = np.exp(np.stack([drift + rng.normal(0.0, 0.05, frames), np.zeros(frames),
                               0.3 * drift + rng.normal(0.0, 0.03, frames)], axis=1))
    ids, frame_of, ranges, colours = [], [], [], []
    for frame in range(frames):
        aside = along - frame * 0.5
        seen = np.flatnonzero(np.abs(aside) < 0.6 * across)
        z = np.hypot(aside[seen], across[seen])[:, None]
        colour = surface[seen] * np.exp(-sigma * z) + veil * (1 - np.exp(-backscatter * z))
        colours.append(colour * balance[frame] * rng.lognormal(0.0, 0.01, colour.shape))
        ids.append(seen), frame_of.append(np.full(len(seen), frame)), ranges.append(z[:, 0])
    injected = np.log(balance[:, [0, 2]] / balance[:, [1]])
    return (np.concatenate(ids), np.concatenate(frame_of), np.concatenate(ranges),
            np.concatenate(colours), injected - np.median(injected, axis=0))


def test_frame_colour_offsets_follow_a_drift_along_the_camera_path():
    """Offsets that drift steadily along the path are the direction the tracks fix least
    (each point's range changes steadily too); the fit must follow them all the same."""
    ids, frame_of, ranges, colours, injected = _survey_tracks()
    cast = frame_colour_offsets(ids, frame_of, ranges, colours)
    assert cast.varies and len(cast.frames) == len(injected)
    error = cast.offsets - injected
    error -= np.median(error, axis=0)                # both are against the median frame
    assert np.sqrt((error ** 2).mean()) < 0.01 and np.abs(error).max() < 0.03


TURBID = ((1.1, 0.66, 0.75), (0.5, 0.6, 0.7), (0.04, 0.22, 0.2))   # attenuation, backscatter,
DEFAULT = ((0.55, 0.25, 0.2), (0.45, 0.3, 0.25), (0.04, 0.2, 0.3))  # veiling light per channel


def _transect_tracks(frames: int = 16, points: int = 1500, seed: int = 0, water=TURBID):
    """A camera moving forward 1.5 m above the seabed, seeing each point from 4 m ahead to
    0.5 m ahead, through ``water``, with no colour cast: the later a frame sees a point, the
    nearer it is, in every track alike."""
    rng = np.random.default_rng(seed)
    along = rng.uniform(0.0, frames * 0.5 + 4.0, points)
    surface = rng.uniform(0.05, 0.8, (points, 3))
    sigma, backscatter, veil = (np.array(v) for v in water)
    ids, frame_of, ranges, colours = [], [], [], []
    for frame in range(frames):
        ahead = along - frame * 0.5
        seen = np.flatnonzero((ahead > 0.5) & (ahead < 4.0))
        z = np.hypot(ahead[seen], 1.5)[:, None]
        colour = surface[seen] * np.exp(-sigma * z) + veil * (1 - np.exp(-backscatter * z))
        colours.append(colour * rng.lognormal(0.0, 0.01, colour.shape))
        ids.append(seen), frame_of.append(np.full(len(seen), frame)), ranges.append(z[:, 0])
    return (np.concatenate(ids), np.concatenate(frame_of), np.concatenate(ranges),
            np.concatenate(colours))


def test_a_transects_range_like_pattern_does_not_make_a_cast_vary():
    """Moving towards what it saw, a drift of the frames' colour is what the range does to
    every track: one pattern of offsets the range term explains all but 1% of, which the
    range term's misfit of turbid water fills with a cast no camera made (0.11 in red). It
    does not count towards whether the cast varies (it did before: ``range_like=0``); where
    the camera white-balanced every frame, the cast varies and the offsets, that pattern
    included, follow it. Tracks seen from all around have no range-like pattern."""
    ids, frame_of, ranges, colours = _transect_tracks()
    found = frame_colour_offsets(ids, frame_of, ranges, colours)
    assert found.spread[0] > 0.1 and found.range_free_spread.max() < 0.08
    assert not found.varies and list(found.range_like) == [1, 1]
    assert found.least_unexplained.max() < 0.01
    assert frame_colour_offsets(ids, frame_of, ranges, colours, range_like=0.0).varies
    ids, frame_of, ranges, colours = _transect_tracks(water=DEFAULT)
    balance = np.exp(np.random.default_rng(5).normal(0.0, 0.15, (16, 3)))
    cast = frame_colour_offsets(ids, frame_of, ranges, colours * balance[frame_of])
    injected = np.log(balance[:, [0, 2]] / balance[:, [1]])
    error = cast.offsets - injected
    assert cast.varies and np.sqrt(((error - np.median(error, 0)) ** 2).mean()) < 0.02
    ids, frame_of, ranges, colours, rng = _tracks_in_water()
    balance = np.exp(rng.normal(0.0, 0.15, (14, 3)))
    kept = frame_colour_offsets(ids, frame_of, ranges, colours * balance[frame_of])
    every = frame_colour_offsets(ids, frame_of, ranges, colours * balance[frame_of],
                                 range_like=0.0)
    assert list(kept.range_like) == [0, 0] and kept.least_unexplained.min() > 0.5
    np.testing.assert_allclose(kept.range_free_spread, every.spread, atol=1e-12)


def test_frames_developed_from_raw_with_one_white_balance_never_vary(tmp_path):
    """The ingest step develops camera RAW files with one white balance for the dataset: no
    frame has a cast of its own, so a spread the offsets find is the range term's misfit and
    the record says the cast does not vary (no correction, no warning); a camera's JPEGs
    keep the verdict."""
    from seathru.io.stored_views import one_white_balance

    cameras, _ = _scene(tmp_path / "poses")
    assert not one_white_balance(cameras)                       # no ingest manifest found
    cameras.source = "simulated"                                # the simulator's own images
    assert one_white_balance(cameras)
    cameras.source = "colmap"
    (tmp_path / "ingest").mkdir()
    cast = frame_colour_offsets(*_transect_tracks(), range_like=0.0)    # a cast that varies
    names = [f"f{i}" for i in range(16)]
    for kind, raw in (("raw", True), ("srgb", False), ("linear", False)):
        (tmp_path / "ingest" / "manifest.json").write_text(json.dumps({"input": {"kind": kind}}))
        assert one_white_balance(cameras) is raw
        record = tracks_io._frame_colour_record(cast, names, one_white_balance(cameras))
        assert record["varies"] is (not raw) and record["one_white_balance"] is raw
        assert (tracks_io.frame_colour_gains({"frame_colour": record}) is None) is raw


def test_frame_colour_offsets_need_two_frames_with_observations():
    ids, frame_of, ranges, colours, _ = _tracks_in_water(frames=2, points=8)
    assert frame_colour_offsets(ids, frame_of, ranges, colours) is None


def test_training_frames_are_brought_to_the_median_frames_colour_cast(tmp_path):
    from seathru.io.training import read_frame_images

    change = {"frame_colour": {"varies": True, "spread": [0.15, 0.05],
                               "offsets": {"a": [0.2, -0.1], "b": [0.0, 0.0]}}}
    gains = tracks_io.frame_colour_gains(change)
    np.testing.assert_allclose(gains["a"], [np.exp(-0.2), 1.0, np.exp(0.1)])
    assert tracks_io.frame_colour_gains({"frame_colour": {**change["frame_colour"],
                                                          "varies": False}}) is None
    assert tracks_io.frame_colour_gains(None) is None
    photographed = np.random.default_rng(1).uniform(0.1, 0.9, (8, 10, 3)).astype(np.float32)
    (tmp_path / "images").mkdir()
    frames = []
    for name in ("a", "b", "c"):
        write_float_tiff(tmp_path / "images" / f"{name}.tiff", photographed)
        frames.append(Frame(name=name, image=f"images/{name}.tiff", width=10, height=8,
                            fx=9.0, fy=9.0, cx=5.0, cy=4.0, c2w=np.eye(4).tolist(), near=0.1,
                            far=5.0, split="train"))
    cameras = CameraSet(frames=frames, near=0.1, far=5.0, root=tmp_path)
    (a, b, c), _ = read_frame_images(cameras, frames, gains=gains)
    np.testing.assert_allclose(a, photographed * np.float32(gains["a"]), rtol=1e-6)
    np.testing.assert_allclose(b, photographed)
    np.testing.assert_allclose(c, photographed)        # no offset measured: as it is
