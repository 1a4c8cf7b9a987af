"""Structure from motion with pycolmap 4.2.1, COLMAP model reading, undistortion maps.

The COLMAP run is split in the usual stages (feature extraction, matching, mapping), each on a
database in a work folder the caller owns. :func:`reconstruct` adds the project's quality gate
on top: a model must register enough images with a low mean reprojection error and, with the
cross-check on, be confirmed by an independent model (the other mapper on the same matches, or
either mapper on the other matcher's matches) agreeing on the poses after a similarity
alignment. Until that happens the alternatives are tried in turn (after a first model that fails
the gate, the same settings with another seed come first); every attempt is recorded.
"""

from __future__ import annotations

import contextlib
import copy
import logging
import shutil
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np
import pycolmap

from seathru.geometry.poses import (c2w_from_cam_from_world, compare_trajectories, depth_bounds,
                                   point_depths)
from seathru.errors import PipelineError

log = logging.getLogger(__name__)

CAMERA_MODELS = ("SIMPLE_RADIAL", "OPENCV", "RADIAL", "SIMPLE_PINHOLE", "PINHOLE")
MATCHERS = ("sequential", "exhaustive")
MAPPERS = ("incremental", "global")


def global_mapping_available() -> bool:
    return hasattr(pycolmap, "global_mapping") and hasattr(pycolmap, "GlobalPipelineOptions")


@dataclass(frozen=True)
class SfmSettings:
    """Everything that changes a COLMAP run; recorded as is in the report."""

    camera_model: str = "SIMPLE_RADIAL"
    single_camera: bool = True
    matcher: str = "sequential"
    overlap: int = 10
    mapper: str = "incremental"
    max_image_size: int = 1600
    max_features: int = 8192
    threads: int = -1
    seed: int = 0
    focal_px: float | None = None   # initial focal length at the matching images' size
    refine_focal: bool = True


@dataclass
class SfmAttempt:
    settings: dict
    role: str = "first"             # first | cross-check | retry
    registered: int = 0
    total: int = 0
    mean_reprojection_px: float | None = None
    num_points: int = 0
    mean_track_length: float | None = None
    seconds: float = 0.0
    passed: bool = False
    unregistered: list[str] = field(default_factory=list)
    error: str | None = None
    agreement: dict | None = None   # the confirming comparison, for the model kept
    comparisons: list[dict] = field(default_factory=list)  # with earlier independent models
    note: str | None = None

    @property
    def registered_fraction(self) -> float:
        return self.registered / self.total if self.total else 0.0

    def to_dict(self) -> dict:
        data = asdict(self)
        data["registered_fraction"] = self.registered_fraction
        return data

    def sort_key(self) -> tuple:
        """Better attempts sort higher: gate passed, more images, lower reprojection error."""
        error = self.mean_reprojection_px if self.mean_reprojection_px is not None else np.inf
        return (self.passed, self.registered, -error)


@dataclass(frozen=True)
class QualityGate:
    """What a model must satisfy to be accepted without retrying.

    The reprojection error limit applies at the resolution SIFT ran at; ``reprojection_scale``
    (matching image size / SIFT size, >= 1) converts it to the model's pixels. Two mappers
    (incremental, global) run on the same matches must agree on the camera poses within
    ``max_disagreement`` of the camera extent and ``max_rotation_disagreement_deg``: a model
    that is self-consistent (low reprojection error) can still be wrong when repeated texture
    gives consistent false matches, and the two mappers rarely fail the same way.
    """

    min_registered_fraction: float = 0.8
    max_reprojection_px: float = 1.0
    reprojection_scale: float = 1.0
    max_disagreement: float = 0.01
    max_rotation_disagreement_deg: float = 1.0

    def check(self, attempt: SfmAttempt) -> bool:
        return (attempt.registered > 0
                and attempt.registered_fraction >= self.min_registered_fraction
                and attempt.mean_reprojection_px is not None
                and attempt.mean_reprojection_px
                <= self.max_reprojection_px * self.reprojection_scale)

    def agree(self, agreement: dict | None) -> bool:
        return (agreement is not None
                and agreement["max_centre_deviation"] <= self.max_disagreement
                and agreement["max_rotation_deviation_deg"] <= self.max_rotation_disagreement_deg)


