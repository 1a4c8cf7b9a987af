"""seathru.io.truth: the simulate step's folder, written from a dive and read back by the readers
the other steps use (cameras, water truth, truth images, DNG tags)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from seathru.errors import PipelineError
from seathru.eval import truth as truth_eval
from seathru.io import truth
from seathru.io.cameras import read_cameras
from seathru.io.dng import read_dng_metadata
from seathru.io.evaluation import read_truth_image
from seathru.io.images import read_image
from seathru.io.raw import jpeg_chroma
from seathru.io.water import read_truth_water
from seathru.sim import dive
from seathru.sim.water import water_params

SPEC = dive.DiveSpec(views=2, width=16, height=12, path="transect",
                     water=water_params("turbid", sigma_bs=[0.1, 0.2, 0.3]), seed=2,
                     fov_deg=60.0, supersample=1, seabed_amplitude=0.0)


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    root = tmp_path_factory.mktemp("truth") / "dive"
    plan = dive.plan_dive(SPEC, {})
    views = list(dive.render_views(SPEC, plan))
    names = truth.view_names(SPEC.views)
    frames = []
    for name, view in zip(names, views):
        truth.write_view(root, name, view, SPEC.sensor, plan.camera)
        frames.append(truth.truth_frame(name, plan.camera, view.c2w, view.range_m, "train"))
    truth.write_records(root, SPEC, plan, frames, test_every=0, open_water_pixels=0)
    return root, plan, dict(zip(names, views))


def test_round_trip_through_the_readers(written):
    root, plan, views = written
    cameras = read_cameras(root / "truth" / "cameras.json")
    assert [f.name for f in cameras.frames] == ["dive_0000", "dive_0001"]
    water = read_truth_water(root / "truth" / "water.json")
    assert (water.sigma_attn, water.sigma_bs, water.c_med) == (
        SPEC.water.sigma_attn, SPEC.water.sigma_bs, SPEC.water.c_med)
    sensor = json.loads((root / "truth" / "sensor.json").read_text())
    assert sensor["dn_per_unit"] == plan.dn_per_unit
    for frame in cameras.frames:
        view = views[frame.name]
        np.testing.assert_array_equal(read_image(cameras.image_path(frame)), view.water)
        np.testing.assert_array_equal(read_truth_image(root / "truth", "clean", frame.name),
                                      view.clean)
        depth = read_truth_image(root / "truth", "depth", frame.name)
        np.testing.assert_array_equal(depth, view.range_m)
        assert frame.near == pytest.approx((1 - truth.NEAR_FAR_MARGIN) * np.nanmin(depth))
        assert frame.far == pytest.approx((1 + truth.NEAR_FAR_MARGIN) * np.nanmax(depth))
        np.testing.assert_allclose(frame.c2w_array, view.c2w)
        tags = read_dng_metadata(root / "raw" / f"{frame.name}.dng")
        assert tags["exposure_time_s"] == view.exposure.exposure_time_s
        assert sensor["images"][frame.name]["iso"] == tags["iso"] == view.exposure.iso
        jpeg = read_image(root / "jpeg" / f"{frame.name}.jpg")
        assert np.abs(jpeg - view.jpeg).mean() < 0.03  # 8-bit JPEG of the developed image
    readme = (root / "README.md").read_text()
    assert "water preset `turbid+custom`" in readme and "[0.1, 0.2, 0.3] /m" in readme
    assert sensor["jpeg"]["chroma"] == "4:2:0" and "4:2:0 chroma sampling" in readme


def test_the_camera_jpegs_colour_resolution_is_a_setting(written, tmp_path):
    """Cameras store colour at half resolution (4:2:0); at 4:4:4 every pixel keeps its own,
    so the stored colour (each channel against the pixel's mean) follows the developed image
    closer."""
    _, plan, views = written
    name, view = next(iter(views.items()))
    errors = {}
    for chroma in ("4:2:0", "4:4:4"):
        sensor = dataclasses.replace(SPEC.sensor, jpeg_chroma=chroma)
        truth.write_view(tmp_path / chroma.replace(":", ""), name, view, sensor, plan.camera)
        path = tmp_path / chroma.replace(":", "") / "jpeg" / f"{name}.jpg"
        assert jpeg_chroma(path) == chroma
        jpeg = read_image(path)
        errors[chroma] = np.abs((jpeg - jpeg.mean(-1, keepdims=True))
                                - (view.jpeg - view.jpeg.mean(-1, keepdims=True))).mean()
    assert errors["4:4:4"] < 0.7 * errors["4:2:0"]
    with pytest.raises(ValueError, match="4:1:1"):
        truth.write_view(tmp_path / "bad", name, view,
                         dataclasses.replace(SPEC.sensor, jpeg_chroma="4:1:1"), plan.camera)


def test_open_water_view_gets_default_bounds():
    assert truth.view_range_limits(np.full((2, 2), np.nan, np.float32)) == (0.1, 10.0)
    assert truth.view_range_limits(np.array([[np.nan, 2.0], [3.0, 4.0]])) == (2.0, 4.0)


def test_only_empty_or_earlier_simulations_are_replaced(written, tmp_path):
    root, _, _ = written
    truth.check_replaceable(root)                 # an earlier simulation
    truth.check_replaceable(tmp_path / "new")     # absent
    (tmp_path / "empty").mkdir()
    truth.check_replaceable(tmp_path / "empty")
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "keep.jpg").write_bytes(b"x")
    (tmp_path / "file").write_text("x")
    for foreign in ("photos", "file"):
        with pytest.raises(PipelineError, match=f"{foreign}: exists and is not an earlier"):
            truth.check_replaceable(tmp_path / foreign)


def test_a_malformed_water_truth_is_refused_naming_the_file(written, tmp_path):
    bad = tmp_path / "water.json"
    data = json.loads((written[0] / "truth" / "water.json").read_text())
    bad.write_text(json.dumps({**data, "sigma_bs": [0.1, 0.2]}))
    with pytest.raises(PipelineError, match="water.json"):
        read_truth_water(bad)


# -- open water (the survey path) --------------------------------------------------------------

SURVEY = dive.DiveSpec(views=2, width=32, height=24, path="survey",
                       water=water_params("coastal_3c"), seed=1, fov_deg=65.0, supersample=2,
                       seabed_amplitude=0.08)


@pytest.fixture(scope="module")
def survey_written(tmp_path_factory):
    root = tmp_path_factory.mktemp("survey") / "dive"
    plan = dive.plan_dive(SURVEY, {})
    views = list(dive.render_views(SURVEY, plan))
    names = truth.view_names(SURVEY.views)
    frames = []
    for name, view in zip(names, views):
        truth.write_view(root, name, view, SURVEY.sensor, plan.camera)
        frames.append(truth.truth_frame(name, plan.camera, view.c2w, view.range_m, "test"))
    open_water = sum(int(np.isinf(view.range_m).sum()) for view in views)
    truth.write_records(root, SURVEY, plan, frames, test_every=1, open_water_pixels=open_water)
    return root, open_water


def test_open_water_is_stored_as_infinite_range_with_finite_bounds(survey_written):
    root, open_water_pixels = survey_written
    cameras = read_cameras(root / "truth" / "cameras.json")
    c_med = np.float32(SURVEY.water.c_med)
    for frame in cameras.frames:
        depth = read_truth_image(root / "truth", "depth", frame.name)
        open_water = np.isposinf(depth)
        assert open_water.any() and not np.isnan(depth).any()
        surface = depth[~open_water]
        assert frame.near == pytest.approx((1 - truth.NEAR_FAR_MARGIN) * surface.min())
        assert frame.far == pytest.approx((1 + truth.NEAR_FAR_MARGIN) * surface.max())
        water = read_image(cameras.image_path(frame))
        assert np.isfinite(water).all()
        # open water in every subsample: c_med exactly; at its edge, a mix with the surface
        padded = np.pad(open_water, 1, mode="edge")
        interior = open_water & np.all([padded[1 + dy:1 + dy + open_water.shape[0],
                                               1 + dx:1 + dx + open_water.shape[1]]
                                        for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0)
        assert interior.any()
        np.testing.assert_array_equal(water[interior], np.broadcast_to(c_med, water[
            interior].shape))
        clean = read_truth_image(root / "truth", "clean", frame.name)
        assert np.isfinite(clean).all() and np.all(clean[open_water] == 0.0)
    assert np.isfinite(cameras.near) and np.isfinite(cameras.far)
    scene = json.loads((root / "truth" / "scene.json").read_text())
    assert scene["path"] == "survey" and scene["open_water_pixels"] == open_water_pixels > 0
    assert scene["seabed"]["slope"] > 0
    readme = (root / "README.md").read_text()
    assert "`+inf`" in readme and "exactly `c_med`" in readme and "path `survey`" in readme
    assert "each subsample ray at its own range" in readme


def test_truth_scores_leave_open_water_out(survey_written):
    """Restored and depth scores against the truth ignore pixels whose true range is infinite:
    whatever a model renders there (no clean truth exists), the scores do not change."""
    root, _ = survey_written
    name = truth.view_names(SURVEY.views)[0]
    clean, water, depth = (read_truth_image(root / "truth", kind, name)
                           for kind in ("clean", "water", "depth"))
    open_water = np.isinf(depth)
    rng = np.random.default_rng(0)
    restored = np.clip(clean + rng.normal(0.0, 0.01, clean.shape), 0, None).astype(np.float32)
    rendered_depth = np.where(open_water, 60.0, depth * 1.02).astype(np.float32)

    def scores(open_water_colour: float) -> dict[str, float]:
        return truth_eval.view_truth_metrics(
            full=water, restored=np.where(open_water[..., None], open_water_colour, restored),
            depth=rendered_depth, clean=clean, water=water, truth_depth=depth,
            gain=np.ones(3), metres_per_unit=1.0)

    dark, bright = scores(0.0), scores(0.8)
    # (full_vs_water is infinite: the full render here is the water truth itself)
    assert all(np.isfinite(value) for key, value in dark.items()
               if key != "full_vs_water_psnr_linear")
    for key in ("restored_psnr_linear", "restored_ssim_linear", "restored_psnr_srgb"):
        assert dark[key] == pytest.approx(bright[key]), key
    assert dark["depth_median_abs_rel"] == pytest.approx(0.02, rel=1e-3)


def test_truth_sparse_model_is_read_as_colmap_points_on_the_true_surfaces(tmp_path):
    from seathru.io.tracks import track_observations

    spec = dive.DiveSpec(views=6, width=32, height=24, path="survey",
                         water=water_params("default"), seed=1, fov_deg=60.0,
                         supersample=1, seabed_amplitude=0.3)
    root = tmp_path / "dive"
    plan = dive.plan_dive(spec, {})
    frames = []
    for name, view in zip(truth.view_names(spec.views), dive.render_views(spec, plan)):
        truth.write_view(root, name, view, spec.sensor, plan.camera)
        frames.append(truth.truth_frame(name, plan.camera, view.c2w, view.range_m, "train"))
    truth.write_records(root, spec, plan, frames, test_every=0, open_water_pixels=0)
    model_dir = truth.write_truth_sparse_model(root, per_view=60, seed=1)
    assert model_dir == root / "truth" / truth.SPARSE_DIR
    cameras = read_cameras(root / "truth" / "cameras.json")
    obs = track_observations(cameras, model_dir)
    ids, counts = np.unique(obs.track_ids, return_counts=True)
    assert len(ids) > 30 and (counts >= 2).all()
    for index, frame in enumerate(cameras.frames):
        here = obs.frames == index
        depth = read_truth_image(root / "truth", "depth", frame.name)
        # within the 1% a view's range must agree to see a point (float32 images)
        np.testing.assert_allclose(obs.ranges[here], depth[obs.rows[here], obs.cols[here]],
                                   rtol=0.011)
    with pytest.raises(PipelineError, match="cameras.json"):
        truth.write_truth_sparse_model(tmp_path / "elsewhere")
