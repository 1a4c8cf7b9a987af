"""A source's COLMAP model kept beside cameras.json (seathru.io.source_model): an LLFF dataset's
``sparse/0`` is kept in the poses' frame when its cameras match ``poses_bounds.npy`` after a
similarity, and left out, with the figures and a warning, when they do not."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from seathru.geometry.poses import Similarity, opencv_to_llff
from seathru.io.dataset_readers import PosedDataset, PosedView, read_llff
from seathru.io.colmap import make_camera
from seathru.io.pose_report import pose_warnings
from seathru.io.source_model import AGREEMENT_SHARE, keep_source_model

WIDTH, HEIGHT, FOCAL = 160, 120, 150.0


def arc_cameras(count: int = 8) -> np.ndarray:
    """OpenCV c2w (count, 4, 4) on an arc 4 units from the origin, each looking at it."""
    c2w = np.tile(np.eye(4), (count, 1, 1))
    for i, angle in enumerate(np.linspace(-0.6, 0.6, count)):
        centre = np.array([4 * np.sin(angle), 0.3 * np.cos(3 * angle), -4 * np.cos(angle)])
        forward = -centre / np.linalg.norm(centre)
        right = np.cross([0.0, 1.0, 0.0], forward)
        right /= np.linalg.norm(right)
        c2w[i, :3, :3] = np.c_[right, np.cross(forward, right), forward]
        c2w[i, :3, 3] = centre
    return c2w


def write_model(folder: Path, names: list[str], c2w: np.ndarray, points: np.ndarray) -> None:
    """A COLMAP text model: one pinhole camera, the images at ``c2w``, each point observed by
    every image it projects into."""
    folder.mkdir(parents=True)
    (folder / "cameras.txt").write_text(
        f"1 PINHOLE {WIDTH} {HEIGHT} {FOCAL} {FOCAL} {WIDTH / 2} {HEIGHT / 2}\n")
    observations: list[list[str]] = [[] for _ in names]
    tracks: list[list[str]] = [[] for _ in points]
    for image, pose in enumerate(c2w):
        cam = (points - pose[:3, 3]) @ pose[:3, :3]
        u = FOCAL * cam[:, 0] / cam[:, 2] + WIDTH / 2
        v = FOCAL * cam[:, 1] / cam[:, 2] + HEIGHT / 2
        for point in np.flatnonzero((cam[:, 2] > 0) & (u >= 0) & (u < WIDTH) & (v >= 0)
                                    & (v < HEIGHT)):
            tracks[point].append(f"{image + 1} {len(observations[image])}")
            observations[image].append(f"{u[point]} {v[point]} {point + 1}")
    lines = []
    for image, (name, pose) in enumerate(zip(names, c2w)):
        rotation = pose[:3, :3].T
        qx, qy, qz, qw = Rotation.from_matrix(rotation).as_quat()
        translation = -rotation @ pose[:3, 3]
        lines += [f"{image + 1} {qw} {qx} {qy} {qz} {' '.join(map(str, translation))} 1 {name}",
                  " ".join(observations[image])]
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    (folder / "points3D.txt").write_text("".join(
        f"{i + 1} {' '.join(map(str, p))} 128 128 128 0.5 {' '.join(t)}\n"
        for i, (p, t) in enumerate(zip(points, tracks)) if t))


def scene_points(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1.0, 1.0, (300, 3))


def posed(names: list[str], c2w: np.ndarray, model: Path) -> PosedDataset:
    camera = make_camera("PINHOLE", WIDTH, HEIGHT, [FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2])
    views = [PosedView(name=n, camera=camera, c2w=p, near=1.0, far=8.0)
             for n, p in zip(names, c2w)]
    return PosedDataset(views=views, source="llff", notes={"model": str(model)})


def kept_points(out: Path) -> np.ndarray:
    model = pycolmap.Reconstruction(out / "sparse")
    return np.array([model.points3D[i].xyz for i in sorted(model.points3D)])


NAMES = [f"dive_{i:04d}" for i in range(8)]


def test_a_model_in_the_poses_frame_is_kept_as_it_is(tmp_path):
    c2w, points = arc_cameras(), scene_points()
    write_model(tmp_path / "sparse" / "0", [f"{n}.JPG" for n in NAMES], c2w, points)
    record = keep_source_model(posed(NAMES, c2w, tmp_path / "sparse" / "0"), tmp_path / "out")
    assert record["kept"] and record["shared_images"] == 8
    assert record["scale"] == pytest.approx(1.0, abs=1e-9)
    assert record["max_position_error_share"] < 1e-6
    source = pycolmap.Reconstruction(tmp_path / "sparse" / "0")
    np.testing.assert_allclose(kept_points(tmp_path / "out"),
                               [source.points3D[i].xyz for i in sorted(source.points3D)],
                               atol=1e-9)


@pytest.mark.parametrize("seed", [1, 2])
def test_a_model_in_another_frame_is_moved_into_the_poses_frame(tmp_path, seed):
    """The model of the same cameras rotated, scaled and shifted (COLMAP rerun, or the poses
    recentred): kept, its points where the poses' frame puts them."""
    rng = np.random.default_rng(seed)
    to_model = Similarity(float(rng.uniform(0.2, 5.0)), Rotation.random(random_state=seed)
                          .as_matrix(), rng.normal(0, 10, 3))
    c2w, points = arc_cameras(), scene_points(seed)
    write_model(tmp_path / "sparse", [f"{n}.png" for n in NAMES], to_model.apply_c2w(c2w),
                to_model.apply(points))
    record = keep_source_model(posed(NAMES, c2w, tmp_path / "sparse"), tmp_path / "out")
    assert record["kept"], record["reason"]
    assert record["scale"] == pytest.approx(1.0 / to_model.scale, rel=1e-6)
    seen = kept_points(tmp_path / "out")
    # every written point is one of the scene's points in the poses' frame
    nearest = np.linalg.norm(seen[:, None] - points[None], axis=-1).min(axis=1)
    assert seen.shape[0] > 100 and nearest.max() < 1e-6
    moved = pycolmap.Reconstruction(tmp_path / "out" / "sparse")
    for image in moved.images.values():
        centre = image.projection_center()
        np.testing.assert_allclose(centre, c2w[NAMES.index(Path(image.name).stem), :3, 3],
                                   atol=1e-6)