@contextlib.contextmanager
def colmap_log_level(verbose: bool) -> Iterator[None]:
    """COLMAP logs every stage at INFO; keep warnings only unless the user asked for debug."""
    previous = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 0 if verbose else 1
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = previous


def initial_camera_params(model: str, focal_px: float, width: int, height: int) -> str:
    """COLMAP parameter string for a camera with a known focal length and no distortion yet."""
    cx, cy = width / 2.0, height / 2.0
    params = {
        "SIMPLE_PINHOLE": [focal_px, cx, cy],
        "PINHOLE": [focal_px, focal_px, cx, cy],
        "SIMPLE_RADIAL": [focal_px, cx, cy, 0.0],
        "RADIAL": [focal_px, cx, cy, 0.0, 0.0],
        "OPENCV": [focal_px, focal_px, cx, cy, 0.0, 0.0, 0.0, 0.0],
    }[model]
    return ",".join(repr(float(p)) for p in params)


def extract_features(database: Path, image_dir: Path, names: list[str], settings: SfmSettings,
                     image_size: tuple[int, int], mask_dir: Path | None = None) -> None:
    """SIFT on the CPU for ``names`` (file names under ``image_dir``) into a new database.

    ``image_size`` (width, height) is that of every image; used for a known focal length.
    ``mask_dir`` holds ``<file name>.png`` masks (black = no features), COLMAP's layout.
    """
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = settings.camera_model
    if settings.focal_px is not None:
        reader.camera_params = initial_camera_params(settings.camera_model, settings.focal_px,
                                                     *image_size)
    if mask_dir is not None:
        reader.mask_path = str(mask_dir)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.use_gpu = False
    extraction.num_threads = settings.threads
    extraction.max_image_size = settings.max_image_size
    extraction.sift.max_num_features = settings.max_features
    mode = pycolmap.CameraMode.SINGLE if settings.single_camera else pycolmap.CameraMode.PER_IMAGE
    pycolmap.extract_features(database, image_dir, image_names=names, camera_mode=mode,
                              reader_options=reader, extraction_options=extraction,
                              device=pycolmap.Device.cpu)


def match_features(database: Path, settings: SfmSettings) -> None:
    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    matching.num_threads = settings.threads
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = settings.seed
    if settings.matcher == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = settings.overlap
        pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing,
                                  verification_options=verification, device=pycolmap.Device.cpu)
    elif settings.matcher == "exhaustive":
        pycolmap.match_exhaustive(database, matching_options=matching,
                                  verification_options=verification, device=pycolmap.Device.cpu)
    else:
        raise PipelineError(f"unknown matcher {settings.matcher!r}; use one of {MATCHERS}")


def map_reconstruction(database: Path, image_dir: Path, output_dir: Path,
                       settings: SfmSettings) -> pycolmap.Reconstruction | None:
    """Run the mapper; return the model with the most registered images (None if no model)."""
    output_dir.mkdir(parents=True, exist_ok=True)
    pycolmap.set_random_seed(settings.seed)
    if settings.mapper == "incremental":
        options = pycolmap.IncrementalPipelineOptions()
        options.num_threads = settings.threads
        options.random_seed = settings.seed
        options.mapper.random_seed = settings.seed
        options.triangulation.random_seed = settings.seed
        options.min_model_size = 3  # small sets: keep any model; we keep the largest anyway
        if not settings.refine_focal:
            options.ba_refine_focal_length = False
            options.mapper.abs_pose_refine_focal_length = False
        models = pycolmap.incremental_mapping(database, image_dir, output_dir, options=options)
    elif settings.mapper == "global":
        if not global_mapping_available():
            raise PipelineError("this pycolmap has no global mapper; use --mapper incremental")
        options = pycolmap.GlobalPipelineOptions()
        options.num_threads = settings.threads
        options.random_seed = settings.seed
        options.min_model_size = 3
        mapper = options.mapper
        mapper.num_threads = settings.threads
        mapper.random_seed = settings.seed
        mapper.rotation_averaging.random_seed = settings.seed
        mapper.global_positioning.random_seed = settings.seed
        mapper.global_positioning.use_gpu = False
        mapper.bundle_adjustment.ceres.use_gpu = False
        if not settings.refine_focal:
            mapper.bundle_adjustment.refine_focal_length = False
        models = pycolmap.global_mapping(database, image_dir, output_dir, options)
    else:
        raise PipelineError(f"unknown mapper {settings.mapper!r}; use one of {MAPPERS}")
    if not models:
        return None
    return max(models.values(), key=lambda model: model.num_reg_images())


