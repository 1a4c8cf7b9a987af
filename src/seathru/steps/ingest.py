"""Decode a dataset's photos (RAW, linear 16-bit or sRGB) to linear images on one exposure scale.

Reads one folder (``--input``, optionally ``--subdir``, e.g. ``images_wb`` of a SeaThru-NeRF
release) and writes, in ``--out`` (replaced atomically, never half-written):

  linear/<stem>.tiff      float32 linear RGB after exposure normalisation and white balance
  linear_<N>/<stem>.tiff  the same, area-averaged down by N (LLFF images_N), per --downscale
  masks/<stem>.png        validity mask (255 valid; clipped pixels dilated), masks_<N>/ likewise
  matching/<stem>.png     8-bit sRGB-encoded copy for feature matching, one global exposure
  manifest.json           settings, dataset gains, per-image metadata, rejected files

Kinds: ``raw`` (anything LibRaw decodes; demosaiced only, by default in the camera's raw colour
space with unit white balance, as SeaThru-NeRF used), ``linear`` (16-bit/float PNG or TIFF used
as stored), ``srgb`` (8-bit JPEG/PNG/TIFF, inverse sRGB transfer), ``auto`` (by extension and bit
depth; when kinds are mixed, e.g. RAW+JPEG pairs, raw wins over linear over srgb and the other
files are listed as rejected).

Exposure: every image is scaled by k_i = median(E) / E_i with E = t * ISO / N^2 from EXIF (a
field no image has is left out; an image missing a field others have keeps k = 1, with a
warning). White balance (--wb): none; camera = the dataset median of the as-shot multipliers
(one set of gains for all views); percentile = SeaThru-NeRF's recipe, each channel divided by its
99.8th percentile over all images, estimated from a regular grid of at most --stats-pixels pixels
per image so memory stays bounded. With --colour srgb, RAW images are converted with LibRaw's
camera-to-sRGB matrix after the camera white balance (the matrix expects white-balanced input),
and a percentile white balance is applied after the matrix.

Masks: a pixel is invalid where any channel is clipped (RAW: a CFA sample at or above
--saturation-threshold x the white level, or at the ADC floor 0, found on the raw grid; encoded
files: the top code or 0), grown by --mask-dilation pixels for demosaic/JPEG spread; resized
masks keep a pixel valid only if every pixel under it is. The percentile white balance uses all
pixels, clipped ones included, as the SeaThru-NeRF recipe does.

Unusable files (unsupported, stripped, truncated, constant output) are rejected with a reason and
the rest continue; the step fails if fewer than --min-images remain. Images are decoded in
--workers spawned processes (LibRaw uses OpenMP, which is not fork-safe), one file per task.
"""

from __future__ import annotations

import argparse
import logging
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import tifffile

from seathru.radiometry import linearise
from seathru.errors import PipelineError
from seathru.io import raw as rawio
from seathru.io.atomic import atomic_dir, write_json
from seathru.io.images import read_mask, write_8bit, write_float_tiff, write_mask

FORMAT = "seathru-ingest/1"
LOG = logging.getLogger(__name__)

