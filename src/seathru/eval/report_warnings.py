"""The warnings the report derives itself, beside those the steps wrote (``warnings.json``,
``seathru.io.warnings``): from the train step's outputs (:func:`training_warnings`: the water
model turned off by ``medium.mode=auto``, training that ended with its PSNR still rising fast,
a held-out PSNR that stopped rising early while the training PSNR went on) and from the
evaluation (:func:`evaluation_warnings`: brighter surfaces next to the open water, colour casts
that change between frames, held-out views that look where no training photograph did). Each
is ``{step, code, message, details}``, the message saying what the user can do. Pure, no file
I/O.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

from seathru.eval.report_records import finite_number
from seathru.eval.report_tracks import slope_part
from seathru.eval.summary import EvaluationSummary
from seathru.eval.track_slope import FRAME_COLOUR_RANGE_LIKE
from seathru.radiometry.glare import brighter_near_open_water


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


def _warning(code: str, message: str, step: str = "train", **details) -> dict:
    return {"step": step, "code": code, "message": message, "details": details}


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
    return [_warning("held_out_view_unseen", message, step="evaluate",
                     unseen_surface_share=shares, all_views=known,
                     threshold=UNSEEN_SHARE_WARN)]


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
    least = [finite_number(v) for v in cast.get("least_unexplained") or []]
    along = any(v is not None and v < FRAME_COLOUR_RANGE_LIKE for v in least)
    path = (" The camera moved towards what it had seen (a transect): the part of the cast "
            "that drifts along the path changes every point's colour as its range does, so "
            "it cannot be told from the water, and the attenuation rests on how it was "
            "split." if along else "")
    message = (f"the photographs' colour cast changes from frame to frame beyond what the "
               f"points and their ranges explain: red and blue against green vary by {spread} "
               f"between frames (root mean square{example}), as a camera's automatic "
               f"white balance makes them. {trained}.{path} Shoot RAW, or set the white "
               f"balance by hand for the dive.")
    return [_warning("colour_varies_between_frames", message, step="evaluate",
                     spread=cast.get("spread"), noise=cast.get("noise"),
                     threshold=cast.get("threshold"), corrected=corrected,
                     drift_along_the_path=along)]


def _brighter_warning(summary: EvaluationSummary | None) -> list[dict]:
    part = slope_part(summary.track_colour_slope if summary is not None else None,
                       "all_views")
    beside = part.get("near_open_water") if part is not None else None
    if not isinstance(beside, dict):
        return []
    coefficients = [finite_number(v) for v in beside.get("coefficient") or []]
    errors = [finite_number(v) for v in beside.get("coefficient_stderr") or []]
    if not brighter_near_open_water(coefficients, errors):
        return []
    darker = ", ".join(f"{100 * (1 - 2 ** c):.0f}%" if c is not None else "?"
                       for c in coefficients)
    beside_slope = ", ".join(f"{v:.3f}" for v in beside.get("slope") or [])
    alone = ", ".join(f"{v:.3f}" for v in (part.get("input") or {}).get("slope") or [])
    removed = [f"{label} {100 * share:.0f}%" for label, key in
               (("the restored render", "restored"), ("the restored photographs", "photographs"))
               if (share := finite_number((beside.get(key) or {}).get("reduction_overall")))
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
    removed_beside = {key: (beside.get(key) or {}).get("reduction_overall")
                      for key in ("restored", "photographs")}
    return [_warning("brighter_near_open_water", message, step="evaluate",
                     coefficient=coefficients, coefficient_stderr=errors,
                     slope_beside=beside.get("slope"), removed_beside=removed_beside,
                     glare_correction=applied)]
