"""The poses step: geometry helpers, dataset readers, COLMAP on real and simulated dives."""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
import tifffile
from hypothesis import given, settings
from hypothesis import strategies as st

from seathru.cli import build_parser
from seathru.radiometry.colour import srgb_to_linear
from seathru.geometry.poses import (FAR_MARGIN, NEAR_MARGIN, compare_trajectories,
                                   complete_bounds, denormalise_c2w, depth_bounds, frustum_corners, range_bounds, llff_to_opencv,
                                   opencv_to_llff, opencv_to_opengl, opengl_to_opencv,
                                   rotation_angle_deg, umeyama, unit_ball_normalisation)
from seathru.errors import PipelineError
from seathru.io.cameras import read_cameras
from seathru.io.warnings import read_warnings
from seathru.io.colmap import make_camera, undistortion
from seathru.io.pose_outputs import image_blur
from seathru.io.tracks import training_depth_observations
from seathru.radiometry.deblur import processing_blur
from seathru.geometry.intrinsics import focal_from_metadata

THREADS = "2"


def run_poses(*argv: str) -> None:
    """Run ``seathru poses`` in-process; PipelineError propagates."""
    args = build_parser().parse_args(["poses", *argv])
    args._run(args)


def source_c2w(path: Path) -> dict[str, np.ndarray]:
    """Camera-to-world poses of a cameras.json, by name, mapped back to source units."""
    cameras = read_cameras(path)
    return {f.name: denormalise_c2w(f.c2w_array, cameras.centre, cameras.scale)
            for f in cameras.frames}


# -- geometry --------------------------------------------------------------------------------

def rotation_from(quaternion) -> np.ndarray:
    w, x, y, z = np.asarray(quaternion, np.float64) / np.linalg.norm(quaternion)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


unit = st.floats(-1.0, 1.0, allow_nan=False)
quaternions = st.tuples(unit, unit, unit, unit).filter(lambda q: np.linalg.norm(q) > 0.2)


@settings(max_examples=60, deadline=None)
@given(quaternions, st.floats(0.01, 100.0), st.tuples(unit, unit, unit),
       st.integers(0, 2**31 - 1))
