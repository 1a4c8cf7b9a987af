"""Decode a dataset's photos (RAW, linear 16-bit or sRGB) to linear images on one exposure scale.

Reads one folder (``--input``, optionally ``--subdir`` or ``--images``), or with ``--layout
llff|colmap|nerfstudio`` the images a posed dataset holds in its own layout, missing ones skipped
(``seathru.io.dataset_readers.layout_images``); a folder of videos gives the sharpest frame of
every ``--video-interval`` seconds (``seathru.io.video``). Writes, in ``--out`` (atomically), the
linear images, their masks, 8-bit copies for matching, ``manifest.json`` (the layout and format:
``seathru.io.manifest``) and ``warnings.json`` (rejected files, missing frames, clipped images).

Kinds (``raw``: demosaiced only (LINEAR), raw colour; ``linear``; ``srgb``: display-encoded,
decoded by the curve the file's ICC profile records, else sRGB's; ``auto``: RAW wins over linear
over sRGB): ``seathru.io.image_folder``. Exposure (k_i = median(E) / E_i, E = t * ISO / N^2 from
EXIF) and white balance (--wb, percentile: the SeaThru-NeRF recipe):
``seathru.radiometry.dataset_transform``. Masks: clipped pixels (``seathru.radiometry.linearise``)
grown by --mask-dilation, or a layout's own. Unusable files are rejected with a reason.
"""

from __future__ import annotations

import argparse
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from seathru import settings
from seathru.errors import PipelineError
from seathru.io.atomic import atomic_dir
from seathru.io.decode_pool import (CRASHED, DecodeTask, FinishTask, WorkerPool, decode_all,
                                    finish_one)
from seathru.io.dataset_readers import LAYOUTS
from seathru.io.image_folder import InputImages, find_inputs
from seathru.io.manifest import build_manifest, ingest_warnings, transfer_summary, write_manifest
from seathru.io.raw import Demosaic, RawSettings
from seathru.io.video import staged_video_frames
from seathru.io.warnings import write_warnings
from seathru.radiometry.dataset_transform import dataset_transform
from seathru.settings import setting

LOG = logging.getLogger(__name__)

STATS_TOTAL_PIXELS = 8_000_000  #: pixels of all images sampled for the dataset statistics


@dataclass
class Settings:
    """Decoding, exposure, white balance and masks of the ingest step."""

    kind: Literal["auto", "raw", "linear", "srgb"] = setting(
        "auto", help="input kind (auto: by extension, then the curve a PNG/TIFF records, "
                     "then its bit depth; srgb: display-encoded)")
    colour: Literal["raw", "srgb"] = setting(
        "raw", help="colour space of RAW output: the camera's raw space (as SeaThru-NeRF) or "
                    "linear sRGB via LibRaw's camera matrix")
    wb: Literal["none", "camera", "percentile"] = setting(
        "percentile", help="white balance (percentile: the SeaThru-NeRF recipe)")
    wb_percentile: float = setting(
        99.8, help="percentile each channel is divided by for --wb percentile")
    demosaic: Demosaic = setting("LINEAR", help="LibRaw demosaic; LINEAR keeps each channel to its "
                                 "own samples, AHD etc. copy green into red and blue (docs/water.md)")
    half_size: bool = setting(
        False, help="RAW: bin each 2x2 CFA block instead of demosaicing (half resolution)")
    exposure_normalise: bool = setting(
        True, help="scale images to one exposure from EXIF t, ISO, N")
    saturation_threshold: float = setting(
        0.98, help="RAW samples at or above this fraction of the white level are saturated")
    mask_dilation: int = setting(1, help="pixels the clipped-pixel mask grows by")
    max_size: int = setting(1600, help="long edge of linear/ in pixels, larger photographs "
                            "downscaled (as nerfstudio); 0: full size (README: memory, protocol)")
    matching_max_size: int = setting(
        0, help="long edge of matching/ in pixels (0: same as linear/)")
    downscale: list[int] = setting(
        default_factory=list, help="factors N for linear_N/ and masks_N/ (e.g. 2 4 8)")
    min_images: int = setting(3, help="fail if fewer usable images remain")
    stats_pixels: int = setting(100_000, help="pixels sampled per image for dataset statistics")
    images: str = setting(
        "auto", help="image folder: auto (llff: images_wb; simulated: raw; else the path or "
                     "its one image subfolder), a name (images_4, DCIM/100GOPRO, jpeg) or all")
    warn_clipped_share: float = setting(
        0.1, help="warn about images with more than this share of clipped pixels")
    video_interval: float = setting(
        1.0, help="videos: one frame per this many seconds, the sharpest of each interval")
    video_max_frames: int = setting(
        200, help="videos: at most this many frames in all (the interval widens to fit)")

    def validate(self) -> None:
        if not 0.0 < self.wb_percentile <= 100.0:
            raise ValueError(f"--wb-percentile {self.wb_percentile}: must be in (0, 100]")
        if not 0.0 < self.saturation_threshold <= 1.0:
            raise ValueError(f"--saturation-threshold {self.saturation_threshold}: must be in "
                             "(0, 1]")
        if any(f < 1 for f in self.downscale):
            raise ValueError(f"--downscale {self.downscale}: factors must be integers >= 1")
        if self.min_images < 1:
            raise ValueError(f"--min-images {self.min_images}: must be at least 1")
        if min(self.max_size, self.matching_max_size, self.stats_pixels - 1) < 0 or \
                not 0.0 <= self.warn_clipped_share <= 1.0:
            raise ValueError("--max-size / --matching-max-size must be >= 0, --stats-pixels >= 1,"
                             " --warn-clipped-share in [0, 1]")
        if not self.video_interval > 0.0 or self.video_max_frames < 1:
            raise ValueError("--video-interval must be > 0, --video-max-frames >= 1")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # Set by the workflow (workflow/rules/ingest.smk), not configuration.
    parser.add_argument("--input", required=True, type=Path, help="folder holding the images")
    parser.add_argument("--subdir", default=None, help="subfolder of --input with the images "
                        "(e.g. images_wb; matched case-insensitively)")
    parser.add_argument("--layout", choices=LAYOUTS, default=None, help="--input is a posed "
                        "dataset in this layout: decode the images it holds (folder: --images)")
    parser.add_argument("--out", required=True, type=Path,
                        help="output folder for this dataset (replaced atomically)")
    parser.add_argument("--workers", type=int, default=0,
                        help="worker processes (0: one per CPU core, at most 8; 1: inline)")
    settings.add_arguments(parser, Settings)


