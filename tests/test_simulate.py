"""The synthetic dive simulator: ray casting, water model, sensor, DNG round trip, CLI output."""

from __future__ import annotations

import functools
import json
import math
import typing

import exifread
import numpy as np
import pytest
import rawpy
import tifffile
from hypothesis import example, given, settings
from hypothesis import strategies as st

from seathru.cli import main as cli_main
from seathru.geometry.intrinsics import focal_from_metadata
from seathru.sim import dive as dive_mod
from seathru.sim import reef
from seathru.sim import scene as scene_mod
from seathru.sim.camera_paths import look_at, orbit_path, transect_path
from seathru.sim.shapes import Box, Ellipsoid, Seabed
from seathru.sim import sensor as sensor_mod
from seathru.sim.water import PRESETS, WaterParams, WaterPreset, water_image, water_params
from seathru.io.cameras import read_cameras
from seathru.io.dng import decode_linear, read_dng_metadata
from seathru.io.raw import read_exif
from seathru.steps.simulate import Settings, simulate

VIEWS, WIDTH, HEIGHT = 4, 96, 72
NAMES = [f"dive_{i:04d}" for i in range(VIEWS)]


@pytest.fixture(scope="module")
def dive(tmp_path_factory):
    """A small default-water orbit written through the CLI."""
    out = tmp_path_factory.mktemp("sim") / "dive"
    code = cli_main(["simulate", "--out", str(out), "--views", str(VIEWS), "--width", str(WIDTH),
                     "--height", str(HEIGHT), "--seed", "3"])
    assert code == 0
    return out


@functools.cache
def _flat_scene() -> scene_mod.Scene:
    """Nothing but the plane z = 0."""
    return scene_mod.build_dive_scene({}, seed=0, seabed=Seabed(amplitude=0.0),
                                      objects=[])


# ------------------------------------------------------------------------------ ray casting

@settings(max_examples=25, deadline=None)
@given(h=st.floats(0.3, 20.0), fov=st.floats(20.0, 120.0))
def test_nadir_camera_over_flat_seabed_sees_h_over_cos(h, fov):
    camera = sensor_mod.Pinhole.from_fov(9, 7, fov)  # odd size: a pixel centre on the axis
    c2w = look_at((0.3, -0.2, h), (0.3, -0.2, 0.0))
    origin, dirs = sensor_mod.pixel_rays(camera, c2w, supersample=1)
    _, depth = scene_mod.render_view(_flat_scene(), origin, dirs)
    assert depth[3, 4] == pytest.approx(h, rel=1e-6)
    u, v = np.meshgrid(np.arange(9) + 0.5, np.arange(7) + 0.5)
    tan2 = ((u - camera.cx) / camera.fx) ** 2 + ((v - camera.cy) / camera.fy) ** 2
    cos_angle = 1.0 / np.sqrt(1.0 + tan2)
    np.testing.assert_allclose(depth, h / cos_angle, rtol=1e-6)


def test_supersampled_range_is_mean_of_subsample_ranges():
    h = 2.0
    camera = sensor_mod.Pinhole.from_fov(8, 6, 70.0)
    c2w = look_at((0.0, 0.0, h), (0.0, 0.0, 0.0))
    origin, dirs = sensor_mod.pixel_rays(camera, c2w, supersample=3)
    _, depth = scene_mod.render_view(_flat_scene(), origin, dirs)
    expected = (h / -dirs[..., 2]).mean(axis=2)
    np.testing.assert_allclose(depth, expected, rtol=1e-6)
    assert depth.min() > h  # no subsample lies exactly on the axis with an even grid


def test_sphere_and_box_ranges_are_exact():
    sphere = Ellipsoid("s", (0.0, 0.0, 1.0), (0.5, 0.5, 0.5))
    box = Box("b", (3.0, 0.0, 1.0), (0.4, 0.3, 0.2), yaw=0.0)
    scene = scene_mod.build_dive_scene({}, seabed=Seabed(amplitude=0.0),
                                       objects=[sphere, box])
    eye = np.array([0.0, 0.0, 4.0])
    dirs = np.array([[0.0, 0.0, -1.0], [3.0, 0.0, -2.8], [1.0, 0.0, -0.2]])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t, index = scene_mod.cast_rays(scene, eye, dirs)
    assert t[0] == pytest.approx(4.0 - 1.5) and index[0] == 0
    # Towards the box top (z = 1.2) at x = 3: the ray reaches z = 1.2 after 2.8 m of drop.
    assert t[1] == pytest.approx(math.hypot(3.0, 2.8)) and index[1] == 1
    # A shallow ray over everything hits the seabed plane z = 0 at range 4 / dz.
    assert index[2] == scene_mod.SEABED and t[2] == pytest.approx(4.0 / 0.2 * math.hypot(1, 0.2))


