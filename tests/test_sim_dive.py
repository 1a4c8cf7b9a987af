"""seathru.sim.dive: the dive plan and per-view synthesis (pure numpy, no files)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from seathru.sim import dive, sensor
from seathru.sim.water import water_image, water_params

SPEC = dive.DiveSpec(views=3, width=16, height=12, path="orbit", water=water_params("default"),
                     seed=5, fov_deg=65.0, supersample=1, seabed_amplitude=0.08)


@pytest.fixture(scope="module")
def plan() -> dive.DivePlan:
    return dive.plan_dive(SPEC, {})


@pytest.fixture(scope="module")
def views(plan) -> list[dive.SimulatedView]:
    return list(dive.render_views(SPEC, plan))


@pytest.mark.parametrize("field, value", [
    ("views", 0), ("width", 15), ("height", 6), ("path", "spiral"), ("fov_deg", 5.0),
    ("supersample", 9), ("seabed_amplitude", -0.1)])
def test_spec_refuses_out_of_range_values_naming_the_field(field, value):
    with pytest.raises(ValueError, match=f"^{field}: "):
        dataclasses.replace(SPEC, **{field: value})


def test_plan_is_deterministic_given_the_seed(plan):
    again = dive.plan_dive(SPEC, {})
    np.testing.assert_array_equal(again.poses, plan.poses)
    assert again.exposures == plan.exposures and again.dn_per_unit == plan.dn_per_unit
    other = dive.plan_dive(dataclasses.replace(SPEC, seed=6), {})
    assert not np.array_equal(other.poses, plan.poses)
    assert len(plan.poses) == len(plan.exposures) == len(plan.noise_seeds) == SPEC.views
    assert (plan.camera.width, plan.camera.height) == (SPEC.width, SPEC.height)


def test_calibration_maps_the_metered_radiance_to_the_metering_fraction(plan):
    config = SPEC.sensor
    nominal = sensor.Exposure(config.nominal_exposure_s, config.iso, config.f_number, 0.0)
    signal = sensor.expected_signal(np.array(plan.metered_radiance), nominal, plan.dn_per_unit)
    assert float(signal) == pytest.approx(config.metering_fraction * config.range_dn)


def test_views_follow_the_water_model_and_the_sensor(plan, views):
    assert len(views) == SPEC.views
    for view, c2w, exposure in zip(views, plan.poses, plan.exposures):
        np.testing.assert_array_equal(view.c2w, c2w)
        assert view.exposure == exposure
        assert view.clean.shape == view.water.shape == view.jpeg.shape == (12, 16, 3)
        assert view.range_m.shape == view.raw.shape == (12, 16)
        assert view.raw.dtype == np.uint16 and view.jpeg.dtype == np.float32
        np.testing.assert_array_equal(view.water, water_image(view.clean, view.range_m,
                                                              SPEC.water))
        np.testing.assert_array_equal(view.jpeg, sensor.develop_jpeg(view.raw, SPEC.sensor))
        assert view.raw.max() <= SPEC.sensor.white_level
        # the raw follows the exposure: its mean above black is the expected signal's, up to noise
        expected = sensor.expected_signal(view.water, exposure, plan.dn_per_unit).mean()
        above_black = view.raw.astype(np.float64).mean() - SPEC.sensor.black_level
        assert above_black == pytest.approx(expected, rel=0.1)


def test_views_do_not_depend_on_the_worker_count(plan, views):
    parallel = list(dive.render_views(SPEC, plan, workers=2))
    for one, two in zip(views, parallel):
        np.testing.assert_array_equal(one.raw, two.raw)
        np.testing.assert_array_equal(one.water, two.water)


SURVEY = dataclasses.replace(SPEC, path="survey", views=4, width=32, height=24, seed=7)


def test_survey_is_deterministic_given_the_seed():
    plan = dive.plan_dive(SURVEY, {})
    again = dive.plan_dive(SURVEY, {})
    np.testing.assert_array_equal(again.poses, plan.poses)
    first, second = (list(dive.render_views(SURVEY, p)) for p in (plan, again))
    for one, two in zip(first, second):
        for name in ("raw", "water", "clean", "range_m", "jpeg"):
            np.testing.assert_array_equal(getattr(one, name), getattr(two, name))
    assert any(np.isposinf(view.range_m).any() for view in first)  # it is the open-water path
    other = dive.plan_dive(dataclasses.replace(SURVEY, seed=8), {})
    assert not np.array_equal(other.poses, plan.poses)


def test_each_path_has_its_scene():
    reef_scene = dive.build_scene("survey", {}, 0, 0.08)
    plain = dive.build_scene("orbit", {}, 0, 0.08)
    assert reef_scene.seabed.slope > 0.3 and plain.seabed.slope == 0.0
    assert plain.seabed.amplitude == reef_scene.seabed.amplitude == 0.08
