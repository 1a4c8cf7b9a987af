"""The evaluate step's file contracts (seathru.io.evaluation): summary.json, metrics.csv and the
inputs it reads (LPIPS weights, train log)."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from seathru.errors import PipelineError
from seathru.eval.summary import (SUPPORT_COLUMNS, TRUTH_COLUMNS, VIEW_COLUMNS,
                                  EvaluationSummary, MetricScale, RenderSpeed, TrainingSummary,
                                  TruthSummary, WaterComparison)
from seathru.io.cameras import CameraSet, Frame
from seathru.io.evaluation import (EVALUATION_FORMAT, camera_centres, read_lpips_weights,
                                   read_metrics, read_summary, read_train_log, view_support,
                                   write_metrics, write_summary)
from seathru.io.images import write_float_tiff
from seathru.io.water import WaterReport

WATER = WaterReport.from_parameters({"mode": "global", "sigma_attn": [0.8, 0.4, 0.3],
                                     "sigma_bs": [0.5, 0.25, 0.2], "c_med": [0.05, 0.2, 0.3]},
                                    0.5).to_dict()


def make_summary(**changes) -> EvaluationSummary:
    truth = TruthSummary(
        colour_gain=[2.0, 1.25, 0.8], colour_gain_note="gain",
        metric_scale=MetricScale(scale=2.2, rms_residual=1e-9, relative_residual=1e-10,
                                 method="similarity alignment of 4 camera centres"),
        water=WaterComparison(truth={"sigma_attn": [0.5, 0.2, 0.1]},
                              fitted={"sigma_attn": [0.4, 0.2, 0.1]},
                              relative_error={"sigma_attn": [0.2, 0.0, None]}))
    values = dict(dataset="dive", views=2,
                  means={"psnr_linear": 30.5, "ssim_linear": 0.9, "lpips": "unavailable"},
                  lpips="unavailable: no --lpips-weights given",
                  render=RenderSpeed(fps=12.5, seconds_per_frame=0.08, resolution=[48, 36],
                                     device="cpu"),
                  training=TrainingSummary(time_s=41.5, steps=100, final_loss=0.005,
                                           final_test_psnr=24.0),
                  water_fitted=WATER, medium_selection={"chosen": "global", "reason": "x"},
                  truth=truth)
    values.update(changes)
    return EvaluationSummary(**values)


@pytest.mark.parametrize("summary", [make_summary(),
                                     make_summary(truth=None, training=None, water_fitted=None,
                                                  medium_selection=None, render=RenderSpeed())])
def test_summary_round_trip(tmp_path, summary):
    write_summary(tmp_path / "summary.json", summary)
    assert read_summary(tmp_path / "summary.json") == summary
    data = json.loads((tmp_path / "summary.json").read_text())
    assert data["format"] == EVALUATION_FORMAT and list(data)[0] == "format"


def test_summary_writes_nan_as_null(tmp_path):
    summary = make_summary(means={"psnr_linear": float("nan"), "depth_corr": float("inf")})
    summary.truth.metric_scale.rms_residual = float("nan")
    write_summary(tmp_path / "summary.json", summary)
    text = (tmp_path / "summary.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    read = read_summary(tmp_path / "summary.json")
    assert read.means == {"psnr_linear": None, "depth_corr": None}
    assert read.truth.metric_scale.rms_residual is None


@pytest.mark.parametrize("change, message", [
    (lambda d: d.pop("views"), r"summary\.views is missing"),
    (lambda d: d.update(views="two"), r"summary\.views has the wrong type"),
    (lambda d: d["truth"].pop("metric_scale"), r"summary\.truth\.metric_scale is missing"),
    (lambda d: d["training"].update(time_s=None), r"summary\.training\.time_s must not be null"),
    (lambda d: d["water_fitted"].update(mode="murky"), "not a valid water file"),
    (lambda d: d.update(format="seathru-evaluation/0"), "expected format"),
])
def test_malformed_summary_names_the_file_and_the_field(tmp_path, change, message):
    path = tmp_path / "evaluate" / "summary.json"
    write_summary(path, make_summary())
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))
    with pytest.raises(PipelineError, match=message) as error:
        read_summary(path)
    assert str(path) in str(error.value)


def test_metrics_round_trip_keeps_the_contract_columns(tmp_path):
    rows = [{"dataset": "d", "view": f"{i:03d}", "psnr_linear": 30.0 + i, "ssim_linear": 0.9,
             "psnr_srgb": 28.0, "ssim_srgb": 0.8, "lpips": "unavailable",
             **{c: 0.5 for c in reversed(TRUTH_COLUMNS)}} for i in range(2)]
    write_metrics(tmp_path / "metrics.csv", rows)
    table = read_metrics(tmp_path / "metrics.csv")
    assert list(table.columns) == [*VIEW_COLUMNS, *TRUTH_COLUMNS]
    assert list(table["view"]) == ["000", "001"]     # names stay text
    assert list(table["psnr_linear"]) == [30.0, 31.0]


def test_a_views_unseen_surface_comes_from_its_support_and_opacity(tmp_path):
    """The share of the rendered surface (opacity >= 0.5) no training photograph backs at all
    (support 0), from the render step's files; open water does not count."""
    folder = tmp_path / "test" / "v"
    folder.mkdir(parents=True)
    opacity = np.ones((4, 5), np.float32)
    opacity[0] = 0.1                                      # a row of open water
    support = np.full((4, 5), 2.0, np.float32)
    support[0] = 0.0                                      # unseen, but water: not counted
    support[1, :3] = 0.0                                  # 3 of the 15 surface pixels unseen
    support[2, 0] = np.nan                                # no source: unseen
    write_float_tiff(folder / "opacity.tiff", opacity)
    assert view_support(tmp_path, "v") == {}              # no restored_support written
    write_float_tiff(folder / "restored_support.tiff", support)
    assert view_support(tmp_path, "v") == {"unseen_surface_share": pytest.approx(4 / 15)}
    write_float_tiff(folder / "opacity.tiff", np.zeros((4, 5), np.float32))
    assert view_support(tmp_path, "v") == {}              # nothing but water
    rows = [{"dataset": "d", "view": "v", "psnr_linear": 30.0, "ssim_linear": 0.9,
             "psnr_srgb": 28.0, "ssim_srgb": 0.8, "lpips": "unavailable",
             "unseen_surface_share": 0.25}]
    write_metrics(tmp_path / "metrics.csv", rows)
    assert list(read_metrics(tmp_path / "metrics.csv").columns) == [*VIEW_COLUMNS,
                                                                      *SUPPORT_COLUMNS]