def test_undulating_seabed_hit_is_on_surface_and_first():
    seabed = Seabed(amplitude=0.15)
    rng = np.random.default_rng(0)
    n = 400
    origins = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-3, 3, n),
                               rng.uniform(0.5, 3.0, n)])
    dirs = np.column_stack([rng.normal(size=n), rng.normal(size=n), -rng.uniform(0.15, 1.0, n)])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t = seabed.intersect(origins, dirs)
    assert np.all(np.isfinite(t))
    hit = origins + t[:, None] * dirs
    np.testing.assert_allclose(hit[:, 2], seabed.height(hit[:, 0], hit[:, 1]), atol=1e-9)
    fractions = np.linspace(0.0, 0.999, 400)
    before = origins[:, None, :] + (t[:, None] * fractions)[..., None] * dirs[:, None, :]
    assert np.all(before[..., 2] > seabed.height(before[..., 0], before[..., 1]) - 1e-9)


def test_open_water_gives_infinite_range_zero_clean_and_c_med():
    camera = sensor_mod.Pinhole.from_fov(8, 6, 40.0)
    c2w = look_at((0.0, 0.0, 1.0), (5.0, 0.0, 3.0))  # looking up: no surface
    origin, dirs = sensor_mod.pixel_rays(camera, c2w, supersample=2)
    clean, depth = scene_mod.render_view(_flat_scene(), origin, dirs)
    assert np.all(np.isposinf(depth)) and np.all(clean == 0.0)
    for params in (PRESETS["default"], PRESETS["clear"]):
        np.testing.assert_array_equal(water_image(clean, depth, params),
                                      np.broadcast_to(np.float32(params.c_med), clean.shape))
    # NaN ranges (older outputs) and non-finite clean values there give c_med too, never NaN.
    nan_clean = np.full_like(clean, np.nan)
    np.testing.assert_array_equal(water_image(nan_clean, np.full_like(depth, np.nan),
                                              PRESETS["turbid"]),
                                  np.broadcast_to(np.float32(PRESETS["turbid"].c_med),
                                                  clean.shape))


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), slope_deg=st.floats(5.0, 40.0),
       amplitude=st.sampled_from([0.0, 0.08, 0.15]))
@example(seed=16, slope_deg=31.2890625, amplitude=0.15)   # a ray grazing the slope for ~1 m
def test_reef_slope_hit_is_on_surface_and_first_and_misses_stay_above(seed, slope_deg,
                                                                     amplitude):
    """Rays in every direction (up the slope too) from points above a reef slope: a hit lies on
    the seabed with nothing before it; a miss stays above the seabed along the whole ray."""
    seabed = Seabed(amplitude=amplitude, slope=math.tan(math.radians(slope_deg)),
                              slope_direction=0.7, crest=2.0, crest_width=0.8)
    rng = np.random.default_rng(seed)
    n = 300
    xy = rng.uniform(-3.0, 3.0, (n, 2))
    origins = np.column_stack([xy, seabed.height(xy[:, 0], xy[:, 1])
                               + rng.uniform(0.3, 2.0, n)])
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t = seabed.intersect(origins, dirs)
    hit = np.isfinite(t)
    assert 0.1 < hit.mean() < 0.95  # the sample holds both
    points = origins[hit] + t[hit, None] * dirs[hit]
    np.testing.assert_allclose(points[:, 2], seabed.height(points[:, 0], points[:, 1]),
                               atol=1e-8)
    fractions = np.linspace(0.0, 0.999, 2000)
    before = origins[hit, None, :] + (t[hit, None] * fractions)[..., None] * dirs[hit, None, :]
    assert np.all(before[..., 2] > seabed.height(before[..., 0], before[..., 1]) - 1e-9)
    # Misses: sampled densely out to 200 m the ray never goes below the seabed.
    along = np.linspace(0.0, 200.0, 20_001)
    missed = origins[~hit, None, :] + along[None, :, None] * dirs[~hit, None, :]
    assert np.all(missed[..., 2] > seabed.height(missed[..., 0], missed[..., 1]))


