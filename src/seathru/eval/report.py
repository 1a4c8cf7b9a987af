"""The cross-dataset report: the summary table (one row per dataset of the sheet) and the
self-contained HTML page (``templates/report.html.j2``). Pure, no file I/O: the report step
reads each dataset's files into a ``seathru.eval.report_records.DatasetRecord`` and writes what
these return.

The parts live beside this module: what a dataset's files say and why a dataset failed
(``report_records``), the warnings the report derives itself, the "needs a look" column
(``report_warnings``), and the colour along COLMAP tracks (``report_tracks``).

Where the evaluate step ran a community protocol (``evaluate.protocol=nerfbaselines``), its
means sit beside ours as ``<protocol>_psnr`` / ``_ssim`` / ``_lpips`` (:func:`protocol_cells`);
where it measured a colour chart, the mean CIEDE2000 and grey angular error of the photo, the
ingest image and the restored render are the ``chart_*`` columns (:func:`chart_cells`) and the
page's "Colour charts" section (:func:`chart_rows`). Datasets without them add nothing. The
page's "Settings chosen" section says why the capacity and the medium model were chosen
(:func:`settings_notes`).
"""

from __future__ import annotations

import base64
from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd

from seathru.eval.report_records import (DatasetRecord, capacity_level, capacity_record,
                                         finite_number, medium_name, run_selection,
                                         training_passes)
from seathru.eval.report_tracks import (TRACK_SLOPE_FOLLOWED_MIN, TRACK_SLOPE_GOAL,
                                        track_slope_cells, track_slope_rows)
from seathru.eval.report_warnings import needs_a_look
from seathru.eval.summary import EvaluationSummary
from seathru.eval.truth import WATER_KEYS

#: The colour chart's images (keys of the evaluate step's ``colour_chart``) and their labels.
CHART_IMAGES = (("stored", "photo"), ("ingest", "ingest"), ("restored", "restored"),
                ("restored_photo", "restored_photo"))
CHART_COLUMNS = (*(f"chart_de00_{label}" for _, label in CHART_IMAGES),
                 *(f"chart_grey_deg_{label}" for _, label in CHART_IMAGES))
TABLE_COLUMNS = (
    "dataset", "source", "options", "status", "warnings", "needs_a_look", "failed_step",
    "error", "views", "cameras", "focal_start",
    "psnr_linear", "ssim_linear", "psnr_srgb", "ssim_srgb", "lpips",
    "restored_psnr_linear", "restored_psnr_linear_covered", "restored_ssim_linear",
    "photo_restored_psnr_linear", "reprojected_restored_psnr_linear",
    "reprojected_restored_psnr_linear_supported", "supported_share",
    "full_vs_clean_psnr_linear",
    "depth_median_abs_rel", "depth_corr", *CHART_COLUMNS, "track_slope_reduction",
    "photo_track_slope_reduction", "train_time_s", "train_steps",
    "capacity", "passes", "render_fps", "render_resolution", "medium")
ALWAYS_SHOWN = ("dataset", "status", "warnings", "needs_a_look", "error", "failed_step")
#: A protocol's means shown, in this order, as ``<protocol>_<metric>`` after ``lpips``.
PROTOCOL_METRICS = ("psnr", "ssim", "lpips", "lpips_vgg")
PROTOCOL_NOTES = {
    "nerfbaselines": "NerfBaselines' default protocol (evaluate.protocol=nerfbaselines): the "
                     "render taken back to the stored images' encoding and geometry, 8-bit, "
                     "against the stored images as they are on disk; comparable with published "
                     "NerfBaselines results, not with psnr_linear"}


def settings_notes(records: Sequence[DatasetRecord]) -> list[dict]:
    """Per run with a recorded choice (the page's "Settings chosen"): ``dataset``,
    ``capacity`` (:func:`capacity_level`), ``capacity_reason``, ``kept_explicit`` (settings
    ``auto`` left as they were set), ``medium`` (:func:`medium_name`), ``medium_requested`` and
    ``medium_reason``, ``view_colour`` (on or off) and ``view_colour_reason``, ``far_factor``
    (how far the object field was sampled, as a multiple of the cameras' far bound) and
    ``far_factor_reason``; None where not recorded."""
    notes = []
    for record in records:
        selection, capacity = run_selection(record), capacity_record(record)
        level = capacity_level(record)
        if selection is None and level is None:
            continue
        reason = (capacity or {}).get("reason")
        if reason is None and level is not None:
            reason = f"set by train.preset={level}" if capacity is not None else (
                f"train.preset={level} in model.pt (no capacity record)")
        kept = (capacity or {}).get("kept_explicit")
        notes.append({"dataset": record.dataset, "capacity": level,
                      "capacity_reason": None if reason is None else str(reason),
                      "kept_explicit": [str(k) for k in kept] if isinstance(kept, list) else [],
                      "medium": medium_name(selection),
                      "medium_requested": (selection or {}).get("requested"),
                      "medium_reason": (selection or {}).get("reason"),
                      **_choice_note(selection, "view_dependent_colour", "view_colour"),
                      **_choice_note(selection, "far_factor", "far_factor")})
    return notes


