"""The cross-dataset report: one row per dataset of the sheet, why failed datasets failed, what
needs a look in the others, and the self-contained HTML page (``templates/report.html.j2``).
Pure, no file I/O: the report step reads the files into :class:`DatasetRecord` and
:class:`StepLog` and writes what these return.

"Needs a look": the warnings the steps wrote (``warnings.json``, ``seathru.io.warnings``), and
two the report derives from the train step's outputs (:func:`training_warnings`): the water
model turned off by ``medium.mode=auto``, and training that ended with its held-out PSNR still
rising fast (far from convergence).

Where the evaluate step ran a community protocol (``evaluate.protocol=nerfbaselines``), its
means sit beside ours as ``<protocol>_psnr`` / ``_ssim`` / ``_lpips`` (:func:`protocol_cells`);
where it measured a colour chart, the mean CIEDE2000 and grey angular error of the photo, the
ingest image and the restored render are the ``chart_*`` columns (:func:`chart_cells`) and the
page's "Colour charts" section (:func:`chart_rows`). Where it fitted the colour's slope
against range along COLMAP tracks (``track_colour_slope``, ``seathru.eval.track_slope``), the
share of the input's slope the restoration removed over all views is ``track_slope_reduction``
(:func:`track_slope_cells`) and the page's "Colour along COLMAP tracks" section gives the
slopes per channel against the :data:`TRACK_SLOPE_GOAL` (:func:`track_slope_rows`). Datasets
without them add nothing.

What the train step chose, from its ``selection.json`` and ``model.pt``: the capacity level
(``capacity``: ``auto → fast`` when ``train.preset=auto`` chose it, ``quality`` for a named
preset: :func:`capacity_level`), the passes over the training pixels the run made (``passes``:
:func:`training_passes`) and, in the page's "Settings chosen" section, why the capacity and the
medium model were chosen (:func:`settings_notes`).
"""

from __future__ import annotations

import base64
import json
import re
from collections.abc import Mapping, Sequence
from typing import Any
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from seathru.eval.summary import EvaluationSummary
from seathru.eval.truth import WATER_KEYS
from seathru.radiometry.glare import brighter_near_open_water

ERROR_LINE = re.compile(r"seathru (?P<step>[\w-]+): error: (?P<message>.*)")
STOPPED_BY_LINE = re.compile(r"\(stopped by (?P<cause>\w+)[;)]")
NOT_RUN = "no results and no logs (not run yet?)"
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
#: The share of the input's colour slope along tracks a restoration should remove on a real dive.
TRACK_SLOPE_GOAL = 0.7
#: Below this share of the input's slope followed by the full render, the report says the
#: reduction says little (the model never held the range dependence it "removed").
TRACK_SLOPE_FOLLOWED_MIN = 0.5
#: The parts of ``track_colour_slope`` (views of the tracks' observations) and their labels.
TRACK_SLOPE_PARTS = (("all_views", "all views"), ("held_out_views", "held-out views"),
                     ("near_tracks", "nearest 90% of tracks"),
                     ("far_tracks", "farthest 10% of tracks"))
#: Parts that evaluations before them do not have: shown only where present.
OPTIONAL_TRACK_SLOPE_PARTS = ("near_tracks", "far_tracks")
ALWAYS_SHOWN = ("dataset", "status", "warnings", "needs_a_look", "error", "failed_step")
#: A protocol's means shown, in this order, as ``<protocol>_<metric>`` after ``lpips``.
PROTOCOL_METRICS = ("psnr", "ssim", "lpips", "lpips_vgg")
PROTOCOL_NOTES = {
    "nerfbaselines": "NerfBaselines' default protocol (evaluate.protocol=nerfbaselines): the "
                     "render taken back to the stored images' encoding and geometry, 8-bit, "
                     "against the stored images as they are on disk; comparable with published "
                     "NerfBaselines results, not with psnr_linear"}


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


def _capacity_record(record: DatasetRecord) -> dict | None:
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
    capacity = _capacity_record(record)
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
    scene = (_capacity_record(record) or {}).get("scene")
    pixels = _positive(scene.get("train_pixels")) if isinstance(scene, dict) else None
    run = record.training_run or {}
    steps, batch = _positive(run.get("steps")), _positive(run.get("batch_rays"))
    if pixels is None or steps is None or batch is None:
        return None
    return steps * batch / pixels


