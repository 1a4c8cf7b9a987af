"""The cross-dataset report: one row per dataset of the sheet, why failed datasets failed, and
the self-contained HTML page (``templates/report.html.j2``). Pure, no file I/O: the report step
reads the files into :class:`DatasetRecord` and :class:`StepLog` and writes what these return.
"""

from __future__ import annotations

import base64
import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from seathru.eval.summary import EvaluationSummary
from seathru.eval.truth import WATER_KEYS

ERROR_LINE = re.compile(r"seathru (?P<step>[\w-]+): error: (?P<message>.*)")
NOT_RUN = "no results and no logs (not run yet?)"
TABLE_COLUMNS = (
    "dataset", "source", "options", "status", "failed_step", "error", "views",
    "psnr_linear", "ssim_linear", "psnr_srgb", "ssim_srgb", "lpips",
    "restored_psnr_linear", "restored_ssim_linear", "full_vs_clean_psnr_linear",
    "depth_median_abs_rel", "depth_corr", "train_time_s", "train_steps", "render_fps",
    "render_resolution", "medium")
ALWAYS_SHOWN = ("dataset", "status", "error", "failed_step")


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
    status: str = "ok"                  # "ok" (evaluated) or "failed"
    failed_step: str | None = None
    error: str | None = None
    summary: EvaluationSummary | None = None
    metrics: pd.DataFrame | None = None
    train_log: pd.DataFrame | None = None
    water: dict[str, list[float]] | None = None   # fitted water per source unit (water.json)


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


def medium_name(selection) -> str | None:
    """The medium model the train step chose, from its ``selection.json`` content."""
    if not isinstance(selection, dict):
        return None
    for key in ("final_mode", "chosen", "mode", "medium", "selected"):
        if key in selection:
            return str(selection[key])
    return json.dumps(selection)[:80]


def summary_table(records: Sequence[DatasetRecord]) -> pd.DataFrame:
    """One row per dataset: status, failure, metric means, training and render figures. Columns
    of :data:`TABLE_COLUMNS` that no dataset has are left out."""
    rows = []
    for record in records:
        row = {"dataset": record.dataset, "source": record.source, "options": record.options,
               "status": record.status, "failed_step": record.failed_step,
               "error": record.error}
        summary = record.summary
        row["views"] = summary.views if summary else None
        means = summary.means if summary else {}
        row.update({key: means[key] for key in TABLE_COLUMNS if key in means})
        training = summary.training if summary else None
        row["train_time_s"] = training.time_s if training else None
        row["train_steps"] = training.steps if training else None
        log = record.train_log
        if row["train_time_s"] is None and log is not None and "wall_time_s" in log:
            row["train_time_s"] = float(log["wall_time_s"].max())
        render = summary.render if summary else None
        row["render_fps"] = render.fps if render else None
        resolution = render.resolution if render else None
        row["render_resolution"] = ("x".join(map(str, resolution))
                                    if isinstance(resolution, list) and len(resolution) == 2
                                    and not isinstance(resolution[0], list) else None)
        row["medium"] = medium_name(summary.medium_selection if summary else None)
        rows.append(row)
    table = pd.DataFrame(rows)
    columns = [c for c in TABLE_COLUMNS if c in table.columns and
               (c in ALWAYS_SHOWN or table[c].notna().any())]
    return table[columns]


def water_values(record: DatasetRecord) -> tuple[dict | None, dict | None, str]:
    """(fitted, truth, unit) of a dataset's water: in 1/m against the truth where the truth is
    known, else per unit of its own reconstruction; (None, None, "") without either."""
    truth = record.summary.truth if record.summary else None
    if truth is not None and truth.water.fitted:
        return truth.water.fitted, truth.water.truth, "1/m"
    if record.water is None:
        return None, None, ""
    return record.water, None, "1/source unit"


# ----------------------------------------------------------------------------------------- HTML

def format_cell(value) -> str:
    """A table cell: numbers to 4 significant digits, missing values as a dash."""
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "—"
    if isinstance(value, (float, np.floating)):
        return f"{value:.4g}"
    return str(value)


def format_triple(values) -> str:
    if values is None:
        return "—"
    return ", ".join(format_cell(None if v is None else float(v)) for v in np.ravel(values))


def _template():
    import jinja2

    environment = jinja2.Environment(loader=jinja2.PackageLoader("seathru.eval", "templates"),
                                     autoescape=True, undefined=jinja2.StrictUndefined,
                                     trim_blocks=True, lstrip_blocks=True)
    environment.filters.update(cell=format_cell, triple=format_triple,
                               base64=lambda data: base64.b64encode(data).decode("ascii"))
    return environment.get_template("report.html.j2")


def render_html(table: pd.DataFrame, records: Sequence[DatasetRecord],
                plots: Mapping[str, bytes], strips: Mapping[str, bytes], generated: str) -> str:
    """The self-contained report page: the summary table, failures, water against the truth,
    and the plots and image strips (PNG bytes) inlined.

    Args:
        table: from :func:`summary_table`.
        plots: file name -> PNG; strips: dataset -> PNG.
        generated: the time stamp shown on the page.
    """
    rows = [{"css": "ok" if row["status"] == "ok" else "failed",
             "cells": [None if not isinstance(v, str) and pd.isna(v) else v
                       for v in row.tolist()]}
            for _, row in table.iterrows()]
    water_rows = []
    for record in records:
        truth = record.summary.truth if record.summary else None
        if truth is None or not truth.water.fitted:
            continue
        water = truth.water
        water_rows += [{"dataset": record.dataset, "key": key, "fitted": water.fitted.get(key),
                        "truth": (water.truth or {}).get(key),
                        "error": (water.relative_error or {}).get(key)} for key in WATER_KEYS]
    return _template().render(
        columns=list(table.columns), rows=rows, records=records,
        failures=[r for r in records if r.status != "ok"], water_rows=water_rows,
        plots=plots, strips=strips, generated=generated)