def test_reef_slope_height_gradient_matches_finite_differences():
    seabed = Seabed(amplitude=0.08, slope=0.5, slope_direction=1.2, crest=1.0,
                              crest_width=0.6)
    x, y = np.meshgrid(np.linspace(-4, 4, 9), np.linspace(-4, 4, 9))
    height, gx, gy = seabed.height_and_gradient(x, y)
    np.testing.assert_allclose(height, seabed.height(x, y), atol=1e-12)
    step = 1e-6
    np.testing.assert_allclose(gx, (seabed.height(x + step, y) - seabed.height(x - step, y))
                               / (2 * step), atol=1e-6)
    np.testing.assert_allclose(gy, (seabed.height(x, y + step) - seabed.height(x, y - step))
                               / (2 * step), atol=1e-6)
    assert np.hypot(gx, gy).max() <= seabed.lipschitz()
    assert height.max() <= seabed.top()
    # Far below the crest the slope rises at its gradient; far above it the reef top is flat.
    u = lambda px, py: px * math.cos(1.2) + py * math.sin(1.2)  # noqa: E731
    flat = Seabed(amplitude=0.0, slope=0.5, slope_direction=1.2, crest=1.0)
    assert flat.height(np.array(-20 * math.cos(1.2)), np.array(-20 * math.sin(1.2))) \
        == pytest.approx(0.5 * u(-20 * math.cos(1.2), -20 * math.sin(1.2)), abs=1e-9)
    assert flat.height(np.array(30 * math.cos(1.2)), np.array(30 * math.sin(1.2))) \
        == pytest.approx(0.5 * 1.0, abs=1e-9)


@pytest.mark.parametrize("path", ["orbit", "transect"])
def test_paths_are_rotations_looking_at_the_scene(path):
    scene = scene_mod.build_dive_scene({}, seed=1)
    rng = np.random.default_rng(2)
    poses = (orbit_path(scene, 8, rng) if path == "orbit"
             else transect_path(scene, 8, rng))
    camera = sensor_mod.Pinhole.from_fov(32, 24, 65.0)
    for c2w in poses:
        rotation = c2w[:3, :3]
        np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
        assert np.linalg.det(rotation) == pytest.approx(1.0)
        np.testing.assert_array_equal(c2w[3], [0, 0, 0, 1])
        assert c2w[2, 3] > 1.0  # above the seabed
        assert c2w[2, 2] < -0.3  # optical axis (z) points down into the scene
        origin, dirs = sensor_mod.pixel_rays(camera, c2w, supersample=1)
        _, depth = scene_mod.render_view(scene, origin, dirs)
        assert np.isfinite(depth).mean() > 0.99
        assert np.nanmedian(depth) < 8.0
    if path == "orbit":  # the orbit target is near the image centre in every view
        for c2w in poses:
            local = c2w[:3, :3].T @ (np.asarray(scene.target) - c2w[:3, 3])
            u = camera.fx * local[0] / local[2] + camera.cx
            v = camera.fy * local[1] / local[2] + camera.cy
            assert local[2] > 0 and abs(u - camera.cx) < 0.15 * camera.width \
                and abs(v - camera.cy) < 0.15 * camera.height


def test_colmap_registers_a_small_survey_with_centres_within_one_percent(tmp_path):
    """14 survey views (320x240): every view registers, camera centres within 1% of the
    trajectory's extent after a similarity alignment, the camera rotations agree."""
    from seathru.cli import build_parser
    from seathru.geometry.poses import compare_trajectories, denormalise_c2w

    simulate(tmp_path / "sim", Settings(views=14, path="survey", supersample=1, seed=0))
    ingest = tmp_path / "ingest"  # the layout poses reads: JPEGs to match, linear images
    ingest.mkdir()
    (ingest / "matching").symlink_to(tmp_path / "sim" / "jpeg", target_is_directory=True)
    (ingest / "linear").symlink_to(tmp_path / "sim" / "truth" / "water",
                                   target_is_directory=True)
    args = build_parser().parse_args(["poses", "--ingest", str(ingest), "--out",
                                      str(tmp_path / "poses"), "--threads", "1"])
    args._run(args)

    def poses(path):
        cameras = read_cameras(path)
        return {f.name: denormalise_c2w(f.c2w_array, cameras.centre, cameras.scale)
                for f in cameras.frames}

    found, expected = poses(tmp_path / "poses" / "cameras.json"), poses(
        tmp_path / "sim" / "truth" / "cameras.json")
    assert sorted(found) == sorted(expected)
    names = sorted(expected)
    estimate, reference = (np.array([p[n] for n in names]) for p in (found, expected))
    comparison = compare_trajectories(estimate, reference)
    assert comparison.max_relative_position_error < 0.01
    assert comparison.rotation_errors_deg.max() < 1.5
    # The path is nearly straight, so the alignment's roll about it comes from small sways;
    # the relative rotations between the views are sharper.
    relative = [np.degrees(np.arccos(np.clip((np.trace(
        (estimate[i, :3, :3].T @ estimate[i + 1, :3, :3]).T
        @ (reference[i, :3, :3].T @ reference[i + 1, :3, :3])) - 1) / 2, -1, 1)))
        for i in range(len(names) - 1)]
    assert max(relative) < 0.5