def settings_notes(records: Sequence[DatasetRecord]) -> list[dict]:
    """Per run with a recorded choice (the page's "Settings chosen"): ``dataset``,
    ``capacity`` (:func:`capacity_level`), ``capacity_reason``, ``kept_explicit`` (settings
    ``auto`` left as they were set), ``medium`` (:func:`medium_name`), ``medium_requested`` and
    ``medium_reason``, ``view_colour`` (on or off) and ``view_colour_reason``, ``far_factor``
    (how far the object field was sampled, as a multiple of the cameras' far bound) and
    ``far_factor_reason``; None where not recorded."""
    notes = []
    for record in records:
        selection, capacity = run_selection(record), _capacity_record(record)
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


def stopped_by(lines: Sequence[str]) -> str | None:
    """What ended training (``steps`` or ``time``), from the train step's log lines, or None."""
    return next((m["cause"] for m in map(STOPPED_BY_LINE.search, reversed(lines)) if m), None)


def psnr_rise(train_log: pd.DataFrame | None, window: float = 0.2) -> dict | None:
    """How much the PSNR rose over the last ``window`` share of training time.

    Uses the held-out ``test_psnr`` when it has values before the window and at the end, else
    ``train_psnr``; the value at the window's start is interpolated linearly in time.

    Returns:
        ``{"column", "rise_db", "from_s", "to_s", "final_psnr"}``, or None without enough
        values.

    Example::

        psnr_rise(pd.DataFrame({"wall_time_s": [0, 8, 10], "test_psnr": [10, 18, 20]}))
        # -> {"column": "test_psnr", "rise_db": 2.0, "from_s": 8.0, ...}
    """
    if train_log is None or "wall_time_s" not in train_log:
        return None
    for column in ("test_psnr", "train_psnr"):
        if column not in train_log:
            continue
        rows = train_log[["wall_time_s", column]].apply(pd.to_numeric, errors="coerce").dropna()
        times, values = rows["wall_time_s"].to_numpy(float), rows[column].to_numpy(float)
        if len(times) < 2 or times[-1] <= 0:
            continue
        start = (1.0 - window) * times[-1]
        if times[0] > start:
            continue
        begin = float(np.interp(start, times, values))
        return {"column": column, "rise_db": float(values[-1] - begin), "from_s": float(start),
                "to_s": float(times[-1]), "final_psnr": float(values[-1])}
    return None


def held_out_plateau(train_log: pd.DataFrame | None, within_db: float = 0.25,
                     early: float = 0.1, train_rise_db: float = 2.0) -> dict | None:
    """Whether the held-out PSNR stopped rising early while the training PSNR kept rising.

    The held-out PSNR reached within ``within_db`` of its best in the first ``early`` share of
    the training time, and the training PSNR rose more than ``train_rise_db`` after that: the
    model went on fitting the training views without getting better at new ones, which more
    training time does not mend (on the real d3_reef frames: held-out 17 dB from the first 7 s
    of a 15-min run on, training 18 to 22 dB; ``benchmarks/results/reef_15min.md``).

    Returns:
        ``{"held_out_best_db", "held_out_final_db", "within_db", "reached_s", "to_s",
        "train_rise_db"}``, or None when the log does not show it (or lacks the columns).

    Example::

        held_out_plateau(pd.DataFrame({"wall_time_s": [0, 5, 50, 100],
                                       "test_psnr": [10, 17, 17.1, 17],
                                       "train_psnr": [10, 18, 20, 22]}))
        # -> {"reached_s": 5.0, "train_rise_db": 4.0, ...}
    """
    if train_log is None or not {"wall_time_s", "test_psnr", "train_psnr"} <= set(train_log):
        return None
    numeric = train_log[["wall_time_s", "test_psnr", "train_psnr"]].apply(pd.to_numeric,
                                                                          errors="coerce")
    held = numeric[["wall_time_s", "test_psnr"]].dropna()
    fitted = numeric[["wall_time_s", "train_psnr"]].dropna()
    if len(held) < 3 or len(fitted) < 2:
        return None
    times, values = held["wall_time_s"].to_numpy(float), held["test_psnr"].to_numpy(float)
    total = float(times[-1])
    reached = float(times[np.argmax(values >= values.max() - within_db)])
    if total <= 0 or reached > early * total:
        return None
    train_times = fitted["wall_time_s"].to_numpy(float)
    train_values = fitted["train_psnr"].to_numpy(float)
    rise = float(train_values[-1] - np.interp(reached, train_times, train_values))
    if rise <= train_rise_db:
        return None
    return {"held_out_best_db": float(values.max()), "held_out_final_db": float(values[-1]),
            "within_db": within_db, "reached_s": reached, "to_s": total, "train_rise_db": rise}


