"""Structure from motion with pycolmap 4.2.1: the COLMAP runs behind ``seathru poses``.

The COLMAP run is split in the usual stages (feature extraction, matching, mapping), each on a
database in a work folder the caller owns. :func:`reconstruct` runs the attempts the quality
policy asks for (``seathru.geometry.quality``: gate, retries, cross-check) and keeps the model it
chooses; every attempt is recorded. :func:`colmap_poses` is the whole ``--source colmap`` path:
8-bit grey (CLAHE) copies of the ingest matching images, an initial focal length, the
reconstruction, the model written to ``sparse/`` and the report fields.
"""

from __future__ import annotations

import contextlib
import logging
import shutil
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np
import pycolmap

from seathru.errors import PipelineError
from seathru.geometry.intrinsics import FocalPrior, initial_camera_params
from seathru.geometry.quality import (MAPPERS, MATCHERS, STILL_SHIFT, PairMotion, QualityGate,
                                      SfmAttempt,
                                      SfmRun, SfmSettings, confirmed_run, failure_message,
                                      plan_attempts, pose_agreement, reprojection_scale,
                                      unconfirmed_message, unconfirmed_run)
from seathru.io.colmap import model_images, registered_c2w
from seathru.io.dataset_readers import PosedDataset, PosedView
from seathru.io.manifest import IngestFolder
from seathru.io.pose_report import ColmapDetails
from seathru.radiometry.linearise import matching_grey

log = logging.getLogger(__name__)


def global_mapping_available() -> bool:
    return hasattr(pycolmap, "global_mapping") and hasattr(pycolmap, "GlobalPipelineOptions")


@contextlib.contextmanager
def colmap_log_level(verbose: bool) -> Iterator[None]:
    """COLMAP logs every stage at INFO; keep warnings only unless the user asked for debug."""
    previous = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 0 if verbose else 1
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = previous


def extract_features(database: Path, image_dir: Path, names: list[str], settings: SfmSettings,
                     image_size: tuple[int, int], mask_dir: Path | None = None,
                     sizes: dict[str, tuple[int, int]] | None = None) -> None:
    """SIFT on the CPU for ``names`` (file names under ``image_dir``) into a new database.

    ``image_size`` (width, height) is that of every image; used for a known focal length.
    ``mask_dir`` holds ``<file name>.png`` masks (black = no features), COLMAP's layout.
    ``settings.camera_mode`` ``per-size`` gives the images of each size in ``sizes`` (by file
    name) one camera: COLMAP's own modes share one camera or none (its ``AUTO`` needs EXIF,
    which the matching PNGs do not have), so each size is extracted on its own with one.
    """
    if settings.camera_mode == "per-size":
        groups: dict[tuple[int, int], list[str]] = {}
        for name in names:
            groups.setdefault(tuple((sizes or {})[name]), []).append(name)
        for size, group in sorted(groups.items()):
            extract_features(database, image_dir, group, replace(settings, camera_mode="single"),
                             size, mask_dir)
        return
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
    mode = pycolmap.CameraMode.SINGLE if settings.camera_mode == "single" \
        else pycolmap.CameraMode.PER_IMAGE
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