#: Memory bound for dataset statistics (percentile WB, matching exposure), in pixels overall.
STATS_TOTAL_PIXELS = 8_000_000
KIND_PRIORITY = ("raw", "linear", "srgb")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--input", required=True, type=Path, help="folder holding the images")
    parser.add_argument("--subdir", default=None,
                        help="subfolder of --input with the images (e.g. images_wb; matched "
                             "case-insensitively)")
    parser.add_argument("--out", required=True, type=Path,
                        help="output folder for this dataset (replaced atomically)")
    parser.add_argument("--kind", choices=("auto",) + KIND_PRIORITY, default="auto",
                        help="input kind (default: auto, by extension and bit depth)")
    parser.add_argument("--colour", choices=("raw", "srgb"), default="raw",
                        help="colour space of RAW output: the camera's raw space (default, as "
                             "SeaThru-NeRF) or linear sRGB via LibRaw's camera matrix")
    parser.add_argument("--wb", choices=("none", "camera", "percentile"), default="percentile",
                        help="white balance (default: percentile, the SeaThru-NeRF recipe)")
    parser.add_argument("--wb-percentile", type=float, default=99.8,
                        help="percentile each channel is divided by for --wb percentile")
    parser.add_argument("--demosaic", choices=rawio.SUPPORTED_DEMOSAIC, default="AHD",
                        help="LibRaw demosaic algorithm (default AHD)")
    parser.add_argument("--half-size", action="store_true",
                        help="RAW: bin each 2x2 CFA block instead of demosaicing (half resolution)")
    parser.add_argument("--exposure-normalise", action=argparse.BooleanOptionalAction,
                        default=True, help="scale images to one exposure from EXIF t, ISO, N")
    parser.add_argument("--saturation-threshold", type=float, default=0.98,
                        help="RAW samples at or above this fraction of the white level are "
                             "saturated (default 0.98)")
    parser.add_argument("--mask-dilation", type=int, default=1,
                        help="pixels the clipped-pixel mask grows by (default 1)")
    parser.add_argument("--max-size", type=int, default=0,
                        help="long edge of linear/ in pixels (0: full resolution)")
    parser.add_argument("--matching-max-size", type=int, default=0,
                        help="long edge of matching/ in pixels (0: same as linear/)")
    parser.add_argument("--downscale", type=int, nargs="*", default=[],
                        help="factors N for linear_N/ and masks_N/ (e.g. 2 4 8)")
    parser.add_argument("--min-images", type=int, default=3,
                        help="fail if fewer usable images remain (default 3)")
    parser.add_argument("--stats-pixels", type=int, default=100_000,
                        help="pixels sampled per image for dataset statistics (default 100000)")
    parser.add_argument("--workers", type=int, default=0,
                        help="worker processes (0: one per CPU core, at most 8; 1: inline)")


# --- tasks run in worker processes ----------------------------------------------------------

@dataclass(frozen=True)
class DecodeTask:
    source: str
    name: str
    kind: str
    work_dir: str
    raw_settings: rawio.RawSettings
    max_size: int
    mask_dilation: int
    sample_pixels: int


@dataclass
class Decoded:
    """What pass 1 tells the main process about one image (small: no full image)."""

    name: str
    source: str
    kind: str
    width: int = 0
    height: int = 0
    source_size: list[int] = field(default_factory=list)
    exposure: dict[str, Any] = field(default_factory=dict)
    camera_wb: np.ndarray | None = None
    colour_matrix: np.ndarray | None = None
    samples: np.ndarray | None = None
    saturated_fraction: float = 0.0
    black_clipped_fraction: float = 0.0
    invalid_fraction: float = 0.0
    metadata: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    reason: str | None = None


def _decode_one(task: DecodeTask) -> Decoded:
    """Pass 1: decode, resize to --max-size, write the unscaled linear image and the final mask
    into the work folder; return metadata and a pixel sample."""
    result = Decoded(name=task.name, source=task.source, kind=task.kind)
    try:
        if task.kind == "raw":
            decoded = rawio.decode_raw(task.source, task.raw_settings)
        else:
            decoded = rawio.read_encoded(task.source, task.kind)
    except rawio.DecodeError as exc:
        result.reason = str(exc)
        return result
    except Exception as exc:  # noqa: BLE001 - any failure on one file must not stop the dataset
        LOG.debug("decoding %s failed", task.source, exc_info=True)
        result.reason = f"could not be decoded ({type(exc).__name__}: {exc})"
        return result

    image = decoded.image
    invalid = decoded.saturated | decoded.black_clipped
    result.saturated_fraction = float(decoded.saturated.mean())
    result.black_clipped_fraction = float(decoded.black_clipped.mean())
    invalid = linearise.dilate_invalid(invalid, task.mask_dilation)
    height, width = image.shape[:2]
    result.source_size = [width, height]
    size = linearise.fit_size(width, height, task.max_size)
    image = linearise.resize_area(image, size)
    valid = linearise.resize_mask(~invalid, size)
    result.width, result.height = size
    result.invalid_fraction = float(1.0 - valid.mean())

    work = Path(task.work_dir)
    write_float_tiff(work / "linear" / f"{task.name}.tiff", image)
    write_mask(work / "masks" / f"{task.name}.png", valid)

    result.samples = linearise.sample_pixels(image, task.sample_pixels)
    exif = decoded.exposure
    result.exposure = {"exposure_time": exif.exposure_time, "iso": exif.iso,
                       "f_number": exif.f_number, "source": dict(exif.source)}
    result.camera_wb = decoded.camera_wb
    result.colour_matrix = decoded.colour_matrix
    result.metadata = decoded.metadata
    result.warnings = list(decoded.warnings)
    return result