def _warning(code: str, message: str, **details) -> dict:
    return {"step": "train", "code": code, "message": message, "details": details}


def training_warnings(selection, train_log: pd.DataFrame | None, stopped: str | None = None,
                      rising_db: float = 1.0, window: float = 0.2) -> list[dict]:
    """Warnings the report derives from the train step's outputs (``{step, code, message,
    details}``, as ``seathru.io.warnings``).

    Args:
        selection: the content of ``selection.json`` (the medium model chosen and why).
        train_log: ``train_log.csv``; stopped: ``steps`` / ``time`` / None (:func:`stopped_by`).
        rising_db, window: training is far from converged when the PSNR rose more than
            ``rising_db`` over the last ``window`` share of its time (:func:`psnr_rise`).

    Also warns when the held-out PSNR stopped rising early while the training PSNR went on
    (:func:`held_out_plateau`).
    """
    found = []
    if isinstance(selection, dict):
        chosen = selection.get("final_mode", selection.get("chosen"))
        if chosen == "off" and selection.get("requested") != "off":
            reason = selection.get("reason") or "no reason recorded"
            found.append(_warning(
                "water_model_off", f"the water model was turned off ({reason}); the model is a "
                f"plain NeRF and its 'restored' images keep the water's colour; if this dive has "
                f"water, set train.medium.mode=global", requested=selection.get("requested"),
                chosen=chosen))
    rise = psnr_rise(train_log, window)
    if rise is not None and rise["rise_db"] > rising_db:
        advice = {"time": "training stopped at its time budget far from convergence: give it "
                          "more train.max_minutes",
                  "steps": "training reached train.steps while still improving: raise "
                           "train.steps (and train.max_minutes)"}.get(
            stopped, "raise train.max_minutes or train.steps")
        which = "held-out" if rise["column"] == "test_psnr" else "training"
        found.append(_warning(
            "not_converged", f"the {which} PSNR still rose {rise['rise_db']:.2f} dB over the last "
            f"{window:.0%} of training ({rise['from_s']:.3g} s to {rise['to_s']:.3g} s, "
            f"> {rising_db:g} dB): {advice}", stopped_by=stopped, threshold_db=rising_db,
            **rise))
    plateau = held_out_plateau(train_log)
    if plateau is not None:
        found.append(_warning(
            "held_out_plateau", f"the held-out PSNR was within {plateau['within_db']:g} dB of "
            f"its best ({plateau['held_out_best_db']:.2f} dB) after "
            f"{plateau['reached_s']:.3g} s of {plateau['to_s']:.3g} s while the training PSNR "
            f"rose another "
            f"{plateau['train_rise_db']:.1f} dB: the model fits the training views without "
            f"getting better at new ones, and more training time will not change that (too "
            f"few views of each surface, or camera poses that disagree); the novel views and "
            f"the water rest on what the training views alone show", **plateau))
    return found


def needs_a_look(warnings: Sequence[dict]) -> str | None:
    """The summary cell of a dataset's warnings: ``step: code`` each, ``; ``-separated."""
    return "; ".join(f"{w['step']}: {w['code']}" for w in warnings) or None


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


def _finite(value) -> float | None:
    number = value if isinstance(value, (int, float)) and not isinstance(value, bool) else None
    return float(number) if number is not None and np.isfinite(number) else None