def compare_models(model: pycolmap.Reconstruction | None,
                   other: pycolmap.Reconstruction | None) -> dict | None:
    """:func:`seathru.geometry.quality.pose_agreement` of two models' registered images."""
    if model is None or other is None:
        return None
    return pose_agreement(registered_c2w(model), registered_c2w(other))


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
    features: dict[str, int] = field(default_factory=dict)  # SIFT keypoints per image name
    matched: dict[str, int] = field(default_factory=dict)  # inliers of each image's best pair
    motion: PairMotion | None = None  # pair_motion of the matches

    @property
    def passed(self) -> bool:
        return self.chosen is not None and self.chosen.passed


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
                retry: bool = True, cross_check: bool = True, verbose: bool = False,
                sizes: dict[str, tuple[int, int]] | None = None) -> SfmResult:
    """Extract, match and map ``names`` with the quality gate, retries and cross-check.

    Features are extracted once (``sizes``: each file's (width, height), for
    ``camera_mode`` ``per-size``); each matcher's database is built once and copied for every
    mapping attempt so the attempts do not see each other's writes.

    Without ``cross_check`` the first model that passes the gate is kept (after retrying with
    another seed, then the alternatives of ``seathru.geometry.quality.plan_attempts``). With
    it, a model must also be confirmed by an independent model (other mapper or other matcher)
    agreeing with its poses: a self-consistent model (every image, low reprojection error) can
    still be wrong when repeated texture produces consistent false matches, and both mappers
    fail that way at times. Models built on the user's matcher are the candidates (for ordered
    dive sets the sequential matches hold fewer false pairs); the other matcher's models serve
    as witnesses, and become candidates when no model on the user's matcher is confirmed
    (``seathru.geometry.quality.confirmed_run``); where the first attempt registers nothing
    and the matched features hardly move between photographs (:func:`largest_pair_shift`
    below ``STILL_SHIFT``: taken from one place), nothing else is tried. Among confirmed
    candidates the one tried first wins, unless a gate-passing model that disagrees with it
    has a ``gate.rival_error_ratio`` times lower mean reprojection error; when no candidate
    is confirmed, the one with the lowest mean reprojection error is kept, marked
    unconfirmed. The result also holds each image's SIFT feature count, its best pair's
    verified matches and the largest shift, for the failure message.
    """
    work_dir.mkdir(parents=True, exist_ok=True)
    runner = _Runner(image_dir, names, work_dir, gate)
    plan = plan_attempts(settings, retry, cross_check, global_mapping_available())
    runs: list[SfmRun] = []
    comparisons: dict[tuple[int, int], dict | None] = {}
    motions: dict[Path, PairMotion | None] = {}   # pair_motion by matched database
    chosen: SfmRun | None = None
    with colmap_log_level(verbose):
        start = time.perf_counter()
        extract_features(runner.features_db, image_dir, names, settings, image_size, mask_dir,
                         sizes)
        features = feature_counts(runner.features_db)
        log.info("SIFT features for %d images in %.1f s (median %d an image)", len(names),
                 time.perf_counter() - start, int(np.median(list(features.values()) or [0])))
        queue = list(plan)
        while queue and chosen is None:
            current = queue.pop(0)
            role = ("first" if not runs else
                    "cross-check" if cross_check and runs[0].attempt.passed else "retry")
            attempt, model = runner.run(current, role)
            runs.append(SfmRun(current, attempt, model))
            if len(runs) == 1 and attempt.registered == 0 and runner.matched:
                first_db = next(iter(runner.matched.values()))
                motions[first_db] = motion = pair_motion(first_db)
                if motion is not None and motion.largest_shift < STILL_SHIFT:
                    log.warning("matched features move at most %.2f%% of the image diagonal "
                                "between photographs: taken from one place, no retry",
                                100 * motion.largest_shift)
                    break
            if len(runs) == 1 and not attempt.passed and retry:
                queue.insert(0, replace(current, seed=current.seed + 1))
            if not cross_check:
                chosen = runs[-1] if attempt.passed else None
            else:
                chosen = confirmed_run(runs, comparisons, gate, settings.matcher,
                                       compare_models)
        if chosen is None and runs:
            chosen = unconfirmed_run(runs, settings.matcher, cross_check)
    # the exhaustive matcher's pairs, where it ran, are every pair
    databases = sorted(runner.matched.items(), key=lambda item: item[0][0] != "exhaustive")
    support = best_pair_inliers(databases[0][1], features) if databases else {}
    if databases and databases[0][1] not in motions:
        motions[databases[0][1]] = pair_motion(databases[0][1])
    motion = motions[databases[0][1]] if databases else None
    if chosen is None or chosen.attempt.registered == 0:
        return SfmResult(None, None, runner.attempts, features, support, motion)
    return SfmResult(chosen.model, chosen.attempt, runner.attempts, features, support, motion)


def feature_counts(database: Path) -> dict[str, int]:
    """SIFT keypoints of each image (by file name) in a COLMAP database."""
    db = pycolmap.Database.open(database)
    try:
        return {image.name: int(db.num_keypoints_for_image(image.image_id))
                for image in db.read_all_images()}
    finally:
        db.close()


def best_pair_inliers(database: Path, features: dict[str, int]) -> dict[str, int]:
    """Verified (inlier) matches of each image's best pair in a matched COLMAP database, by
    file name (``features``' names: an image in no pair has 0)."""
    db = pycolmap.Database.open(database)
    try:
        names = {image.image_id: image.name for image in db.read_all_images()}
        best = dict.fromkeys(features, 0)
        for pair_id, inliers in zip(*db.read_two_view_geometry_num_inliers()):
            for image_id in pycolmap.pair_id_to_image_pair(pair_id):
                name = names[image_id]
                best[name] = max(best.get(name, 0), int(inliers))
        return best
    finally:
        db.close()