def registered_names(model: pycolmap.Reconstruction | None) -> set[str]:
    if model is None:
        return set()
    return {model.image(image_id).name for image_id in model.reg_image_ids()}


def registered_c2w(model: pycolmap.Reconstruction) -> dict[str, np.ndarray]:
    """OpenCV camera-to-world (4, 4) of every registered image, by image name."""
    return {model.image(i).name: c2w_from_cam_from_world(model.image(i).cam_from_world().matrix())
            for i in model.reg_image_ids()}


def compare_models(model: pycolmap.Reconstruction | None,
                   other: pycolmap.Reconstruction | None) -> dict | None:
    """How far two models of the same images disagree, after a similarity alignment.

    Returns the largest camera-centre deviation as a fraction of the camera extent (largest
    distance between two camera centres) and the largest rotation deviation in degrees, over
    the images both registered; None when fewer than 3 are shared or the cameras coincide.
    """
    if model is None or other is None:
        return None
    poses, other_poses = registered_c2w(model), registered_c2w(other)
    common = sorted(set(poses) & set(other_poses))
    if len(common) < 3:
        return None
    comparison = compare_trajectories(np.array([other_poses[n] for n in common]),
                                      np.array([poses[n] for n in common]))
    if comparison.extent <= 0:
        return None
    return {"common_images": len(common),
            "max_centre_deviation": float(comparison.position_errors.max() / comparison.extent),
            "max_rotation_deviation_deg": float(comparison.rotation_errors_deg.max())}


def describe_model(attempt: SfmAttempt, model: pycolmap.Reconstruction | None,
                   names: list[str]) -> None:
    """Fill an attempt's statistics from its model."""
    registered = registered_names(model)
    attempt.total = len(names)
    attempt.registered = len(registered & set(names))
    attempt.unregistered = [name for name in names if name not in registered]
    if model is not None and model.num_points3D() > 0:
        attempt.num_points = int(model.num_points3D())
        attempt.mean_reprojection_px = float(model.compute_mean_reprojection_error())
        attempt.mean_track_length = float(model.compute_mean_track_length())


@dataclass
class SfmResult:
    model: pycolmap.Reconstruction | None
    chosen: SfmAttempt | None
    attempts: list[SfmAttempt]

    @property
    def passed(self) -> bool:
        return self.chosen is not None and self.chosen.passed


def alternatives(settings: SfmSettings, cross_check: bool = True) -> list[SfmSettings]:
    """Independent ways to map the same images, the user's first.

    The other mapper on the same matches, then the other matcher (exhaustive for sequential and
    vice versa) with each mapper. Seeds are not a source of independent evidence: with the same
    matches COLMAP's mappers nearly always return the same model whatever the seed.
    """
    mappers = [settings.mapper]
    if global_mapping_available() and cross_check:
        mappers.append("global" if settings.mapper == "incremental" else "incremental")
    elif settings.mapper == "incremental" and global_mapping_available():
        mappers.append("global")
    other_matcher = "exhaustive" if settings.matcher == "sequential" else "sequential"
    return [replace(settings, matcher=matcher, mapper=mapper)
            for matcher in (settings.matcher, other_matcher) for mapper in mappers]


def _independent(a: SfmSettings, b: SfmSettings) -> bool:
    return (a.matcher, a.mapper) != (b.matcher, b.mapper)


