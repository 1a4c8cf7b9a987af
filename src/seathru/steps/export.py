"""Export the cameras for other tools: nerfstudio, COLMAP and the SeaThru-NeRF layout.

Reads the poses step's output (``cameras.json``, the undistorted linear ``images/``, ``masks/``
and, for COLMAP runs, ``sparse/``) and writes into ``--out`` (replaced atomically):

  nerfstudio/transforms.json   open with ``ns-train nerfacto --data <out>/nerfstudio`` or the
                               nerfstudio viewer; 8-bit image copies and masks beside it
  colmap/sparse/0/*.txt        open in COLMAP's GUI (File > Import model, images in
                               ``<out>/colmap/images``), or use as a ``colmap`` dataset
  seathru_nerf/                the SeaThru-NeRF release's layout (images_wb/ linear 8-bit,
                               poses_bounds.npy, sparse/0): for the SeaThru-NeRF code,
                               NerfBaselines, or as an ``llff`` dataset

Poses are in the units of the source reconstruction, cameras are the poses step's pinhole
cameras; the conventions are ``seathru.io.exports``.
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from seathru import settings
from seathru.io.exports import export_poses
from seathru.settings import setting

log = logging.getLogger(__name__)


@dataclass
class Settings:
    """Exports of the cameras: nerfstudio, a COLMAP text model and the SeaThru-NeRF layout."""

    image_format: Literal["png", "jpg"] = setting(
        "png", help="format of the 8-bit image copies beside the exports")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--poses", required=True, type=Path,
                        help="output folder of the poses step (cameras.json, images/)")
    parser.add_argument("--out", required=True, type=Path,
                        help="output folder (nerfstudio/, colmap/, seathru_nerf/; replaced atomically)")
    settings.add_arguments(parser, Settings)


def run(args: argparse.Namespace) -> None:
    cfg = settings.from_namespace(Settings, args)
    summary = export_poses(args.poses, args.out, cfg.image_format)
    llff = summary["seathru_nerf"] or (f"no SeaThru-NeRF layout ("
                                       f"{summary['seathru_nerf_skipped']}: LLFF rows hold "
                                       f"one centred focal length)")
    log.info("export: %d frames, %d points: %s, %s and %s", summary["frames"],
             summary["points"], summary["nerfstudio"], summary["colmap"], llff)
