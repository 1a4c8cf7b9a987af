"""The warnings the report derives itself (seathru.eval.report_warnings): from the train
step's log and selection, and from the evaluation."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from seathru.eval.report_warnings import (evaluation_warnings, held_out_plateau, psnr_rise,
                                          training_warnings)
from tests.test_eval_report import evaluation_summary, track_slope_record


def _log(times, test=None, train=None) -> pd.DataFrame:
    data = {"wall_time_s": times}
    if test is not None:
        data["test_psnr"] = test
    if train is not None:
        data["train_psnr"] = train
    return pd.DataFrame(data)


def test_psnr_rise_over_the_last_share_of_time():
    rise = psnr_rise(_log([0.0, 50.0, 80.0, 100.0], test=[10.0, 20.0, 24.0, 25.0]))
    assert rise["column"] == "test_psnr" and rise["from_s"] == 80.0
    assert rise["rise_db"] == pytest.approx(1.0) and rise["final_psnr"] == 25.0
    # interpolated at 80 s between 50 s (20 dB) and 100 s (26 dB); NaN rows skipped
    rise = psnr_rise(_log([0.0, 50.0, 75.0, 100.0], test=[10.0, 20.0, np.nan, 26.0]))
    assert rise["rise_db"] == pytest.approx(26.0 - 23.6)
    # held-out values only at the end: the training PSNR is used
    rise = psnr_rise(_log([0.0, 90.0, 100.0], test=[np.nan, 20.0, 21.0],
                          train=[5.0, 19.0, 22.0]), window=0.5)
    assert rise["column"] == "train_psnr"
    assert rise["rise_db"] == pytest.approx(22.0 - (5.0 + 14.0 * 50.0 / 90.0))
    assert psnr_rise(None) is None and psnr_rise(_log([0.0], test=[1.0])) is None


def test_training_warnings_for_water_off_and_rising_psnr():
    rising = _log([0.0, 80.0, 100.0], test=[10.0, 20.0, 23.0])
    found = training_warnings({"requested": "auto", "chosen": "off", "final_mode": "off",
                               "reason": "fitted water is negligible"}, rising, "time",
                              rising_db=1.0)
    assert [w["code"] for w in found] == ["water_model_off", "not_converged"]
    assert all(w["step"] == "train" for w in found)
    assert "fitted water is negligible" in found[0]["message"]
    assert "train.medium.mode=global" in found[0]["message"]
    assert "3.00 dB" in found[1]["message"] and "time budget" in found[1]["message"]
    assert "train.max_minutes" in found[1]["message"]
    assert found[1]["details"]["stopped_by"] == "time"
    steps = training_warnings(None, rising, "steps")
    assert "raise train.steps" in steps[0]["message"]
    # asked for no water, or converged: nothing to look at
    assert training_warnings({"requested": "off", "chosen": "off"},
                             _log([0.0, 80.0, 100.0], test=[10.0, 22.9, 23.0])) == []
    assert training_warnings({"requested": "auto", "final_mode": "global"}, rising,
                             rising_db=5.0) == []


def test_a_held_out_psnr_that_stops_early_while_training_goes_on_is_flagged():
    # d3_reef's 15-min run, thinned: held-out flat at 16.4-16.8 dB from 7 s on
    reef = _log([0.06, 3.9, 7.1, 34.3, 129.1, 481.9, 900.0],
                test=[14.4, 16.46, 16.74, 16.63, 16.61, 16.78, 16.68],
                train=[14.1, 17.58, 17.94, 18.53, 19.46, 21.16, 21.57])
    plateau = held_out_plateau(reef)
    assert plateau["reached_s"] == pytest.approx(7.1)
    assert plateau["train_rise_db"] == pytest.approx(21.57 - 17.94)
    found = training_warnings({"requested": "auto", "final_mode": "veiling"}, reef, "time")
    assert [w["code"] for w in found] == ["held_out_plateau"]
    assert "16.78 dB" in found[0]["message"] and "7.1 s of 900 s" in found[0]["message"]
    # a held-out PSNR that rises with the training one (the demo): no warning
    demo = _log([0.1, 10.0, 60.0, 120.0, 180.0], test=[14.0, 22.0, 26.0, 27.6, 28.4],
                train=[14.0, 22.5, 27.0, 28.5, 29.5])
    assert held_out_plateau(demo) is None
    # an early plateau while the training PSNR also stalls: converged, not overfitting
    stalled = _log([0.1, 5.0, 60.0, 180.0], test=[14.0, 20.0, 20.1, 20.0],
                   train=[14.0, 21.0, 21.5, 21.9])
    assert held_out_plateau(stalled) is None
    assert held_out_plateau(None) is None
    assert held_out_plateau(_log([0.0, 1.0], test=[1, 2])) is None


def test_brighter_near_open_water_warns_with_the_slope_beside_it():
    """d3_reef's reading (coefficients -0.33, -0.32, -0.28 at 23-32 standard errors) warns, with
    the darkening per doubling of distance (2 ** c) and the slopes with and without the term;
    the demo's (within 0.005 of 0), a loose fit or a single channel does not."""
    summary = evaluation_summary("reef", 17.0)
    summary.track_colour_slope = track_slope_record(0.5)
    part = summary.track_colour_slope["all_views"]
    part["near_open_water"] = {"slope": [-0.109, 0.006, 0.083], "stderr": [0.009] * 3,
                               "coefficient": [-0.328, -0.317, -0.276],
                               "coefficient_stderr": [0.012, 0.010, 0.009], "observations": 19156}
    [warning] = evaluation_warnings(summary)
    assert warning["step"] == "evaluate" and warning["code"] == "brighter_near_open_water"
    darker = [f"{100 * (1 - 2 ** c):.0f}%" for c in (-0.328, -0.317, -0.276)]
    assert darker == ["20%", "20%", "17%"] and ", ".join(darker) in warning["message"]
    assert "-0.109, 0.006, 0.083" in warning["message"] and "removed" not in warning["message"]
    part["near_open_water"]["restored"] = {"reduction_overall": 0.948}
    part["near_open_water"]["photographs"] = {"reduction_overall": 0.881}
    [warning] = evaluation_warnings(summary)
    assert ("of that change the restored render 95% and the restored photographs 88% removed"
            in warning["message"])
    assert warning["details"]["removed_beside"] == {"restored": 0.948, "photographs": 0.881}
    assert "restored images keep it" in warning["message"]
    summary.medium_selection = {"glare_correction": {"coefficient": -0.296, "near": 0.07,
                                                     "reference": 0.22, "far": 0.48}}
    [warning] = evaluation_warnings(summary)
    assert "divided by a brightening of -0.30 log colour" in warning["message"]
    assert "keep it" not in warning["message"]
    assert warning["details"]["glare_correction"]["coefficient"] == -0.296
    for coefficient, stderr in (([-0.005, 0.001, -0.001], [0.003] * 3),      # the demo
                                ([-0.3, -0.3, -0.3], [0.2] * 3),              # not measured
                                ([-0.3, 0.0, 0.0], [0.01] * 3)):              # one channel
        part["near_open_water"].update(coefficient=coefficient, coefficient_stderr=stderr)
        assert evaluation_warnings(summary) == []
    del part["near_open_water"]
    assert evaluation_warnings(summary) == [] and evaluation_warnings(None) == []