# ------------------------------------------------------------------------------ water model

@settings(max_examples=50, deadline=None)
@given(j=st.lists(st.floats(0.0, 1.0), min_size=3, max_size=3),
       z=st.floats(0.0, 50.0),
       attn=st.lists(st.floats(0.0, 3.0), min_size=3, max_size=3),
       bs=st.lists(st.floats(0.0, 3.0), min_size=3, max_size=3),
       med=st.lists(st.floats(0.0, 1.0), min_size=3, max_size=3))
def test_water_image_matches_float64_reference(j, z, attn, bs, med):
    params = WaterParams(tuple(attn), tuple(bs), tuple(med))
    clean = np.array(j, np.float32).reshape(1, 1, 3)
    got = water_image(clean, np.array([[z]], np.float32), params)[0, 0]
    zz = float(np.float32(z))
    jj = clean[0, 0].astype(np.float64)
    expected = [jj[c] * math.exp(-attn[c] * zz) + med[c] * (1.0 - math.exp(-bs[c] * zz))
                for c in range(3)]
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-7)


@settings(max_examples=50, deadline=None)
@example(radiance=[[0.5, 0.4, 0.3], [0.1, 0.2, 0.2]], ranges=[1.0, 10.0])  # an occluding edge
@example(radiance=[[0.3, 0.3, 0.3], [0.0, 0.0, 0.0]], ranges=[2.0, math.inf])  # the skyline
@given(radiance=st.lists(st.lists(st.floats(0.0, 1.0), min_size=3, max_size=3), min_size=1,
                         max_size=4),
       ranges=st.lists(st.one_of(st.floats(0.0, 50.0), st.just(math.inf)), min_size=4,
                       max_size=4))
def test_a_pixel_with_water_is_the_mean_of_its_rays_each_at_its_own_range(radiance, ranges):
    params = PRESETS["default"]
    count = len(radiance)
    ranges = ranges[:count]
    got = dive_mod.subsampled_water_image(np.array(radiance).reshape(1, 1, count, 3),
                                          np.array(ranges).reshape(1, 1, count), params)[0, 0]
    rays = [[params.c_med[c] if math.isinf(z) else
             j[c] * math.exp(-params.sigma_attn[c] * z)
             + params.c_med[c] * (1.0 - math.exp(-params.sigma_bs[c] * z)) for c in range(3)]
            for j, z in zip(radiance, ranges)]
    np.testing.assert_allclose(got, np.mean(rays, axis=0), rtol=1e-6, atol=1e-7)
    if count == 2 and ranges == [1.0, 10.0]:
        # at the pixel's mean range, 5.5 m, red would be half as bright
        at_mean = water_image(np.mean(radiance, axis=0).reshape(1, 1, 3), np.array([[5.5]]),
                              params)[0, 0]
        assert got[0] > 1.5 * at_mean[0]


def test_clear_water_image_equals_clean_image_exactly():
    scene = scene_mod.build_dive_scene({}, seed=4)
    camera = sensor_mod.Pinhole.from_fov(40, 30, 65.0)
    c2w = orbit_path(scene, 3, np.random.default_rng(0))[1]
    origin, dirs = sensor_mod.pixel_rays(camera, c2w, supersample=2)
    clean, depth = scene_mod.render_view(scene, origin, dirs)
    assert np.isfinite(depth).all()
    water = water_image(clean, depth, water_params("clear"))
    np.testing.assert_array_equal(water, clean)
    assert not np.array_equal(water_image(clean, depth, water_params("default")), clean)


def test_water_params_scale_and_override():
    scaled = water_params("default", scale=2.0)
    np.testing.assert_allclose(scaled.sigma_attn, 2.0 * np.array(PRESETS["default"].sigma_attn))
    custom = water_params("default", sigma_bs=[0.1, 0.2, 0.3])
    assert custom.sigma_bs == (0.1, 0.2, 0.3) and custom.preset == "default+custom"
    turbid = PRESETS["turbid"]
    assert math.exp(-turbid.sigma_attn[1] * 3.5) == pytest.approx(0.1, abs=0.01)