class _Runner:
    """Runs mapping attempts on shared features and per-matcher match databases."""

    def __init__(self, image_dir: Path, names: list[str], work_dir: Path, gate: QualityGate):
        self.image_dir, self.names, self.work_dir, self.gate = image_dir, names, work_dir, gate
        self.features_db = work_dir / "features.db"
        self.matched: dict[tuple, Path] = {}
        self.attempts: list[SfmAttempt] = []

    def run(self, settings: SfmSettings, role: str
            ) -> tuple[SfmAttempt, pycolmap.Reconstruction | None]:
        index = len(self.attempts)
        attempt = SfmAttempt(settings=asdict(settings), role=role, total=len(self.names))
        start = time.perf_counter()
        model = None
        try:
            key = (settings.matcher, settings.overlap)
            if key not in self.matched:
                matched_db = self.work_dir / f"matches_{settings.matcher}.db"
                shutil.copyfile(self.features_db, matched_db)
                match_features(matched_db, settings)
                self.matched[key] = matched_db
            database = self.work_dir / f"attempt_{index}.db"
            shutil.copyfile(self.matched[key], database)
            model = map_reconstruction(database, self.image_dir,
                                       self.work_dir / f"attempt_{index}", settings)
            describe_model(attempt, model, self.names)
            attempt.passed = self.gate.check(attempt)
        except PipelineError:
            raise
        except Exception as exc:  # COLMAP raises plain RuntimeErrors; record and go on
            attempt.error = f"{type(exc).__name__}: {exc}"
            attempt.unregistered = list(self.names)
        attempt.seconds = round(time.perf_counter() - start, 2)
        self.attempts.append(attempt)
        log.info("attempt %d, %s (%s matching, %s mapping, seed %d): %d/%d registered, mean "
                 "reprojection error %s px, %s", index + 1, role, settings.matcher,
                 settings.mapper, settings.seed, attempt.registered, attempt.total,
                 _fmt(attempt.mean_reprojection_px),
                 "passed" if attempt.passed else "failed the gate")
        return attempt, model


def reconstruct(image_dir: Path, names: list[str], work_dir: Path, settings: SfmSettings,
                gate: QualityGate, image_size: tuple[int, int], mask_dir: Path | None = None,
                retry: bool = True, cross_check: bool = True, verbose: bool = False
                ) -> SfmResult:
    """Extract, match and map ``names`` with the quality gate, retries and cross-check.

    Features are extracted once; each matcher's database is built once and copied for every
    mapping attempt so the attempts do not see each other's writes.

    Without ``cross_check`` the first model that passes the gate is kept (after retrying with
    another seed, then the alternatives of :func:`alternatives`). With it, a model must also be
    confirmed by an independent model (other mapper or other matcher) agreeing with its poses:
    a self-consistent model (every image, low reprojection error) can still be wrong when
    repeated texture produces consistent false matches, and both mappers fail that way at
    times. Models built on the user's matcher are the candidates (for ordered dive sets the
    sequential matches hold fewer false pairs); the other matcher's models serve as witnesses,
    and become candidates only when no model on the user's matcher passes the gate. Among
    confirmed candidates the one tried first wins; when no candidate is confirmed, the one with
    the lowest mean reprojection error is kept, marked unconfirmed.
    """
    work_dir.mkdir(parents=True, exist_ok=True)
    runner = _Runner(image_dir, names, work_dir, gate)
    plan = alternatives(settings, cross_check)
    if not retry:
        plan = [p for p in plan if p.matcher == settings.matcher] if cross_check else [settings]
    runs: list[_Run] = []
    comparisons: dict[tuple[int, int], dict | None] = {}
    chosen: _Run | None = None
    with colmap_log_level(verbose):
        start = time.perf_counter()
        extract_features(runner.features_db, image_dir, names, settings, image_size, mask_dir)
        log.info("SIFT features for %d images in %.1f s", len(names), time.perf_counter() - start)
        queue = list(plan)
        while queue and chosen is None:
            current = queue.pop(0)
            role = ("first" if not runs else
                    "cross-check" if cross_check and runs[0].attempt.passed else "retry")
            attempt, model = runner.run(current, role)
            runs.append(_Run(current, attempt, model))
            if len(runs) == 1 and not attempt.passed and retry:
                queue.insert(0, replace(current, seed=current.seed + 1))
            if not cross_check:
                chosen = runs[-1] if attempt.passed else None
            else:
                chosen = _confirmed(runs, comparisons, gate, settings.matcher)
        if chosen is None and runs:
            chosen = _unconfirmed(runs, settings.matcher, cross_check)
    if chosen is None or chosen.attempt.registered == 0:
        return SfmResult(model=None, chosen=None, attempts=runner.attempts)
    return SfmResult(model=chosen.model, chosen=chosen.attempt, attempts=runner.attempts)


