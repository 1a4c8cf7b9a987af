"""Every posed source layout through the dataset sheet and the real Snakemake API, up to the
report: tiny datasets built in a tmp folder from ../shared/data/fern_llff (10 of its images_8
frames, downscaled to 126x94, with its poses_bounds.npy) arranged as

- ``llff_wb``: the SeaThru-NeRF release (``images_wb/`` beside a decoy ``images/``,
  ``poses_bounds.npy`` and the ``sparse/0`` its poses came from, naming the full-size JPEGs):
  ``ingest.images=auto`` must take images_wb, read as linear, and the model be kept;
- ``llff_n``: LLFF ``images_2/`` and ``images_4/``, ``ingest.images=images_4`` chooses;
- ``nerfstudio``: ``transforms.json`` whose frames point into ``images/``, two of them listed but
  missing, intrinsics at a larger size (one frame with its own), a ``sparse_pc.ply`` for bounds;
- ``colmap_text`` / ``colmap_bin``: ``images/`` + ``sparse/0`` as COLMAP text and binary models
  (written from poses_bounds.npy, synthetic points for the bounds; the binary one names its
  images in a subfolder);
- ``unconfirmed_warn`` / ``unconfirmed_fail``: a plain folder of images posed by COLMAP with a
  quality gate no model can pass (``poses.max_reproj_px`` tiny), kept with
  ``poses.on_unconfirmed=warn`` (the report shows it; it trains on a 9 s budget, to stop by
  time) or failing the dataset (the default).

Each finished dataset is checked against fern's own poses (same cameras, same names) and for a
held-out PSNR at evaluate (150 steps: about 15-17 dB); the report must list every dataset, the
failure with its advice and the warnings in its "needs a look" column (report.rising_psnr_db is
set low: every tiny run is far from converged). About 2 minutes on 2 cores.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pycolmap
import pytest
import yaml
from scipy.spatial.transform import Rotation

from seathru.geometry.poses import denormalise_c2w, llff_to_opencv, opencv_to_opengl
from seathru.io.cameras import read_cameras
from seathru.io.warnings import read_warnings
from tests.test_pipeline_e2e import run_workflow

pytestmark = pytest.mark.slow

FRAMES = 10            # fern images used (every other one of the 20)
SIZE = (126, 94)       # width, height of the fixture's images (fern images_8 / 4)
MISSING = ("image040", "image041")   # nerfstudio frames listed without a file


# -- the fixtures: fern arranged as each layout ------------------------------------------------

def fern_frames(fern: Path) -> tuple[list[str], list[np.ndarray], np.ndarray]:
    """(names, images at SIZE, their poses_bounds rows) of every other fern frame."""
    paths = sorted((fern / "images_8").glob("*.png"))[::2][:FRAMES]
    rows = np.load(fern / "poses_bounds.npy")[::2][:FRAMES]
    images = [cv2.resize(cv2.imread(str(p)), SIZE, interpolation=cv2.INTER_AREA) for p in paths]
    return [p.stem for p in paths], images, rows


def write_images(folder: Path, names: list[str], images: list[np.ndarray],
                 scale: float = 1.0) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name, image in zip(names, images):
        if scale != 1.0:
            image = cv2.resize(image, (round(SIZE[0] * scale), round(SIZE[1] * scale)),
                               interpolation=cv2.INTER_LINEAR)
        cv2.imwrite(str(folder / f"{name}.png"), image)


def cameras_of(rows: np.ndarray) -> tuple[np.ndarray, float, float, float]:
    """OpenCV c2w (N, 4, 4) and the full-size (height, width, focal) of poses_bounds rows."""
    poses = rows[:, :15].reshape(-1, 3, 5)
    height, width, focal = poses[0, :, 4]
    return llff_to_opencv(poses[:, :, :4]), float(height), float(width), float(focal)


def scene_points(rows: np.ndarray, seed: int = 0) -> np.ndarray:
    """Points in front of the cameras between their LLFF bounds (for bounds, not for looks)."""
    c2w, height, width, focal = cameras_of(rows)
    rng = np.random.default_rng(seed)
    points = []
    for pose, (near, far) in zip(c2w, rows[:, 15:]):
        pixels = rng.uniform([0.1 * width, 0.1 * height], [0.9 * width, 0.9 * height], (40, 2))
        rays = np.c_[(pixels[:, 0] - width / 2) / focal, (pixels[:, 1] - height / 2) / focal,
                     np.ones(len(pixels))]
        depth = rng.uniform(1.2 * near, 0.8 * far, (len(pixels), 1))
        points.append((rays * depth) @ pose[:3, :3].T + pose[:3, 3])
    return np.concatenate(points)


def build_llff_wb(fern: Path, root: Path) -> None:
    names, images, rows = fern_frames(fern)
    write_images(root / "images_wb", names, images)
    write_images(root / "images", names, images, scale=2.0)   # auto must not take it
    np.save(root / "poses_bounds.npy", rows)
    write_colmap_text(root / "sparse" / "0", [f"{n}.JPG" for n in names], rows)


def build_llff_n(fern: Path, root: Path) -> None:
    names, images, rows = fern_frames(fern)
    write_images(root / "images_4", names, images)
    write_images(root / "images_2", names, images, scale=2.0)
    np.save(root / "poses_bounds.npy", rows)


def write_ply(path: Path, points: np.ndarray) -> None:
    header = ("ply\nformat ascii 1.0\n"
              f"element vertex {len(points)}\nproperty float x\nproperty float y\n"
              "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
              "end_header\n")
    path.write_text(header + "".join(f"{x:.6f} {y:.6f} {z:.6f} 128 128 128\n"
                                     for x, y, z in points))


def build_nerfstudio(fern: Path, root: Path) -> None:
    names, images, rows = fern_frames(fern)
    write_images(root / "images", names, images)
    c2w, height, width, focal = cameras_of(rows)
    scale = 4 * SIZE[0] / width             # intrinsics at 4x the images' size (504x378)
    frames = [{"file_path": f"images/{name}.png",
               "transform_matrix": opencv_to_opengl(pose).tolist()}
              for name, pose in zip(names, c2w)]
    frames[3].update({"fl_x": focal * scale, "fl_y": focal * scale})   # a frame's own values
    frames += [{"file_path": f"images/{name}.png", "transform_matrix": frames[0][
        "transform_matrix"]} for name in MISSING]
    write_ply(root / "sparse_pc.ply", scene_points(rows))
    (root / "transforms.json").write_text(json.dumps({
        "camera_model": "OPENCV", "fl_x": focal * scale, "fl_y": focal * scale,
        "cx": 2 * SIZE[0], "cy": 2 * SIZE[1], "w": 4 * SIZE[0], "h": 4 * SIZE[1],
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "ply_file_path": "sparse_pc.ply",
        "frames": frames}, indent=1))


def write_colmap_text(model: Path, names: list[str], rows: np.ndarray) -> None:
    """COLMAP text model (one PINHOLE camera at 2x the images' size) with synthetic points
    observed by every camera that sees them."""
    c2w, height, width, focal = cameras_of(rows)
    size = (2 * SIZE[0], 2 * SIZE[1])
    f = focal * size[0] / width
    points = scene_points(rows)
    observations: dict[int, list[tuple[float, float, int]]] = {i: [] for i in range(len(names))}
    tracks: dict[int, list[tuple[int, int]]] = {}
    for image_id, pose in enumerate(c2w):
        cam = (points - pose[:3, 3]) @ pose[:3, :3]
        u = f * cam[:, 0] / cam[:, 2] + size[0] / 2
        v = f * cam[:, 1] / cam[:, 2] + size[1] / 2
        visible = (cam[:, 2] > 0) & (u >= 0) & (u < size[0]) & (v >= 0) & (v < size[1])
        for point_id in np.flatnonzero(visible):
            tracks.setdefault(int(point_id), []).append((image_id + 1,
                                                         len(observations[image_id])))
            observations[image_id].append((float(u[point_id]), float(v[point_id]),
                                           int(point_id) + 1))
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text(
        f"1 PINHOLE {size[0]} {size[1]} {f} {f} {size[0] / 2} {size[1] / 2}\n")
    lines = []
    for image_id, (name, pose) in enumerate(zip(names, c2w)):
        rotation = pose[:3, :3].T
        translation = -rotation @ pose[:3, 3]
        qx, qy, qz, qw = Rotation.from_matrix(rotation).as_quat()
        lines.append(f"{image_id + 1} {qw} {qx} {qy} {qz} {' '.join(map(str, translation))} 1 "
                     f"{name}")
        lines.append(" ".join(f"{u} {v} {pid}" for u, v, pid in observations[image_id]))
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    (model / "points3D.txt").write_text("".join(
        f"{pid + 1} {' '.join(map(str, points[pid]))} 128 128 128 0.5 "
        + " ".join(f"{i} {k}" for i, k in track) + "\n" for pid, track in tracks.items()))


def build_colmap_text(fern: Path, root: Path) -> None:
    names, images, rows = fern_frames(fern)
    write_images(root / "images", names, images)
    write_colmap_text(root / "sparse" / "0", [f"{n}.png" for n in names], rows)


def build_colmap_bin(fern: Path, root: Path) -> None:
    """Binary model whose images are named in a subfolder (images/dive/<name>.png)."""
    names, images, rows = fern_frames(fern)
    write_images(root / "images" / "dive", names, images)
    write_colmap_text(root / "text", [f"dive/{n}.png" for n in names], rows)
    (root / "sparse" / "0").mkdir(parents=True)
    pycolmap.Reconstruction(root / "text").write_binary(root / "sparse" / "0")
    shutil.rmtree(root / "text")


def build_images(fern: Path, root: Path) -> None:
    names, images, _ = fern_frames(fern)
    write_images(root, names, images, scale=2.0)


BUILDERS = {"llff_wb": build_llff_wb, "llff_n": build_llff_n, "nerfstudio": build_nerfstudio,
            "colmap_text": build_colmap_text, "colmap_bin": build_colmap_bin,
            "unconfirmed_warn": build_images}
# the sheet: dataset, source, folder, options
UNCONFIRMABLE = "poses.max_reproj_px=0.0001; poses.retry=false; poses.cross_check=false"
ROWS = (("llff_wb", "llff", "llff_wb", ""),
        ("llff_n", "llff", "llff_n", "ingest.images=images_4"),
        ("nerfstudio", "nerfstudio", "nerfstudio", ""),
        ("colmap_text", "colmap", "colmap_text", ""),
        ("colmap_bin", "colmap", "colmap_bin", ""),
        ("unconfirmed_warn", "images", "unconfirmed_warn",
         f"{UNCONFIRMABLE}; poses.on_unconfirmed=warn; train.max_minutes=0.15; "
         "train.steps=100000"),
        ("unconfirmed_fail", "images", "unconfirmed_warn", UNCONFIRMABLE))
POSED = ("llff_wb", "llff_n", "nerfstudio", "colmap_text", "colmap_bin")

CONFIG = {
    "datasets": "config/datasets.tsv", "results": "results", "logs": "logs",
    "train": {"steps": 150, "max_minutes": 2.0, "batch_rays": 512, "checkpoint_every": 0,
              "progress": False, "log_every": 25,
              "field": {"density_res": [32, 48, 64], "plane_res": [32, 64, 96],
                        "plane_coarse_res": 16, "density_coarse_res": 16},
              "medium": {"refit_rays": 4096, "refit_steps": 30}, "optim": {"warmup_steps": 10}},
    "render": {"path_frames": 0},
    # every tiny run is far from converged: the report must say so
    "report": {"rising_psnr_db": 0.02},
    "resources": {"default": {"threads": 1, "mem_mb": 2000, "runtime": 30, "gpu": 0}},
}


@pytest.fixture(scope="module")
def sources_run(shared_data, tmp_path_factory):
    fern = shared_data / "fern_llff"
    if not (fern / "poses_bounds.npy").is_file():
        pytest.skip(f"{fern}: fern_llff with poses_bounds.npy not found")
    workdir = tmp_path_factory.mktemp("sources")
    for name, build in BUILDERS.items():
        build(fern, workdir / "data" / name)
    (workdir / "config").mkdir()
    (workdir / "config" / "config.yaml").write_text(yaml.safe_dump(CONFIG))
    (workdir / "config" / "datasets.tsv").write_text("dataset\tsource\tpath\toptions\n" + "".join(
        f"{dataset}\t{source}\tdata/{folder}\t{options}\n"
        for dataset, source, folder, options in ROWS))
    start = time.perf_counter()
    succeeded = run_workflow(workdir)
    return {"workdir": workdir, "succeeded": succeeded, "seconds": time.perf_counter() - start,
            "fern": fern}


def results(run, dataset: str) -> Path:
    return run["workdir"] / "results" / dataset


def log_tail(run, dataset: str) -> str:
    logs = sorted((run["workdir"] / "logs" / dataset).glob("*.log"))
    return "\n".join(f"== {p.name}\n{p.read_text()[-1500:]}" for p in logs)


# -- every layout finishes, with fern's own cameras --------------------------------------------

@pytest.mark.parametrize("dataset", POSED + ("unconfirmed_warn",))
def test_each_layout_runs_to_evaluate(sources_run, dataset):
    summary = results(sources_run, dataset) / "evaluate" / "summary.json"
    assert summary.is_file(), log_tail(sources_run, dataset)
    metrics = pd.read_csv(results(sources_run, dataset) / "evaluate" / "metrics.csv")
    # 150 steps of fern (in air): where no water is chosen at step 60, the right answer, the
    # run has 90 steps to recover from the switch (llff_n 12.35-12.60 dB; with the water's fog
    # 13 and more); the unconfirmed one trains 9 s only
    floor = 8.0 if dataset == "unconfirmed_warn" else 12.0
    assert len(metrics) >= 1 and metrics["psnr_linear"].mean() > floor, metrics


@pytest.mark.parametrize("dataset", POSED)
def test_posed_layouts_keep_the_datasets_cameras(sources_run, dataset):
    names, _, rows = fern_frames(sources_run["fern"])
    expected, height, width, focal = cameras_of(rows)
    cameras = read_cameras(results(sources_run, dataset) / "poses" / "cameras.json")
    assert [f.name for f in cameras.frames] == names, log_tail(sources_run, dataset)
    c2w = denormalise_c2w(np.array([f.c2w for f in cameras.frames]), cameras.centre,
                          cameras.scale)
    np.testing.assert_allclose(c2w, expected, atol=1e-5)
    frame = cameras.frames[0]
    assert (frame.width, frame.height) == SIZE
    assert frame.fx == pytest.approx(focal * SIZE[0] / width, rel=1e-3)


def manifest(run, dataset: str) -> dict:
    return json.loads((results(run, dataset) / "ingest" / "manifest.json").read_text())


def test_llff_auto_takes_the_release_images_wb_as_linear(sources_run):
    layout = manifest(sources_run, "llff_wb")["input"]["layout"]
    assert layout["images"] == "images_wb" and layout["kind"] == "linear"
    assert "SeaThru-NeRF" in layout["reason"]
    assert manifest(sources_run, "llff_wb")["input"]["kind"] == "linear"


def test_llff_release_model_is_kept_and_trained_on(sources_run):
    """The release's sparse/0 is kept as poses/sparse: training has depth rays from it."""
    report = json.loads((results(sources_run, "llff_wb") / "poses" / "report.json").read_text())
    model = report["source_model"]
    assert model["kept"] and model["shared_images"] == FRAMES, model
    assert model["max_position_error_share"] < 1e-6 and report["source_points_kept"] > 100
    kept = pycolmap.Reconstruction(results(sources_run, "llff_wb") / "poses" / "sparse")
    assert kept.num_points3D() == report["source_points_kept"]
    train_log = "".join(p.read_text() for p in
                        (sources_run["workdir"] / "logs" / "llff_wb").glob("train*.log"))
    assert "sparse depth:" in train_log, train_log[-2000:]
    other = json.loads((results(sources_run, "llff_n") / "poses" / "report.json").read_text())
    assert "source_model" not in other and not (results(sources_run, "llff_n") / "poses"
                                                / "sparse").exists()


def test_llff_option_chooses_images_n(sources_run):
    data = manifest(sources_run, "llff_n")
    assert data["input"]["layout"]["images"] == "images_4"
    assert data["input"]["kind"] == "srgb"   # an LLFF images_N folder holds sRGB images
    report = json.loads((results(sources_run, "llff_n") / "poses" / "report.json").read_text())
    assert report["reader_notes"]["names_from"].endswith("images_4")


def test_nerfstudio_missing_frames_are_named_in_the_manifest_and_warnings(sources_run):
    data = manifest(sources_run, "nerfstudio")
    assert sorted(m["name"] for m in data["input"]["layout"]["missing"]) == list(MISSING)
    warnings = read_warnings(results(sources_run, "nerfstudio") / "ingest" / "warnings.json")
    missing = [w for w in warnings if w["code"] == "missing_frames"]
    assert len(missing) == 1 and all(name in missing[0]["message"] for name in MISSING)
    poses = read_warnings(results(sources_run, "nerfstudio") / "poses" / "warnings.json")
    assert not [w for w in poses if w["code"] == "posed_without_image"]   # said once, by ingest


def test_colmap_binary_model_finds_images_in_a_subfolder(sources_run):
    data = manifest(sources_run, "colmap_bin")
    assert data["input"]["layout"]["missing"] == []
    assert all("/dive/" in image["source_path"] for image in data["images"])


# -- an unconfirmed camera model ---------------------------------------------------------------

def test_unconfirmed_model_fails_the_dataset_with_what_to_try(sources_run):
    assert not sources_run["succeeded"], "unconfirmed_fail should have failed the run"
    log = (sources_run["workdir"] / "logs" / "unconfirmed_fail" / "poses.log").read_text()
    assert "seathru poses: error: the camera model was not confirmed" in log, log[-3000:]
    for advice in ("mean reprojection error", "poses.matcher=exhaustive", "poses.mapper=global",
                   "poses.max_image_size", "poses.clahe", "poses.on_unconfirmed=warn"):
        assert advice in log
    assert not (results(sources_run, "unconfirmed_fail") / "poses").exists()


def test_report_shows_failures_and_warnings(sources_run):
    report = sources_run["workdir"] / "results" / "report"
    table = pd.read_csv(report / "summary.csv").set_index("dataset")
    assert set(table.index) == {row[0] for row in ROWS}
    assert table.loc["unconfirmed_fail", "status"] == "failed"
    assert "not confirmed" in table.loc["unconfirmed_fail", "error"]
    assert "poses: unconfirmed_poses" in table.loc["unconfirmed_warn", "needs_a_look"]
    assert "ingest: missing_frames" in table.loc["nerfstudio", "needs_a_look"]
    assert table.loc["nerfstudio", "warnings"] >= 1
    html = (report / "summary.html").read_text()
    assert "Needs a look" in html and "unconfirmed_poses" in html
    assert "image040" in html   # the missing frame, named


def test_report_derives_training_warnings(sources_run):
    table = pd.read_csv(sources_run["workdir"] / "results" / "report" / "summary.csv")
    table = table.set_index("dataset")
    for dataset in POSED + ("unconfirmed_warn",):
        assert "train: not_converged" in table.loc[dataset, "needs_a_look"], dataset
    html = (sources_run["workdir"] / "results" / "report" / "summary.html").read_text()
    # unconfirmed_warn ran out of its time budget (train.max_minutes=0.15), the others of steps
    assert "stopped at its time budget" in html and "reached train.steps" in html


def test_run_time_is_small(sources_run):
    print(f"sources e2e: {sources_run['seconds']:.0f} s")
    assert sources_run["seconds"] < 300