def test_umeyama_recovers_a_random_similarity(quaternion, scale, translation, seed):
    points = np.random.default_rng(seed).normal(size=(12, 3))
    rotation = rotation_from(quaternion)
    target = scale * points @ rotation.T + 10.0 * np.asarray(translation)
    found = umeyama(points, target)
    assert found.scale == pytest.approx(scale, rel=1e-9)
    np.testing.assert_allclose(found.rotation, rotation, atol=1e-9)
    np.testing.assert_allclose(found.apply(points), target, atol=1e-8 * max(1.0, scale))


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_umeyama_returns_a_proper_rotation_for_mirrored_points(seed):
    points = np.random.default_rng(seed).normal(size=(10, 3))
    mirrored = points * np.array([1.0, 1.0, -1.0])
    found = umeyama(points, mirrored, with_scale=False)
    assert found.scale == 1.0
    assert np.linalg.det(found.rotation) == pytest.approx(1.0)
    np.testing.assert_allclose(found.rotation @ found.rotation.T, np.eye(3), atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(st.tuples(unit, unit, unit).filter(lambda a: np.linalg.norm(a) > 0.1),
       st.floats(0.0, 179.0), quaternions)
def test_rotation_angle_is_the_axis_angle(axis, angle_deg, base):
    axis = np.asarray(axis) / np.linalg.norm(axis)
    half = math.radians(angle_deg) / 2.0
    turn = rotation_from([math.cos(half), *(math.sin(half) * axis)])
    start = rotation_from(base)
    assert rotation_angle_deg(start, start @ turn) == pytest.approx(angle_deg, abs=1e-5)


def test_llff_to_opencv_maps_the_axes_and_round_trips():
    rng = np.random.default_rng(3)
    rotation = rotation_from(rng.normal(size=4))
    down, right, back = rotation.T  # LLFF columns
    llff = np.concatenate([rotation, rng.normal(size=(3, 1))], axis=1)[None]
    c2w = llff_to_opencv(llff)[0]
    np.testing.assert_allclose(c2w[:3, 0], right)
    np.testing.assert_allclose(c2w[:3, 1], down)
    np.testing.assert_allclose(c2w[:3, 2], -back)
    np.testing.assert_allclose(c2w[:3, 3], llff[0, :, 3])
    assert np.linalg.det(c2w[:3, :3]) == pytest.approx(1.0)
    np.testing.assert_allclose(opencv_to_llff(c2w[None]), llff, atol=1e-15)
    gl = opencv_to_opengl(c2w)
    np.testing.assert_allclose(gl[:3, 1], -down)  # OpenGL y is up
    np.testing.assert_allclose(opengl_to_opencv(gl), c2w)


def test_depth_bounds_are_margined_percentiles_of_points_in_front():
    depths = np.concatenate([np.linspace(1.0, 10.0, 100001), [-5.0, 0.0, np.nan]])
    near, far = depth_bounds(depths)
    assert near == pytest.approx(NEAR_MARGIN * np.percentile(np.linspace(1, 10, 100001), 0.1))
    assert far == pytest.approx(FAR_MARGIN * np.percentile(np.linspace(1, 10, 100001), 99.9))
    with pytest.raises(ValueError):
        depth_bounds(np.array([-1.0, 0.0]))


@settings(max_examples=30, deadline=None)
@given(st.floats(0.2, 5.0), st.floats(1.5, 20.0), st.floats(50.0, 800.0),
       st.integers(0, 2**31 - 1))
def test_range_bounds_hold_every_pixel_ray_up_to_the_far_depth(near, stretch, focal, seed):
    rng = np.random.default_rng(seed)
    width, height = int(rng.integers(16, 640)), int(rng.integers(16, 480))
    k = np.array([[focal, 0, width * rng.uniform(0.3, 0.7)],
                  [0, focal * rng.uniform(0.8, 1.2), height * rng.uniform(0.3, 0.7)], [0, 0, 1]])
    far = near * stretch
    near_range, far_range = range_bounds(near, far, k, width, height)
    pixels = np.column_stack([rng.uniform(0, width, 500), rng.uniform(0, height, 500),
                              np.ones(500)])
    unit_depth = pixels @ np.linalg.inv(k).T
    ranges_at_far = far * np.linalg.norm(unit_depth, axis=1)   # range of depth-far points
    ranges_at_near = near * np.linalg.norm(unit_depth, axis=1)
    assert near_range == near and np.all(ranges_at_near >= near_range)
    assert np.all(ranges_at_far <= far_range * (1 + 1e-12))
    # tight: a corner ray reaches the far range exactly
    corner = np.array([0.0, 0.0, 1.0]) @ np.linalg.inv(k).T
    assert far * np.linalg.norm(corner) <= far_range * (1 + 1e-12)   # rounding: equal at best
    assert far_range == pytest.approx(far * max(np.linalg.norm(np.array([u, v, 1.0]) @ np.linalg.inv(k).T)
                                                for u in (0, width) for v in (0, height)))


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_unit_ball_normalisation_holds_every_frustum(seed):
    rng = np.random.default_rng(seed)
    count = int(rng.integers(2, 7))
    c2w = np.tile(np.eye(4), (count, 1, 1))
    for pose in c2w:
        pose[:3, :3] = rotation_from(rng.normal(size=4))
        pose[:3, 3] = rng.normal(scale=5.0, size=3) + 100.0
    k = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    fars = rng.uniform(1.0, 20.0, count)
    centre, scale = unit_ball_normalisation(c2w, np.repeat(k[None], count, 0),
                                            np.tile([320, 240], (count, 1)), fars)
    radii = []
    for pose, far in zip(c2w, fars):
        # random points inside the frustum, between the camera and its far bound
        u, v = rng.uniform(0, 320, 50), rng.uniform(0, 240, 50)
        depth = rng.uniform(0, far, 50)
        rays = np.stack([(u - 160) / 300, (v - 120) / 300, np.ones(50)], 1)
        points = (depth[:, None] * rays) @ pose[:3, :3].T + pose[:3, 3]
        radii.append(np.linalg.norm((points - centre) * scale, axis=1))
        corners = frustum_corners(pose, k, 320, 240, far)
        radii.append(np.linalg.norm((corners - centre) * scale, axis=1))
    radii = np.concatenate(radii)
    assert radii.max() <= 1.0 + 1e-9
    assert radii.max() > 0.5  # tight: the furthest frustum corner is on the sphere


def test_compare_trajectories_finds_a_displaced_camera():
    rng = np.random.default_rng(0)
    reference = np.tile(np.eye(4), (8, 1, 1))
    reference[:, :3, 3] = rng.normal(size=(8, 3))
    similarity = umeyama(rng.normal(size=(5, 3)), rng.normal(size=(5, 3)))
    estimate = reference.copy()
    estimate[:, :3, :3] = similarity.rotation.T @ reference[:, :3, :3]
    estimate[:, :3, 3] = (reference[:, :3, 3] - similarity.translation) @ similarity.rotation \
        / similarity.scale
    exact = compare_trajectories(estimate, reference)
    assert exact.max_relative_position_error < 1e-9
    assert exact.rotation_errors_deg.max() < 1e-5
    estimate[3, :3, 3] += 0.5 / similarity.scale
    assert compare_trajectories(estimate, reference).max_relative_position_error > 0.02


def test_complete_bounds_applies_overrides_and_fills_gaps_with_the_scene():
    # the scene's bounds come from the frames that have both (frame 0 only)
    near, far, filled = complete_bounds([0.5, None, 2.0], [4.0, 9.0, None])
    assert (near, far, filled) == ([0.5, 0.5, 2.0], [4.0, 9.0, 4.0], [False, True, True])
    assert complete_bounds([None, None], [3.0, None], near_override=1.0) == (
        [1.0, 1.0], [3.0, 3.0], [False, True])
    assert complete_bounds([None], [None], 0.2, 7.0) == ([0.2], [7.0], [False])
    with pytest.raises(ValueError):
        complete_bounds([None, 1.0], [2.0, None])


# -- undistortion ----------------------------------------------------------------------------

def test_undistortion_maps_rays_onto_the_pinhole_camera():
    camera = make_camera("OPENCV", 200, 150, [180.0, 185.0, 101.0, 74.0, -0.12, 0.03,
                                              0.001, -0.002])
    warp = undistortion(camera)
    # an image whose value at each pixel is the x of its normalised (undistorted) ray
    u, v = np.meshgrid(np.arange(200) + 0.5, np.arange(150) + 0.5)
    rays = camera.cam_from_img(np.stack([u.ravel(), v.ravel()], 1))
    distorted = rays[:, 0].reshape(150, 200).astype(np.float32)
    straight = warp.warp_image(np.repeat(distorted[..., None], 3, axis=2))[..., 0]
    expected = (np.arange(warp.width) + 0.5 - warp.cx) / warp.fx
    interior = straight[5:-5, 5:-5]
    np.testing.assert_allclose(interior, np.broadcast_to(expected[5:-5], interior.shape),
                               atol=2e-4)
    # COLMAP's undistorter keeps only pixels seen by the source: the whole mask stays valid
    mask = warp.warp_mask(np.ones((150, 200), bool))
    assert mask.dtype == bool and mask[2:-2, 2:-2].all()
    holes = np.ones((150, 200), bool)
    holes[60:90, 80:120] = False
    warped = warp.warp_mask(holes)
    assert 0 < (~warped).sum() < 3 * 30 * 40


def _source_and_expected(camera, warp, texture):
    """``texture`` (a function of the ray's x/z, y/z) on the distorted source camera, and what
    the undistorted camera should see of it."""
    v, u = np.mgrid[0:camera.height, 0:camera.width] + 0.5
    rays = camera.cam_from_img(np.stack([u.ravel(), v.ravel()], 1))
    source = texture(rays[:, 0], rays[:, 1]).reshape(camera.height, camera.width, 3)
    fv, fu = np.mgrid[0:warp.height, 0:warp.width] + 0.5
    return source, texture((fu - warp.cx) / warp.fx, (fv - warp.cy) / warp.fy)


def test_image_blur_follows_how_each_image_was_decoded_resized_and_resampled():
    raw = {"name": "raw", "kind": "raw", "decoder": {"demosaic": "LINEAR"},
           "source_size": [400, 300]}
    binned = {"name": "binned", "kind": "raw", "decoder": {"demosaic": "half_size"},
              "source_size": [200, 150]}
    jpeg = {"name": "jpeg", "kind": "srgb", "decoder": {}, "source_size": [200, 150]}
    warped = undistortion(make_camera("SIMPLE_RADIAL", 200, 150, [150.0, 100.0, 75.0, 0.05]))
    straight = undistortion(make_camera("SIMPLE_PINHOLE", 200, 150, [150.0, 100.0, 75.0]))
    assert straight.map_x is None and warped.map_x is not None
    # a RAW decoded at 400 px wide, trained at 200: half the demosaic's blur, plus the warp's
    assert image_blur(raw, warped, "linear") == processing_blur(
        "LINEAR", warped.width / 400, "linear")
    assert image_blur(raw, straight, "linear") == processing_blur("LINEAR", 0.5)
    assert image_blur(binned, straight, "linear") == [0.0, 0.0, 0.0]
    assert image_blur(jpeg, warped, "cubic") == [0.0, 0.0, 0.0]
    assert image_blur(jpeg, warped, "linear") == processing_blur(None, 1.0, "linear")
    assert image_blur(None, warped, "linear") is None


def test_cubic_undistortion_keeps_the_detail_bilinear_blurs():
    camera = make_camera("SIMPLE_RADIAL", 160, 120, [130.0, 80.0, 60.0, -0.02])
    warp = undistortion(camera)

    def fine(x, y):   # a period of about 4 pixels: the detail a bilinear warp averages away
        return np.stack([0.5 + 0.4 * np.sin(200 * x), 0.5 + 0.4 * np.cos(170 * y),
                         0.5 + 0.4 * np.sin(150 * (x - y))], -1).astype(np.float32)

    source, expected = _source_and_expected(camera, warp, fine)
    inner = (slice(4, -4), slice(4, -4))
    error = {how: np.sqrt(np.mean((warp.warp_image(source, how)[inner] - expected[inner]) ** 2))
             for how in ("linear", "cubic")}
    assert error["cubic"] < 0.5 * error["linear"], error

    # the cubic kernel overshoots at an edge; radiance stays non-negative
    step = np.zeros((120, 160, 3), np.float32)
    step[:, 80:] = 1.0
    assert warp.warp_image(step, "linear").min() >= 0
    cubic = warp.warp_image(step, "cubic")
    assert cubic.min() >= 0 and cubic.max() > 1.0


def test_cubic_undistortion_masks_every_pixel_a_masked_one_reaches():
    camera = make_camera("SIMPLE_RADIAL", 80, 60, [70.0, 40.0, 30.0, 0.05])
    warp = undistortion(camera)
    mask = np.ones((60, 80), bool)
    mask[30, 40] = False   # one clipped pixel
    # destination pixels whose 4x4 cubic kernel reads source pixel (30, 40)
    column, row = np.floor(warp.map_x).astype(int), np.floor(warp.map_y).astype(int)
    reached = (np.abs(column - 40 + 0.5) <= 1.5) & (np.abs(row - 30 + 0.5) <= 1.5)
    cubic = warp.warp_mask(mask, "cubic")
    assert reached.sum() >= 4 and not cubic[reached].any()
    assert (~cubic).sum() <= 4 * reached.sum()    # and not much more
    assert (~warp.warp_mask(mask)).sum() <= 2     # nearest: the pixel itself
    image = np.ones((60, 80, 3), np.float32)
    image[30, 40] = 5.0                            # its value spreads where the mask says
    spread = np.abs(warp.warp_image(image, "cubic") - 1).max(-1) > 1e-5
    assert not (spread & cubic).any()


def test_pinhole_cameras_are_not_resampled():
    warp = undistortion(make_camera("PINHOLE", 64, 48, [50.0, 50.0, 32.0, 24.0]))
    image = np.random.default_rng(0).random((48, 64, 3)).astype(np.float32)
    assert warp.map_x is None and warp.warp_image(image) is image
    assert (warp.fx, warp.cx, warp.width) == (50.0, 32.0, 64)


# -- known intrinsics ------------------------------------------------------------------------

def test_focal_from_manifest_reads_exif_fields():
    per_image = {"images": [{"name": "a", "exif": {"FocalLengthIn35mmFilm": "28"}},
                            {"name": "b", "exif": {"FocalLengthIn35mmFilm": 28}}]}
    focal, how = focal_from_metadata(per_image, 600, 400)
    assert focal == pytest.approx(28 / math.hypot(36, 24) * math.hypot(600, 400))
    assert "35 mm" in how
    focal, _ = focal_from_metadata({"focal_length_mm": "12/1", "sensor_width_mm": 24.0}, 800, 600)
    assert focal == pytest.approx(400.0)
    mixed = {"images": [{"focal_length_px": 500}, {"focal_length_px": 700}]}
    assert focal_from_metadata(mixed, 800, 600)[0] is None
    assert focal_from_metadata({"settings": {}}, 800, 600)[0] is None


# -- readers ---------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def fern_ingest(shared_data, tmp_path_factory) -> Path:
    """An ingest-like folder from fern images_8: PNG matching copies, float TIFF linear images,
    masks with an invalid border."""
    root = tmp_path_factory.mktemp("fern_ingest")
    for folder in ("matching", "linear", "masks"):
        (root / folder).mkdir()
    for path in sorted((shared_data / "fern_llff" / "images_8").glob("*.png")):
        shutil.copy(path, root / "matching" / path.name)
        encoded = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB) / 255.0
        tifffile.imwrite(root / "linear" / f"{path.stem}.tiff",
                         srgb_to_linear(encoded).astype(np.float32), photometric="rgb")
        mask = np.zeros(encoded.shape[:2], np.uint8)
        mask[4:-4, 4:-4] = 255
        cv2.imwrite(str(root / "masks" / f"{path.stem}.png"), mask)
    return root