def _choice_note(selection: dict | None, key: str, name: str) -> dict:
    """``{name, name_reason}`` of selection.json's ``key`` (``{"chosen", "reason"}``)."""
    choice = (selection or {}).get(key)
    if not isinstance(choice, dict) or "chosen" not in choice:
        return {name: None, f"{name}_reason": None}
    return {name: f"{choice['chosen']:g}" if isinstance(choice["chosen"], (int, float))
            and not isinstance(choice["chosen"], bool) else str(choice["chosen"]),
            f"{name}_reason": choice.get("reason")}


def protocol_cells(summary: EvaluationSummary | None) -> dict[str, float | None]:
    """``<protocol>_<metric>`` -> the protocol's mean over its views, for the metrics of
    :data:`PROTOCOL_METRICS` it has; {} without a protocol evaluation.

    Example::

        protocol_cells(summary)   # {"nerfbaselines_psnr": 27.1, "nerfbaselines_ssim": 0.83}
    """
    protocol = summary.protocol if summary is not None else None
    means = protocol.get("means") if isinstance(protocol, dict) else None
    if not isinstance(means, dict):
        return {}
    name = str(protocol.get("protocol") or "protocol")
    return {f"{name}_{metric}": means[metric] for metric in PROTOCOL_METRICS if metric in means}


def measured_chart(summary: EvaluationSummary | None) -> dict | None:
    """The evaluate step's colour-chart result when a chart was measured (on at least one
    image), else None (no chart found, an older summary)."""
    chart = summary.colour_chart if summary is not None else None
    if not isinstance(chart, dict) or chart.get("source") in (None, "none"):
        return None
    if not any(isinstance(chart.get(key), dict) and "mean_delta_e00" in chart[key]
               for key, _ in CHART_IMAGES):
        return None
    return chart


def chart_cells(summary: EvaluationSummary | None) -> dict[str, float | None]:
    """The ``chart_*`` columns (:data:`CHART_COLUMNS`): mean CIEDE2000 and grey angular error
    (degrees) of the chart on the photo, the ingest image and the restored render; None where
    that image was not measured; {} without a measured chart."""
    chart = measured_chart(summary)
    if chart is None:
        return {}
    cells = {}
    for key, label in CHART_IMAGES:
        part = chart.get(key) if isinstance(chart.get(key), dict) else {}
        cells[f"chart_de00_{label}"] = part.get("mean_delta_e00")
        cells[f"chart_grey_deg_{label}"] = part.get("mean_grey_angular_error_deg")
    return cells


def camera_cells(poses: dict | None) -> dict[str, str | None]:
    """``cameras``: where the cameras came from and how well (COLMAP's registered images, mean
    reprojection error, whether an independent model confirmed them; or the reader and its
    frames); ``focal_start``: what COLMAP's focal length started from (the photographs' EXIF,
    the settings, or nothing: its own estimate). None without the poses step's report.

    Example::

        camera_cells({"source": "colmap", "registered": 24, "total": 24,
                      "mean_reprojection_px": 0.25, "gate_passed": True,
                      "initial_focal_px": 249.6,
                      "initial_focal_source": "manifest 35 mm equivalent focal length"})
        # {"cameras": "COLMAP 24/24, 0.25 px, confirmed",
        #  "focal_start": "manifest 35 mm equivalent focal length"}
    """
    if not poses:
        return {"cameras": None, "focal_start": None}
    if poses.get("source") != "colmap":
        return {"cameras": f"{poses.get('source')} ({poses.get('frames')} frames)",
                "focal_start": None}
    error = poses.get("mean_reprojection_px")
    return {"cameras": f"COLMAP {poses.get('registered')}/{poses.get('total')}, "
                       + (f"{error:.2f} px, " if error is not None else "")
                       + ("confirmed" if poses.get("gate_passed") else "not confirmed"),
            "focal_start": poses.get("initial_focal_source")
            if poses.get("initial_focal_px") is not None else "none (COLMAP's own estimate)"}


def _ordered_columns(columns: Sequence[str]) -> list[str]:
    """:data:`TABLE_COLUMNS` order, each protocol's columns right after ``lpips``."""
    protocol = [c for c in columns if c not in TABLE_COLUMNS]
    at = TABLE_COLUMNS.index("lpips") + 1
    return [c for c in (*TABLE_COLUMNS[:at], *protocol, *TABLE_COLUMNS[at:]) if c in columns]