def test_metrics_without_a_contract_column_is_refused(tmp_path):
    pd.DataFrame({"dataset": ["d"], "view": ["a"], "psnr_linear": [1.0]}).to_csv(
        tmp_path / "metrics.csv", index=False)
    with pytest.raises(PipelineError, match=r"metrics\.csv: missing columns \['ssim_linear'"):
        read_metrics(tmp_path / "metrics.csv")
    with pytest.raises(PipelineError, match="run the 'evaluate' step"):
        read_metrics(tmp_path / "none.csv")


def test_train_log_reader(tmp_path):
    assert read_train_log(tmp_path / "train_log.csv") is None
    (tmp_path / "train_log.csv").write_text("step,wall_time_s\n0,0.5\n10,2.0\n")
    assert read_train_log(tmp_path / "train_log.csv")["wall_time_s"].max() == 2.0


def test_lpips_weights_reader(tmp_path):
    import torch

    assert read_lpips_weights(tmp_path / "absent") is None
    folder = tmp_path / "lpips"
    folder.mkdir()
    torch.save({"features.0.weight": torch.ones(2)}, folder / "trunk.pth")
    torch.save({"lin0.model.1.weight": torch.zeros(3)}, folder / "lin.pt")
    (folder / "notes.txt").write_text("ignored")
    state = read_lpips_weights(folder)
    assert sorted(state) == ["features.0.weight", "lin0.model.1.weight"]
    (folder / "broken.pth").write_bytes(b"not a torch file")
    with pytest.raises(PipelineError, match=r"broken\.pth: cannot be read as a torch state dict"):
        read_lpips_weights(folder)


def test_camera_centres_in_file_and_source_units():
    c2w = [[1.0, 0, 0, 0.2], [0, 1.0, 0, -0.4], [0, 0, 1.0, 0.6], [0, 0, 0, 1.0]]
    frame = Frame(name="a", image="a.tiff", width=4, height=3, fx=2.0, fy=2.0, cx=2.0, cy=1.5,
                  c2w=c2w, near=0.1, far=5.0)
    cameras = CameraSet(frames=[frame], near=0.1, far=5.0, centre=[10.0, 0.0, -1.0], scale=0.2)
    assert camera_centres(cameras)["a"].tolist() == [0.2, -0.4, 0.6]
    assert camera_centres(cameras, source_units=True)["a"] == pytest.approx([11.0, -2.0, 2.0])
