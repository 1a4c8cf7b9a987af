"""Ingest's per-file work, run in a pool of spawned worker processes.

Two passes, one file per task, so a dataset never has to fit in memory:

1. :func:`decode_one` decodes a file, resizes it to ``max_size``, writes the unscaled linear
   image and its validity mask (clipping, and the dataset's own mask where it has one) into
   the work folder and returns metadata and a pixel sample;
2. :func:`finish_one` applies the dataset-level linear map (estimated in between from the
   samples, ``seathru.radiometry.dataset_transform``) and writes the final linear image, its
   LLFF ``linear_<N>/`` and ``masks_<N>/`` copies and the 8-bit matching copy.

Workers are spawned, not forked: LibRaw uses OpenMP, which is not fork-safe.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import tifffile

from seathru.errors import PipelineError
from seathru.io import raw as rawio
from seathru.io.dataset_readers import read_source_mask
from seathru.io.image_folder import RejectedFile
from seathru.io.images import read_mask, write_8bit, write_float_tiff, write_mask
from seathru.radiometry import linearise
from seathru.radiometry.dataset_transform import ImageStatistics

LOG = logging.getLogger(__name__)


# --- pass 1: decode -------------------------------------------------------------------------

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
    mask: str | None = None     # the dataset's own mask (nerfstudio mask_path; 0 = ignore)


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

    def statistics(self) -> ImageStatistics:
        return ImageStatistics(samples=self.samples, exposure_time=self.exposure["exposure_time"],
                               iso=self.exposure["iso"], f_number=self.exposure["f_number"],
                               camera_wb=self.camera_wb, colour_matrix=self.colour_matrix)


def decode_one(task: DecodeTask) -> Decoded:
    """Pass 1: decode, resize to ``max_size``, write the unscaled linear image and the final
    mask into the work folder; return metadata and a pixel sample."""
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
    try:
        kept = None if task.mask is None else read_source_mask(task.mask, width, height)
    except PipelineError as exc:
        result.reason = str(exc)
        return result
    except Exception as exc:  # noqa: BLE001 - a bad mask rejects its image, not the dataset
        result.reason = f"{task.mask}: mask cannot be read ({type(exc).__name__}: {exc})"
        return result
    result.source_size = [width, height]
    size = linearise.fit_size(width, height, task.max_size)
    image = linearise.resize_area(image, size)
    valid = linearise.resize_mask(~invalid, size)
    result.width, result.height = size
    result.invalid_fraction = float(1.0 - valid.mean())   # clipping only, not the given mask
    if kept is not None:
        valid &= linearise.resize_mask(kept, size)

    work = Path(task.work_dir)
    write_float_tiff(work / "linear" / f"{task.name}.tiff", image)
    write_mask(work / "masks" / f"{task.name}.png", valid)

    result.samples = linearise.sample_pixels(image, task.sample_pixels)
    exif = decoded.exposure
    result.exposure = {"exposure_time": exif.exposure_time, "iso": exif.iso,
                       "f_number": exif.f_number, "source": dict(exif.source),
                       "focal_length_mm": exif.focal_length_mm,
                       "focal_length_35mm": exif.focal_length_35mm}
    result.camera_wb = decoded.camera_wb
    result.colour_matrix = decoded.colour_matrix
    result.metadata = decoded.metadata
    result.warnings = list(decoded.warnings)
    return result


# --- pass 2: finish -------------------------------------------------------------------------

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


@dataclass
class Finished:
    """What pass 2 wrote for one image: ``downscaled`` by factor (as a string: the manifest's
    key) with ``linear``, ``mask``, ``width``, ``height``; the matching copy's size."""

    downscaled: dict[str, dict[str, Any]]
    matching_size: list[int]


def finish_one(task: FinishTask) -> Finished:
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
        size = linearise.llff_downscaled_size(width, height, factor)
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
    return Finished(downscaled=outputs, matching_size=list(size))


# --- the pool -------------------------------------------------------------------------------

def _init_worker(threads: int) -> None:
    # LibRaw's OpenMP and OpenCV would otherwise each start one thread per core in every worker.
    os.environ["OMP_NUM_THREADS"] = str(threads)
    import cv2

    cv2.setNumThreads(threads)


#: The result of a task whose worker process died twice.
CRASHED = object()


class WorkerPool:
    """``map(func, tasks)`` over ``workers`` spawned processes (inline for 1), one pool reused
    by both passes.

    A task whose worker process dies (a native crash in LibRaw) is retried alone in a fresh
    process, so one bad file cannot take down the others; if it dies again its result is
    ``CRASHED``.
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
        results: list = [CRASHED] * len(tasks)
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


def decode_all(pool: WorkerPool, tasks: Sequence[DecodeTask],
               masks: dict[str, str] | None = None) -> tuple[list[Decoded], list[RejectedFile]]:
    """Pass 1 over ``tasks``: the decoded images, and the files rejected with a reason (each
    logged as a warning), both in task order. ``masks``: view name -> the dataset's own mask
    of that view (``seathru.io.image_folder.InputImages.masks``), set on its task."""
    tasks = [replace(task, mask=masks[task.name]) if masks and task.name in masks else task
             for task in tasks]
    decoded: list[Decoded] = []
    rejected: list[RejectedFile] = []
    for task, result in zip(tasks, pool.map(decode_one, tasks)):
        if result is CRASHED:
            result = Decoded(task.name, task.source, task.kind,
                             reason="the decoder process crashed on this file")
        if result.reason:
            item: RejectedFile = {"file": Path(task.source).name, "reason": result.reason}
            rejected.append(item)
            LOG.warning("rejected %s: %s", item["file"], item["reason"])
        else:
            decoded.append(result)
    return decoded, rejected
