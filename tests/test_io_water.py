"""The water file contracts (seathru.io.water): the train step's water.json and the simulator's
truth/water.json."""

from __future__ import annotations

import json

import pytest

from seathru.errors import PipelineError
from seathru.io.water import (WATER_FORMAT, WaterReport, WaterValues, read_truth_water,
                              read_water, write_water)

GLOBAL_PARAMS = {"mode": "global", "sigma_attn": [0.8, 0.4, 0.3], "sigma_bs": [0.5, 0.25, 0.2],
                 "c_med": [0.05, 0.2, 0.3]}
VIEW_PARAMS = {**GLOBAL_PARAMS, "mode": "view",
               "min": {"sigma_attn": [0.7, 0.3, 0.2], "sigma_bs": [0.4, 0.2, 0.1],
                       "c_med": [0.04, 0.1, 0.2]},
               "max": {"sigma_attn": [0.9, 0.5, 0.4], "sigma_bs": [0.6, 0.3, 0.3],
                       "c_med": [0.06, 0.3, 0.4]}}


def test_global_water_has_the_train_step_layout():
    scale = 0.25
    data = WaterReport.from_parameters(GLOBAL_PARAMS, scale).to_dict()
    per_source = {k: [v * scale for v in GLOBAL_PARAMS[k]] for k in ("sigma_attn", "sigma_bs")}
    assert data["format"] == WATER_FORMAT and data["mode"] == "global"
    assert data["scale"] == scale and "source unit" in data["units"]
    assert data["normalised"] == {k: GLOBAL_PARAMS[k] for k in ("sigma_attn", "sigma_bs",
                                                                  "c_med")}
    assert data["per_source_unit"] == per_source
    assert data["sigma_attn"] == per_source["sigma_attn"]
    assert data["sigma_bs"] == per_source["sigma_bs"]
    assert data["c_med"] == GLOBAL_PARAMS["c_med"]
    assert not {"note", "min", "max", "normalised_min", "normalised_max"} & set(data)


def test_view_dependent_water_keeps_its_range():
    scale = 2.0
    data = WaterReport.from_parameters(VIEW_PARAMS, scale).to_dict()
    assert "mean over training rays" in data["note"]
    for bound in ("min", "max"):
        assert data[f"normalised_{bound}"] == VIEW_PARAMS[bound]
        assert data[bound]["sigma_attn"] == [v * scale for v in VIEW_PARAMS[bound]["sigma_attn"]]
        assert data[bound]["c_med"] == VIEW_PARAMS[bound]["c_med"]


@pytest.mark.parametrize("params", [GLOBAL_PARAMS, VIEW_PARAMS])
def test_water_round_trip(tmp_path, params):
    report = WaterReport.from_parameters(params, 0.5)
    write_water(tmp_path / "water.json", report)
    assert read_water(tmp_path / "water.json") == report
    assert json.loads((tmp_path / "water.json").read_text()) == report.to_dict()


def test_water_written_before_the_format_key_is_read(tmp_path):
    legacy = WaterReport.from_parameters(GLOBAL_PARAMS, 0.5).to_dict()
    del legacy["format"]
    (tmp_path / "water.json").write_text(json.dumps(legacy))
    report = read_water(tmp_path / "water.json")
    assert report.normalised == WaterValues.from_mapping(GLOBAL_PARAMS, "params")
    assert list(report.per_source_unit.sigma_bs) == legacy["per_source_unit"]["sigma_bs"]


def test_missing_water_is_none_only_when_allowed(tmp_path):
    assert read_water(tmp_path / "water.json", missing_ok=True) is None
    with pytest.raises(PipelineError, match="water.json: file not found; run the 'train'"):
        read_water(tmp_path / "water.json")


