"""The export step: nerfstudio transforms.json, a COLMAP text model and the SeaThru-NeRF
layout, read back through the project's own readers (``seathru.io.dataset_readers``) and compared with the camera file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from seathru.cli import main
from seathru.geometry.poses import denormalise_c2w, depth_bounds, pixel_of_points
from seathru.io.cameras import CameraSet, Frame, read_cameras, write_cameras
from seathru.io.colmap import read_model
from seathru.io.dataset_readers import read_colmap_model, read_llff, read_nerfstudio
from seathru.io.exports import (NERFSTUDIO_APPLIED, colmap_reconstruction,
                                llff_camera_problem, nerfstudio_transforms)
from seathru.io.images import read_image, write_float_tiff, write_mask
from seathru.io.source_model import keep_source_model

CENTRE, SCALE = np.array([3.0, -1.0, 2.0]), 0.25


def _cameras(views: int = 5, seed: int = 0) -> CameraSet:
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(views):
        c2w = np.eye(4)
        c2w[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.6, 3)).as_matrix()
        c2w[:3, 3] = rng.normal(0, 1, 3)
        width = 40 if i < 3 else 36   # two sizes: two COLMAP cameras, per-frame intrinsics
        frames.append(Frame(name=f"img_{i:02d}", image=f"images/img_{i:02d}.tiff",
                            mask=f"masks/img_{i:02d}.png", width=width, height=30,
                            fx=33.0 + i, fy=34.0 + i, cx=width / 2 + 0.3, cy=15.2,
                            c2w=c2w.tolist(), near=0.1, far=3.0,
                            split="test" if i == 0 else "train"))
    return CameraSet(frames=frames, near=0.1, far=3.0, centre=CENTRE.tolist(), scale=SCALE,
                     source="colmap")


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    root = tmp_path_factory.mktemp("export")
    poses = root / "poses"
    cameras = _cameras()
    rng = np.random.default_rng(1)
    for frame in cameras.frames:
        write_float_tiff(poses / frame.image, rng.random((frame.height, frame.width, 3)) * 1.2)
        write_mask(poses / frame.mask, rng.random((frame.height, frame.width)) > 0.1)
    write_cameras(poses / "cameras.json", cameras)
    points = rng.normal(0, 1, (7, 3))
    model = pycolmap.Reconstruction()
    for xyz in points:
        model.add_point3D(xyz, pycolmap.Track(), np.array([10, 200, 30], np.uint8))
    (poses / "sparse").mkdir()
    model.write(poses / "sparse")
    assert main(["export", "--poses", str(poses), "--out", str(root / "export")]) == 0
    return {"root": root, "cameras": read_cameras(poses / "cameras.json"), "points": points}


def _source_poses(cameras: CameraSet) -> dict[str, np.ndarray]:
    return {f.name: denormalise_c2w(f.c2w_array, CENTRE, SCALE) for f in cameras.frames}


def test_nerfstudio_export_reads_back_to_the_source_cameras(exported):
    dataset = read_nerfstudio(exported["root"] / "export" / "nerfstudio")
    data = json.loads((exported["root"] / "export" / "nerfstudio" / "transforms.json")
                      .read_text())
    applied = np.vstack([np.asarray(data["applied_transform"]), [0, 0, 0, 1]])
    np.testing.assert_allclose(applied[:3], NERFSTUDIO_APPLIED)
    source = _source_poses(exported["cameras"])
    frames = {f.name: f for f in exported["cameras"].frames}
    assert sorted(v.name for v in dataset.views) == sorted(source)
    for view in dataset.views:
        # back from nerfstudio's world (applied_transform) to the source reconstruction's
        np.testing.assert_allclose(np.linalg.inv(applied) @ view.c2w, source[view.name],
                                   atol=1e-9)
        frame = frames[view.name]
        assert (view.camera.width, view.camera.height) == (frame.width, frame.height)
        np.testing.assert_allclose(view.camera.params, [frame.fx, frame.fy, frame.cx, frame.cy])
    assert "bounds_from" in dataset.notes          # the sparse points came along, as a PLY


def test_nerfstudio_export_has_8bit_images_and_masks_beside_it(exported):
    folder = exported["root"] / "export" / "nerfstudio"
    data = json.loads((folder / "transforms.json").read_text())
    for entry in data["frames"]:
        frame = next(f for f in exported["cameras"].frames
                     if f.name in entry["file_path"])
        image = read_image(folder / entry["file_path"])
        linear = read_image(exported["root"] / "poses" / frame.image)
        encoded = np.where(np.clip(linear, 0, 1) <= 0.0031308, 12.92 * np.clip(linear, 0, 1),
                           1.055 * np.clip(linear, 0, 1) ** (1 / 2.4) - 0.055)
        assert image.shape == linear.shape
        assert np.abs(image - encoded).max() <= 0.5 / 255 + 1e-6
        assert (folder / entry["mask_path"]).is_file()


def test_colmap_export_reads_back_to_the_source_cameras(exported):
    model_dir = exported["root"] / "export" / "colmap"
    assert {p.name for p in (model_dir / "sparse" / "0").iterdir()} >= {
        "cameras.txt", "images.txt", "points3D.txt"}
    dataset = read_colmap_model(model_dir)
    source = _source_poses(exported["cameras"])
    frames = {f.name: f for f in exported["cameras"].frames}
    assert sorted(v.name for v in dataset.views) == sorted(source)
    for view in dataset.views:
        np.testing.assert_allclose(view.c2w, source[view.name], atol=1e-9)
        frame = frames[view.name]
        assert view.camera.model_name == "PINHOLE"
        np.testing.assert_allclose(view.camera.params, [frame.fx, frame.fy, frame.cx, frame.cy])
        assert (model_dir / "images" / f"{view.name}.png").is_file()
    model = read_model(model_dir)
    assert model.num_cameras() == len({(f.width, f.fx) for f in frames.values()})
    xyz = np.array(sorted(p.xyz.tolist() for p in model.points3D.values()))
    np.testing.assert_allclose(xyz, np.array(sorted(exported["points"].tolist())), atol=1e-9)


def test_writers_carry_lens_distortion_through_both_formats(tmp_path):
    cameras = _cameras(views=3, seed=2)
    distortion = {f.name: {"k1": -0.08 + 0.01 * i, "k2": 0.01, "p1": 0.001, "p2": -0.002}
                  for i, f in enumerate(cameras.frames)}
    names = {f.name: f"{f.name}.png" for f in cameras.frames}
    (tmp_path / "ns").mkdir()
    (tmp_path / "ns" / "transforms.json").write_text(json.dumps(nerfstudio_transforms(
        cameras, {n: f"images/{v}" for n, v in names.items()}, distortion=distortion)))
    model_dir = tmp_path / "colmap" / "sparse" / "0"
    model_dir.mkdir(parents=True)
    colmap_reconstruction(cameras, names, distortion=distortion).write_text(model_dir)
    for dataset in (read_nerfstudio(tmp_path / "ns"), read_colmap_model(tmp_path / "colmap")):
        for view in dataset.views:
            frame = next(f for f in cameras.frames if f.name == view.name)
            k = distortion[view.name]
            assert view.camera.model_name == "OPENCV"
            np.testing.assert_allclose(view.camera.params,
                                       [frame.fx, frame.fy, frame.cx, frame.cy, k["k1"],
                                        k["k2"], k["p1"], k["p2"]])


def test_export_without_sparse_points_writes_an_empty_points_file(tmp_path, exported):
    poses = tmp_path / "poses"
    cameras = _cameras(views=2, seed=3)
    for frame in cameras.frames:
        write_float_tiff(poses / frame.image, np.full((frame.height, frame.width, 3), 0.2))
    write_cameras(poses / "cameras.json", cameras)
    assert main(["export", "--poses", str(poses), "--out", str(tmp_path / "export"),
                 "--image-format", "jpg"]) == 0
    model = read_model(tmp_path / "export" / "colmap")
    assert model.num_points3D() == 0 and model.num_images() == 2
    data = json.loads((tmp_path / "export" / "nerfstudio" / "transforms.json").read_text())
    assert all(f["file_path"].endswith(".jpg") and "mask_path" not in f for f in data["frames"])
    assert "ply_file_path" not in data


def test_export_names_a_missing_camera_file(tmp_path, capsys):
    assert main(["export", "--poses", str(tmp_path), "--out", str(tmp_path / "e")]) == 2
    assert "cameras.json" in capsys.readouterr().err


def test_points_with_tracks_are_observed_where_colmap_projects_them(tmp_path):
    cameras = _cameras(views=4, seed=3)
    rng = np.random.default_rng(4)
    # points in front of the first camera, 1-3 units away (source units)
    first = denormalise_c2w(cameras.frames[0].c2w_array, CENTRE, SCALE)
    local = np.column_stack([rng.uniform(-0.3, 0.3, (60, 2)), np.ones(60)]) \
        * rng.uniform(4, 12, (60, 1))
    points = local @ first[:3, :3].T + first[:3, 3]
    normalised = (points - CENTRE) * SCALE
    seen = np.stack([pixel_of_points(f.c2w_array, f.fx, f.fy, f.cx, f.cy, f.width, f.height,
                                     normalised)[3] for f in cameras.frames], axis=1)
    seen[:, 0] = True
    names = {f.name: f"{f.name}.png" for f in cameras.frames}
    colmap_reconstruction(cameras, names, points, seen=seen).write(tmp_path)
    model = read_model(tmp_path)
    by_name = {Path(image.name).stem: image for image in model.images.values()}
    column_of = {f.name: v for v, f in enumerate(cameras.frames)}
    assert model.num_points3D() == len(points)
    for point in model.points3D.values():
        index = int(np.argmin(np.linalg.norm(points - point.xyz, axis=1)))
        np.testing.assert_allclose(point.xyz, points[index], atol=1e-9)
        observed = set()
        for element in point.track.elements:
            image = model.image(element.image_id)
            observed.add(column_of[Path(image.name).stem])
            xy = image.points2D[element.point2D_idx].xy
            np.testing.assert_allclose(xy, image.project_point(point.xyz), atol=1e-6)
        assert observed == set(np.flatnonzero(seen[index]))
    assert sum(by_name[f.name].num_points3D for f in cameras.frames) == seen.sum()
    with pytest.raises(ValueError, match="seen"):
        colmap_reconstruction(cameras, names, points, seen=seen[:, :2])


def _points_before_first_camera(cameras: CameraSet, count: int = 60, seed: int = 4):
    """Points 4-12 source units in front of the first camera, and (M, V) which frames see
    them inside their image (the first always)."""
    rng = np.random.default_rng(seed)
    first = denormalise_c2w(cameras.frames[0].c2w_array, CENTRE, SCALE)
    local = np.column_stack([rng.uniform(-0.3, 0.3, (count, 2)), np.ones(count)]) \
        * rng.uniform(4, 12, (count, 1))
    points = local @ first[:3, :3].T + first[:3, 3]
    normalised = (points - CENTRE) * SCALE
    seen = np.stack([pixel_of_points(f.c2w_array, f.fx, f.fy, f.cx, f.cy, f.width, f.height,
                                     normalised)[3] for f in cameras.frames], axis=1)
    seen[:, 0] = True
    return points, seen


def test_the_colmap_export_carries_the_tracks_and_reads_back_with_bounds(tmp_path):
    """The poses step's model has tracks; the export keeps them (observations of frames
    matched by name), so the project's own reader takes each view's bounds from the points it
    sees, as from the source model (the export is usable as a ``colmap`` dataset)."""
    cameras = _cameras(views=4, seed=3)
    points, seen = _points_before_first_camera(cameras)
    poses = tmp_path / "poses"
    for frame in cameras.frames:
        write_float_tiff(poses / frame.image, np.full((frame.height, frame.width, 3), 0.3))
    write_cameras(poses / "cameras.json", cameras)
    (poses / "sparse").mkdir()
    names = {f.name: f"{f.name}.png" for f in cameras.frames}
    colmap_reconstruction(cameras, names, points, seen=seen).write(poses / "sparse")
    assert main(["export", "--poses", str(poses), "--out", str(tmp_path / "export")]) == 0
    model = read_model(tmp_path / "export" / "colmap")
    column_of = {f.name: v for v, f in enumerate(cameras.frames)}
    for point in model.points3D.values():
        index = int(np.argmin(np.linalg.norm(points - point.xyz, axis=1)))
        assert {column_of[Path(model.image(e.image_id).name).stem]
                for e in point.track.elements} == set(np.flatnonzero(seen[index]))
    source = {v.name: (v.near, v.far) for v in read_colmap_model(poses / "sparse").views}
    exported = {v.name: (v.near, v.far) for v in read_colmap_model(
        tmp_path / "export" / "colmap").views}
    assert exported.keys() == source.keys()
    assert exported[cameras.frames[0].name][0] is not None
    for name, bounds in exported.items():
        if source[name][0] is None:
            assert bounds == (None, None)
        else:
            assert bounds == pytest.approx(source[name], rel=1e-9)


def test_a_colmap_model_without_tracks_takes_bounds_from_the_points_in_view(tmp_path):
    """Points with no tracks (some writers leave them out, and exports made before this
    session): each camera's bounds come from the points in front of it and inside its image,
    the first camera's from all of them; a camera that sees none gets none here (the poses
    step gives it the scene's)."""
    cameras = _cameras(views=4, seed=3)
    points, seen = _points_before_first_camera(cameras)
    names = {f.name: f"{f.name}.png" for f in cameras.frames}
    colmap_reconstruction(cameras, names, points).write(tmp_path)
    views = {v.name: v for v in read_colmap_model(tmp_path).views}
    first = views[cameras.frames[0].name]
    depths = (points - first.c2w[:3, 3]) @ first.c2w[:3, 2]
    assert (first.near, first.far) == pytest.approx(depth_bounds(depths), rel=1e-9)
    for column, frame in enumerate(cameras.frames):
        assert (views[frame.name].near is None) == (not seen[:, column].any())


