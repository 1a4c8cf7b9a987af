"""Export the cameras for other tools: a nerfstudio dataset and a COLMAP text model.

Reads the poses step's output (``cameras.json``, the undistorted linear ``images/``, ``masks/``
and, for COLMAP runs, ``sparse/``) and writes into ``--out`` (replaced atomically):

  nerfstudio/transforms.json   open with ``ns-train nerfacto --data <out>/nerfstudio`` or the
                               nerfstudio viewer; 8-bit image copies and masks beside it
  colmap/sparse/0/*.txt        open in COLMAP's GUI (File > Import model, images in
                               ``<out>/colmap/images``), or use as a ``colmap`` dataset

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
    """Exports of the cameras: nerfstudio transforms.json and a COLMAP text model."""

    image_format: Literal["png", "jpg"] = setting(
        "png", help="format of the 8-bit image copies beside the exports")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--poses", required=True, type=Path,
                        help="output folder of the poses step (cameras.json, images/)")
    parser.add_argument("--out", required=True, type=Path,
                        help="output folder (nerfstudio/, colmap/; replaced atomically)")
    settings.add_arguments(parser, Settings)


def run(args: argparse.Namespace) -> None:
    cfg = settings.from_namespace(Settings, args)
    summary = export_poses(args.poses, args.out, cfg.image_format)
    log.info("export: %d frames, %d points: %s and %s", summary["frames"], summary["points"],
             summary["nerfstudio"], summary["colmap"])