def summary_table(records: Sequence[DatasetRecord]) -> pd.DataFrame:
    """One row per dataset: status, failure, metric means, protocol means, colour chart,
    training and render figures. Columns of :data:`TABLE_COLUMNS` (and protocol columns) that no
    dataset has are left out."""
    rows = []
    for record in records:
        row = {"dataset": record.dataset, "source": record.source, "options": record.options,
               "status": record.status, "warnings": len(record.warnings),
               "needs_a_look": needs_a_look(record.warnings),
               "failed_step": record.failed_step, "error": record.error}
        summary = record.summary
        row["views"] = summary.views if summary else None
        row.update(camera_cells(record.poses))
        means = summary.means if summary else {}
        row.update({key: means[key] for key in TABLE_COLUMNS if key in means})
        row.update(protocol_cells(summary))
        row.update(chart_cells(summary))
        row.update(track_slope_cells(summary))
        training = summary.training if summary else None
        row["train_time_s"] = training.time_s if training else None
        row["train_steps"] = training.steps if training else None
        row["capacity"] = capacity_level(record)
        row["passes"] = training_passes(record)
        log = record.train_log
        if row["train_time_s"] is None and log is not None and "wall_time_s" in log:
            row["train_time_s"] = float(log["wall_time_s"].max())
        render = summary.render if summary else None
        row["render_fps"] = render.fps if render else None
        resolution = render.resolution if render else None
        row["render_resolution"] = ("x".join(map(str, resolution))
                                    if isinstance(resolution, list) and len(resolution) == 2
                                    and not isinstance(resolution[0], list) else None)
        row["medium"] = medium_name(run_selection(record))
        rows.append(row)
    table = pd.DataFrame(rows)
    columns = [c for c in _ordered_columns(list(table.columns))
               if c in ALWAYS_SHOWN or table[c].notna().any()]
    return table[columns]


def chart_rows(records: Sequence[DatasetRecord]) -> list[dict]:
    """One row per dataset with a measured colour chart (the page's "Colour charts" table):
    ``dataset``, ``chart``, ``view``, ``excluded`` (occluded and clipped patches, 1-based),
    ``patches_used`` and per image of :data:`CHART_IMAGES` (by label) ``de00`` /
    ``grey_deg`` (means) or ``reason`` it was not measured."""
    rows = []
    for record in records:
        chart = measured_chart(record.summary)
        if chart is None:
            continue
        images, used = {}, None
        for key, label in CHART_IMAGES:
            part = chart.get(key) if isinstance(chart.get(key), dict) else {}
            absent = "a RAW source: no photo" if key == "stored" else "not measured"
            images[label] = {"de00": part.get("mean_delta_e00"),
                             "grey_deg": part.get("mean_grey_angular_error_deg"),
                             "reason": part.get("reason") if part else absent}
            used = part.get("patches_used", used)
        excluded = sorted({int(i) + 1 for i in (*chart.get("occluded", []),
                                                *chart.get("clipped", []))})
        rows.append({"dataset": record.dataset, "chart": chart.get("chart"),
                     "view": chart.get("image"), "excluded": excluded,
                     "patches_used": used, "images": images})
    return rows


def water_intervals(record: DatasetRecord) -> tuple[dict | None, dict | None]:
    """(95% intervals, determined flags) of a dataset's water, in the units of
    :func:`water_values`; (None, None) when training did not assess them."""
    truth = record.summary.truth if record.summary else None
    if truth is not None and truth.water.fitted:
        return truth.water.interval95, truth.water.determined
    uncertainty = (record.water or {}).get("uncertainty")
    if not uncertainty:
        return None, None
    intervals = uncertainty.get("interval95")
    per_metre = (record.water or {}).get("per_metre") or {}
    if intervals is not None and per_metre.get("interval95"):
        intervals = {**intervals, **per_metre["interval95"]}
    return intervals, uncertainty.get("determined")


def water_values(record: DatasetRecord) -> tuple[dict | None, dict | None, str]:
    """(fitted, truth, unit) of a dataset's water: in 1/m against the truth where the truth is
    known, in 1/m where the camera file knew the metric scale (``poses.metres_per_unit``), else
    per unit of its own reconstruction; (None, None, "") without any."""
    truth = record.summary.truth if record.summary else None
    if truth is not None and truth.water.fitted:
        return truth.water.fitted, truth.water.truth, "1/m"
    if record.water is None:
        return None, None, ""
    fitted = {k: record.water[k] for k in WATER_KEYS if k in record.water}
    per_metre = record.water.get("per_metre") or {}
    if all(k in per_metre for k in ("sigma_attn", "sigma_bs")):
        return {**fitted, "sigma_attn": per_metre["sigma_attn"],
                "sigma_bs": per_metre["sigma_bs"]}, None, "1/m"
    return fitted, None, "1/source unit"