JERLOV = [name for name in PRESETS if name.startswith(("oceanic_", "coastal_"))]


def test_water_presets_span_clear_oceanic_to_turbid_coastal():
    assert {"default", "clear", "turbid"} <= set(PRESETS) and len(JERLOV) >= 6
    assert all(params.preset == name for name, params in PRESETS.items())
    distinct = {(p.sigma_attn, p.sigma_bs, p.c_med) for p in PRESETS.values()}
    assert len(distinct) == len(PRESETS)
    for name in ["default", *JERLOV]:  # turbid keeps its published values, G = B backscatter
        attn, bs, med = (np.array(v) for v in (PRESETS[name].sigma_attn, PRESETS[name].sigma_bs,
                                               PRESETS[name].c_med))
        for values in (attn, bs, med):
            assert np.all(values > 0) and len(set(values.tolist())) == 3, name
        assert np.all(np.abs(attn - bs) > 0.1 * attn), name  # backscatter is not attenuation
    # In the listed order, from the clearest oceanic to the most turbid coastal water: the mean
    # attenuation and the blue attenuation grow; oceanic water takes red first, coastal water
    # takes blue before green (dissolved matter).
    mean_attn = [float(np.mean(PRESETS[name].sigma_attn)) for name in JERLOV]
    blue = [PRESETS[name].sigma_attn[2] for name in JERLOV]
    assert mean_attn == sorted(mean_attn) and blue == sorted(blue)
    for name in JERLOV:
        red, green, blue_ = PRESETS[name].sigma_attn
        assert red > green, name
        if name.startswith("oceanic_"):
            assert red > blue_, name
        else:
            assert blue_ > green, name


@pytest.mark.parametrize("preset", list(PRESETS))
def test_every_preset_forms_finite_images_with_open_water(preset):
    clean = np.array([[[0.3, 0.2, 0.1], [0.0, 0.0, 0.0], [0.5, 0.5, 0.5]]], np.float32)
    depth = np.array([[0.5, np.inf, 40.0]], np.float32)
    image = water_image(clean, depth, water_params(preset))
    assert np.isfinite(image).all()
    np.testing.assert_array_equal(image[0, 1], np.float32(PRESETS[preset].c_med))


# ------------------------------------------------------------------------------ survey

SURVEY_SPEC = dive_mod.DiveSpec(views=24, width=64, height=48, path="survey",
                                water=water_params("default"), seed=0, fov_deg=65.0,
                                supersample=1, seabed_amplitude=0.08)


@pytest.fixture(scope="module")
def survey() -> list[dive_mod.SimulatedView]:
    """The demo's survey (24 views) at 64x48 pixels, procedural textures."""
    plan = dive_mod.plan_dive(SURVEY_SPEC, {})
    return list(dive_mod.render_views(SURVEY_SPEC, plan))


def test_survey_sees_open_water_in_every_frame_and_ranges_from_half_a_metre_to_beyond_20(
        survey):
    finite = []
    for view in survey:
        open_water = ~np.isfinite(view.range_m)
        assert np.all(np.isposinf(view.range_m[open_water]))
        assert 0.02 < open_water.mean() < 0.5  # open water in part of every frame
        # above the crest line: the top row is mostly open water, the bottom row is reef
        assert open_water[0].mean() > 0.4 and not open_water[-1].any()
        finite.append(view.range_m[~open_water])
    ranges = np.concatenate(finite)
    assert ranges.min() < 0.6 and ranges.max() > 20.0
    assert np.mean(ranges > 10.0) > 0.005 and np.median(ranges) < 5.0


def test_survey_water_formation_is_finite_with_c_med_in_open_water(survey):
    c_med = np.float32(SURVEY_SPEC.water.c_med)
    for view in survey:
        open_water = ~np.isfinite(view.range_m)
        assert np.isfinite(view.water).all() and np.isfinite(view.clean).all()
        assert np.isfinite(view.jpeg).all()
        np.testing.assert_array_equal(view.water[open_water], np.broadcast_to(
            c_med, (int(open_water.sum()), 3)))
        assert np.all(view.clean[open_water] == 0.0)
        # One subsample a pixel: the water at the pixel's range is the water of its one ray.
        np.testing.assert_array_equal(view.water, water_image(view.clean, view.range_m,
                                                              SURVEY_SPEC.water))


