"""Camera poses and intrinsics: COLMAP (pycolmap) or an existing dataset, to one cameras.json.

Inputs: the ``ingest`` output folder (``matching/``, ``linear/``, ``masks/``, manifest).

``--source colmap`` (default) runs SIFT + matching + mapping on the matching copies (CLAHE
contrast first, for murky water). Quality gate (``seathru.geometry.quality``): registered
fraction, mean reprojection error, confirmation by an independent model agreeing on the poses
(``--cross-check``) and no disagreeing model with a much lower error; retries with another
seed, mapper, matcher. Too few registered images is an error; a model not confirmed fails the
step with what disagreed and what to try (``--on-unconfirmed fail``) or is kept with a warning.
``--source llff|colmap-model|nerfstudio`` reads the poses in ``--source-dir`` instead.

Outputs (``--out``, swapped in only when complete):
  cameras.json       pinhole cameras (seathru-cameras/1), OpenCV c2w, normalised units
  images/<stem>.tiff linear float32 images, undistorted to those pinhole cameras
  masks/<stem>.png   validity masks, warped the same way (255 = valid)
  report.json        what was tried and measured (every COLMAP attempt, unregistered images)
  warnings.json      unconfirmed model, unregistered images, frames left out (seathru.io.warnings)
  sparse/            the COLMAP model: computed, or the source's (seathru.io.source_model)

Normalisation: normalised = (source - centre) * scale puts every camera's [near, far] frustum
inside the unit ball (``seathru.io.pose_outputs``).
"""

from __future__ import annotations

import argparse
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from seathru import settings
from seathru.geometry.intrinsics import CameraModel, FocalPrior
from seathru.geometry.quality import CameraMode, Mapper, Matcher, QualityGate, SfmSettings
from seathru.io.atomic import atomic_dir
from seathru.io.colmap import Interpolation
from seathru.io.dataset_readers import READERS, read_posed_dataset
from seathru.io.manifest import IngestFolder
from seathru.io.pose_outputs import write_pose_outputs
from seathru.io.pose_report import FORMAT, pose_warnings, write_pose_report
from seathru.io.sfm import colmap_poses
from seathru.io.warnings import write_warnings
from seathru.settings import setting

log = logging.getLogger(__name__)


@dataclass
class Settings:
    """Camera poses: COLMAP's run and quality gate, or how existing poses are read."""

    linear_folder: str = setting(
        "linear", help="folder of the ingest output with the linear images to undistort "
                       "(e.g. linear_4 for a downscaled copy)")
    test_every: int = setting(
        8, help="every N-th image in sorted name order is a test image (0: none)")
    near: float | None = setting(
        None, help="override every near bound: depth along the optical axis, source units")
    far: float | None = setting(
        None, help="override every far bound: depth along the optical axis, source units "
                   "(cameras.json stores it as the range of the longest corner ray)")
    camera_model: CameraModel = setting("SIMPLE_RADIAL", help="COLMAP camera model")
    undistort_interpolation: Interpolation = setting(
        "linear", help="resampling onto the undistorted pinhole cameras: cubic keeps the detail "
                       "(and the noise) bilinear smooths; see docs/water.md")
    camera_mode: CameraMode = setting(
        "auto", help="one camera for all images, per image size, or per image; auto: per size")
    matcher: Matcher = setting(
        "sequential", help="sequential for ordered dive sets (transects, orbits), exhaustive "
                           "for small unordered sets")
    overlap: int = setting(10, help="sequential matching: neighbours each image is matched with")
    mapper: Mapper = setting("incremental", help="incremental or global (GLOMAP)")
    max_image_size: int = setting(
        1600, help="SIFT runs on images downscaled to this longest side (-1: full size)")
    max_features: int = setting(8192, help="SIFT features per image")
    seed: int = setting(0, help="random seed of COLMAP's RANSAC/mapper")
    clahe: bool = setting(True, help="local contrast equalisation (CLAHE) of the matching copies")
    clahe_clip: float = setting(2.0, help="CLAHE clip limit")
    clahe_tiles: int = setting(8, help="CLAHE tiles per side")
    focal_px: float | None = setting(None, help="known focal length in pixels of the matching "
                                     "images (unset: the photographs' EXIF 35 mm equivalent)")
    focal_mm: float | None = setting(None, help="known focal length in mm (with sensor_width_mm)")
    sensor_width_mm: float | None = setting(None, help="sensor width in mm")
    refine_focal: bool = setting(
        True, help="refine a known focal length in bundle adjustment (false keeps it fixed)")
    min_registered: float = setting(
        0.8, help="quality gate: least fraction of images registered (else error)")
    max_reproj_px: float = setting(
        1.0, help="quality gate: largest mean reprojection error in pixels")
    retry: bool = setting(
        True, help="on a failed gate, retry with another seed, the global mapper and exhaustive "
                   "matching, keeping the best model")
    cross_check: bool = setting(
        True, help="map the same matches with the other mapper too; if the poses disagree, "
                   "keep the global mapper's model")
    max_disagreement: float = setting(
        0.01, help="cross-check: largest camera-centre deviation between the two models, as a "
                   "fraction of the camera extent")
    max_rotation_disagreement_deg: float = setting(
        1.0, help="cross-check: largest camera rotation deviation, degrees")
    rival_error_ratio: float = setting(
        1.5, help="cross-check: set a model aside where one that disagrees with it has this "
                  "times lower mean reprojection error, e.g. a mirrored scene (0: never)")
    metres_per_unit: float | None = setting(None, help="metres per unit of the reconstruction, "
                                            "if known (unset: not known); water.json per metre")
    on_unconfirmed: Literal["fail", "warn"] = setting(
        "fail", help="a camera model the quality gate did not confirm: fail the dataset (saying "
                     "what disagreed and what to try) or warn (train on it, the report shows it)")

    def validate(self) -> None:
        if not 0.0 < self.min_registered <= 1.0:
            raise ValueError(f"--min-registered must be in (0, 1], got {self.min_registered}")
        if self.metres_per_unit is not None and not self.metres_per_unit > 0:
            raise ValueError(f"--metres-per-unit must be positive, got {self.metres_per_unit}")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # Set by the workflow (workflow/rules/poses.smk), not configuration.
    parser.add_argument("--ingest", required=True, type=Path,
                        help="the ingest step's output folder (matching/, linear/, masks/)")
    parser.add_argument("--out", required=True, type=Path,
                        help="output folder (replaced atomically)")
    parser.add_argument("--source", choices=("colmap",) + READERS, default="colmap",
                        help="run COLMAP (default) or read existing poses from --source-dir")
    parser.add_argument("--source-dir", type=Path,
                        help="llff: folder with poses_bounds.npy; colmap-model: a model folder "
                             "(or one holding sparse/0); nerfstudio: transforms.json or its "
                             "folder")
    parser.add_argument("--threads", type=int, default=-1, help="CPU threads (-1: all)")
    settings.add_arguments(parser, Settings)