def test_a_model_of_other_cameras_is_left_out_with_a_warning(tmp_path, caplog):
    c2w, points = arc_cameras(), scene_points()
    write_model(tmp_path / "sparse" / "0", [f"{n}.png" for n in NAMES], c2w, points)
    moved = c2w.copy()
    moved[3, :3, 3] += np.array([0.0, 1.0, 0.0]) * 10 * AGREEMENT_SHARE * 4.5  # ~ 10x allowed
    record = keep_source_model(posed(NAMES, moved, tmp_path / "sparse" / "0"), tmp_path / "out")
    assert not record["kept"] and not (tmp_path / "out" / "sparse").exists()
    assert record["max_position_error_share"] > AGREEMENT_SHARE
    assert "do not match the poses" in record["reason"]
    assert "not kept" in caplog.text
    report = {"posed_without_linear_image": [], "linear_images_without_pose": [],
              "frames": 8, "test_frames": 1, "source_model": record}
    warnings = [w for w in pose_warnings(report) if w["code"] == "source_model_not_kept"]
    assert len(warnings) == 1 and str(tmp_path / "sparse" / "0") in warnings[0]["message"]


def test_a_model_naming_other_images_is_left_out(tmp_path):
    c2w, points = arc_cameras(), scene_points()
    write_model(tmp_path / "sparse" / "0", [f"other_{i}.png" for i in range(8)], c2w, points)
    record = keep_source_model(posed(NAMES, c2w, tmp_path / "sparse" / "0"), tmp_path / "out")
    assert not record["kept"] and record["shared_images"] == 0
    assert "named like a posed view" in record["reason"]


def test_the_llff_reader_names_the_model_beside_poses_bounds(tmp_path):
    c2w = arc_cameras()
    rows = np.c_[np.concatenate([opencv_to_llff(c2w), np.tile(
        np.array([[HEIGHT], [WIDTH], [FOCAL]]), (len(c2w), 1, 1))], axis=2).reshape(-1, 15),
        np.tile([1.0, 8.0], (len(c2w), 1))]
    np.save(tmp_path / "poses_bounds.npy", rows)
    (tmp_path / "images_wb").mkdir()
    for name in NAMES:
        (tmp_path / "images_wb" / f"{name}.png").write_bytes(b"")
    assert "model" not in read_llff(tmp_path).notes
    write_model(tmp_path / "sparse" / "0", [f"{n}.png" for n in NAMES], c2w, scene_points())
    dataset = read_llff(tmp_path)
    assert dataset.notes["model"] == str(tmp_path / "sparse" / "0")
    record = keep_source_model(dataset, tmp_path / "out")
    assert record["kept"] and record["max_rotation_error_deg"] < 1e-6