def test_survey_path_swims_along_the_reef_looking_up_the_slope():
    scene = reef.build_reef_scene({}, seed=0)
    poses = reef.survey_path(scene, 24, np.random.default_rng(0))
    for c2w in poses:
        rotation = c2w[:3, :3]
        np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
        assert np.linalg.det(rotation) == pytest.approx(1.0)
        centre, forward = c2w[:3, 3], rotation[:, 2]
        ground = float(scene.seabed.height(centre[0], centre[1]))
        assert 0.9 < centre[2] - ground < 1.5  # about a metre above the reef
        assert forward[1] > 0.5 and abs(forward[2]) < 0.3  # up the slope, near the horizon
        assert centre[1] < scene.seabed.crest - 3.0  # downslope of the crest
    travel = poses[-1, :3, 3] - poses[0, :3, 3]
    assert travel[0] > 3.0 and abs(travel[1]) < 0.5  # along the contour (x)


# ------------------------------------------------------------------------------ sensor

def test_raw_noise_follows_poisson_gaussian_model():
    config = sensor_mod.SensorConfig()
    rng = np.random.default_rng(5)
    for level in (0.0, 300.0, 4000.0):
        raw = sensor_mod.capture_raw(np.full((200, 200), level), config.iso, config, rng)
        value = raw.astype(np.float64) - config.black_level
        sigma = float(sensor_mod.noise_sigma_dn(np.array(level), config.iso, config))
        assert value.mean() == pytest.approx(level, abs=4 * sigma / 200 + 0.5)
        assert value.std() == pytest.approx(sigma, rel=0.05)
    saturated = sensor_mod.capture_raw(np.full((4, 4), 1e6), config.iso, config, rng)
    assert np.all(saturated == config.white_level)


@settings(max_examples=40, deadline=None)
@given(level=st.integers(0, 16383))
def test_camera_jpeg_matches_float64_reference(level):
    config = sensor_mod.SensorConfig()
    raw = np.full((4, 6), level, dtype=np.uint16)  # flat: demosaicing keeps the value
    normalised = min(max((level - config.black_level) / config.range_dn, 0.0), 1.0)
    linear = min(max(sensor_mod.JPEG_WHITE / config.metering_fraction * normalised, 0.0), 1.0)
    expected = linear * 12.92 if linear <= 0.0031308 else 1.055 * linear ** (1 / 2.4) - 0.055
    np.testing.assert_allclose(sensor_mod.develop_jpeg(raw, config), expected, atol=1e-6)


def test_the_camera_jpegs_auto_white_balance_greys_each_frame_within_its_limit():
    config = sensor_mod.SensorConfig(jpeg_white_balance="auto")
    rng = np.random.default_rng(3)
    for cast in ((0.2, 0.5, 0.6), (0.05, 0.5, 0.4)):   # blue-green water; red faded past 4x
        signal = np.ones((32, 48, 3)) * np.array(cast) * config.range_dn * 0.5
        signal *= rng.uniform(0.8, 1.2, (32, 48, 1))
        raw = sensor_mod.capture_raw(sensor_mod.mosaic_rggb(signal), config.iso, config, rng)
        developed = sensor_mod.normalise_raw(sensor_mod.demosaic_bilinear(raw), config)
        gains = sensor_mod.auto_white_balance_gains(developed)
        means = developed.astype(np.float64).reshape(-1, 3).mean(0)
        reference = np.clip(means[1] / means, 0.25, 4.0)      # float64, written out
        np.testing.assert_allclose(gains, reference, rtol=1e-9)
        balanced = sensor_mod.develop_jpeg(raw, config)
        plain = sensor_mod.develop_jpeg(raw, sensor_mod.SensorConfig())
        assert not np.allclose(balanced, plain)
        linear = balanced ** 2.2                                  # near enough for the means
        ratio = linear[..., 0].mean() / linear[..., 1].mean()
        assert (ratio == pytest.approx(1.0, abs=0.1)) == (gains[0] < 4.0)


def test_choices_of_the_settings_are_the_tables():
    assert typing.get_args(dive_mod.CameraPath) == tuple(dive_mod.CAMERA_PATHS)
    assert typing.get_args(WaterPreset) == tuple(PRESETS)


# ------------------------------------------------------------------------------ written files