@dataclass(frozen=True)
class FinishTask:
    name: str
    work_dir: str
    gains: np.ndarray
    matrix: np.ndarray | None
    post_gains: np.ndarray | None
    downscale: tuple[int, ...]
    matching_max_size: int
    matching_scale: float


def _finish_one(task: FinishTask) -> dict[str, Any]:
    """Pass 2: apply the dataset-level linear map, write final linear, downscales, matching."""
    work = Path(task.work_dir)
    linear_path = work / "linear" / f"{task.name}.tiff"
    image = linearise.apply_colour(tifffile.imread(linear_path), task.gains, task.matrix,
                                   task.post_gains)
    write_float_tiff(linear_path, image)
    height, width = image.shape[:2]
    valid = None
    outputs: dict[str, Any] = {}
    for factor in task.downscale:
        if valid is None:
            valid = read_mask(work / "masks" / f"{task.name}.png")
        size = linearise.downscaled_size(width, height, factor)
        write_float_tiff(work / f"linear_{factor}" / f"{task.name}.tiff",
                         linearise.resize_area(image, size))
        write_mask(work / f"masks_{factor}" / f"{task.name}.png",
                   linearise.resize_mask(valid, size))
        outputs[str(factor)] = {"linear": f"linear_{factor}/{task.name}.tiff",
                                "mask": f"masks_{factor}/{task.name}.png",
                                "width": size[0], "height": size[1]}
    size = linearise.fit_size(width, height, task.matching_max_size)
    write_8bit(work / "matching" / f"{task.name}.png",
               linearise.matching_image(linearise.resize_area(image, size), task.matching_scale))
    return {"downscaled": outputs, "matching_size": list(size)}


def _init_worker(threads: int) -> None:
    # LibRaw's OpenMP and OpenCV would otherwise each start one thread per core in every worker.
    os.environ["OMP_NUM_THREADS"] = str(threads)
    import cv2

    cv2.setNumThreads(threads)


_CRASHED = object()