def evaluation_warnings(summary: EvaluationSummary | None,
                        metrics: pd.DataFrame | None = None) -> list[dict]:
    """``brighter_near_open_water`` where the evaluation found the same surfaces brighter in
    the frames that show them next to the open water (``track_colour_slope``'s
    ``near_open_water``, ``seathru.io.tracks``): light no water model makes (veiling glare in
    the housing's port, a camera's local tone mapping), which the restored images keep;
    ``colour_varies_between_frames`` where the frames' colour casts differ beyond what the
    points and their ranges explain (its ``frame_colour``: a camera's automatic white balance);
    and ``held_out_view_unseen`` where more than :data:`UNSEEN_SHARE_WARN` of a held-out view's
    surface, and more than twice the other held-out views' share, is in no training
    photograph (``metrics``' ``unseen_surface_share``: a view at the end of the camera path).

    Example::

        evaluation_warnings(summary, metrics)   # [] or [{"step": "evaluate", "code": ...}]
    """
    return (_brighter_warning(summary) + _frame_colour_warning(summary)
            + _unseen_warning(metrics))


#: The share of a held-out view's surface no training photograph sees above which, and above
#: twice the other held-out views' median, the report warns that its scores measure a guess.
#: The demo's first view: 0.16 (its others 0.02, 0.03); d3_reef's first: 0.39 (0.11, 0.13).
UNSEEN_SHARE_WARN = 0.1


def _unseen_warning(metrics: pd.DataFrame | None) -> list[dict]:
    if metrics is None or "unseen_surface_share" not in metrics.columns:
        return []
    known = {str(view): float(share) for view, share
             in zip(metrics["view"], pd.to_numeric(metrics["unseen_surface_share"],
                                                    errors="coerce")) if np.isfinite(share)}

    def others(view: str) -> float:
        rest = [share for name, share in known.items() if name != view]
        return float(np.median(rest)) if rest else 0.0

    shares = {view: share for view, share in known.items()
              if share > UNSEEN_SHARE_WARN and share > 2.0 * others(view)}
    if not shares:
        return []
    listed = ", ".join(f"{view} ({100 * share:.0f}% of its surface)"
                       for view, share in shares.items())
    which = "held-out view" if len(shares) == 1 else "held-out views"
    message = (f"{which} {listed} {'shows' if len(shares) == 1 else 'show'} surfaces that no "
               f"training photograph sees (by the model's own depth), far more than the other "
               f"held-out views. Scores and the restored view there measure the model's guess, "
               f"not the reconstruction: the other views' figures are the fairer ones. A "
               f"held-out view at either end of the camera path (every 8th image, the first "
               f"included) often looks where no other photograph did.")
    return [{"step": "evaluate", "code": "held_out_view_unseen", "message": message,
             "details": {"unseen_surface_share": shares, "all_views": known,
                         "threshold": UNSEEN_SHARE_WARN}}]


def _frame_colour_warning(summary: EvaluationSummary | None) -> list[dict]:
    slope = summary.track_colour_slope if summary is not None else None
    cast = slope.get("frame_colour") if isinstance(slope, dict) else None
    if not isinstance(cast, dict) or not cast.get("varies"):
        return []
    spread = ", ".join(f"{100 * v:.0f}%" for v in cast.get("spread") or [])
    offsets = cast.get("offsets") or {}
    worst = max(offsets, key=lambda name: max(abs(v) for v in offsets[name]), default=None)
    example = (f"; farthest from the median frame: {worst}, "
               f"{', '.join(f'{100 * v:+.0f}%' for v in offsets[worst])}" if worst else "")
    corrected = isinstance((summary.medium_selection or {}).get("frame_colour_correction"),
                           dict)
    trained = ("The model was trained on the photographs brought to the median frame's cast "
               "(train.frame_colour auto), which undoes most of it but not all (the simulated "
               "survey white-balanced frame by frame, two runs: red attenuation within 1%, "
               "green and blue 11-12% and 18-20% low with intervals that miss the truth, "
               "against up to 33% off without)"
               if corrected else
               "No water model follows it, so the fitted water is off, possibly more than its "
               "intervals say (the simulated survey white-balanced frame by frame: up to 33% "
               "off, three intervals missing the truth)")
    message = (f"the photographs' colour cast changes from frame to frame beyond what the "
               f"points and their ranges explain: red and blue against green vary by {spread} "
               f"between frames (root mean square{example}), as a camera's automatic "
               f"white balance makes them. {trained}. Shoot RAW, or set the white balance by "
               f"hand for the dive.")
    return [{"step": "evaluate", "code": "colour_varies_between_frames", "message": message,
             "details": {"spread": cast.get("spread"), "noise": cast.get("noise"),
                         "threshold": cast.get("threshold"), "corrected": corrected}}]


