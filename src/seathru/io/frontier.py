"""``evaluate/frontier.csv``: one run's quality against training time, and what it is made from.

``frontier.csv`` has one row per quality snapshot of the train step, by training time, columns
:data:`seathru.eval.frontier.FRONTIER_COLUMNS`:

- ``step``, ``elapsed_s``: the optimisation step and the training time (s) of the snapshot;
- ``test_psnr_images``: held-out PSNR (linear, dB) on whole images at ``downscale``, as the
  train step measured it (``train/snapshots.csv``, all held-out views pooled);
- ``restored_psnr_linear``: simulated dives: the snapshot's restored renders against the clean
  truth block-averaged to ``downscale``, with the final evaluation's colour gain (mean over the
  held-out views, 8-bit quantised, as ``restored_psnr_linear`` of ``metrics.csv``);
- ``medium``: the water model at the snapshot; ``<key>_rel_error_<r|g|b>`` for ``sigma_attn``,
  ``sigma_bs``, ``c_med``: simulated dives: relative error of the snapshot's water against the
  true water (1/m by the metric scale, c_med by the colour gain: as ``summary.json``'s
  ``truth.water``);
- ``downscale``: the snapshots' downscale.

Empty cells: not measured (not simulated, no water, or a snapshot whose renders are missing: one
taken before a resumed run's restart). The inputs are the train step's ``snapshots.csv``
(``seathru.io.training.read_snapshots``) and ``snapshots/step_NNNNNNN.npz`` (``<view>.rgb``,
``<view>.restored``, float16, written by ``seathru.io.training.write_snapshots``).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd

from seathru.errors import PipelineError
from seathru.eval import frontier
from seathru.eval.summary import TruthSummary
from seathru.io.atomic import write_text
from seathru.io.cameras import CameraSet
from seathru.io.evaluation import read_truth_image, truth_on_frames
from seathru.io.training import read_snapshot_renders, read_snapshots, snapshot_path
from seathru.io.water import read_truth_water
from seathru.radiometry.linearise import block_average, resize_area

log = logging.getLogger(__name__)

FRONTIER_NAME = "frontier.csv"
_HINT = "re-run the 'evaluate' step"


def _truth_like(truth_dir: Path, kind: str, view: str, like: np.ndarray, downscale: int,
                cache: dict, on_frame: Callable[[np.ndarray, str], np.ndarray] | None
                ) -> np.ndarray:
    """The truth image of a view at a snapshot's resolution: mapped onto the view's camera
    (``on_frame``, when the camera file is known), block means at ``downscale``, area-resized
    when the sizes still differ (a camera file whose images were resized)."""
    key = (kind, view, like.shape[:2], downscale)
    if key not in cache:
        image = read_truth_image(truth_dir, kind, view)
        if on_frame is not None:
            image = on_frame(image, view)
        averaged = block_average(image, downscale)
        if averaged.shape[:2] != like.shape[:2]:
            averaged = resize_area(image, (like.shape[1], like.shape[0]))
        cache[key] = averaged
    return cache[key]


def frontier_table(train_dir: str | os.PathLike, truth_dir: str | os.PathLike | None = None,
                   truth: TruthSummary | None = None, cameras: CameraSet | None = None
                   ) -> pd.DataFrame:
    """The rows of ``frontier.csv`` for one run (no rows when training took no snapshots).

    Args:
        train_dir: the train step's folder (``snapshots.csv``, ``snapshots/``).
        truth_dir: simulated dives: the simulate step's ``truth/``; with it, ``truth``: the
            final evaluation's comparison (its colour gain and metric scale are used).
        cameras: the camera file the run trained on; with it the truth images go onto its
            (undistorted) cameras as in the final evaluation, without it they are resized.
    """
    snapshots = read_snapshots(Path(train_dir))
    rows, cache = [], {}
    on_frame = None if cameras is None else truth_on_frames(cameras)
    scored = truth_dir is not None and truth is not None
    true_water = read_truth_water(Path(truth_dir) / "water.json").as_dict() if scored else None
    for snapshot in snapshots:
        downscale = int(snapshot.get("downscale") or 1)
        restored, errors = None, None
        if scored:
            gain = np.asarray(truth.colour_gain, dtype=np.float64)
            errors = frontier.snapshot_water_errors(snapshot, true_water,
                                                    truth.metric_scale.scale, gain)
            renders = read_snapshot_renders(train_dir, int(snapshot["step"]))
            if renders is None:
                log.warning("%s not found: no restored score at step %d",
                            snapshot_path(train_dir, snapshot["step"]), snapshot["step"])
            else:
                restored = frontier.snapshot_restored_psnr(
                    ((render["restored"],
                      _truth_like(Path(truth_dir), "clean", view, render["restored"],
                                  downscale, cache, on_frame),
                      _truth_like(Path(truth_dir), "depth", view, render["restored"],
                                  downscale, cache, on_frame))
                     for view, render in sorted(renders.items()) if "restored" in render), gain)
        rows.append(frontier.frontier_row(snapshot, downscale, restored, errors))
    table = pd.DataFrame(rows, columns=list(frontier.FRONTIER_COLUMNS))
    return table.sort_values("elapsed_s", kind="stable").reset_index(drop=True)


def write_frontier(path: str | os.PathLike, table: pd.DataFrame) -> None:
    """Write ``frontier.csv`` atomically (empty cells for NaN)."""
    write_text(path, table[list(frontier.FRONTIER_COLUMNS)].to_csv(index=False,
                                                                   float_format="%.6g"))


def read_frontier(path: str | os.PathLike) -> pd.DataFrame:
    """Read ``frontier.csv`` (numbers as floats, ``medium`` as text).

    Raises:
        PipelineError: naming the file when it is missing, not a table, lacks a column or holds
        a value that is not a number.
    """
    try:
        table = pd.read_csv(path, dtype={"medium": str}, keep_default_na=False,
                            na_values=[""])
    except FileNotFoundError:
        raise PipelineError(f"{path}: file not found; {_HINT}") from None
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise PipelineError(f"{path}: cannot be read as a table ({exc}); {_HINT}") from None
    missing = [c for c in frontier.FRONTIER_COLUMNS if c not in table.columns]
    if missing:
        raise PipelineError(f"{path}: missing columns {missing}; {_HINT}")
    for column in frontier.FRONTIER_COLUMNS:
        if column == "medium":
            table[column] = table[column].fillna("")
            continue
        values = pd.to_numeric(table[column], errors="coerce")
        bad = values.isna() & table[column].notna()
        if bad.any():
            raise PipelineError(f"{path}: column {column!r} holds "
                                f"{table[column][bad].iloc[0]!r}, not a number; {_HINT}")
        table[column] = values.astype(float)
    return table[list(frontier.FRONTIER_COLUMNS)]