def test_llff_reader_reproduces_poses_bounds(shared_data, fern_ingest, tmp_path):
    out = tmp_path / "poses"
    run_poses("--ingest", str(fern_ingest), "--out", str(out), "--source", "llff",
              "--source-dir", str(shared_data / "fern_llff"))
    data = np.load(shared_data / "fern_llff" / "poses_bounds.npy")
    cameras = read_cameras(out / "cameras.json")
    assert [f.name for f in cameras.frames] == [f"image{i:03d}" for i in range(20)]
    c2w = denormalise_c2w(np.array([f.c2w for f in cameras.frames]), cameras.centre,
                          cameras.scale)
    np.testing.assert_allclose(opencv_to_llff(c2w), data[:, :15].reshape(-1, 3, 5)[:, :, :4],
                               atol=1e-9)
    height, width, focal = data[0, :15].reshape(3, 5)[:, 4]
    frame = cameras.frames[0]
    assert (frame.width, frame.height) == (504, 378)
    assert frame.fx == pytest.approx(focal * 504 / width)
    assert frame.fy == pytest.approx(focal * 378 / height)
    assert (frame.cx, frame.cy) == (252.0, 189.0)
    # the depth bounds of poses_bounds.npy, as ranges along the rays (far: the corner rays')
    corner = math.hypot(252.0 / frame.fx, 189.0 / frame.fy, 1.0)
    bounds = np.array([[f.near / NEAR_MARGIN, f.far / FAR_MARGIN / corner] for f in cameras.frames])
    np.testing.assert_allclose(bounds / cameras.scale, data[:, 15:], rtol=1e-9)
    assert [f.split for f in cameras.frames].count("test") == 3  # images 0, 8, 16
    assert cameras.frames[8].split == "test"
    image = tifffile.imread(out / frame.image)
    assert image.dtype == np.float32 and image.shape == (378, 504, 3)
    np.testing.assert_array_equal(image, tifffile.imread(fern_ingest / "linear" /
                                                         "image000.tiff"))
    mask = cv2.imread(str(out / frame.mask), cv2.IMREAD_GRAYSCALE)
    assert mask[0, 0] == 0 and mask[189, 252] == 255