def test_cli_writes_every_documented_file(dive):
    for name in NAMES:
        for rel in (f"raw/{name}.dng", f"jpeg/{name}.jpg", f"truth/clean/{name}.tiff",
                    f"truth/water/{name}.tiff", f"truth/depth/{name}.tiff"):
            assert (dive / rel).is_file(), rel
    for rel in ("truth/cameras.json", "truth/water.json", "truth/sensor.json",
                "truth/scene.json", "README.md"):
        assert (dive / rel).is_file(), rel
    readme = (dive / "README.md").read_text()
    for rel in ("raw/<name>.dng", "jpeg/<name>.jpg", "truth/clean", "truth/water",
                "truth/depth", "cameras.json", "water.json", "sensor.json", "scene.json"):
        assert rel in readme
    assert not [p for p in dive.parent.iterdir() if p.name.startswith(".")]  # no temporaries

    cameras = read_cameras(dive / "truth" / "cameras.json")
    assert cameras.source == "simulated" and cameras.scale == 1.0 and cameras.centre == [0, 0, 0]
    assert [f.name for f in cameras.frames] == NAMES
    assert [f.split for f in cameras.frames] == ["test", "train", "train", "train"]
    for frame in cameras.frames:
        image = tifffile.imread(cameras.image_path(frame))
        depth = tifffile.imread(dive / "truth" / "depth" / f"{frame.name}.tiff")
        assert image.shape == (HEIGHT, WIDTH, 3) and image.dtype == np.float32
        assert depth.shape == (HEIGHT, WIDTH)
        assert frame.near <= np.nanmin(depth) and np.nanmax(depth) <= frame.far
        assert cameras.near <= frame.near and frame.far <= cameras.far
        assert (frame.width, frame.height) == (WIDTH, HEIGHT)
    water = json.loads((dive / "truth" / "water.json").read_text())
    assert water["preset"] == "default" and "1/m" in water["units"]