@pytest.mark.parametrize("change, message", [
    (lambda d: d.update(mode="murky"), "mode must be one of"),
    (lambda d: d.update(scale=0), "scale must be a positive number"),
    (lambda d: d.pop("normalised"), "normalised is not an object"),
    (lambda d: d["normalised"].update(sigma_bs=[1.0, 2.0]), "normalised.sigma_bs must be a list"),
    (lambda d: d["normalised"].update(c_med=["a", 1, 2]), "normalised.c_med must be a list"),
    (lambda d: d.update(format="seathru-water/9"), "expected format"),
])
def test_malformed_water_names_the_file_and_the_field(tmp_path, change, message):
    data = WaterReport.from_parameters(GLOBAL_PARAMS, 0.5).to_dict()
    change(data)
    path = tmp_path / "run" / "water.json"
    path.parent.mkdir()
    path.write_text(json.dumps(data))
    with pytest.raises(PipelineError, match=message) as error:
        read_water(path)
    assert str(path) in str(error.value)


def test_water_file_that_is_not_json(tmp_path):
    (tmp_path / "water.json").write_text("{not json")
    with pytest.raises(PipelineError, match="water.json: not valid JSON"):
        read_water(tmp_path / "water.json")


def test_truth_water_as_the_simulator_writes_it(tmp_path):
    path = tmp_path / "water.json"
    path.write_text(json.dumps({"sigma_attn": [0.55, 0.25, 0.2], "sigma_bs": [0.45, 0.3, 0.25],
                                "c_med": [0.04, 0.2, 0.28], "units": "1/m", "preset": "default"}))
    truth = read_truth_water(path)
    assert truth.sigma_attn == (0.55, 0.25, 0.2) and truth.c_med == (0.04, 0.2, 0.28)
    path.write_text(json.dumps({"sigma_attn": [0.55, 0.25, 0.2]}))
    with pytest.raises(PipelineError, match=r"water.json: not a valid truth water file .*sigma_bs"):
        read_truth_water(path)
    with pytest.raises(PipelineError, match="simulate"):
        read_truth_water(tmp_path / "none.json")


def test_water_that_could_not_be_checked_is_flagged_with_open_intervals(tmp_path):
    reason = "only 0 rays reach opaque surfaces"
    report = WaterReport.from_parameters(GLOBAL_PARAMS, 0.5, {"skipped": reason})
    assert len(report.undetermined) == 9
    assert reason in report.undetermined_message()
    data = report.to_dict()
    assert data["uncertainty"]["not_assessed"] == reason
    assert all(pair == [0.0, None] for pair in data["uncertainty"]["interval95"]["sigma_attn"])
    write_water(tmp_path / "water.json", report)
    assert read_water(tmp_path / "water.json") == report
    # no water, nothing to flag
    assert WaterReport.from_parameters({**GLOBAL_PARAMS, "mode": "off"}, 0.5,
                                       {"skipped": reason}).uncertainty is None


def test_open_water_below_the_horizon_is_written_with_its_least_surface_range(tmp_path):
    half = {k: [0.01, 0.5, 0.01] for k in ("sigma_attn", "sigma_bs", "c_med")}
    assessment = {"halfwidth95": half,
                  "determined": {k: [True, False, True] for k in half},
                  "surface_fit": {k: list(GLOBAL_PARAMS[k]) for k in half},
                  "pixels": 1000, "groups": 50, "open_water_beyond": 2.0}
    report = WaterReport.from_parameters(GLOBAL_PARAMS, 0.5, assessment)
    below = report.to_dict()["uncertainty"]["open_water_below_horizon"]
    assert below["least_surface_range"] == pytest.approx(4.0)     # 2 normalised / 0.5
    assert "below the horizon" in below["note"]
    assert "below the horizon" in report.undetermined_message()
    write_water(tmp_path / "water.json", report)
    assert read_water(tmp_path / "water.json") == report
    plain = WaterReport.from_parameters(GLOBAL_PARAMS, 0.5, {**assessment,
                                                             "open_water_beyond": None})
    assert "open_water_below_horizon" not in plain.to_dict()["uncertainty"]
    assert "horizon" not in plain.undetermined_message()