def run(args: argparse.Namespace) -> None:
    cfg: Settings = settings.from_namespace(Settings, args)
    found = find_inputs(Path(args.input), args.subdir, args.layout, cfg.images, cfg.kind)
    with staged_video_frames(found.videos, Path(args.out), cfg.video_interval,
                             cfg.video_max_frames) as video:
        _decode(args, cfg, found.with_video(video))


def _decode(args: argparse.Namespace, cfg: Settings, found: InputImages) -> None:
    folder, selected, rejected = found.folder, found.selected, found.rejected
    workers = max(1, min(args.workers or min(os.cpu_count() or 1, 8), len(selected)))
    sample_pixels = min(cfg.stats_pixels, max(4096, STATS_TOTAL_PIXELS // max(1, len(selected))))
    raw_settings = RawSettings(cfg.demosaic, cfg.half_size, cfg.saturation_threshold)
    downscale = tuple(sorted(set(cfg.downscale) - {1}))
    LOG.info("ingest %s: %s%s; %d images, %d workers", folder, found.detection["note"],
             f"; {found.reason}" if found.reason else "", len(selected), workers)
    out = Path(args.out)
    with atomic_dir(out) as work, WorkerPool(workers) as pool:
        decoded, failed = decode_all(pool, masks=found.masks, tasks=[
            DecodeTask(str(path), name, kind, str(work), raw_settings, cfg.max_size,
                       cfg.mask_dilation, sample_pixels) for path, name, kind in selected])
        rejected += failed
        if len(decoded) < cfg.min_images:
            listing = "; ".join(f"{r['file']}: {r['reason']}" for r in rejected) or "none"
            raise PipelineError(
                f"{folder}: only {len(decoded)} usable image(s) of {len(selected)} "
                f"(--min-images {cfg.min_images}); {len(rejected)} rejected: {listing}")
        try:
            transform = dataset_transform([d.statistics() for d in decoded],
                                          found.detection["kind"], cfg.wb, cfg.wb_percentile,
                                          cfg.colour, cfg.exposure_normalise)
        except ValueError as exc:
            raise PipelineError(f"--wb percentile: {exc}; use --wb none or camera") from exc
        for d, warnings in zip(decoded, transform.image_warnings):
            d.warnings.extend(warnings)
        finished = pool.map(finish_one, [
            FinishTask(d.name, str(work), transform.image_gains(i), transform.matrices[i],
                       transform.post_gains, downscale, cfg.matching_max_size,
                       transform.matching_scale) for i, d in enumerate(decoded)])
        if any(f is CRASHED for f in finished):
            raise PipelineError(f"{out}: a worker process crashed while writing outputs "
                                "(out of memory?); rerun with fewer --workers")
        manifest = build_manifest(
            cfg, folder=folder, given=args.input, subdir=found.subdir, detection=found.detection,
            decoded=decoded, finished=finished, transform=transform, rejected=rejected,
            downscale=downscale, stats_pixels_per_image=sample_pixels, workers=workers,
            layout=found.layout, video=found.video)
        write_manifest(work / "manifest.json", manifest)
        write_warnings(work / "warnings.json", ingest_warnings(manifest, cfg.warn_clipped_share),
                       LOG)
    LOG.info("ingest: %d images written to %s, %d rejected; stored values decoded by %s",
             len(decoded), out, len(rejected), transfer_summary(manifest))