def run(args: argparse.Namespace) -> None:
    start = time.perf_counter()
    cfg: Settings = settings.from_namespace(Settings, args)
    ingest = IngestFolder(args.ingest, cfg.linear_folder)
    with atomic_dir(args.out) as out:
        if args.source == "colmap":
            sfm = SfmSettings(
                camera_model=cfg.camera_model, camera_mode=cfg.camera_mode,
                matcher=cfg.matcher, overlap=cfg.overlap, mapper=cfg.mapper,
                max_image_size=cfg.max_image_size, max_features=cfg.max_features,
                threads=args.threads, seed=cfg.seed, refine_focal=cfg.refine_focal)
            gate = QualityGate(cfg.min_registered, cfg.max_reproj_px, 1.0, cfg.max_disagreement,
                               cfg.max_rotation_disagreement_deg, cfg.rival_error_ratio)
            focal = FocalPrior(cfg.focal_px, cfg.focal_mm, cfg.sensor_width_mm, ingest.manifest)
            dataset, details = colmap_poses(ingest, out, sfm, gate, focal, cfg.clahe,
                                            cfg.clahe_clip, cfg.clahe_tiles, cfg.retry,
                                            cfg.cross_check, cfg.on_unconfirmed)
        else:
            layout = ingest.layout or {}
            folder = Path(layout["root"], layout["images"]) if layout.get("layout") == "llff" \
                else None
            dataset = read_posed_dataset(args.source, args.source_dir, sorted(ingest.linear),
                                         image_folder=folder)
            details = {"reader_notes": dataset.notes}
        summary = write_pose_outputs(dataset, ingest, out, cfg.near, cfg.far, cfg.test_every,
                                     str(args.source_dir or ingest.root),
                                     cfg.undistort_interpolation, cfg.metres_per_unit)
        arguments = {k: str(v) if isinstance(v, Path) else v for k, v in
                     {**vars(args), **settings.to_dict(cfg)}.items() if not k.startswith("_")}
        report = {"format": FORMAT, "source": dataset.source, "ingest": str(args.ingest),
                  "arguments": arguments, **details, **summary,
                  "seconds": round(time.perf_counter() - start, 2)}
        write_pose_report(out / "report.json", report)
        write_warnings(out / "warnings.json", pose_warnings(report, ingest.layout), log)
    log.info("poses: %d frames written to %s in %.1f s", report["frames"], args.out,
             report["seconds"])