def test_llff_reader_names_rows_from_images_wb_and_scales_focal(tmp_path):
    source, ingest = tmp_path / "dataset", tmp_path / "ingest"
    (source / "Images_wb").mkdir(parents=True)
    (ingest / "linear").mkdir(parents=True)
    rng = np.random.default_rng(1)
    rows = []
    for i, name in enumerate(["b_02", "a_01", "c_03"]):
        cv2.imwrite(str(source / "Images_wb" / f"{name}.png"), np.zeros((30, 40, 3), np.uint8))
        cv2.imwrite(str(ingest / "linear" / f"{name}.png"), np.zeros((15, 20, 3), np.uint8))
    for i in range(3):  # rows in sorted name order: a_01, b_02, c_03
        pose = np.concatenate([rotation_from(rng.normal(size=4)), [[i], [0.0], [0.0]],
                               [[3000.0], [4000.0], [3200.0]]], axis=1)
        rows.append(np.concatenate([pose.ravel(), [2.0 + i, 50.0]]))
    np.save(source / "poses_bounds.npy", np.array(rows))
    out = tmp_path / "out"
    run_poses("--ingest", str(ingest), "--out", str(out), "--source", "llff", "--source-dir",
              str(source), "--test-every", "0")
    cameras = read_cameras(out / "cameras.json")
    assert [f.name for f in cameras.frames] == ["a_01", "b_02", "c_03"]
    assert cameras.frames[0].fx == pytest.approx(3200.0 * 20 / 4000)
    centres = denormalise_c2w(np.array([f.c2w for f in cameras.frames]), cameras.centre,
                              cameras.scale)[:, 0, 3]
    np.testing.assert_allclose(centres, [0.0, 1.0, 2.0], atol=1e-12)
    assert {f.split for f in cameras.frames} == {"train"}


def test_nerfstudio_reader_converts_opengl_and_skips_missing_images(tmp_path, caplog):
    ingest = tmp_path / "ingest"
    (ingest / "linear").mkdir(parents=True)
    rng = np.random.default_rng(2)
    frames, expected = [], {}
    for i in range(4):
        c2w = np.eye(4)
        c2w[:3, :3] = rotation_from(rng.normal(size=4))
        c2w[:3, 3] = rng.normal(size=3)
        name = f"frame_{i:05d}"
        frames.append({"file_path": f"images/{name}.jpg",
                       "transform_matrix": opencv_to_opengl(c2w).tolist()})
        if i != 2:  # frame 2's image is missing
            cv2.imwrite(str(ingest / "linear" / f"{name}.png"), np.zeros((60, 80, 3), np.uint8))
            expected[name] = c2w
    frames[3].update({"fl_x": 150.0, "fl_y": 152.0})  # per-frame intrinsics override
    transforms = {"camera_model": "OPENCV", "fl_x": 100.0, "fl_y": 101.0, "cx": 79.0,
                  "cy": 61.0, "w": 160, "h": 120, "frames": frames}
    (tmp_path / "transforms.json").write_text(json.dumps(transforms))
    out = tmp_path / "out"
    argv = ["--ingest", str(ingest), "--out", str(out), "--source", "nerfstudio",
            "--source-dir", str(tmp_path)]
    with pytest.raises(PipelineError, match="--near and --far"):
        run_poses(*argv)
    assert not out.exists()
    run_poses(*argv, "--near", "0.5", "--far", "4.0")
    assert "frame_00002" in caplog.text
    cameras = read_cameras(out / "cameras.json")
    assert cameras.source == "nerfstudio"
    found = source_c2w(out / "cameras.json")
    assert sorted(found) == sorted(expected)
    for name, c2w in expected.items():
        np.testing.assert_allclose(found[name], c2w, atol=1e-9)
    by_name = {f.name: f for f in cameras.frames}
    assert by_name["frame_00000"].fx == pytest.approx(50.0)  # 160 -> 80 pixels wide
    assert by_name["frame_00000"].cy == pytest.approx(30.5)
    assert by_name["frame_00003"].fx == pytest.approx(75.0)
    assert by_name["frame_00000"].near == pytest.approx(0.5 * cameras.scale)
    report = json.loads((out / "report.json").read_text())
    assert report["posed_without_linear_image"] == ["frame_00002"]


# -- COLMAP on real data ---------------------------------------------------------------------

