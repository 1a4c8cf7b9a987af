"""What the report step reads about one dataset (or one sweep run) from its results and logs.

For ``RESULTS/<dataset>/``: ``evaluate/summary.json``, ``metrics.csv`` and ``frontier.csv``,
``train/train_log.csv``, ``water.json`` and ``selection.json`` (the medium model and the
capacity level chosen, and why; the copy in ``summary.json`` first), ``poses/report.json``
(where the cameras came from), ``train/model.pt``'s training record (steps, rays per step,
preset: ``seathru.io.model.read_training_record``), each step's ``warnings.json`` and the
render step's display images ``render/test/<view>/*.png``;
``LOGS/<dataset>/<step>.log`` for why a dataset without results failed. Everything lands in a
:class:`seathru.eval.report_records.DatasetRecord`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import pandas as pd

from seathru.errors import PipelineError
from seathru.eval.report_plots import STRIP_COLUMNS, strip_views
from seathru.eval.report_records import (ERROR_LINE, DatasetRecord, StepLog, diagnose_failure,
                                         stopped_by)
from seathru.eval.report_warnings import evaluation_warnings, training_warnings
from seathru.io.evaluation import read_metrics, read_summary, read_train_log
from seathru.io.frontier import FRONTIER_NAME, read_frontier
from seathru.io.images import read_image
from seathru.io.jsonfile import read_json
from seathru.io.pose_report import read_pose_report
from seathru.io.warnings import read_dataset_warnings
from seathru.io.water import read_water

log = logging.getLogger(__name__)


def collect_record(row: pd.Series, results: Path, logs: Path | None, step_order: Sequence[str],
                   rising_db: float = 1.0, window: float = 0.2) -> DatasetRecord:
    """What the report shows about one row of the (sweep-expanded) sheet, from its results.

    Args:
        row: ``dataset`` and, when present, ``source``, ``options``, ``base``, ``variant``
            (``seathru.io.sheet.expand_sweeps``).
        results, logs: the results and logs folders.
        step_order: the pipeline's steps in order (failure diagnosis, warning order).
        rising_db, window: the ``not_converged`` warning's threshold
            (``seathru.eval.report_warnings.training_warnings``).
    """
    dataset = str(row["dataset"]).strip()
    base = Path(results) / dataset
    record = DatasetRecord(dataset, source=row.get("source", ""), options=row.get("options", ""),
                           base=str(row.get("base", "") or dataset),
                           variant=str(row.get("variant", "") or ""))
    summary_path = base / "evaluate" / "summary.json"
    try:
        record.summary = read_summary(summary_path) if summary_path.is_file() else None
    except PipelineError as exc:   # a damaged summary fails this dataset, not the report
        record.status, record.failed_step, record.error = "failed", "evaluate", str(exc)
    if record.summary is None and record.status == "ok":
        step_logs = read_step_logs(logs, dataset)
        record.status = "failed"
        record.failed_step, record.error = diagnose_failure(step_logs, step_order)
        finished = stopped_after(step_logs, [base, Path(results) / record.base])
        if finished is not None:
            record.status, record.failed_step = "incomplete", None
            record.error = (f"stopped after {finished}: its results are complete and no later "
                            "step has run (the workflow was stopped early, e.g. by --until, or "
                            "is still running); run it again to continue")
    metrics_path = base / "evaluate" / "metrics.csv"
    if record.summary is not None and metrics_path.is_file():
        record.metrics = read_metrics(metrics_path)
    frontier_path = base / "evaluate" / FRONTIER_NAME
    if record.summary is not None and frontier_path.is_file():
        try:
            record.frontier = read_frontier(frontier_path)
        except PipelineError as exc:   # the frontier is left out, the dataset stays
            log.warning("%s", exc)
    poses_path = base / "poses" / "report.json"
    if poses_path.is_file():
        try:
            record.poses = dict(read_pose_report(poses_path))
        except PipelineError as exc:   # the cameras' columns are left empty, the dataset stays
            log.warning("%s", exc)
    record.train_log = read_train_log(base / "train" / "train_log.csv")
    water_path = base / "train" / "water.json"
    if water_path.is_file():
        try:
            record.water = read_water(water_path).to_dict()
        except PipelineError as exc:
            log.warning("%s", exc)
    selection = (record.summary.medium_selection if record.summary else None) or read_json(
        base / "train" / "selection.json", missing_ok=True)
    record.selection = selection if isinstance(selection, dict) else None
    record.training_run = read_run_record(base / "train" / "model.pt")
    train_log = [s for s in read_step_logs(logs, dataset) if s.step == "train"]
    stopped = (stopped_by(train_log[0].lines) if train_log else None) or (
        record.training_run or {}).get("stopped_by")
    record.warnings = read_dataset_warnings(base, step_order) + training_warnings(
        selection, record.train_log, stopped, rising_db, window) + evaluation_warnings(
        record.summary, record.metrics)
    record.warnings.sort(key=lambda w: step_order.index(w["step"]) if w["step"] in step_order
                         else len(step_order))
    return record


def stopped_after(step_logs: Sequence[StepLog], folders: Sequence[Path]) -> str | None:
    """The step a dataset without results stopped after, where that is all that happened: no
    log has an error line (``seathru.eval.report_records.ERROR_LINE``) and the step of the
    newest log wrote its results (``<folder>/<step>/``, written atomically, so present only
    when the step finished). None otherwise: a failure, or no logs."""
    if not step_logs or any(ERROR_LINE.search(line) for log in step_logs for line in log.lines):
        return None
    newest = max(step_logs, key=lambda log: log.mtime)
    return newest.step if any((Path(f) / newest.step).is_dir() for f in folders) else None


def read_run_record(model_path: Path) -> dict | None:
    """``model.pt``'s training record (``seathru.io.model.read_training_record``); None without
    the file, or when it cannot be read (logged: the report goes on without it)."""
    if not Path(model_path).is_file():
        return None
    from seathru.io.model import read_training_record   # imports torch: only when needed

    try:
        return read_training_record(model_path)
    except PipelineError as exc:
        log.warning("%s", exc)
        return None


def read_step_logs(logs: Path | None, dataset: str) -> list[StepLog]:
    """The step logs ``LOGS/<dataset>/*.log`` of a dataset ([] without any)."""
    folder = None if logs is None else Path(logs) / dataset
    if folder is None or not folder.is_dir():
        return []
    return [StepLog(path.stem, path.stat().st_mtime,
                    path.read_text(errors="replace").splitlines())
            for path in folder.glob("*.log")]


def read_strip_images(dataset_dir: Path, count: int) -> dict[str, dict]:
    """view -> {strip column -> display image or None} for the views shown in the strip."""
    test_dir = dataset_dir / "render" / "test"
    available = [p.name for p in test_dir.iterdir() if p.is_dir()] if test_dir.is_dir() else []
    return {view: {name: read_image(path) if (path := test_dir / view / f"{name}.png").is_file()
                   else None for name, _ in STRIP_COLUMNS}
            for view in strip_views(available, count)}