def _brighter_warning(summary: EvaluationSummary | None) -> list[dict]:
    part = _slope_part(summary.track_colour_slope if summary is not None else None,
                       "all_views")
    beside = part.get("near_open_water") if part is not None else None
    if not isinstance(beside, dict):
        return []
    coefficients = [_finite(v) for v in beside.get("coefficient") or []]
    errors = [_finite(v) for v in beside.get("coefficient_stderr") or []]
    if not brighter_near_open_water(coefficients, errors):
        return []
    darker = ", ".join(f"{100 * (1 - 2 ** c):.0f}%" if c is not None else "?"
                       for c in coefficients)
    beside_slope = ", ".join(f"{v:.3f}" for v in beside.get("slope") or [])
    alone = ", ".join(f"{v:.3f}" for v in (part.get("input") or {}).get("slope") or [])
    removed = [f"{label} {100 * share:.0f}%" for label, key in
               (("the restored render", "restored"), ("the restored photographs", "photographs"))
               if (share := _finite((beside.get(key) or {}).get("reduction_overall")))
               is not None]
    of_that = f"; of that change {' and '.join(removed)} removed" if removed else ""
    applied = (summary.medium_selection or {}).get("glare_correction")
    kept = (f"the model was trained on the photographs divided by a brightening of "
            f"{applied.get('coefficient', float('nan')):+.2f} log colour per unit of log "
            f"distance (train.glare auto), and the restored images are measured against the "
            f"photographs as they are, so the track slope (track_slope_reduction) still holds "
            f"what the correction did not take out" if isinstance(applied, dict) else
            "the restored images keep it, and the track slope (track_slope_reduction) "
            "measures it as well as the water")
    message = (f"the photographs are brighter next to the open water in the frame: the same "
               f"surface is {darker} (R, G, B) darker each time its distance to the open water "
               f"in the image doubles. With that taken into account the colour changes with "
               f"range by {beside_slope} per unit along the COLMAP tracks, against {alone} "
               f"without{of_that}. Veiling glare in the housing's port or a camera's local "
               f"tone mapping do this, the water does not: {kept}.")
    return [{"step": "evaluate", "code": "brighter_near_open_water", "message": message,
             "details": {"coefficient": coefficients, "coefficient_stderr": errors,
                         "slope_beside": beside.get("slope"),
                         "removed_beside": {key: (beside.get(key) or {}).get("reduction_overall")
                                            for key in ("restored", "photographs")},
                         "glare_correction": applied}}]


def _slope_part(slope: dict | None, key: str) -> dict | None:
    """A measured part of ``track_colour_slope`` (with its ``reduction``), else None."""
    part = slope.get(key) if isinstance(slope, dict) else None
    return part if isinstance(part, dict) and "reduction" in part else None


def track_slope_cells(summary: EvaluationSummary | None) -> dict[str, float | None]:
    """``track_slope_reduction``: the share of the input's colour slope along COLMAP tracks
    the restored render removed over all views (``reduction_overall``; 1 removes all of it,
    below 0 made it steeper), and ``photo_track_slope_reduction``, the same for the restored
    photographs where the evaluation measured them; {} where it fitted none.

    Example::

        track_slope_cells(summary)
        # {"track_slope_reduction": 0.66, "photo_track_slope_reduction": 0.87}
    """
    part = _slope_part(summary.track_colour_slope if summary is not None else None, "all_views")
    if part is None:
        return {}
    cells = {"track_slope_reduction": _finite(part.get("reduction_overall"))}
    photographs = part.get("photographs")
    if isinstance(photographs, dict) and "reduction_overall" in photographs:
        cells["photo_track_slope_reduction"] = _finite(photographs.get("reduction_overall"))
    return cells