def _centred(cameras: CameraSet) -> CameraSet:
    """The same cameras with one focal length and a centred principal point (LLFF's)."""
    for frame in cameras.frames:
        frame.fy, frame.cx, frame.cy = frame.fx, frame.width / 2, frame.height / 2
    return cameras


def test_the_seathru_nerf_export_reads_back_as_an_llff_dataset(tmp_path):
    """images_wb (linear, one gain), poses_bounds.npy and sparse/0 as the release has them:
    the project's LLFF reader finds the same cameras, the same names and bounds, and keeps the
    model in the poses' frame; the gain brings the brightest 0.1% under 1."""
    cameras = _centred(_cameras(views=4, seed=3))
    points, seen = _points_before_first_camera(cameras)
    poses = tmp_path / "poses"
    rng = np.random.default_rng(5)
    linear = {}
    for frame in cameras.frames:
        linear[frame.name] = rng.random((frame.height, frame.width, 3)) * 1.6
        write_float_tiff(poses / frame.image, linear[frame.name])
    write_cameras(poses / "cameras.json", cameras)
    (poses / "sparse").mkdir()
    colmap_reconstruction(cameras, {f.name: f"{f.name}.png" for f in cameras.frames}, points,
                          seen=seen).write(poses / "sparse")
    assert main(["export", "--poses", str(poses), "--out", str(tmp_path / "export")]) == 0
    root = tmp_path / "export" / "seathru_nerf"
    record = json.loads((root / "export.json").read_text())
    every = np.concatenate([v.ravel() for v in linear.values()])
    assert record["linear_gain"] == pytest.approx(1 / np.quantile(every, 0.999), rel=0.02)
    dataset = read_llff(root)
    assert [v.name for v in dataset.views] == sorted(linear)
    for view in dataset.views:
        frame = next(f for f in cameras.frames if f.name == view.name)
        np.testing.assert_allclose(view.c2w, denormalise_c2w(frame.c2w_array, CENTRE, SCALE),
                                   atol=1e-9)
        assert (view.camera.width, view.camera.height) == (frame.width, frame.height)
        assert view.camera.params[0] == pytest.approx(frame.fx)
        assert view.near < frame.near / SCALE and view.far > frame.far / SCALE
        stored = read_image(root / "images_wb" / f"{view.name}.png")
        expected = np.round(np.clip(linear[view.name] * record["linear_gain"], 0, 1) * 255)
        np.testing.assert_array_equal(np.round(stored * 255), expected)
    kept = keep_source_model(dataset, tmp_path / "kept")
    assert kept["kept"] and kept["shared_images"] == 4 and kept["points"] == len(points)
    assert kept["max_position_error_share"] < 1e-9


def test_cameras_llff_cannot_hold_skip_the_seathru_nerf_layout_saying_why(exported):
    """The module fixture's cameras have fx != fy: no seathru_nerf/, the others written."""
    assert not (exported["root"] / "export" / "seathru_nerf").exists()
    assert (exported["root"] / "export" / "colmap" / "sparse" / "0").is_dir()
    assert "differ" in llff_camera_problem(exported["cameras"])
    assert llff_camera_problem(_centred(_cameras())) is None