class WorkerPool:
    """``map(func, tasks)`` over ``workers`` spawned processes (inline for 1), one pool reused
    by both passes.

    A task whose worker process dies (a native crash in LibRaw) is retried alone in a fresh
    process, so one bad file cannot take down the others; if it dies again its result is
    ``_CRASHED``.
    """

    def __init__(self, workers: int):
        self.workers = workers
        self.threads = max(1, (os.cpu_count() or 1) // max(1, workers))
        self._context = multiprocessing.get_context("spawn")  # rawpy/OpenMP are not fork-safe
        self._executor: ProcessPoolExecutor | None = None

    def _new_executor(self, workers: int) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(max_workers=workers, mp_context=self._context,
                                   initializer=_init_worker, initargs=(self.threads,))

    def map(self, func: Callable, tasks: Sequence) -> list:
        if self.workers <= 1:
            return [func(task) for task in tasks]
        if self._executor is None:
            self._executor = self._new_executor(self.workers)
        results: list = [_CRASHED] * len(tasks)
        retry = []
        futures = {self._executor.submit(func, task): index for index, task in enumerate(tasks)}
        for future in as_completed(futures):
            try:
                results[futures[future]] = future.result()
            except BrokenProcessPool:
                retry.append(futures[future])
        if retry:
            self.close()
            for index in sorted(retry):
                with self._new_executor(1) as single:
                    try:
                        results[index] = single.submit(func, tasks[index]).result()
                    except BrokenProcessPool:
                        LOG.error("worker process died on %s", tasks[index])
        return results

    def close(self) -> None:
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None

    def __enter__(self) -> "WorkerPool":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# --- input selection ------------------------------------------------------------------------

def resolve_input(folder: Path, subdir: str | None) -> Path:
    """The image folder: ``folder/subdir`` (case-insensitive match of ``subdir``) or ``folder``."""
    if not folder.is_dir():
        raise PipelineError(f"--input {folder}: folder not found")
    if not subdir:
        return folder
    exact = folder / subdir
    if exact.is_dir():
        return exact
    matches = [p for p in folder.iterdir() if p.is_dir() and p.name.lower() == subdir.lower()]
    if len(matches) == 1:
        return matches[0]
    available = sorted(p.name for p in folder.iterdir() if p.is_dir())
    raise PipelineError(f"--subdir {subdir}: no such folder in {folder} "
                        f"(subfolders: {', '.join(available) or 'none'})")


def select_files(folder: Path, kind: str) -> tuple[list[tuple[Path, str, str]], list[dict],
                                                   dict[str, Any]]:
    """Images to decode as ``(path, name, kind)``, rejected files and what was detected.

    Names are file stems; files are taken in sorted name order so a duplicate stem (IMG_1.dng
    and IMG_1.DNG) always rejects the same, later file.
    """
    candidates = []
    ignored = []
    for path in sorted(folder.iterdir(), key=lambda p: p.name):
        if path.name.startswith(".") or not path.is_file():
            continue
        detected = rawio.detect_kind(path)
        if detected is None:
            ignored.append(path.name)
        else:
            candidates.append((path, detected))
    counts = {k: sum(1 for _, d in candidates if d == k) for k in KIND_PRIORITY}
    counts = {k: v for k, v in counts.items() if v}
    if not candidates:
        with_images = sorted(p.name for p in folder.iterdir() if p.is_dir() and any(
            rawio.detect_kind(f) for f in p.iterdir() if f.is_file()))
        hint = (f"; subfolders with images: {', '.join(with_images)} (use --subdir)"
                if with_images else "")
        raise PipelineError(f"{folder}: no image files (RAW, JPEG, PNG, TIFF) found{hint}")

    if kind == "auto":
        dataset_kind = next(k for k in KIND_PRIORITY if k in counts)
        note = f"detected {dataset_kind} from " + ", ".join(f"{v} {k}" for k, v in counts.items())
    else:
        dataset_kind = kind
        note = f"requested {kind}; found " + ", ".join(f"{v} {k}" for k, v in counts.items())
    selected, rejected, taken = [], [], {}
    for path, detected in candidates:
        if kind == "auto" or dataset_kind == "raw":
            usable = detected == dataset_kind
        else:  # an explicit linear/srgb kind decides the transfer of any encoded file
            usable = detected != "raw"
        if not usable:
            rejected.append({"file": path.name, "reason": (
                f"{detected} file ({path.suffix}) in a dataset of kind {dataset_kind}; "
                f"only {dataset_kind} files are used (pass --kind to choose)")})
            continue
        if path.stem in taken:
            rejected.append({"file": path.name, "reason": (
                f"duplicate image name {path.stem!r}: {taken[path.stem]} already provides it")})
            continue
        taken[path.stem] = path.name
        selected.append((path, path.stem, dataset_kind))
    detection = {"kind": dataset_kind, "requested": kind, "counts": counts, "note": note,
                 "ignored": ignored}
    return selected, rejected, detection


# --- the step -------------------------------------------------------------------------------

def _check_args(args: argparse.Namespace) -> None:
    if not 0.0 < args.wb_percentile <= 100.0:
        raise PipelineError(f"--wb-percentile {args.wb_percentile}: must be in (0, 100]")
    if not 0.0 < args.saturation_threshold <= 1.0:
        raise PipelineError(f"--saturation-threshold {args.saturation_threshold}: must be in "
                            "(0, 1]")
    if any(f < 1 for f in args.downscale):
        raise PipelineError(f"--downscale {args.downscale}: factors must be integers >= 1")
    if args.min_images < 1:
        raise PipelineError(f"--min-images {args.min_images}: must be at least 1")
    if args.max_size < 0 or args.matching_max_size < 0 or args.stats_pixels < 1:
        raise PipelineError("--max-size / --matching-max-size must be >= 0, --stats-pixels >= 1")


def run(args: argparse.Namespace) -> None:
    _check_args(args)
    folder = resolve_input(Path(args.input), args.subdir)
    selected, rejected, detection = select_files(folder, args.kind)
    workers = args.workers or min(os.cpu_count() or 1, 8)
    workers = max(1, min(workers, len(selected)))
    sample_pixels = min(args.stats_pixels, max(4096, STATS_TOTAL_PIXELS // max(1, len(selected))))
    raw_settings = rawio.RawSettings(demosaic=args.demosaic, half_size=args.half_size,
                                     saturation_threshold=args.saturation_threshold)
    downscale = tuple(sorted(set(args.downscale) - {1}))
    LOG.info("ingest %s: %s; %d images, %d workers", folder, detection["note"], len(selected),
             workers)
    for item in rejected:
        LOG.warning("rejected %s: %s", item["file"], item["reason"])

    out = Path(args.out)
    with atomic_dir(out) as work, WorkerPool(workers) as pool:
        tasks = [DecodeTask(str(path), name, kind, str(work), raw_settings, args.max_size,
                            args.mask_dilation, sample_pixels) for path, name, kind in selected]
        decoded: list[Decoded] = []
        for task, result in zip(tasks, pool.map(_decode_one, tasks)):
            if result is _CRASHED:
                result = Decoded(task.name, task.source, task.kind,
                                 reason="the decoder process crashed on this file")
            if result.reason:
                item = {"file": Path(task.source).name, "reason": result.reason}
                rejected.append(item)
                LOG.warning("rejected %s: %s", item["file"], item["reason"])
            else:
                decoded.append(result)
        if len(decoded) < args.min_images:
            listing = "; ".join(f"{r['file']}: {r['reason']}" for r in rejected) or "none"
            raise PipelineError(
                f"{folder}: only {len(decoded)} usable image(s) of {len(selected)} "
                f"(--min-images {args.min_images}); {len(rejected)} rejected: {listing}")

        dataset = _dataset_transform(decoded, args, detection["kind"])
        finish = [FinishTask(d.name, str(work), dataset["gains"][i], dataset["matrices"][i],
                             dataset["post_gains"], downscale, args.matching_max_size or 0,
                             dataset["matching_scale"]) for i, d in enumerate(decoded)]
        finished = pool.map(_finish_one, finish)
        if any(f is _CRASHED for f in finished):
            raise PipelineError(f"{out}: a worker process crashed while writing outputs "
                                "(out of memory?); rerun with fewer --workers")
        manifest = _manifest(args, folder, detection, decoded, finished, dataset, rejected,
                             downscale, workers, sample_pixels)
        write_json(work / "manifest.json", manifest)
    LOG.info("ingest %s: %d images written to %s, %d rejected", folder, len(decoded), out,
             len(rejected))


def _dataset_transform(decoded: list[Decoded], args: argparse.Namespace,
                       kind: str) -> dict[str, Any]:
    """Per-image exposure factors, the dataset white balance and the matching exposure."""
    count = len(decoded)
    if args.exposure_normalise:
        norm = linearise.exposure_normalisation(
            [d.exposure["exposure_time"] for d in decoded], [d.exposure["iso"] for d in decoded],
            [d.exposure["f_number"] for d in decoded])
        for d, warnings in zip(decoded, norm.warnings):
            d.warnings.extend(warnings)
        factors = norm.factors
        exposure = {"normalised": True, "reference": norm.reference,
                    "fields_used": list(norm.fields_used),
                    "definition": "E = t * ISO / N^2 over fields_used; factor = reference / E, "
                                  "reference = median E; factor 1 where E is unknown"}
        values = norm.exposure
    else:
        factors = np.ones(count)
        values = np.full(count, np.nan)
        exposure = {"normalised": False, "reference": None, "fields_used": []}

    warnings: list[str] = []
    use_matrix = args.colour == "srgb" and kind == "raw"
    camera = None
    if args.wb == "camera" or (use_matrix and args.wb == "percentile"):
        camera = linearise.dataset_camera_gains([d.camera_wb for d in decoded])
        if camera is None:
            warnings.append("no as-shot white balance in the files (only RAW files carry "
                            "one): camera white balance gains set to 1")
    gains_camera = camera if camera is not None else np.ones(3)

    matrices: list[np.ndarray | None] = [None] * count
    if use_matrix:
        for i, d in enumerate(decoded):
            if d.colour_matrix is None:
                d.warnings.append("LibRaw has no camera-to-sRGB matrix for this camera: left "
                                  "in camera raw colour")
            matrices[i] = d.colour_matrix

    def transformed(pre: np.ndarray, post: np.ndarray | None) -> np.ndarray:
        return np.concatenate([linearise.apply_colour(d.samples, pre * factors[i], matrices[i],
                                                      post) for i, d in enumerate(decoded)])

    post_gains = None
    percentile_levels = None
    if args.wb == "percentile":
        if use_matrix:
            post_gains, percentile_levels = _percentile(transformed(gains_camera, None), args)
            gains = gains_camera
        else:
            gains, percentile_levels = _percentile(transformed(np.ones(3), None), args)
    else:
        gains = gains_camera if args.wb == "camera" else np.ones(3)

    samples = transformed(gains, post_gains)
    matching_scale = linearise.matching_exposure(samples)
    white_balance = {
        "method": args.wb,
        "gains": [float(g) for g in gains],
        "gains_space": "camera raw" if kind == "raw" else "as stored",
        "post_matrix_gains": [float(g) for g in post_gains] if post_gains is not None else None,
        "percentile": args.wb_percentile if args.wb == "percentile" else None,
        "percentile_levels": [float(v) for v in percentile_levels]
        if percentile_levels is not None else None,
        "camera_gains": [float(g) for g in camera] if camera is not None else None,
        "sampled_pixels": int(samples.shape[0]),
    }
    return {"factors": factors, "exposure_values": values, "exposure": exposure,
            "gains": [gains * factors[i] for i in range(count)], "matrices": matrices,
            "post_gains": post_gains, "matching_scale": matching_scale,
            "white_balance": white_balance, "colour": "srgb-linear" if use_matrix else (
                "camera raw" if kind == "raw" else "as stored"), "warnings": warnings}


def _value_scale(args: argparse.Namespace) -> str:
    if args.wb == "percentile":
        return (f"linear; the dataset's {args.wb_percentile}th percentile of each channel is 1.0")
    return ("linear; 1.0 = the white level (top code) at the dataset's median exposure, "
            "times the white balance gains")


def _percentile(samples: np.ndarray, args: argparse.Namespace) -> tuple[np.ndarray, np.ndarray]:
    try:
        return linearise.percentile_gains(samples, args.wb_percentile)
    except ValueError as exc:
        raise PipelineError(f"--wb percentile: {exc}; use --wb none or camera") from exc


def _manifest(args, folder: Path, detection, decoded: list[Decoded], finished, dataset,
              rejected, downscale, workers, sample_pixels) -> dict[str, Any]:
    images = []
    for i, (d, f) in enumerate(zip(decoded, finished)):
        value = dataset["exposure_values"][i]
        images.append({
            "name": d.name,
            "source": Path(d.source).name,
            "source_path": str(Path(d.source).resolve()),
            "kind": d.kind,
            "width": d.width,
            "height": d.height,
            "source_size": d.source_size,
            "linear": f"linear/{d.name}.tiff",
            "mask": f"masks/{d.name}.png",
            "matching": f"matching/{d.name}.png",
            "matching_size": f["matching_size"],
            "downscaled": f["downscaled"],
            "exposure_time": d.exposure["exposure_time"],
            "iso": d.exposure["iso"],
            "f_number": d.exposure["f_number"],
            "exposure_metadata_source": d.exposure["source"],
            "exposure_value": None if not np.isfinite(value) else float(value),
            "exposure_factor": float(dataset["factors"][i]),
            "saturated_fraction": d.saturated_fraction,
            "black_clipped_fraction": d.black_clipped_fraction,
            "clipped_fraction": d.invalid_fraction,
            "camera_wb_gains": d.camera_wb.tolist() if d.camera_wb is not None else None,
            "colour_matrix": dataset["matrices"][i].tolist()
            if dataset["matrices"][i] is not None else None,
            "decoder": d.metadata,
            "warnings": d.warnings,
        })
    return {
        "format": FORMAT,
        "input": {"folder": str(folder.resolve()), "given": str(args.input),
                  "subdir": args.subdir, **detection},
        "settings": {
            "kind": args.kind, "colour": args.colour, "wb": args.wb,
            "wb_percentile": args.wb_percentile, "demosaic": args.demosaic,
            "half_size": args.half_size, "exposure_normalise": args.exposure_normalise,
            "saturation_threshold": args.saturation_threshold,
            "mask_dilation": args.mask_dilation, "max_size": args.max_size,
            "matching_max_size": args.matching_max_size, "downscale": list(downscale),
            "min_images": args.min_images, "stats_pixels_per_image": sample_pixels,
            "workers": workers,
            "raw_decoding": "LibRaw: per-channel black subtracted, / (white - black), unit WB, "
                            "raw colour, gamma (1, 1), 16-bit, no auto brightness, "
                            "adjust_maximum_thr 0, orientation from the file",
        },
        "colour_space": dataset["colour"],
        "values": _value_scale(args),
        "exposure": dataset["exposure"],
        "white_balance": dataset["white_balance"],
        "matching": {"exposure_scale": dataset["matching_scale"],
                     "target_median": linearise.MATCHING_TARGET_MEDIAN,
                     "encoding": "sRGB transfer of clip(scale * linear), 8-bit PNG"},
        "warnings": dataset["warnings"],
        "images": images,
        "rejected": rejected,
    }