@dataclass
class _Run:
    settings: SfmSettings
    attempt: SfmAttempt
    model: pycolmap.Reconstruction | None


def _candidates(runs: list[_Run], matcher: str) -> list[_Run]:
    passed = [run for run in runs if run.attempt.passed]
    return [run for run in passed if run.settings.matcher == matcher] or passed


def _confirmed(runs: list[_Run], comparisons: dict, gate: QualityGate,
               matcher: str) -> _Run | None:
    """The earliest candidate that an independent gate-passing model agrees with."""
    passed = [run for run in runs if run.attempt.passed]
    for candidate in _candidates(runs, matcher):
        for witness in passed:
            if witness is candidate or not _independent(candidate.settings, witness.settings):
                continue
            i, j = sorted((runs.index(candidate), runs.index(witness)))
            if (i, j) not in comparisons:
                agreement = compare_models(runs[i].model, runs[j].model)
                comparisons[(i, j)] = agreement
                runs[j].attempt.comparisons.append({"with_attempt": i + 1, **(agreement or {})})
                if not gate.agree(agreement):
                    log.warning("attempts %d and %d disagree on the poses (%s)", i + 1, j + 1,
                                _describe(agreement))
            if gate.agree(comparisons[(i, j)]):
                candidate.attempt.agreement = comparisons[(i, j)]
                candidate.attempt.note = (
                    f"confirmed by attempt {runs.index(witness) + 1} ({witness.settings.matcher}"
                    f" matching, {witness.settings.mapper} mapping)")
                return candidate
    return None


def _unconfirmed(runs: list[_Run], matcher: str, cross_check: bool) -> _Run:
    candidates = _candidates(runs, matcher)
    if not candidates:
        return max(runs, key=lambda run: run.attempt.sort_key())
    best = min(candidates, key=lambda run: run.attempt.mean_reprojection_px)
    if cross_check:
        best.attempt.passed = False
        best.attempt.note = ("no independent model agreed with it; kept as the candidate with the "
                             "lowest mean reprojection error")
        log.warning("no independent COLMAP model confirmed the poses; keeping attempt %d "
                    "unconfirmed", runs.index(best) + 1)
    return best


def _describe(agreement: dict | None) -> str:
    if agreement is None:
        return "fewer than 3 images in common"
    return (f"camera centres {agreement['max_centre_deviation']:.2%} of the camera extent, "
            f"rotations {agreement['max_rotation_deviation_deg']:.2f} deg apart")


def _fmt(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.3f}"


# -- reading models --------------------------------------------------------------------------

def find_model_dir(path: Path) -> Path:
    """A COLMAP model folder: ``path`` itself, or ``path/sparse/0``, ``path/sparse``, ``path/0``."""
    for candidate in (path, path / "sparse" / "0", path / "sparse", path / "0"):
        if any((candidate / f"cameras.{ext}").exists() for ext in ("bin", "txt")):
            return candidate
    raise PipelineError(f"{path}: no COLMAP model found (looked for cameras.bin or cameras.txt "
                        f"in it and in sparse/0, sparse, 0); pass the model folder")


def read_model(path: Path) -> pycolmap.Reconstruction:
    model_dir = find_model_dir(Path(path))
    try:
        return pycolmap.Reconstruction(model_dir)
    except Exception as exc:
        raise PipelineError(f"{model_dir}: COLMAP model cannot be read ({exc})") from None


@dataclass
class ModelImage:
    """One registered image of a COLMAP model, in source units."""

    name: str                # file name as stored in the model
    camera: pycolmap.Camera  # possibly distorted, at the model's resolution
    c2w: np.ndarray          # (4, 4) OpenCV camera-to-world
    near: float | None
    far: float | None