def test_water_per_metre_where_the_camera_file_knows_the_scale(tmp_path):
    half = {k: [0.01, 0.5, 0.02] for k in ("sigma_attn", "sigma_bs", "c_med")}
    assessment = {"halfwidth95": half, "determined": {k: [True, False, True] for k in half},
                  "surface_fit": {k: list(GLOBAL_PARAMS[k]) for k in half},
                  "pixels": 1000, "groups": 50}
    scale, metres = 0.5, 0.25          # a source unit (COLMAP's) is 25 cm
    report = WaterReport.from_parameters(GLOBAL_PARAMS, scale, assessment, metres)
    data = report.to_dict()
    assert data["metres_per_source_unit"] == metres
    for key in ("sigma_attn", "sigma_bs"):
        assert data["per_metre"][key] == pytest.approx(
            [v * scale / metres for v in GLOBAL_PARAMS[key]])
        for per_metre, per_unit in zip(data["per_metre"]["interval95"][key],
                                       data["uncertainty"]["interval95"][key]):
            assert per_metre == pytest.approx([None if v is None else v / metres
                                               for v in per_unit])
    write_water(tmp_path / "water.json", report)
    assert read_water(tmp_path / "water.json") == report
    # unknown scale: no per-metre numbers at all, rather than per-unit ones called metres
    assert "per_metre" not in WaterReport.from_parameters(GLOBAL_PARAMS, scale).to_dict()
    data["metres_per_source_unit"] = -1.0
    (tmp_path / "bad.json").write_text(json.dumps(data))
    with pytest.raises(PipelineError, match="metres_per_source_unit must be a positive"):
        read_water(tmp_path / "bad.json")


def test_values_moved_by_what_the_images_cannot_tell_are_named_with_that_reason(tmp_path):
    """An orbit: sigma_bs[G] and c_med are wider than 25%; sigma_attn[R] is within +-15% but
    the veiling light beyond the surfaces moves it by 9% (``ambiguity95``)."""
    half = {"sigma_attn": [0.12, 0.02, 0.02], "sigma_bs": [0.02, 0.2, 0.02],
            "c_med": [0.03, 0.1, 0.1]}
    ambiguity = {"sigma_attn": [0.072, 0.0, 0.0], "sigma_bs": [0.0, 0.15, 0.0],
                 "c_med": [0.03, 0.1, 0.1]}
    assessment = {"halfwidth95": half, "ambiguity95": ambiguity,
                  "determined": {"sigma_attn": [False, True, True],
                                 "sigma_bs": [True, False, True], "c_med": [False] * 3},
                  "surface_fit": {k: list(GLOBAL_PARAMS[k]) for k in half},
                  "pixels": 1000, "groups": 50}
    report = WaterReport.from_parameters(GLOBAL_PARAMS, 0.5, assessment)
    message = report.undetermined_message()
    assert "sigma_bs[G], c_med[R], c_med[G], c_med[B] (95% interval wider than +-25%)" in message
    assert "sigma_attn[R] (up to 9%), moved by what the images cannot tell (the veiling " \
        "light beyond the farthest surfaces" in message
    assert report.to_dict()["uncertainty"]["normalised"]["ambiguity95"] == ambiguity
    write_water(tmp_path / "water.json", report)
    assert read_water(tmp_path / "water.json") == report
    # files written before session 47 have no ambiguity95: every flag reads as a wide interval
    data = report.to_dict()
    del data["uncertainty"]["normalised"]["ambiguity95"]
    old = WaterReport.from_dict(data)
    assert "ambiguity95" not in old.uncertainty
    assert "sigma_attn[R], sigma_bs[G]" in old.undetermined_message()
    assert "cannot tell" not in old.undetermined_message()


def test_seabed_that_may_lie_behind_the_open_water_is_named_once():
    half = {k: [0.01, 0.5, 0.01] for k in ("sigma_attn", "sigma_bs", "c_med")}
    ambiguity = {k: [0.0, 0.3, 0.005] for k in half}
    ambiguity["sigma_attn"] = [0.1, 0.3, 0.0]       # 12.5% of 0.8
    assessment = {"halfwidth95": half, "ambiguity95": ambiguity,
                  "determined": {k: [k != "sigma_attn", False, True] for k in half},
                  "surface_fit": {k: list(GLOBAL_PARAMS[k]) for k in half},
                  "pixels": 1000, "groups": 50, "open_water_beyond": 2.0}
    message = WaterReport.from_parameters(GLOBAL_PARAMS, 0.5, assessment).undetermined_message()
    assert "sigma_attn[R] (up to 12%), moved by what the images cannot tell (the " \
        "photographs' open water looks below the horizon: it may be far seabed" in message
    assert message.count("below the horizon") == 1