#: Two-view relations COLMAP explains by a homography alone: the camera turned about one
#: point, or the scene is a plane (without a focal length COLMAP cannot tell which).
HOMOGRAPHY_CONFIGURATIONS = frozenset({
    pycolmap.TwoViewGeometryConfiguration.PLANAR, pycolmap.TwoViewGeometryConfiguration.PANORAMIC,
    pycolmap.TwoViewGeometryConfiguration.PLANAR_OR_PANORAMIC})


def pair_motion(database: Path) -> PairMotion | None:
    """How the photographs of a matched COLMAP database move against each other, over its
    verified pairs (``seathru.geometry.quality.PairMotion``; a homography alone relates a pair
    of :data:`HOMOGRAPHY_CONFIGURATIONS`); None where no pair was verified."""
    db = pycolmap.Database.open(database)
    try:
        cameras = {camera.camera_id: camera for camera in db.read_all_cameras()}
        camera_of = {image.image_id: image.camera_id for image in db.read_all_images()}
        keypoints: dict[int, np.ndarray] = {}
        largest, pairs, homographies = None, 0, 0
        for pair_id, geometry in zip(*db.read_two_view_geometries()):
            matches = geometry.inlier_matches
            if len(matches) == 0:
                continue
            pairs += 1
            homographies += geometry.config in HOMOGRAPHY_CONFIGURATIONS
            first, second = pycolmap.pair_id_to_image_pair(pair_id)
            for image_id in (first, second):
                if image_id not in keypoints:
                    keypoints[image_id] = db.read_keypoints(image_id)[:, :2]
            moved = np.linalg.norm(keypoints[first][matches[:, 0]]
                                   - keypoints[second][matches[:, 1]], axis=1)
            camera = cameras[camera_of[first]]
            shift = float(np.median(moved) / np.hypot(camera.width, camera.height))
            largest = shift if largest is None else max(largest, shift)
        return None if largest is None else PairMotion(largest, homographies / pairs, pairs)
    finally:
        db.close()


def _fmt(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.3f}"


# -- the --source colmap path ----------------------------------------------------------------

def prepare_matching_images(ingest: IngestFolder, names: list[str], image_dir: Path,
                            mask_dir: Path, clahe_clip: float | None, clahe_tiles: int = 8
                            ) -> tuple[dict[str, tuple[int, int]], bool]:
    """Write grey 8-bit copies (CLAHE'd unless ``clahe_clip`` is None) and COLMAP-named masks.

    Returns each copy's (width, height) by file name and whether any mask was written.
    """
    image_dir.mkdir(parents=True)
    sizes, any_mask = {}, False
    for name in names:
        source = ingest.matching[name]
        image = cv2.imread(str(source), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise PipelineError(f"{source}: cannot be read as an image")
        image = matching_grey(image, clahe_clip, clahe_tiles)
        sizes[f"{name}.png"] = (image.shape[1], image.shape[0])
        cv2.imwrite(str(image_dir / f"{name}.png"), image)
        if name in ingest.matching_masks:
            mask = cv2.imread(str(ingest.matching_masks[name]), cv2.IMREAD_GRAYSCALE)
            if mask.shape != image.shape:
                mask = cv2.resize(mask, (image.shape[1], image.shape[0]),
                                  interpolation=cv2.INTER_NEAREST)
            mask_dir.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(mask_dir / f"{name}.png.png"), mask)
            any_mask = True
    return sizes, any_mask


