"""Quality against training time: each run's snapshots scored, and the frontier across runs.
Pure, no file I/O.

The train step measures the model on whole held-out images at log-spaced training times (the
quality snapshots: ``train/snapshots.csv`` and the held-out renders at a reduced resolution).
The evaluate step turns them into one row per snapshot (:func:`frontier_row`): the held-out PSNR
the train step measured and, for simulated dives, the restored renders against the clean truth
block-averaged to the snapshot's resolution (:func:`snapshot_restored_psnr`, with the colour
gain of the final evaluation) and the water against the true water
(:func:`snapshot_water_errors`, converted as ``seathru.eval.truth.compare_water`` does). The
report puts the runs of one scene (a sheet row and its sweep variants) on the same axes: the
Pareto front (:func:`pareto_front`: the best PSNR reached by any run within a time) and the time
each run needed to get within 0.5 dB of its own final PSNR (:func:`time_to_within`), each run
labelled with its capacity level (``auto → fast``, ``quality``: so ``train.preset=auto`` compares
with the named presets) and the passes over its training pixels it made.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import numpy as np

import pandas as pd

from seathru.eval import metrics
from seathru.eval.report_records import DatasetRecord, capacity_level, training_passes
from seathru.eval.truth import WATER_KEYS, compare_water

CHANNELS = "rgb"
WATER_ERROR_COLUMNS = tuple(f"{key}_rel_error_{c}" for key in WATER_KEYS for c in CHANNELS)
FRONTIER_COLUMNS = ("step", "elapsed_s", "test_psnr_images", "restored_psnr_linear", "medium",
                    *WATER_ERROR_COLUMNS, "downscale")
WITHIN_DB = 0.5
WITHIN_COLUMN = f"time_to_within_{WITHIN_DB:g}db_s"
SHEET_ROW = "(sheet row)"    # the variant cell of a sheet's own row in the table
SUMMARY_COLUMNS = ("dataset", "variant", "run", "capacity", "passes", "status", "psnr_linear",
                   "train_time_s",
                   "snapshot_final_psnr", WITHIN_COLUMN, "within_share_of_training",
                   "restored_psnr_linear", "snapshot_final_restored_psnr",
                   "render_s_per_frame", "snapshots")


def snapshot_restored_psnr(views: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]],
                           gain: np.ndarray) -> float:
    """Mean over the held-out views of the restored render's linear PSNR against the clean
    truth, scored as the final evaluation does (``seathru.eval.truth.view_truth_metrics``: the
    colour gain applied, 8-bit quantised, open-water pixels left out).

    Args:
        views: per view ``(restored (h, w, 3), clean (h, w, 3), truth_depth (h, w))`` at the
            snapshot's resolution; a pixel is scored where the clean image and the range are
            finite.
        gain: ``(3,)``, the final evaluation's colour gain (``truth.colour_gain``).

    Returns:
        the mean PSNR in dB; NaN without views.
    """
    scores = []
    for restored, clean, depth in views:
        defined = np.all(np.isfinite(clean), axis=-1) & np.isfinite(depth)
        # as metrics.image_metrics' psnr_linear (without its SSIM, which small images lack)
        prediction = np.where(defined[..., None], np.asarray(gain) * restored, 0.0)
        target = np.where(defined[..., None], clean, 0.0)
        scores.append(metrics.psnr(metrics.quantise_8bit(prediction),
                                   metrics.quantise_8bit(target), valid=defined))
    return float(np.mean(scores)) if scores else float("nan")


def snapshot_water_errors(snapshot: Mapping[str, float | None],
                          truth: Mapping[str, list[float]], metres_per_unit: float,
                          gain: np.ndarray) -> dict[str, float]:
    """Relative error per channel of a snapshot's water against the truth.

    Args:
        snapshot: a ``snapshots.csv`` row: ``sigma_attn_r`` ... ``c_med_b`` in normalised units
            and the pipeline's colour scale (None where not recorded).
        truth: the true water (``sigma_attn``, ``sigma_bs`` in 1/m, ``c_med``), each ``(3,)``.
        metres_per_unit, gain: the final evaluation's metric scale and colour gain.

    Returns:
        :data:`WATER_ERROR_COLUMNS` -> relative error (NaN when the snapshot has no water).
    """
    values = {key: [snapshot.get(f"{key}_{c}") for c in CHANNELS] for key in WATER_KEYS}
    if any(v is None or not np.isfinite(v) for channel in values.values() for v in channel):
        return dict.fromkeys(WATER_ERROR_COLUMNS, float("nan"))
    errors = compare_water(values, truth, metres_per_unit, gain).relative_error
    return {f"{key}_rel_error_{c}": float(errors[key][i]) for key in WATER_KEYS
            for i, c in enumerate(CHANNELS)}


def frontier_row(snapshot: Mapping[str, float | str | None], downscale: int,
                 restored_psnr: float | None = None,
                 water_errors: Mapping[str, float] | None = None) -> dict:
    """One row of ``frontier.csv`` (:data:`FRONTIER_COLUMNS`) from a ``snapshots.csv`` row and,
    for simulated dives, its scores against the truth (None / NaN without them)."""
    nan = float("nan")
    row = {"step": int(snapshot["step"]), "elapsed_s": float(snapshot["elapsed_s"]),
           "test_psnr_images": nan if snapshot.get("test_psnr_images") is None
           else float(snapshot["test_psnr_images"]),
           "restored_psnr_linear": nan if restored_psnr is None else float(restored_psnr),
           "medium": snapshot.get("medium") or ""}
    row.update({column: float((water_errors or {}).get(column, nan))
                for column in WATER_ERROR_COLUMNS})
    row["downscale"] = int(downscale)
    return row


def _finite_points(times, values) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    times = np.asarray(times, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    keep = np.flatnonzero(np.isfinite(times) & np.isfinite(values))
    order = keep[np.lexsort((-values[keep], times[keep]))]   # by time, best value first
    return order, times[order], values[order]


def pareto_front(times, values) -> np.ndarray:
    """The points on the front of "best value within a time": each beats every point that took
    no longer (NaN points ignored).

    Args:
        times: ``(N,)`` seconds (training time, or render time per frame).
        values: ``(N,)`` higher is better (PSNR).

    Returns:
        indices into the inputs, by increasing time (and value): the staircase
        ``max(values[times <= t])`` steps up at each.

    Example::

        pareto_front([1, 2, 3, 4], [10, 9, 12, 12])   # array([0, 2])
    """
    order, _, sorted_values = _finite_points(times, values)
    front, best = [], -np.inf
    for index, value in zip(order, sorted_values):
        if value > best:
            front.append(index)
            best = value
    return np.asarray(front, dtype=int)


def time_to_within(times, values, margin_db: float = WITHIN_DB) -> float | None:
    """The first time at which a run's PSNR is within ``margin_db`` of its final PSNR (the value
    at its last time), from its snapshots (NaN values ignored); None without any.

    The snapshots are log-spaced, so this is the snapshot time at which the run first got
    there, not an interpolation between snapshots.

    Example::

        time_to_within([5, 10, 20, 40], [20.0, 24.0, 25.6, 26.0])   # 20.0
    """
    _, sorted_times, sorted_values = _finite_points(times, values)
    if not len(sorted_times):
        return None
    final = sorted_values[sorted_times == sorted_times[-1]][0]
    reached = np.flatnonzero(sorted_values >= final - margin_db)
    return float(sorted_times[reached[0]])


# ------------------------------------------------------------------------------- the report's side

def runs_by_dataset(records: Iterable[DatasetRecord]) -> dict[str, list[DatasetRecord]]:
    """The runs of each sheet dataset (its own row first, then its sweep variants), in order."""
    groups: dict[str, list[DatasetRecord]] = {}
    for record in records:
        groups.setdefault(record.base or record.dataset, []).append(record)
    return {base: sorted(runs, key=lambda r: r.variant != "") for base, runs in groups.items()}


def snapshot_curve(record: DatasetRecord, column: str = "test_psnr_images"
                   ) -> tuple[np.ndarray, np.ndarray]:
    """``(elapsed_s, values)`` of a run's snapshots with a finite ``column``, by time."""
    table = record.frontier
    if table is None or column not in table or not len(table):
        return np.zeros(0), np.zeros(0)
    times = table["elapsed_s"].to_numpy(np.float64)
    values = table[column].to_numpy(np.float64)
    keep = np.isfinite(times) & np.isfinite(values)
    order = np.argsort(times[keep], kind="stable")
    return times[keep][order], values[keep][order]


