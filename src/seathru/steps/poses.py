"""Camera poses and intrinsics: COLMAP (pycolmap) or an existing dataset, to one cameras.json.

Inputs: the ``ingest`` output folder (``matching/`` 8-bit copies for feature matching,
``linear/`` float linear images, optional ``masks/`` and ``manifest.json``).

``--source colmap`` (default) runs SIFT + matching + mapping on the matching copies (CLAHE
contrast first, for murky water) and keeps the largest model. Quality gate: registered fraction,
mean reprojection error and (``--cross-check``) confirmation by an independent model, i.e. the
other mapper (incremental / global) or the other matcher (sequential / exhaustive) agreeing on
the poses after a similarity alignment: repeated texture can give a wrong model with every
image registered and a low reprojection error. Failing models are followed by retries (another
seed, the other mapper, the other matcher). Fewer registered images than ``--min-registered``
is an error; a model that registers enough but fails the rest of the gate is kept with a warning
and ``gate_passed: false`` in the report. ``--source llff|colmap-model|nerfstudio`` reads poses
that already exist in ``--source-dir`` instead.

Outputs (``--out``, swapped in only when complete):
  cameras.json       pinhole cameras (seathru-cameras/1), OpenCV c2w, normalised units
  images/<stem>.tiff linear float32 images, undistorted to those pinhole cameras
  masks/<stem>.png   validity masks, warped the same way (255 = valid)
  report.json        what was tried and measured (every COLMAP attempt, unregistered images)
  sparse/            the COLMAP model used (colmap source only)

Normalisation: normalised = (source - centre) * scale where centre is the middle of the
bounding box of all camera centres and all frustum corners at each image's far bound, and scale
puts the furthest of those points on the unit sphere; every ray segment [near, far] of every
camera then lies inside the unit ball.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import shutil
import time
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np

from seathru.geometry.poses import normalise_c2w, range_bounds, unit_ball_normalisation
from seathru.errors import PipelineError
from seathru.io.atomic import atomic_dir, write_json
from seathru.io.cameras import CameraSet, Frame, every_nth_split, write_cameras
from seathru.io.colmap import (CAMERA_MODELS, MAPPERS, MATCHERS, QualityGate, SfmSettings,
                               camera_at_size, camera_dict, global_mapping_available,
                               model_images, reconstruct, undistortion)
from seathru.io.dataset_readers import (PosedDataset, PosedView, list_images, read_colmap_model,
                                        read_llff, read_nerfstudio)
from seathru.io.images import read_image, read_mask, write_float_tiff, write_mask

log = logging.getLogger(__name__)

SOURCES = ("colmap", "llff", "colmap-model", "nerfstudio")
NORMALISATION_METHOD = ("centre = middle of the axis-aligned bounding box of all camera centres "
                        "and all image-corner points at each frame's far bound; scale = 1 / "
                        "distance from the centre to the furthest of those points, so every "
                        "camera's [near, far] frustum lies inside the unit ball")
# 35 mm equivalent focal lengths are defined on the 36 x 24 mm frame diagonal.
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    io = parser.add_argument_group("inputs and outputs")
    io.add_argument("--ingest", required=True, type=Path,
                    help="the ingest step's output folder (matching/, linear/, masks/)")
    io.add_argument("--out", required=True, type=Path, help="output folder (replaced atomically)")
    io.add_argument("--source", choices=SOURCES, default="colmap",
                    help="run COLMAP (default) or read existing poses from --source-dir")
    io.add_argument("--source-dir", type=Path,
                    help="llff: folder with poses_bounds.npy; colmap-model: a model folder (or "
                         "one holding sparse/0); nerfstudio: transforms.json or its folder")
    io.add_argument("--linear-folder", default="linear",
                    help="folder of the ingest output with the linear images to undistort "
                         "(default: linear; e.g. linear_4 for a downscaled copy)")
    io.add_argument("--test-every", type=int, default=8,
                    help="every N-th image in sorted name order is a test image (0: none)")
    io.add_argument("--near", type=float,
                    help="override every near bound: depth along the optical axis, source units")
    io.add_argument("--far", type=float,
                    help="override every far bound: depth along the optical axis, source units "
                         "(cameras.json stores it as the range of the longest corner ray)")

    sfm = parser.add_argument_group("COLMAP (--source colmap)")
    sfm.add_argument("--camera-model", choices=CAMERA_MODELS, default="SIMPLE_RADIAL")
    sfm.add_argument("--camera-mode", choices=("single", "per-image"), default="single",
                     help="one camera shared by all images (default) or one per image")
    sfm.add_argument("--matcher", choices=MATCHERS, default="sequential",
                     help="sequential for ordered dive sets (transects, orbits; default), "
                          "exhaustive for small unordered sets")
    sfm.add_argument("--overlap", type=int, default=10,
                     help="sequential matching: neighbours each image is matched with")
    sfm.add_argument("--mapper", choices=MAPPERS, default="incremental",
                     help="incremental (default) or global (GLOMAP)")
    sfm.add_argument("--max-image-size", type=int, default=1600,
                     help="SIFT runs on images downscaled to this longest side (-1: full size)")
    sfm.add_argument("--max-features", type=int, default=8192, help="SIFT features per image")
    sfm.add_argument("--threads", type=int, default=-1, help="CPU threads (-1: all)")
    sfm.add_argument("--seed", type=int, default=0, help="random seed of COLMAP's RANSAC/mapper")
    sfm.add_argument("--clahe", action=argparse.BooleanOptionalAction, default=True,
                     help="local contrast equalisation (CLAHE) of the matching copies")
    sfm.add_argument("--clahe-clip", type=float, default=2.0, help="CLAHE clip limit")
    sfm.add_argument("--clahe-tiles", type=int, default=8, help="CLAHE tiles per side")
    sfm.add_argument("--focal-px", type=float,
                     help="known focal length in pixels of the matching images")
    sfm.add_argument("--focal-mm", type=float, help="known focal length in mm (with "
                     "--sensor-width-mm)")
    sfm.add_argument("--sensor-width-mm", type=float, help="sensor width in mm")
    sfm.add_argument("--refine-focal", action=argparse.BooleanOptionalAction, default=True,
                     help="refine a known focal length in bundle adjustment (--no-refine-focal "
                          "keeps it fixed)")
    sfm.add_argument("--min-registered", type=float, default=0.8,
                     help="quality gate: least fraction of images registered (else error)")
    sfm.add_argument("--max-reproj-px", type=float, default=1.0,
                     help="quality gate: largest mean reprojection error in pixels")
    sfm.add_argument("--retry", action=argparse.BooleanOptionalAction, default=True,
                     help="on a failed gate, retry with another seed, the global mapper and "
                          "exhaustive matching, keeping the best model")
    sfm.add_argument("--cross-check", action=argparse.BooleanOptionalAction, default=True,
                     help="map the same matches with the other mapper too; if the poses "
                          "disagree, keep the global mapper's model")
    sfm.add_argument("--max-disagreement", type=float, default=0.01,
                     help="cross-check: largest camera-centre deviation between the two "
                          "models, as a fraction of the camera extent (default 0.01)")
    sfm.add_argument("--max-rotation-disagreement-deg", type=float, default=1.0,
                     help="cross-check: largest camera rotation deviation, degrees")


# -- the ingest folder -----------------------------------------------------------------------

def _by_stem(folder: Path) -> dict[str, Path]:
    files: dict[str, Path] = {}
    for path in list_images(folder):
        if path.stem in files:
            raise PipelineError(f"{folder}: two images share the name {path.stem!r} "
                                f"({files[path.stem].name}, {path.name})")
        files[path.stem] = path
    return files


class IngestFolder:
    def __init__(self, root: Path, linear_folder: str = "linear"):
        self.root = Path(root)
        if not self.root.is_dir():
            raise PipelineError(f"{self.root}: ingest folder not found; run the 'ingest' step")
        self.linear_dir = self.root / linear_folder
        self.linear = _by_stem(self.linear_dir)
        if not self.linear:
            raise PipelineError(f"{self.linear_dir}: no linear images; run the 'ingest' step or "
                                f"pick another --linear-folder")
        self.matching = _by_stem(self.root / "matching")
        # linear_<N>/ comes with masks_<N>/ at the same size
        suffix = linear_folder[len("linear"):] if linear_folder.startswith("linear") else ""
        masks_dir = self.root / f"masks{suffix}"
        self.masks_dir = masks_dir if masks_dir.is_dir() else self.root / "masks"
        self.masks = _by_stem(self.masks_dir)
        self.matching_masks = _by_stem(self.root / "masks")  # full size, like matching/
        self.manifest = None
        manifest = self.root / "manifest.json"
        if manifest.exists():
            try:
                self.manifest = json.loads(manifest.read_text())
            except json.JSONDecodeError as exc:
                raise PipelineError(f"{manifest}: not valid JSON ({exc})") from None


# -- known focal length ----------------------------------------------------------------------

_FOCAL_KEYS = {
    "px": ("focal_length_px", "focal_px"),
    "mm": ("focal_length_mm", "focal_mm", "focallength", "exif focallength"),
    "35mm": ("focal_length_35mm", "focal_35mm", "focallengthin35mmfilm",
             "exif focallengthin35mmfilm"),
    "sensor": ("sensor_width_mm",),
}


def _number(value) -> float | None:
    """EXIF numbers arrive as numbers, '24', '24/1' or [24]."""
    if isinstance(value, (list, tuple)) and len(value) == 1:
        value = value[0]
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, str):
        try:
            if "/" in value:
                num, den = value.split("/", 1)
                return float(num) / float(den)
            return float(value)
        except (ValueError, ZeroDivisionError):
            return None
    return None


def _collect(data, found: dict[str, list[float]]) -> None:
    if isinstance(data, dict):
        for key, value in data.items():
            lowered = str(key).lower()
            for kind, keys in _FOCAL_KEYS.items():
                if lowered in keys:
                    number = _number(value)
                    if number is not None and number > 0:
                        found[kind].append(number)
            _collect(value, found)
    elif isinstance(data, list):
        for item in data:
            _collect(item, found)


def focal_from_manifest(manifest, width: int, height: int) -> tuple[float | None, str]:
    """Focal length in pixels at ``width`` x ``height`` from EXIF data in the ingest manifest.

    Looks anywhere in the manifest for focal_length_px, focal_length_mm (+ sensor_width_mm) or
    focal_length_35mm (EXIF FocalLengthIn35mmFilm) keys. All images must agree within 1 %.
    """
    if not manifest:
        return None, "no manifest"
    found: dict[str, list[float]] = {kind: [] for kind in _FOCAL_KEYS}
    _collect(manifest, found)

    def agreed(values: list[float]) -> float | None:
        if not values:
            return None
        middle = float(np.median(values))
        return middle if max(abs(v - middle) for v in values) <= 0.01 * middle else None

    focal_px, focal_mm, focal_35 = agreed(found["px"]), agreed(found["mm"]), agreed(found["35mm"])
    sensor = agreed(found["sensor"])
    if focal_px is not None:
        return focal_px, "manifest focal_length_px"
    if focal_mm is not None and sensor is not None:
        return focal_mm / sensor * width, "manifest focal_length_mm / sensor_width_mm"
    if focal_35 is not None:
        return (focal_35 / FULL_FRAME_DIAGONAL_MM * math.hypot(width, height),
                "manifest 35 mm equivalent focal length")
    if any(found.values()):
        return None, "manifest focal lengths missing a sensor width or not the same for all"
    return None, "no focal length in the manifest"


def known_focal(args, ingest: IngestFolder, width: int, height: int) -> tuple[float | None, str]:
    if args.focal_px is not None:
        return args.focal_px, "--focal-px"
    if args.focal_mm is not None:
        if args.sensor_width_mm is None:
            raise PipelineError("--focal-mm needs --sensor-width-mm (or give --focal-px)")
        return args.focal_mm / args.sensor_width_mm * width, "--focal-mm / --sensor-width-mm"
    return focal_from_manifest(ingest.manifest, width, height)


# -- COLMAP ----------------------------------------------------------------------------------

def prepare_matching_images(ingest: IngestFolder, names: list[str], image_dir: Path,
                            mask_dir: Path, clahe: bool, clip: float, tiles: int
                            ) -> tuple[tuple[int, int] | None, bool]:
    """Write grey 8-bit copies (CLAHE'd when asked) and COLMAP-named masks.

    Returns the common image size (None if sizes differ) and whether any mask was written.
    COLMAP turns colour into grey before SIFT anyway, so the equalisation runs on grey.
    """
    image_dir.mkdir(parents=True)
    equaliser = cv2.createCLAHE(clipLimit=clip, tileGridSize=(tiles, tiles)) if clahe else None
    sizes, any_mask = set(), False
    for name in names:
        source = ingest.matching[name]
        image = cv2.imread(str(source), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise PipelineError(f"{source}: cannot be read as an image")
        if image.dtype == np.uint16:
            image = (image // 257).astype(np.uint8)
        elif image.dtype != np.uint8:
            image = np.round(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8)
        if image.ndim == 3:
            image = cv2.cvtColor(image[..., :3], cv2.COLOR_BGR2GRAY)
        if equaliser is not None:
            image = equaliser.apply(image)
        sizes.add((image.shape[1], image.shape[0]))
        cv2.imwrite(str(image_dir / f"{name}.png"), image)
        if name in ingest.matching_masks:
            mask = cv2.imread(str(ingest.matching_masks[name]), cv2.IMREAD_GRAYSCALE)
            if mask.shape != image.shape:
                mask = cv2.resize(mask, (image.shape[1], image.shape[0]),
                                  interpolation=cv2.INTER_NEAREST)
            mask_dir.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(mask_dir / f"{name}.png.png"), mask)
            any_mask = True
    return (sizes.pop() if len(sizes) == 1 else None), any_mask


def failure_message(result, total: int, gate: QualityGate) -> str:
    chosen = result.chosen
    registered = chosen.registered if chosen else 0
    tried = "; ".join(
        f"{a.settings['matcher']} matching + {a.settings['mapper']} mapping, seed "
        f"{a.settings['seed']}: {a.registered}/{a.total}" + (f" ({a.error})" if a.error else "")
        for a in result.attempts)
    unregistered = chosen.unregistered if chosen else []
    listed = ", ".join(unregistered[:20]) + (" ..." if len(unregistered) > 20 else "")
    return (f"COLMAP registered only {registered} of {total} images in its largest model "
            f"(need {gate.min_registered_fraction:.0%}). Tried: {tried}. Try --matcher "
            f"exhaustive for an unordered set or a larger --overlap for an ordered transect, "
            f"more features (--max-features 16384), a larger --max-image-size, a known focal "
            f"length (--focal-px or --focal-mm with --sensor-width-mm), or remove images that "
            f"do not overlap the others"
            + (f". Unregistered: {listed}" if unregistered else ""))


def run_colmap(args, ingest: IngestFolder, out: Path) -> tuple[PosedDataset, dict]:
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
    size, any_mask = prepare_matching_images(ingest, names, image_dir, mask_dir, args.clahe,
                                             args.clahe_clip, args.clahe_tiles)
    single = args.camera_mode == "single"
    if single and size is None:
        raise PipelineError(f"{ingest.root / 'matching'}: images have different sizes, so they "
                            f"cannot share one camera; use --camera-mode per-image")
    focal_px, focal_source = (None, "not used (images of different sizes)")
    if size is not None:
        focal_px, focal_source = known_focal(args, ingest, *size)
    if focal_px is not None:
        log.info("initial focal length %.1f px (%s)", focal_px, focal_source)
    settings = SfmSettings(camera_model=args.camera_model, single_camera=single,
                           matcher=args.matcher, overlap=args.overlap, mapper=args.mapper,
                           max_image_size=args.max_image_size, max_features=args.max_features,
                           threads=args.threads, seed=args.seed, focal_px=focal_px,
                           refine_focal=args.refine_focal)
    # COLMAP reports reprojection errors in the matching images' pixels; the limit is meant
    # at the size SIFT ran at.
    longest = max(size) if size is not None else 0
    reprojection_scale = (max(1.0, longest / args.max_image_size)
                          if args.max_image_size > 0 and longest else 1.0)
    gate = QualityGate(args.min_registered, args.max_reproj_px, reprojection_scale,
                       args.max_disagreement, args.max_rotation_disagreement_deg)
    result = reconstruct(image_dir, [f"{name}.png" for name in names], work, settings, gate,
                         size or (0, 0), mask_dir if any_mask else None, retry=args.retry,
                         cross_check=args.cross_check, verbose=log.isEnabledFor(logging.DEBUG))
    chosen = result.chosen
    if chosen is None or chosen.registered_fraction < gate.min_registered_fraction:
        raise PipelineError(failure_message(result, len(names), gate))
    if not chosen.passed:
        log.warning("the best COLMAP model (%d/%d registered, mean reprojection error %s px) "
                    "did not pass the quality gate (%s); continuing with it", chosen.registered,
                    chosen.total, chosen.mean_reprojection_px, chosen.note or
                    f"--max-reproj-px {gate.max_reprojection_px}")
    unregistered = [Path(name).stem for name in chosen.unregistered]
    if unregistered:
        log.warning("%d of %d images not registered (left out): %s", len(unregistered),
                    len(names), ", ".join(unregistered))
    (out / "sparse").mkdir()
    result.model.write(out / "sparse")
    views = [PosedView(name=Path(image.name).stem, camera=image.camera, c2w=image.c2w,
                       near=image.near, far=image.far) for image in model_images(result.model)]
    shutil.rmtree(work)
    report = {
        "clahe": {"enabled": args.clahe, "clip": args.clahe_clip, "tiles": args.clahe_tiles},
        "initial_focal_px": focal_px, "initial_focal_source": focal_source,
        "extraction_masks": any_mask,
        "global_mapping_available": global_mapping_available(),
        "gate": asdict(gate), "gate_passed": chosen.passed,
        "attempts": [a.to_dict() for a in result.attempts],
        "chosen_attempt": result.attempts.index(chosen) + 1,  # attempts count from 1
        "registered": chosen.registered, "total": len(names),
        "mean_reprojection_px": chosen.mean_reprojection_px,
        "unregistered": unregistered,
        "left_out_not_in_both_folders": ignored,
    }
    return PosedDataset(views=views, source="colmap"), report


# -- common output ---------------------------------------------------------------------------

def read_source(args, ingest: IngestFolder) -> PosedDataset:
    if args.source_dir is None:
        raise PipelineError(f"--source {args.source} needs --source-dir")
    if not args.source_dir.exists():
        raise PipelineError(f"{args.source_dir}: --source-dir not found")
    if args.source == "llff":
        return read_llff(args.source_dir, fallback_names=sorted(ingest.linear))
    if args.source == "colmap-model":
        return read_colmap_model(args.source_dir)
    return read_nerfstudio(args.source_dir)


def fill_bounds(views: list[PosedView], near: float | None, far: float | None,
                where: str) -> None:
    """Apply overrides; give frames without bounds the scene-wide ones."""
    for view in views:
        view.near = near if near is not None else view.near
        view.far = far if far is not None else view.far
    known = [v for v in views if v.near is not None and v.far is not None]
    if not known:
        raise PipelineError(f"{where}: no near/far bounds in the source (no sparse points); "
                            f"pass --near and --far in the source's units")
    scene_near, scene_far = min(v.near for v in known), max(v.far for v in known)
    for view in views:
        if view.near is None or view.far is None:
            log.warning("%s: no bounds of its own; using the scene's", view.name)
            view.near = scene_near if view.near is None else view.near
            view.far = scene_far if view.far is None else view.far
        if not 0 < view.near < view.far:
            raise PipelineError(f"{view.name}: invalid bounds near={view.near}, far={view.far}")


def write_outputs(dataset: PosedDataset, ingest: IngestFolder, out: Path, args) -> dict:
    """Undistort the linear images and masks, normalise, write cameras.json; report fields."""
    by_name = {view.name: view for view in dataset.views}
    views = [by_name[name] for name in sorted(by_name) if name in ingest.linear]
    without_image = sorted(set(by_name) - set(ingest.linear))
    without_pose = sorted(set(ingest.linear) - set(by_name))
    if without_image:
        log.warning("%d posed images have no linear image in %s and are skipped: %s",
                    len(without_image), ingest.linear_dir, ", ".join(without_image))
    if without_pose:
        log.warning("%d images have no pose and are left out: %s", len(without_pose),
                    ", ".join(without_pose))
    if not views:
        raise PipelineError(f"none of the posed images has a linear image in "
                            f"{ingest.linear_dir}; do the names match?")
    fill_bounds(views, args.near, args.far, str(args.source_dir or ingest.root))
    (out / "images").mkdir()
    (out / "masks").mkdir()
    cache: dict[tuple, object] = {}
    records = []
    for view in views:
        image = read_image(ingest.linear[view.name])
        if image.ndim == 2:
            image = np.repeat(image[..., None], 3, axis=2)
        height, width = image.shape[:2]
        camera = camera_at_size(view.camera, width, height)
        key = (camera.model_name, width, height, tuple(np.round(camera.params, 9)))
        if key not in cache:
            cache[key] = undistortion(camera)
        warp = cache[key]
        mask = np.ones((height, width), bool)
        if view.name in ingest.masks:
            mask = read_mask(ingest.masks[view.name])
            if mask.shape != (height, width):
                mask = cv2.resize(mask.astype(np.uint8), (width, height),
                                  interpolation=cv2.INTER_NEAREST) > 0
        write_float_tiff(out / "images" / f"{view.name}.tiff", warp.warp_image(image))
        write_mask(out / "masks" / f"{view.name}.png", warp.warp_mask(mask))
        records.append((view, warp))
    c2w = np.array([view.c2w for view, _ in records])
    intrinsics = np.array([[[w.fx, 0, w.cx], [0, w.fy, w.cy], [0, 0, 1]] for _, w in records])
    sizes = np.array([[w.width, w.height] for _, w in records])
    try:
        centre, scale = unit_ball_normalisation(c2w, intrinsics, sizes,
                                                np.array([v.far for v, _ in records]))
    except ValueError as exc:
        raise PipelineError(f"cannot normalise the scene: {exc}") from None
    normalised = normalise_c2w(c2w, centre, scale)
    split = every_nth_split([v.name for v, _ in records], args.test_every)
    frames = []
    for (view, warp), pose, k in zip(records, normalised, intrinsics):
        near, far = range_bounds(view.near, view.far, k, warp.width, warp.height)
        frames.append(Frame(name=view.name, image=f"images/{view.name}.tiff",
                            mask=f"masks/{view.name}.png", width=warp.width, height=warp.height,
                            fx=warp.fx, fy=warp.fy, cx=warp.cx, cy=warp.cy, c2w=pose.tolist(),
                            near=near * scale, far=far * scale, split=split[view.name]))
    cameras = CameraSet(frames=frames, near=min(f.near for f in frames),
                        far=max(f.far for f in frames), centre=centre.tolist(), scale=scale,
                        source=dataset.source)
    write_cameras(out / "cameras.json", cameras)
    distorted = {json.dumps(camera_dict(view.camera), sort_keys=True) for view, _ in records}
    return {
        "frames": len(frames),
        "test_frames": sum(f.split == "test" for f in frames),
        "normalisation": {"centre": centre.tolist(), "scale": scale,
                          "method": NORMALISATION_METHOD},
        "near": cameras.near, "far": cameras.far,
        "source_cameras": [json.loads(d) for d in sorted(distorted)],
        "undistorted": len(cache) > 0 and any(w.map_x is not None for w in cache.values()),
        "posed_without_linear_image": without_image,
        "linear_images_without_pose": without_pose,
    }


def run(args: argparse.Namespace) -> None:
    start = time.perf_counter()
    if not 0.0 < args.min_registered <= 1.0:
        raise PipelineError(f"--min-registered must be in (0, 1], got {args.min_registered}")
    ingest = IngestFolder(args.ingest, args.linear_folder)
    with atomic_dir(args.out) as out:
        if args.source == "colmap":
            dataset, report = run_colmap(args, ingest, out)
        else:
            dataset = read_source(args, ingest)
            report = {"reader_notes": dataset.notes}
        report = {"source": dataset.source, "ingest": str(args.ingest),
                  "arguments": {k: (str(v) if isinstance(v, Path) else v)
                                for k, v in vars(args).items() if not k.startswith("_")},
                  **report, **write_outputs(dataset, ingest, out, args)}
        report["seconds"] = round(time.perf_counter() - start, 2)
        write_json(out / "report.json", report)
    log.info("poses: %d frames written to %s in %.1f s", report["frames"], args.out,
             report["seconds"])
