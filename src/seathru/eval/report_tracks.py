"""The report's "Colour along COLMAP tracks": where the evaluate step fitted the colour's slope
against range along the tracks (``track_colour_slope``, ``seathru.eval.track_slope``), the share
of the input's slope the restoration removed over all views is the summary table's
``track_slope_reduction`` (:func:`track_slope_cells`), and the page gives the slopes per channel
and per part of the tracks against the :data:`TRACK_SLOPE_GOAL` (:func:`track_slope_rows`),
with how much of the input's slope the full render follows (:func:`followed_share`). Pure, no
file I/O.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from seathru.eval.report_records import DatasetRecord, finite_number
from seathru.eval.summary import EvaluationSummary


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


def slope_part(slope: dict | None, key: str) -> dict | None:
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
    part = slope_part(summary.track_colour_slope if summary is not None else None, "all_views")
    if part is None:
        return {}
    cells = {"track_slope_reduction": finite_number(part.get("reduction_overall"))}
    photographs = part.get("photographs")
    if isinstance(photographs, dict) and "reduction_overall" in photographs:
        cells["photo_track_slope_reduction"] = finite_number(photographs.get("reduction_overall"))
    return cells


def _slope_fit(record) -> list[tuple[float | None, float | None]]:
    """(slope, stderr) per channel of one slope record (``seathru.eval.track_slope``)."""
    record = record if isinstance(record, dict) else {}
    slopes, errors = list(record.get("slope") or []), list(record.get("stderr") or [])
    return [(finite_number(s), finite_number(errors[i]) if i < len(errors) else None)
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
            part, raw = slope_part(slope, key), slope.get(key)
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
            overall = finite_number(part.get("reduction_overall"))
            parts.append({
                "label": label, "reason": None,
                "tracks": (part.get("input") or {}).get("tracks"),
                "observations": (part.get("input") or {}).get("observations"),
                "channels": [{"channel": name, "input": inputs[i],
                              "restored": restored[i] if i < len(restored) else (None, None),
                              "rendered": rendered[i] if i < len(rendered) else (None, None),
                              "photo": photo[i] if i < len(photo) else (None, None),
                              "reduction": finite_number(reduction[i]) if i < len(reduction)
                              else None,
                              "photo_reduction": finite_number(photo_reduction[i])
                              if i < len(photo_reduction) else None}
                             for i, name in enumerate("RGB"[:len(inputs)])],
                "overall": overall,
                "photo_overall": finite_number(photographs.get("reduction_overall")),
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