@pytest.fixture(scope="module")
def fern_colmap(fern_ingest, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("fern_colmap") / "poses"
    run_poses("--ingest", str(fern_ingest), "--out", str(out), "--threads", THREADS)
    return out


def test_colmap_on_fern_registers_all_and_agrees_with_llff(shared_data, fern_colmap):
    report = json.loads((fern_colmap / "report.json").read_text())
    assert report["registered"] == report["total"] == 20
    assert report["unregistered"] == []
    assert report["mean_reprojection_px"] < 1.0
    assert report["gate_passed"]  # including the cross-check by an independent model
    data = np.load(shared_data / "fern_llff" / "poses_bounds.npy")
    reference = llff_to_opencv(data[:, :15].reshape(-1, 3, 5)[:, :, :4])
    found = source_c2w(fern_colmap / "cameras.json")
    estimate = np.array([found[f"image{i:03d}"] for i in range(20)])
    comparison = compare_trajectories(estimate, reference)
    assert comparison.max_relative_position_error < 0.02
    assert comparison.rotation_errors_deg.max() < 1.0


def test_colmap_outputs_follow_the_camera_contract(fern_colmap):
    cameras = read_cameras(fern_colmap / "cameras.json")
    assert cameras.source == "colmap" and len(cameras.frames) == 20
    for frame in cameras.frames:
        image = tifffile.imread(cameras.image_path(frame))
        assert image.dtype == np.float32 and image.shape == (frame.height, frame.width, 3)
        mask = cv2.imread(str(cameras.mask_path(frame)), cv2.IMREAD_GRAYSCALE)
        assert mask.shape == (frame.height, frame.width)
        assert mask[0, 0] == 0 and mask[frame.height // 2, frame.width // 2] == 255
        assert 0 < frame.near < frame.far <= 2.0
        rotation = frame.c2w_array[:3, :3]
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-9)
        assert np.linalg.norm(frame.c2w_array[:3, 3]) <= 1.0
    assert cameras.near == min(f.near for f in cameras.frames)
    assert {f.name for f in cameras.split("test")} == {"image000", "image008", "image016"}
    # the whole frustum of every camera (up to its depth bound) lies in the unit ball; far is a
    # range, reached at that depth by the longest corner ray
    for frame in cameras.frames:
        _, stretch = range_bounds(1.0, 1.0, frame.intrinsics, frame.width, frame.height)
        corners = frustum_corners(frame.c2w_array, frame.intrinsics, frame.width,
                                  frame.height, frame.far / stretch)
        assert np.linalg.norm(corners, axis=1).max() <= 1.0 + 1e-9
    report = json.loads((fern_colmap / "report.json").read_text())
    assert report["attempts"][0]["settings"]["matcher"] == "sequential"
    assert report["source_cameras"][0]["model"] == "SIMPLE_RADIAL"
    assert report["undistort_interpolation"] == "linear"
    # this ingest folder has no manifest: how its images were decoded is not known
    assert all(f.blur_px is None for f in cameras.frames)
    assert (fern_colmap / "sparse" / "cameras.bin").exists()
    assert not (fern_colmap / "_colmap_work").exists()


def test_colmap_model_reader_reproduces_the_colmap_run(fern_ingest, fern_colmap, tmp_path):
    out = tmp_path / "model"
    run_poses("--ingest", str(fern_ingest), "--out", str(out), "--source", "colmap-model",
              "--source-dir", str(fern_colmap))
    first = read_cameras(fern_colmap / "cameras.json")
    again = read_cameras(out / "cameras.json")
    assert again.scale == pytest.approx(first.scale) and again.centre == pytest.approx(
        first.centre)
    for a, b in zip(first.frames, again.frames):
        assert (a.name, a.width, a.height) == (b.name, b.width, b.height)
        np.testing.assert_allclose(a.c2w_array, b.c2w_array, atol=1e-9)
        assert (a.fx, a.near, a.far) == pytest.approx((b.fx, b.near, b.far))
        np.testing.assert_array_equal(tifffile.imread(first.image_path(a)),
                                      tifffile.imread(again.image_path(b)))
    # the source's points stay beside the cameras, for depth supervision and the tracks
    source = pycolmap.Reconstruction(fern_colmap / "sparse")
    assert pycolmap.Reconstruction(out / "sparse").num_points3D() == source.num_points3D() > 0
    report = json.loads((out / "report.json").read_text())
    assert report["source_points_kept"] == source.num_points3D()
    assert report["source_model"]["kept"] and report["source_model"]["points"] > 0
    depth = training_depth_observations(again)
    assert depth is not None and len(depth.ranges) > 100


def test_known_focal_from_the_manifest_can_be_held_fixed(shared_data, tmp_path):
    """EXIF 35 mm equivalent focal length in the ingest manifest, kept fixed in the mapping."""
    ingest = tmp_path / "ingest"
    for folder in ("matching", "linear"):
        (ingest / folder).mkdir(parents=True)
        for path in sorted((shared_data / "fern_llff" / "images_8").glob("*.png"))[:8]:
            shutil.copy(path, ingest / folder / path.name)
    exif = {"FocalLengthIn35mmFilm": 28}
    (ingest / "manifest.json").write_text(json.dumps(
        {"images": [{"name": p.stem, "exif": exif} for p in (ingest / "linear").iterdir()]}))
    out = tmp_path / "poses"
    run_poses("--ingest", str(ingest), "--out", str(out), "--threads", THREADS,
              "--no-refine-focal", "--no-cross-check", "--camera-model", "PINHOLE")
    expected = 28 / math.hypot(36, 24) * math.hypot(504, 378)
    report = json.loads((out / "report.json").read_text())
    assert report["initial_focal_px"] == pytest.approx(expected)
    assert report["registered"] == 8
    frame = read_cameras(out / "cameras.json").frames[0]
    assert frame.fx == pytest.approx(expected) and frame.fy == pytest.approx(expected)


def test_images_of_two_sizes_get_a_camera_per_size_unless_one_is_asked_for(shared_data,
                                                                            tmp_path):
    """Every other fern frame cropped to 16:9 (a camera switched between modes): the default
    (auto) gives each size one camera, per-image one camera per image; one shared camera
    fails, naming the setting."""
    ingest = tmp_path / "ingest"
    for folder in ("matching", "linear"):
        (ingest / folder).mkdir(parents=True)
    paths = sorted((shared_data / "fern_llff" / "images_8").glob("*.png"))[:8]
    for index, path in enumerate(paths):
        image = cv2.imread(str(path))
        if index % 2:
            image = image[47:47 + 284]
        for folder in ("matching", "linear"):
            cv2.imwrite(str(ingest / folder / path.name), image)
    with pytest.raises(PipelineError, match="poses.camera_mode to auto, per-size or per-image"):
        run_poses("--ingest", str(ingest), "--out", str(tmp_path / "single"), "--threads",
                  THREADS, "--no-cross-check", "--camera-mode", "single")
    cropped = {path.stem for index, path in enumerate(paths) if index % 2}
    for mode in ("auto", "per-image"):
        out = tmp_path / mode
        run_poses("--ingest", str(ingest), "--out", str(out), "--threads", THREADS,
                  "--no-cross-check", "--camera-mode", mode)
        frames = read_cameras(out / "cameras.json").frames
        assert len(frames) >= 6
        # undistorted to pinhole cameras, a few pixels smaller than their size
        for frame in frames:
            assert (frame.height < 290) == (frame.name in cropped), (frame.name, frame.height)
        assert len({f.name in cropped for f in frames}) == 2
        model = pycolmap.Reconstruction(out / "sparse")
        used = {image.camera_id for image in model.images.values()}
        assert len(used) == (2 if mode == "auto" else len(model.images)), mode
        report = json.loads((out / "report.json").read_text())
        assert report["attempts"][0]["settings"]["camera_mode"] == \
            ("per-size" if mode == "auto" else "per-image")


def _failed_poses(tmp_path, frames: dict) -> tuple[str, Path]:
    """Run the poses step on an ingest folder of ``frames`` (name -> uint8 RGB) that must
    fail: its message and the output folder it must not leave."""
    ingest = tmp_path / "ingest"
    for folder in ("matching", "linear"):
        (ingest / folder).mkdir(parents=True)
        for name, image in frames.items():
            cv2.imwrite(str(ingest / folder / f"{name}.png"), image[..., ::-1])
    out = tmp_path / "results" / "poses"
    with pytest.raises(PipelineError) as failure:
        run_poses("--ingest", str(ingest), "--out", str(out), "--threads", THREADS)
    return str(failure.value), out


def test_unrelated_images_fail_with_advice_and_leave_nothing(tmp_path):
    import skimage.data

    frames = {}
    for name in ("astronaut", "camera", "coffee", "chelsea", "rocket", "coins", "clock"):
        image = getattr(skimage.data, name)()
        image = np.stack([image] * 3, -1) if image.ndim == 2 else image[..., :3]
        frames[name] = cv2.resize(image, (240, 180), interpolation=cv2.INTER_AREA)
    message, out = _failed_poses(tmp_path, frames)
    assert "registered only 0 of 7 images" in message
    for advice in ("poses.max_features=16384", "poses.max_image_size", "poses.focal_px",
                   "poses.clahe=false"):
        assert advice in message
    assert "poses.matcher" not in message  # both matchers were tried
    assert "global mapping" in message and "exhaustive matching" in message  # retries listed
    # seven photographs of seven things: none shares a matched feature with another
    assert "No image shares 15 verified feature matches with any other image" in message
    assert "views of another place share nothing" in message
    assert not out.exists()
    assert list((tmp_path / "results").iterdir()) == []


def test_photographs_from_one_place_fail_saying_the_camera_must_move(tmp_path):
    """A fixed camera's time-lapse: one view, sensor noise only. COLMAP cannot triangulate
    from it; the message says why instead of suggesting settings, after a single attempt."""
    import skimage.data

    scene = cv2.resize(skimage.data.coffee(), (240, 180), interpolation=cv2.INTER_AREA)
    rng = np.random.default_rng(0)
    message, out = _failed_poses(tmp_path, {
        f"timelapse_{i:03d}": np.clip(scene + rng.normal(0.0, 2.0, scene.shape), 0, 255
                                      ).astype(np.uint8) for i in range(8)})
    assert "registered only 0 of 8 images: the photographs were taken from one place" in message
    assert "photographs from several positions" in message
    assert "poses.focal_px" not in message and "poses.max_features" not in message
    assert message.count("seed") == 1          # one attempt: no setting would have helped
    assert not out.exists()


def test_photographs_turned_about_one_point_fail_saying_so(tmp_path):
    """A panning tripod: one centre, the view turned from -8 to +8 degrees (each frame the
    same scene through K R K^-1). No 3D; every matched pair is a homography."""
    import skimage.data

    scene = cv2.resize(skimage.data.astronaut(), (320, 240), interpolation=cv2.INTER_AREA)
    focal, (height, width) = 260.0, scene.shape[:2]
    camera = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]])
    frames = {}
    for index, yaw in enumerate(np.radians(np.linspace(-8.0, 8.0, 8))):
        turn = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
        warped = cv2.warpPerspective(scene, camera @ turn @ np.linalg.inv(camera), (width, height))
        frames[f"pan_{index:03d}"] = np.ascontiguousarray(warped[30:210, 40:280])
    message, out = _failed_poses(tmp_path, frames)
    assert "of the 28 matched pairs of photographs are related by a homography alone" in message
    assert "turned about one point" in message and "poses.focal_px" in message
    assert not out.exists()


