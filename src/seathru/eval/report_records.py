"""What the report knows of one dataset of the sheet, and what that dataset's files say.

:class:`DatasetRecord` holds everything the report shows about one dataset (the report step
fills it through ``seathru.io.report_inputs``) and :class:`StepLog` one of its step logs. From
them: why a dataset without results failed (:func:`diagnose_failure`), what ended its training
(:func:`stopped_by`), and what its train step chose, from ``selection.json`` and ``model.pt``:
the medium model (:func:`medium_name`), the capacity level (``auto → fast`` when
``train.preset=auto`` chose it, the preset's name when one was named: :func:`capacity_level`)
and the passes over the training pixels the run made (:func:`training_passes`). Pure, no file
I/O.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from seathru.eval.summary import EvaluationSummary

#: A step's error line in its log (``seathru <step>: error: <message>``, ``seathru.cli``).
ERROR_LINE = re.compile(r"seathru (?P<step>[\w-]+): error: (?P<message>.*)")
#: The train step's last line says what ended training (``stopped by time`` / ``steps``).
STOPPED_BY_LINE = re.compile(r"\(stopped by (?P<cause>\w+)[;)]")
NOT_RUN = "no results and no logs (not run yet?)"


@dataclass
class StepLog:
    """One step log of a dataset (``LOGS/<dataset>/<step>.log``)."""

    step: str            # the file name's stem
    mtime: float         # modification time, seconds
    lines: list[str]


@dataclass
class DatasetRecord:
    """Everything the report shows about one dataset of the sheet."""

    dataset: str
    source: str = ""
    options: str = ""
    status: str = "ok"          # "ok" (evaluated), "failed" or "incomplete" (stopped early)
    failed_step: str | None = None
    error: str | None = None
    summary: EvaluationSummary | None = None
    metrics: pd.DataFrame | None = None
    train_log: pd.DataFrame | None = None
    water: dict[str, Any] | None = None   # water.json as written (per source unit)
    warnings: list[dict] = field(default_factory=list)  # {step, code, message, details}
    base: str = ""                      # the sheet's dataset a sweep run is on ("" = itself)
    variant: str = ""                   # its sweep variant ("" for the sheet's own row)
    frontier: pd.DataFrame | None = None   # evaluate/frontier.csv (seathru.io.frontier)
    selection: dict | None = None       # the train step's selection.json (medium, capacity)
    # model.pt's training record (steps, elapsed_s, stopped_by, ...) with its config's
    # batch_rays and preset (seathru.io.model.read_training_record)
    training_run: dict | None = None
    poses: dict | None = None           # the poses step's report.json (seathru.io.pose_report)


def diagnose_failure(logs: Sequence[StepLog], step_order: Sequence[str]) -> tuple[str | None, str]:
    """(failing step, message) of a dataset without results, from its step logs.

    The last ``seathru <step>: error: <message>`` line of the most recently written log that has
    one (ties broken by pipeline order); without any, the last line of the newest log.

    Example::

        diagnose_failure([StepLog("ingest", 5.0, ["seathru ingest: error: bad file"])], STEPS)
        # -> ("ingest", "bad file")
    """
    if not logs:
        return None, NOT_RUN

    def newest(candidates):
        return max(candidates, key=lambda c: (c[0].mtime, list(step_order).index(c[0].step)
                                              if c[0].step in step_order else -1))

    with_errors = [(log, match) for log in logs
                   for match in [next((m for m in map(ERROR_LINE.search, reversed(log.lines))
                                       if m), None)] if match is not None]
    if with_errors:
        log, match = newest(with_errors)
        return (match["step"] if match["step"] in step_order else log.step,
                match["message"].strip())
    log, _ = newest([(log, None) for log in logs])
    last_line = next((line.strip() for line in reversed(log.lines) if line.strip()), "")
    return log.step, f"no 'error:' line; last line of {log.step}.log: {last_line or '(empty)'}"


def stopped_by(lines: Sequence[str]) -> str | None:
    """What ended training (``steps`` or ``time``), from the train step's log lines, or None."""
    return next((m["cause"] for m in map(STOPPED_BY_LINE.search, reversed(lines)) if m), None)


def medium_name(selection) -> str | None:
    """The medium model the train step chose, from its ``selection.json`` content."""
    if not isinstance(selection, dict):
        return None
    for key in ("final_mode", "chosen", "mode", "medium", "selected"):
        if key in selection:
            return str(selection[key])
    return json.dumps(selection)[:80]


def run_selection(record: DatasetRecord) -> dict | None:
    """The train step's ``selection.json`` of a run: the record's, else the copy in its
    evaluation summary."""
    if isinstance(record.selection, dict):
        return record.selection
    selection = record.summary.medium_selection if record.summary is not None else None
    return selection if isinstance(selection, dict) else None


def capacity_record(record: DatasetRecord) -> dict | None:
    capacity = (run_selection(record) or {}).get("capacity")
    return capacity if isinstance(capacity, dict) and capacity.get("chosen") else None


def capacity_level(record: DatasetRecord) -> str | None:
    """The capacity level a run trained at: ``auto → <level>`` when ``train.preset=auto``
    chose it, the preset's name when one was named; from ``selection.json``'s ``capacity``,
    else the preset in ``model.pt``'s config (older runs); None without either.

    Example::

        capacity_level(DatasetRecord("d", selection={"capacity": {"requested": "auto",
                                                                  "chosen": "fast"}}))
        # -> "auto → fast"
    """
    capacity = capacity_record(record)
    if capacity is None:
        preset = (record.training_run or {}).get("preset")
        return str(preset) if preset else None
    requested, chosen = capacity.get("requested"), str(capacity["chosen"])
    return chosen if requested in (None, "", chosen) else f"{requested} \u2192 {chosen}"


def _positive(value) -> float | None:
    number = value if isinstance(value, (int, float)) and not isinstance(value, bool) else None
    return float(number) if number is not None and np.isfinite(number) and number > 0 else None


def training_passes(record: DatasetRecord) -> float | None:
    """Passes over the training pixels the run made: ``steps x batch_rays / train_pixels``,
    steps and batch from ``model.pt``, the pixels from the capacity record's ``scene``; None
    when one of them is unknown (a named preset records no scene, older runs no capacity).

    Example::

        training_passes(DatasetRecord("d", selection={"capacity": {"chosen": "fast",
                        "scene": {"train_pixels": 20000}}},
                        training_run={"steps": 100, "batch_rays": 1000}))   # -> 5.0
    """
    scene = (capacity_record(record) or {}).get("scene")
    pixels = _positive(scene.get("train_pixels")) if isinstance(scene, dict) else None
    run = record.training_run or {}
    steps, batch = _positive(run.get("steps")), _positive(run.get("batch_rays"))
    if pixels is None or steps is None or batch is None:
        return None
    return steps * batch / pixels


def finite_number(value) -> float | None:
    """``value`` as a float where it is a finite number (not a bool), else None: the summary
    files' cells may hold None, NaN or text."""
    number = value if isinstance(value, (int, float)) and not isinstance(value, bool) else None
    return float(number) if number is not None and np.isfinite(number) else None