def _slope_fit(record) -> list[tuple[float | None, float | None]]:
    """(slope, stderr) per channel of one slope record (``seathru.eval.track_slope``)."""
    record = record if isinstance(record, dict) else {}
    slopes, errors = list(record.get("slope") or []), list(record.get("stderr") or [])
    return [(_finite(s), _finite(errors[i]) if i < len(errors) else None)
            for i, s in enumerate(slopes)]


def track_slope_rows(records: Sequence[DatasetRecord]) -> list[dict]:
    """One entry per dataset whose evaluation has a ``track_colour_slope`` (the page's
    "Colour along COLMAP tracks"): ``dataset``, ``range_units``, ``reason`` (why nothing was
    fitted, else None) and ``parts``, per :data:`TRACK_SLOPE_PARTS` (by label): ``label``,
    ``reason`` (why that part is missing, else None), ``tracks``, ``observations`` (of the
    input's fit), ``channels`` (``channel``, ``input``, ``restored`` and ``rendered`` (the full
    render; (None, None) in evaluations from before it) as (slope, stderr), ``reduction``),
    ``overall``, ``meets_goal`` (``overall >= TRACK_SLOPE_GOAL``) and ``followed``
    (:func:`followed_share`; None where not measured)."""
    rows = []
    for record in records:
        slope = record.summary.track_colour_slope if record.summary is not None else None
        if not isinstance(slope, dict):
            continue
        parts = []
        for key, label in TRACK_SLOPE_PARTS if slope.get("source") != "none" else ():
            if key in OPTIONAL_TRACK_SLOPE_PARTS and key not in slope:
                continue
            part, raw = _slope_part(slope, key), slope.get(key)
            if part is None:
                reason = raw.get("reason") if isinstance(raw, dict) else None
                parts.append({"label": label, "reason": str(reason or "not measured")})
                continue
            inputs, restored = _slope_fit(part.get("input")), _slope_fit(part.get("restored"))
            rendered = _slope_fit(part.get("rendered"))
            photographs = part.get("photographs") or {}
            photo = _slope_fit(photographs.get("restored"))
            photo_reduction = list(photographs.get("reduction") or [])
            reduction = list(part.get("reduction") or [])
            overall = _finite(part.get("reduction_overall"))
            parts.append({
                "label": label, "reason": None,
                "tracks": (part.get("input") or {}).get("tracks"),
                "observations": (part.get("input") or {}).get("observations"),
                "channels": [{"channel": name, "input": inputs[i],
                              "restored": restored[i] if i < len(restored) else (None, None),
                              "rendered": rendered[i] if i < len(rendered) else (None, None),
                              "photo": photo[i] if i < len(photo) else (None, None),
                              "reduction": _finite(reduction[i]) if i < len(reduction)
                              else None,
                              "photo_reduction": _finite(photo_reduction[i])
                              if i < len(photo_reduction) else None}
                             for i, name in enumerate("RGB"[:len(inputs)])],
                "overall": overall,
                "photo_overall": _finite(photographs.get("reduction_overall")),
                "meets_goal": overall is not None and overall >= TRACK_SLOPE_GOAL,
                "followed": followed_share(inputs, rendered)})
        rows.append({"dataset": record.dataset, "range_units": slope.get("range_units"),
                     "reason": (str(slope.get("reason") or "not measured")
                                if slope.get("source") == "none" else None),
                     "parts": parts})
    return rows


def followed_share(inputs: Sequence[tuple], rendered: Sequence[tuple]) -> float | None:
    """How much of the input's slope the full render follows, over the channels whose input
    slope is at least twice its standard error: ``sum_c rendered_c sign(input_c) /
    sum_c |input_c|`` (1: all of it, 0: none). None without the full render's slopes or
    without a channel whose input slope stands out of its error.

    Args:
        inputs, rendered: per channel ``(slope, stderr)`` (``_slope_fit``).

    Example::

        followed_share([(0.2, 0.01), (0.0, 0.01)], [(0.05, 0.01), (0.3, 0.01)])   # 0.25
    """
    moved, total = 0.0, 0.0
    for (slope, error), (followed, _) in zip(inputs, rendered):
        if slope is None or followed is None or error is None or abs(slope) < 2 * error:
            continue
        moved += followed * np.sign(slope)
        total += abs(slope)
    return moved / total if total > 0 else None


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
    number = _finite(value)
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