def test_views_of_open_water_fail_saying_they_hold_no_features(tmp_path):
    # a diver's frames of blue water: a vertical gradient and sensor noise, nothing to match
    rng = np.random.default_rng(0)
    rows = np.linspace(0.0, 1.0, 180)[:, None, None]
    frames = {}
    for i in range(12):
        water = (np.array([0.05, 0.3, 0.45]) + 0.2 * rows) * np.ones((1, 240, 1))
        water = np.clip(water + rng.normal(0.0, 0.01, water.shape), 0.0, 1.0)
        frames[f"GOPR{i:04d}"] = (water * 255).astype(np.uint8)
    message, _ = _failed_poses(tmp_path, frames)
    assert "registered only 0 of 12 images" in message
    assert "No image shares 15 verified feature matches with any other image" in message
    assert "open water" in message and "GOPR0000" in message


@pytest.fixture(scope="module")
def small_fern_ingest(fern_ingest, tmp_path_factory) -> Path:
    """8 of fern's frames (every other one), as the ingest step lays them out."""
    root = tmp_path_factory.mktemp("small_fern")
    for folder in ("matching", "linear", "masks"):
        (root / folder).mkdir()
        for path in sorted((fern_ingest / folder).iterdir())[:16:2]:
            shutil.copy(path, root / folder / path.name)
    return root


def test_an_unconfirmed_model_fails_by_default_naming_what_to_try(small_fern_ingest, tmp_path):
    """No model can pass a gate of 0.0001 px: the step fails and leaves nothing."""
    out = tmp_path / "poses"
    with pytest.raises(PipelineError) as failure:
        run_poses("--ingest", str(small_fern_ingest), "--out", str(out), "--threads", THREADS,
                  "--max-reproj-px", "0.0001", "--no-retry", "--no-cross-check")
    message = str(failure.value)
    assert message.startswith("the camera model was not confirmed")
    assert re.search(r"mean reprojection error 0\.\d+ px above 0\.0001 px", message), message
    for option in ("poses.matcher=exhaustive", "poses.mapper=global", "poses.max_image_size",
                   "poses.clahe=false", "poses.on_unconfirmed=warn"):
        assert option in message
    assert not out.exists()