def colmap_poses(ingest: IngestFolder, out: Path, settings: SfmSettings, gate: QualityGate,
                 focal: FocalPrior, clahe: bool = True, clahe_clip: float = 2.0,
                 clahe_tiles: int = 8, retry: bool = True, cross_check: bool = True,
                 on_unconfirmed: str = "fail") -> tuple[PosedDataset, ColmapDetails]:
    """Poses of the ingest matching images by COLMAP; the model kept is written to
    ``out/sparse`` (a work folder ``out/_colmap_work`` is removed again).

    ``settings.focal_px`` and ``gate.reprojection_scale`` are set here from the images' size.
    A model kept without passing the whole gate (not confirmed) fails with ``on_unconfirmed``
    ``fail``; with ``warn`` it is returned, ``gate_message`` saying why it is doubtful.

    Raises:
        PipelineError: too few images, no model registers ``gate.min_registered_fraction`` of
            them (the message lists every attempt and what to try), or the model kept is not
            confirmed and ``on_unconfirmed`` is ``fail`` (the message names the disagreement).
    """
    if not ingest.matching:
        raise PipelineError(f"{ingest.root / 'matching'}: no 8-bit matching images; run the "
                            f"'ingest' step")
    names = sorted(set(ingest.matching) & set(ingest.linear))
    ignored = sorted(set(ingest.matching) ^ set(ingest.linear))
    if ignored:
        log.warning("%d images are not in both matching/ and %s/ and are left out: %s",
                    len(ignored), ingest.linear_dir.name, ", ".join(ignored))
    if len(names) < 2:
        raise PipelineError(f"{ingest.root}: need at least 2 images in both matching/ and "
                            f"{ingest.linear_dir.name}/, found {len(names)}")
    work = out / "_colmap_work"
    image_dir, mask_dir = work / "images", work / "masks"
    sizes, any_mask = prepare_matching_images(ingest, names, image_dir, mask_dir,
                                              clahe_clip if clahe else None, clahe_tiles)
    distinct = sorted(set(sizes.values()))
    size = distinct[0] if len(distinct) == 1 else None
    if settings.camera_mode == "single" and size is None:
        raise PipelineError(f"{ingest.root / 'matching'}: images have different sizes, so they "
                            f"cannot share one camera; set poses.camera_mode to auto, per-size "
                            f"or per-image (--camera-mode)")
    if settings.camera_mode == "auto":
        settings = replace(settings, camera_mode="single" if size is not None else "per-size")
        if size is None:
            log.info("the images have %d sizes (%s): one camera per size", len(distinct),
                     ", ".join(f"{w}x{h}" for w, h in distinct))
    focal_px, focal_source = (None, "not used (images of different sizes)")
    if size is not None:
        try:
            focal_px, focal_source = focal.at_size(*size)
        except ValueError as exc:
            raise PipelineError(str(exc)) from None
    if focal_px is not None:
        log.info("initial focal length %.1f px (%s)", focal_px, focal_source)
    settings = replace(settings, focal_px=focal_px)
    gate = replace(gate, reprojection_scale=reprojection_scale(size, settings.max_image_size))
    result = reconstruct(image_dir, [f"{name}.png" for name in names], work, settings, gate,
                         size or (0, 0), mask_dir if any_mask else None, retry=retry,
                         cross_check=cross_check, verbose=log.isEnabledFor(logging.DEBUG),
                         sizes=sizes)
    chosen = result.chosen
    if chosen is None or chosen.registered_fraction < gate.min_registered_fraction:
        by_view = [{Path(file).stem: count for file, count in counts.items()}
                   for counts in (result.matched, result.features)]
        raise PipelineError(failure_message(result.attempts, chosen, len(names), gate, *by_view,
                                            clahe=clahe, focal_known=focal_px is not None,
                                            motion=result.motion))
    gate_message = None
    if not chosen.passed:
        gate_message = unconfirmed_message(result.attempts, chosen, gate, clahe,
                                           kept=on_unconfirmed == "warn",
                                           focal_known=focal_px is not None,
                                           motion=result.motion)
        if on_unconfirmed == "fail":
            raise PipelineError(gate_message)
        log.info("keeping the unconfirmed model (poses.on_unconfirmed=warn)")
    unregistered = [Path(name).stem for name in chosen.unregistered]
    if unregistered:
        log.warning("%d of %d images not registered (left out): %s", len(unregistered),
                    len(names), ", ".join(unregistered))
    (out / "sparse").mkdir()
    result.model.write(out / "sparse")
    views = [PosedView(name=Path(image.name).stem, camera=image.camera, c2w=image.c2w,
                       near=image.near, far=image.far) for image in model_images(result.model)]
    shutil.rmtree(work)
    details: ColmapDetails = {
        "clahe": {"enabled": clahe, "clip": clahe_clip, "tiles": clahe_tiles},
        "initial_focal_px": focal_px, "initial_focal_source": focal_source,
        "extraction_masks": any_mask,
        "global_mapping_available": global_mapping_available(),
        "gate": asdict(gate), "gate_passed": chosen.passed, "gate_message": gate_message,
        "on_unconfirmed": on_unconfirmed,
        "attempts": [a.to_dict() for a in result.attempts],
        "chosen_attempt": result.attempts.index(chosen) + 1,  # attempts count from 1
        "registered": chosen.registered, "total": len(names),
        "mean_reprojection_px": chosen.mean_reprojection_px,
        "unregistered": unregistered,
        "left_out_not_in_both_folders": ignored,
    }
    return PosedDataset(views=views, source="colmap"), details