# ----------------------------------------------------------------------------------------- HTML

def format_cell(value) -> str:
    """A table cell: numbers to 4 significant digits, missing values as a dash."""
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "—"
    if isinstance(value, (float, np.floating)):
        return f"{value:.4g}"
    return str(value)


def format_share(value) -> str:
    """A share as a whole percentage (``0.512`` -> ``51%``), missing values as a dash."""
    number = finite_number(value)
    return "—" if number is None else f"{100 * number:.0f}%"


def format_triple(values) -> str:
    if values is None:
        return "—"
    return ", ".join(format_cell(None if v is None else float(v)) for v in np.ravel(values))


def _template():
    import jinja2

    environment = jinja2.Environment(loader=jinja2.PackageLoader("seathru.eval", "templates"),
                                     autoescape=True, undefined=jinja2.StrictUndefined,
                                     trim_blocks=True, lstrip_blocks=True)
    environment.filters.update(cell=format_cell, triple=format_triple, share=format_share,
                               base64=lambda data: base64.b64encode(data).decode("ascii"))
    return environment.get_template("report.html.j2")


def protocol_notes(records: Sequence[DatasetRecord]) -> list[dict]:
    """What each protocol shown in the table is (``name``, ``note``) and, per dataset, its
    ``views`` and ``ground_truth`` (``datasets``); [] when no dataset ran one."""
    notes: dict[str, dict] = {}
    for record in records:
        protocol = record.summary.protocol if record.summary is not None else None
        if not protocol_cells(record.summary):
            continue
        name = str(protocol.get("protocol") or "protocol")
        entry = notes.setdefault(name, {"name": name, "datasets": [], "note": PROTOCOL_NOTES.get(
            name, f"the {name} protocol")})
        entry["datasets"].append({"dataset": record.dataset, "views": protocol.get("views"),
                                  "ground_truth": protocol.get("ground_truth")})
    return list(notes.values())


def render_html(table: pd.DataFrame, records: Sequence[DatasetRecord],
                plots: Mapping[str, bytes], strips: Mapping[str, bytes], generated: str,
                frontier: pd.DataFrame | None = None,
                fronts: Mapping[str, bytes] | None = None,
                charts: Mapping[str, bytes] | None = None) -> str:
    """The self-contained report page: the summary table, the settings the train step chose and
    why (:func:`settings_notes`), failures, water against the truth, colour charts, colour
    along COLMAP tracks (:func:`track_slope_rows`), quality against time, and the plots and
    image strips (PNG bytes) inlined.

    Args:
        table: from :func:`summary_table`; its ``chart_*`` columns are shown in the "Colour
            charts" section (:func:`chart_rows`) instead of the summary.
        plots: file name -> PNG; strips: dataset -> PNG.
        generated: the time stamp shown on the page.
        frontier: one row per run (``seathru.eval.frontier.frontier_summary``); fronts:
            dataset -> PNG of its frontier figure.
        charts: dataset -> PNG of its chart swatches
            (``seathru.eval.report_plots.plot_chart_swatches``).
    """
    by_name = {record.dataset: record for record in records}
    table = table[[c for c in table.columns if c not in CHART_COLUMNS]]
    rows = []
    for _, row in table.iterrows():
        record = by_name.get(row["dataset"])
        warnings = record.warnings if record is not None else []
        rows.append({"css": {"ok": "warn" if warnings else "ok", "incomplete": "warn"}.get(
                         row["status"], "failed"),
                     "warnings": warnings,
                     "cells": [(column, None if not isinstance(v, str) and pd.isna(v) else v)
                               for column, v in row.items()]})
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
        flagged=[r for r in records if r.warnings],
        plots=plots, strips=strips, generated=generated,
        frontier_columns=[] if frontier is None else list(frontier.columns),
        frontier_rows=[] if frontier is None else [
            [None if not isinstance(v, str) and pd.isna(v) else v for v in row]
            for row in frontier.itertuples(index=False)],
        fronts=fronts or {}, protocols=protocol_notes(records), chart_rows=chart_rows(records),
        settings_notes=settings_notes(records), slope_rows=track_slope_rows(records),
        slope_goal=TRACK_SLOPE_GOAL, followed_min=TRACK_SLOPE_FOLLOWED_MIN,
        chart_labels=[label for _, label in CHART_IMAGES], charts=charts or {})