def test_an_unconfirmed_model_kept_with_warn_names_the_disagreement(small_fern_ingest, tmp_path):
    """Both mappers on the same matches, a cross-check no two models can pass: kept, with the
    disagreement in report.json and warnings.json."""
    out = tmp_path / "poses"
    run_poses("--ingest", str(small_fern_ingest), "--out", str(out), "--threads", THREADS,
              "--max-disagreement", "1e-9", "--no-retry", "--on-unconfirmed", "warn")
    report = json.loads((out / "report.json").read_text())
    assert report["gate_passed"] is False and report["on_unconfirmed"] == "warn"
    comparison = report["attempts"][1]["comparisons"][0]
    assert comparison["with_attempt"] == 1 and comparison["max_centre_deviation"] > 1e-9
    warnings = read_warnings(out / "warnings.json")
    assert [w["code"] for w in warnings] == ["unconfirmed_poses", "few_views"]  # 8 frames
    message = warnings[0]["message"]
    assert f"{comparison['max_centre_deviation']:.2%} of the camera extent" in message
    assert "attempts 1 and 2 disagree on the poses" in message
    assert "kept because poses.on_unconfirmed=warn" in message
    assert "poses.mapper=" not in message   # both mappers were tried already
    assert len(read_cameras(out / "cameras.json").frames) == 8


def test_nerfstudio_k1_to_k4_become_an_equivalent_colmap_camera():
    """nerfstudio's radial factor 1 + k1 r^2 + ... + k4 r^8 through COLMAP's FULL_OPENCV."""
    from seathru.io.dataset_readers import _nerfstudio_camera

    params = {"w": 640, "h": 480, "fl_x": 500.0, "fl_y": 505.0, "cx": 321.0, "cy": 238.5,
              "k1": -0.12, "k2": 0.03, "k3": -0.004, "k4": 0.0006, "p1": 0.001, "p2": -0.0005}
    camera = _nerfstudio_camera(params, "test")
    assert camera.model_name == "FULL_OPENCV"
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-0.7, 0.7, (2, 500))
    r2 = x * x + y * y
    radial = 1 + r2 * (-0.12 + r2 * (0.03 + r2 * (-0.004 + r2 * 0.0006)))
    xd = x * radial + 2 * 0.001 * x * y + -0.0005 * (r2 + 2 * x * x)
    yd = y * radial + 0.001 * (r2 + 2 * y * y) + 2 * -0.0005 * x * y
    expected = np.c_[500.0 * xd + 321.0, 505.0 * yd + 238.5]
    pixels = camera.img_from_cam(np.c_[x, y, np.ones_like(x)])
    np.testing.assert_allclose(pixels, expected, atol=0.05)
    with pytest.raises(PipelineError, match="cannot be represented"):
        _nerfstudio_camera({**params, "k4": 5.0, "k1": 2.0}, "wild")


def test_llff_rows_are_named_by_the_folder_ingest_read(tmp_path):
    """An images_N folder whose names differ from images/ (LLFF's own layout)."""
    source, ingest = tmp_path / "dataset", tmp_path / "ingest"
    (ingest / "linear").mkdir(parents=True)
    for folder, names in (("images", ["IMG_9.JPG", "IMG_7.JPG"]),
                          ("images_8", ["image000.png", "image001.png"])):
        (source / folder).mkdir(parents=True)
        for name in names:
            cv2.imwrite(str(source / folder / name), np.zeros((30, 40, 3), np.uint8))
    for name in ("image000", "image001"):
        cv2.imwrite(str(ingest / "linear" / f"{name}.png"), np.zeros((15, 20, 3), np.uint8))
    rows = [np.concatenate([np.c_[np.eye(3), [[i], [0.0], [0.0]], [[30.0], [40.0], [35.0]]]
                            .ravel(), [1.0, 10.0]]) for i in range(2)]
    np.save(source / "poses_bounds.npy", np.array(rows))
    (ingest / "manifest.json").write_text(json.dumps({"input": {"layout": {
        "layout": "llff", "root": str(source), "images": "images_8"}}}))
    out = tmp_path / "out"
    run_poses("--ingest", str(ingest), "--out", str(out), "--source", "llff", "--source-dir",
              str(source), "--test-every", "0")
    report = json.loads((out / "report.json").read_text())
    assert report["reader_notes"]["names_from"] == str(source / "images_8")
    assert [f.name for f in read_cameras(out / "cameras.json").frames] == ["image000",
                                                                           "image001"]
    # two frames, none held out: nothing wrong with the reader, too few views for a NeRF
    assert [w["code"] for w in read_warnings(out / "warnings.json")] == ["few_views"]


@pytest.mark.slow
def test_colmap_on_d3_reef_registers_most_frames(shared_data, tmp_path):
    """Real underwater frames, default settings at 720x540 (about 30 s on 2 free cores)."""
    ingest = tmp_path / "ingest"
    for folder in ("matching", "linear"):
        shutil.copytree(shared_data / "d3_reef", ingest / folder)
    out = tmp_path / "poses"
    run_poses("--ingest", str(ingest), "--out", str(out), "--threads", THREADS)
    report = json.loads((out / "report.json").read_text())
    assert report["total"] == 20
    assert report["registered"] >= 18
    assert report["mean_reprojection_px"] < 1.0
    assert len(read_cameras(out / "cameras.json").frames) == report["registered"]


# -- COLMAP on simulated dives ---------------------------------------------------------------

def simulate(out: Path, *argv: str) -> None:
    pytest.importorskip("seathru.steps.simulate", reason="the simulate step is not built yet")
    args = build_parser().parse_args(["simulate", "--out", str(out), *argv])
    args._run(args)


def ingest_like(simulated: Path, root: Path) -> Path:
    """The layout poses reads: 8-bit camera JPEGs to match, the linear water images to train."""
    root.mkdir(parents=True)
    (root / "matching").symlink_to(simulated / "jpeg", target_is_directory=True)
    (root / "linear").symlink_to(simulated / "truth" / "water", target_is_directory=True)
    return root