def final_point(record: DatasetRecord) -> dict[str, float | None]:
    """A finished run's final evaluation: ``psnr_linear``, ``restored_psnr_linear``,
    ``train_time_s`` and ``render_s_per_frame`` (None where unknown)."""
    summary = record.summary

    def number(value):
        return float(value) if isinstance(value, (int, float)) and np.isfinite(value) else None

    means = summary.means if summary else {}
    return {"psnr_linear": number(means.get("psnr_linear")),
            "restored_psnr_linear": number(means.get("restored_psnr_linear")),
            "train_time_s": number(summary.training.time_s) if summary and summary.training
            else None,
            "render_s_per_frame": number(summary.render.seconds_per_frame) if summary
            else None}


def frontier_summary(records: Iterable[DatasetRecord]) -> pd.DataFrame:
    """One row per run (:data:`SUMMARY_COLUMNS`): its capacity level and passes over its
    training pixels (``seathru.eval.report_records.capacity_level``, ``training_passes``; empty where
    not recorded), the final evaluation's held-out PSNR and its training time, the last
    snapshot's PSNR and the time the run needed to get within :data:`WITHIN_DB` dB of it
    (:func:`time_to_within`, also as a share of the training time), restored-vs-clean where the
    truth is known, and the render time per frame. The share is of the last snapshot's time (the
    end of training, on the snapshots' clock)."""
    rows = []
    for base, runs in runs_by_dataset(records).items():
        for record in runs:
            times, psnr = snapshot_curve(record)
            _, restored = snapshot_curve(record, "restored_psnr_linear")
            final = final_point(record)
            within = time_to_within(times, psnr)
            train_time = final["train_time_s"]
            snapshot_end = float(times[-1]) if len(times) else None   # the run's own clock
            rows.append({
                "dataset": base, "variant": record.variant or SHEET_ROW, "run": record.dataset,
                "capacity": capacity_level(record), "passes": training_passes(record),
                "status": record.status, "psnr_linear": final["psnr_linear"],
                "train_time_s": train_time,
                "snapshot_final_psnr": float(psnr[-1]) if len(psnr) else None,
                WITHIN_COLUMN: within,
                "within_share_of_training": within / snapshot_end
                if within is not None and snapshot_end else None,
                "restored_psnr_linear": final["restored_psnr_linear"],
                "snapshot_final_restored_psnr": float(restored[-1]) if len(restored) else None,
                "render_s_per_frame": final["render_s_per_frame"],
                "snapshots": len(times)})
    return pd.DataFrame(rows, columns=list(SUMMARY_COLUMNS))