def test_a_colour_cast_that_changes_between_frames_warns_with_its_spread():
    summary = evaluation_summary("phone", 25.0)
    summary.track_colour_slope = track_slope_record(0.5)
    summary.track_colour_slope["frame_colour"] = {
        "spread": [0.150, 0.046], "noise": [0.001, 0.001], "varies": True, "threshold": 0.08,
        "offsets": {"dive_0001": [0.02, -0.01], "dive_0009": [-0.31, 0.08]}}
    [warning] = evaluation_warnings(summary)
    assert warning["code"] == "colour_varies_between_frames"
    assert "vary by 15%, 5% between frames" in warning["message"]
    assert "(root mean square; farthest from the median frame: dive_0009, -31%, +8%)" in \
        warning["message"] and "Shoot RAW" in warning["message"]
    assert "No water model follows it" in warning["message"]
    summary.medium_selection = {"frame_colour_correction": {"gains": {}, "spread": [0.13, 0.04]}}
    [warning] = evaluation_warnings(summary)
    assert "trained on the photographs brought to the median frame's cast" in warning["message"]
    assert warning["details"]["corrected"] is True
    assert not warning["details"]["drift_along_the_path"] and "transect" not in \
        warning["message"]
    summary.track_colour_slope["frame_colour"]["least_unexplained"] = [0.009, 0.010]
    [warning] = evaluation_warnings(summary)        # a transect: the drift is the water's too
    assert warning["details"]["drift_along_the_path"] and "cannot be told from the water" in \
        warning["message"]
    summary.track_colour_slope["frame_colour"].update(spread=[0.038, 0.038], varies=False)
    assert evaluation_warnings(summary) == []                 # d3_reef's reading


def test_a_held_out_view_no_training_photograph_sees_warns_naming_it():
    metrics = pd.DataFrame({"view": ["dive_0000", "dive_0008", "dive_0016"],
                            "unseen_surface_share": [0.158, 0.025, float("nan")]})
    [warning] = evaluation_warnings(None, metrics)
    assert warning["code"] == "held_out_view_unseen"
    assert "held-out view dive_0000 (16% of its surface) shows surfaces" in warning["message"]
    assert "dive_0008" not in warning["message"]
    assert warning["details"]["unseen_surface_share"] == {"dive_0000": 0.158}
    metrics["unseen_surface_share"] = [0.09, 0.0, 0.02]      # every view seen
    assert evaluation_warnings(None, metrics) == []
    metrics["unseen_surface_share"] = [0.387, 0.107, 0.132]  # d3_reef: its first view only
    [warning] = evaluation_warnings(None, metrics)
    assert list(warning["details"]["unseen_surface_share"]) == ["dive_0000"]
    metrics["unseen_surface_share"] = [0.3, 0.25, 0.35]      # all alike: nothing stands out
    assert evaluation_warnings(None, metrics) == []
    assert evaluation_warnings(None, metrics.drop(columns="unseen_surface_share")) == []