def assert_poses_match_truth(out: Path, truth: Path) -> None:
    report = json.loads((out / "report.json").read_text())
    assert report["gate_passed"], report["attempts"]
    found, expected = source_c2w(out / "cameras.json"), source_c2w(truth)
    assert sorted(found) == sorted(expected), "every simulated view must register"
    names = sorted(expected)
    comparison = compare_trajectories(np.array([found[n] for n in names]),
                                      np.array([expected[n] for n in names]))
    assert comparison.max_relative_position_error < 0.01
    assert comparison.rotation_errors_deg.max() < 1.0


@pytest.mark.slow
def test_colmap_recovers_a_simulated_orbit_through_ingest(tmp_path):
    """The real ingest output (matching/, linear_2/, masks_2/) of a simulated orbit."""
    pytest.importorskip("seathru.steps.ingest", reason="the ingest step is not built yet")
    simulated = tmp_path / "sim"
    simulate(simulated, "--views", "14", "--path", "orbit", "--supersample", "1", "--seed", "0")
    ingest = tmp_path / "ingest"
    args = build_parser().parse_args(["ingest", "--input", str(simulated / "jpeg"), "--out",
                                      str(ingest), "--downscale", "2", "--workers", "1"])
    args._run(args)
    out = tmp_path / "poses"
    run_poses("--ingest", str(ingest), "--out", str(out), "--threads", THREADS,
              "--linear-folder", "linear_2")
    assert_poses_match_truth(out, simulated / "truth" / "cameras.json")
    cameras = read_cameras(out / "cameras.json")
    truth = read_cameras(simulated / "truth" / "cameras.json")
    frame = cameras.frames[0]
    # undistortion crops a pixel or two; COLMAP's threaded solve varies the crop under load
    assert 156 <= frame.width <= 160 and frame.fx == pytest.approx(truth.frames[0].fx / 2,
                                                                   rel=0.02)
    assert tifffile.imread(cameras.image_path(frame)).shape == (frame.height, frame.width, 3)


@pytest.mark.slow
def test_colmap_recovers_a_simulated_transect(tmp_path):
    simulated = tmp_path / "sim"
    simulate(simulated, "--views", "14", "--path", "transect", "--supersample", "1",
             "--seed", "0")
    out = tmp_path / "poses"
    run_poses("--ingest", str(ingest_like(simulated, tmp_path / "ingest")), "--out", str(out),
              "--threads", THREADS)
    assert_poses_match_truth(out, simulated / "truth" / "cameras.json")


@pytest.mark.slow
def test_colmap_recovers_a_transect_in_turbid_water(tmp_path):
    simulated = tmp_path / "sim"
    simulate(simulated, "--views", "14", "--path", "transect", "--water", "turbid",
             "--supersample", "1", "--seed", "1")
    out = tmp_path / "poses"
    run_poses("--ingest", str(ingest_like(simulated, tmp_path / "ingest")), "--out", str(out),
              "--threads", THREADS)
    assert_poses_match_truth(out, simulated / "truth" / "cameras.json")


@settings(max_examples=40, deadline=None)
@given(st.floats(-3, 3), st.floats(-1.4, 1.4), st.floats(-3, 3), st.integers(0, 31),
       st.integers(0, 23), st.floats(0.2, 20.0), st.floats(0.05, 0.95), st.floats(0.05, 0.95))
def test_pixel_of_points_finds_the_pixel_whose_ray_passes_through_the_point(
        a, b, c, column, row, distance, du, dv):
    from scipy.spatial.transform import Rotation

    from seathru.geometry.poses import pixel_of_points

    c2w = np.eye(4)
    c2w[:3, :3] = Rotation.from_euler("zyx", [a, b, c]).as_matrix()
    c2w[:3, 3] = [0.3, -1.2, 2.0]
    fx, fy, cx, cy, width, height = 28.0, 30.0, 15.7, 12.2, 32, 24
    # a point on the ray through (column + du, row + dv): inside pixel (column, row)
    direction = np.array([(column + du - cx) / fx, (row + dv - cy) / fy, 1.0])
    point = c2w[:3, :3] @ (direction / np.linalg.norm(direction) * distance) + c2w[:3, 3]
    behind = c2w[:3, 3] - (point - c2w[:3, 3])
    rows, columns, local, inside = pixel_of_points(c2w, fx, fy, cx, cy, width, height,
                                                   np.stack([point, behind]))
    assert (rows[0], columns[0], bool(inside[0])) == (row, column, True)
    assert np.linalg.norm(local[0]) == pytest.approx(distance, rel=1e-9)
    assert not inside[1] and (rows[1], columns[1]) == (0, 0)


def nerfstudio_poses(tmp_path: Path, name: str, *flags: str) -> Path:
    """The poses step on three nerfstudio frames 1 unit apart; its output folder."""
    ingest = tmp_path / "ingest"
    (ingest / "linear").mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(3):
        c2w = np.eye(4)
        c2w[0, 3] = float(i)
        frames.append({"file_path": f"images/f{i}.png", "transform_matrix": c2w.tolist()})
        cv2.imwrite(str(ingest / "linear" / f"f{i}.png"), np.full((30, 40, 3), 90, np.uint8))
    (tmp_path / "transforms.json").write_text(json.dumps(
        {"fl_x": 40.0, "fl_y": 40.0, "cx": 20.0, "cy": 15.0, "w": 40, "h": 30,
         "frames": frames}))
    out = tmp_path / name
    args = build_parser().parse_args(
        ["poses", "--ingest", str(ingest), "--out", str(out), "--source", "nerfstudio",
         "--source-dir", str(tmp_path), "--near", "0.5", "--far", "5", *flags])
    args._run(args)
    return out


def test_a_known_metric_scale_goes_into_the_camera_file(tmp_path):
    scaled = read_cameras(nerfstudio_poses(tmp_path, "scaled", "--metres-per-unit", "0.25")
                          / "cameras.json")
    assert scaled.metres_per_source_unit == 0.25
    plain = nerfstudio_poses(tmp_path, "plain")
    assert read_cameras(plain / "cameras.json").metres_per_source_unit is None
    assert "metres_per_source_unit" not in json.loads(
        (plain / "cameras.json").read_text())["normalisation"]
    with pytest.raises(PipelineError, match="metres-per-unit must be positive"):
        nerfstudio_poses(tmp_path, "negative", "--metres-per-unit", "-1")