def model_images(model: pycolmap.Reconstruction) -> list[ModelImage]:
    """Registered images with OpenCV c2w and LLFF-style bounds from the points each one sees."""
    xyz_by_id = {point_id: point.xyz for point_id, point in model.points3D.items()}
    images = []
    for image_id in sorted(model.reg_image_ids()):
        image = model.image(image_id)
        c2w = c2w_from_cam_from_world(image.cam_from_world().matrix())
        seen = [xyz_by_id[p.point3D_id] for p in image.points2D
                if p.has_point3D() and p.point3D_id in xyz_by_id]
        near = far = None
        if seen:
            with contextlib.suppress(ValueError):
                near, far = depth_bounds(point_depths(c2w, np.asarray(seen)))
        images.append(ModelImage(name=image.name, camera=model.camera(image.camera_id),
                                 c2w=c2w, near=near, far=far))
    return images


# -- cameras and undistortion ----------------------------------------------------------------

def make_camera(model: str, width: int, height: int, params) -> pycolmap.Camera:
    return pycolmap.Camera(model=model, width=int(width), height=int(height),
                           params=[float(p) for p in params])


def camera_at_size(camera: pycolmap.Camera, width: int, height: int) -> pycolmap.Camera:
    """A copy of ``camera`` rescaled to ``width`` x ``height`` (same field of view)."""
    if (camera.width, camera.height) == (width, height):
        return copy.copy(camera)
    if abs(width / camera.width - height / camera.height) > 0.01 * width / camera.width:
        raise PipelineError(
            f"image size {width}x{height} does not have the aspect ratio of the camera "
            f"({camera.width}x{camera.height}); the images must be a scaled version of those "
            f"the poses were computed on")
    scaled = copy.copy(camera)
    scaled.rescale(int(width), int(height))
    return scaled


def camera_dict(camera: pycolmap.Camera) -> dict:
    return {"model": camera.model_name, "width": int(camera.width), "height": int(camera.height),
            "params": [float(p) for p in camera.params]}


@dataclass
class Undistortion:
    """A pinhole camera and the remap tables that warp a distorted image onto it.

    ``map_x``, ``map_y`` are ``(H', W')`` float32 source pixel positions in OpenCV's integer-
    centred convention (``cv2.remap``); None when the source camera is already a pinhole.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    map_x: np.ndarray | None
    map_y: np.ndarray | None

    def warp_image(self, image: np.ndarray) -> np.ndarray:
        if self.map_x is None:
            return image
        return cv2.remap(image, self.map_x, self.map_y, interpolation=cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def warp_mask(self, mask: np.ndarray) -> np.ndarray:
        """Warp a boolean mask (nearest); pixels that come from outside the source are False."""
        if self.map_x is None:
            return mask
        warped = cv2.remap(mask.astype(np.uint8), self.map_x, self.map_y,
                           interpolation=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                           borderValue=0)
        return warped > 0


def undistortion(camera: pycolmap.Camera) -> Undistortion:
    """Pinhole camera (COLMAP's undistorter choice: no blank pixels) and its remap tables."""
    if camera.is_undistorted() or camera.model_name in ("SIMPLE_PINHOLE", "PINHOLE"):
        k = camera.calibration_matrix()
        return Undistortion(float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]),
                            int(camera.width), int(camera.height), None, None)
    pinhole = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), camera)
    fx, fy, cx, cy = (float(v) for v in pinhole.params[:4])
    width, height = int(pinhole.width), int(pinhole.height)
    map_x = np.empty((height, width), np.float32)
    map_y = np.empty((height, width), np.float32)
    u = (np.arange(width) + 0.5 - cx) / fx
    rows_per_chunk = max(1, 2_000_000 // width)
    for top in range(0, height, rows_per_chunk):
        rows = np.arange(top, min(height, top + rows_per_chunk))
        v = (rows + 0.5 - cy) / fy
        xx, yy = np.meshgrid(u, v)
        rays = np.stack([xx.ravel(), yy.ravel(), np.ones(xx.size)], axis=1)
        pixels = camera.img_from_cam(rays, check_cheirality=False)
        # COLMAP puts pixel centres at +0.5, cv2.remap at integers.
        map_x[rows] = (pixels[:, 0] - 0.5).reshape(len(rows), width)
        map_y[rows] = (pixels[:, 1] - 0.5).reshape(len(rows), width)
    return Undistortion(fx, fy, cx, cy, width, height, map_x, map_y)