def test_water_truth_follows_the_formula_not_a_swapped_one(dive):
    water = json.loads((dive / "truth" / "water.json").read_text())
    attn, bs, med = (np.array(water[k]) for k in ("sigma_attn", "sigma_bs", "c_med"))
    rng = np.random.default_rng(0)
    for name in NAMES:
        clean = tifffile.imread(dive / "truth" / "clean" / f"{name}.tiff").astype(np.float64)
        depth = tifffile.imread(dive / "truth" / "depth" / f"{name}.tiff").astype(np.float64)
        image = tifffile.imread(dive / "truth" / "water" / f"{name}.tiff").astype(np.float64)
        # The water acts on each subsample's range: the pixel follows the formula at its mean
        # range only where its range hardly changes across it (its neighbours' agree).
        padded = np.pad(depth, 1, mode="edge")
        window = np.stack([padded[1 + dy:1 + dy + HEIGHT, 1 + dx:1 + dx + WIDTH]
                           for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
        even = (window.max(axis=0) - window.min(axis=0)) < 0.02 * depth
        rows, cols = np.nonzero(even)
        assert rows.size >= 100
        pick = rng.choice(rows.size, 200)
        rows, cols = rows[pick], cols[pick]
        j, z, got = clean[rows, cols], depth[rows, cols, None], image[rows, cols]
        assert np.isfinite(z).all()
        model = j * np.exp(-attn * z) + med * (1.0 - np.exp(-bs * z))
        # (texture that changes across the pixel weighs its rays apart: a few parts in 1000)
        np.testing.assert_allclose(got, model, rtol=5e-3, atol=5e-4)
        swapped = j * np.exp(-bs * z) + med * (1.0 - np.exp(-attn * z))
        assert np.abs(got - swapped).max() > 1e-2


def test_dng_round_trip_through_rawpy(dive):
    sensor = json.loads((dive / "truth" / "sensor.json").read_text())
    black, white = sensor["black_level"], sensor["white_level"]
    span = white - black
    for name in NAMES[:2]:
        path = dive / "raw" / f"{name}.dng"
        shot = sensor["images"][name]
        meta = read_dng_metadata(path)
        assert (meta["black_level"], meta["white_level"], meta["cfa_pattern"]) == (
            black, white, "RGGB")
        assert meta["exposure_time_s"] == shot["exposure_time_s"]
        assert (meta["iso"], meta["f_number"]) == (shot["iso"], shot["f_number"])
        with open(path, "rb") as fh:
            exif = exifread.process_file(fh, details=False)
        exposure = exif["Image ExposureTime"].values[0]
        assert float(exposure.num) / float(exposure.den) == pytest.approx(shot["exposure_time_s"])
        assert int(str(exif["Image ISOSpeedRatings"])) == shot["iso"]
        # the 35 mm equivalent focal length a camera records: read back, the true focal length
        # within its rounding to whole millimetres
        frame = read_cameras(dive / "truth" / "cameras.json").frames[NAMES.index(name)]
        lens, _ = read_exif(path)
        focal_px, _ = focal_from_metadata({"focal_length_35mm": lens.focal_length_35mm},
                                          frame.width, frame.height)
        assert focal_px == pytest.approx(frame.fx, rel=0.02)
        # the camera JPEG records the same exposure and lens, as a camera's does
        jpeg, _ = read_exif(dive / "jpeg" / f"{name}.jpg")
        assert (jpeg.exposure_time, jpeg.iso, jpeg.f_number, jpeg.focal_length_35mm) == \
            pytest.approx((shot["exposure_time_s"], shot["iso"], shot["f_number"],
                           lens.focal_length_35mm), rel=1e-6)

        with rawpy.imread(str(path)) as raw:
            mosaic = raw.raw_image_visible.astype(np.float64)
            assert list(raw.black_level_per_channel) == [black] * 4
            assert raw.white_level == white
            assert raw.color_desc.decode() == "RGBG"
            assert raw.raw_pattern.tolist() == [[0, 1], [3, 2]]
        decoded = decode_linear(path).astype(np.float64)
        assert decoded.shape == (HEIGHT, WIDTH, 3)
        channel = sensor_mod.cfa_channel(HEIGHT, WIDTH)
        native = np.take_along_axis(decoded, channel[..., None], axis=2)[..., 0]
        # At each photosite the decoder keeps the sample: (raw - black) / (white - black).
        np.testing.assert_allclose(native, np.clip((mosaic - black) / span, 0, 1), atol=2e-5)

        water = tifffile.imread(dive / "truth" / "water" / f"{name}.tiff").astype(np.float64)
        scale = shot["exposure_time_s"] * shot["iso"] / 100.0 * sensor["dn_per_unit"]
        expected = np.clip(water * scale / span, 0.0, 1.0)
        expected_native = np.take_along_axis(expected, channel[..., None], axis=2)[..., 0]
        gain = sensor["gain_iso100"] * shot["iso"] / 100.0
        sigma = np.sqrt(gain * expected_native * span + sensor["read_noise_dn"] ** 2) / span
        assert np.all(np.abs(native - expected_native) <= 5.5 * sigma + 1e-4)
        # Interpolated channels: only demosaicing (and noise) error, no bias.
        error = decoded - expected
        assert abs(error.mean()) < 2e-3
        assert np.median(np.abs(error)) < 0.02


def test_rerun_replaces_output_and_refuses_foreign_folder(dive, tmp_path):
    foreign = tmp_path / "photos"
    foreign.mkdir()
    (foreign / "keep.txt").write_text("mine")
    assert cli_main(["simulate", "--out", str(foreign), "--views", "1", "--width", "16",
                     "--height", "12"]) == 2
    assert (foreign / "keep.txt").read_text() == "mine"
    assert cli_main(["simulate", "--out", str(tmp_path / "x"), "--width", "15"]) == 2


@pytest.mark.parametrize("flags, message", [
    (["--width", "15"], "width: need an even number"),
    (["--sigma-attn", "0.1", "-1", "0.2"], "sigma_attn: expected three finite values >= 0"),
    (["--water-scale", "-2"], "water_scale: expected a finite value >= 0"),
    (["--workers", "0"], "workers: need at least 1")])
def test_bad_settings_are_refused_naming_the_setting(tmp_path, capsys, flags, message):
    assert cli_main(["simulate", "--out", str(tmp_path / "x"), *flags]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_a_jpeg_chroma_sampling_the_simulator_does_not_write_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit):
        cli_main(["simulate", "--out", str(tmp_path / "x"), "--jpeg-chroma", "4:1:1"])
    assert "--jpeg-chroma: invalid choice: '4:1:1'" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_output_is_deterministic_and_independent_of_workers(tmp_path):
    base = dict(views=3, width=24, height=16, seed=11, supersample=1)
    simulate(tmp_path / "one", Settings(**base, workers=1))
    simulate(tmp_path / "two", Settings(**base, workers=2))
    for rel in ("raw/dive_0002.dng", "truth/water/dive_0001.tiff", "jpeg/dive_0000.jpg",
                "truth/cameras.json", "truth/sensor.json"):
        assert (tmp_path / "one" / rel).read_bytes() == (tmp_path / "two" / rel).read_bytes()
    other = tmp_path / "other"
    simulate(other, Settings(**{**base, "seed": 12}))
    assert (other / "raw/dive_0002.dng").read_bytes() != (tmp_path / "one" /
                                                          "raw/dive_0002.dng").read_bytes()
