"""The report's domain code (seathru.eval.report) and the per-dataset summary
(seathru.eval.summary): failure diagnosis, the summary table, the HTML template."""

from __future__ import annotations

import base64
import re

import numpy as np
import pandas as pd
import pytest

from seathru.eval import summary as dataset_summary
from seathru.eval.report import (NOT_RUN, DatasetRecord, StepLog, diagnose_failure,
                                 evaluation_warnings, held_out_plateau, medium_name, psnr_rise,
                                 render_html, stopped_by, summary_table, training_warnings)
from seathru.eval.summary import EvaluationSummary, RenderSpeed, TrainingSummary
from seathru.steps import STEP_ORDER

PNG = b"\x89PNG\r\n\x1a\n" + bytes(range(40))


def test_failure_is_the_last_error_line_of_the_newest_log_with_one():
    logs = [StepLog("poses", 100.0, ["seathru poses: error: stale"]),
            StepLog("ingest", 200.0, ["seathru ingest: error: first", "warning",
                                      "seathru ingest: error: the real one  ", "done"]),
            StepLog("train", 300.0, ["step 10 loss 0.1"])]
    assert diagnose_failure(logs, STEP_ORDER) == ("ingest", "the real one")


def test_failure_without_error_lines_quotes_the_newest_log():
    logs = [StepLog("ingest", 1.0, ["ok"]),
            StepLog("train", 2.0, ["Traceback", "RuntimeError: CUDA out of memory", ""])]
    step, message = diagnose_failure(logs, STEP_ORDER)
    assert step == "train"
    assert message == "no 'error:' line; last line of train.log: RuntimeError: CUDA out of memory"
    assert diagnose_failure([], STEP_ORDER) == (None, NOT_RUN)


def test_failure_ties_go_to_the_later_step():
    logs = [StepLog("train", 5.0, ["seathru train: error: late"]),
            StepLog("poses", 5.0, ["seathru poses: error: early"])]
    assert diagnose_failure(logs, STEP_ORDER) == ("train", "late")


def test_medium_name_reads_the_selection():
    assert medium_name({"chosen": "global", "reason": "x"}) == "global"
    assert medium_name({"final_mode": "view", "mode": "auto"}) == "view"
    assert medium_name(None) is None
    assert medium_name({"other": 1}) == '{"other": 1}'


def _summary(dataset: str, psnr: float, fps: float | None = 20.0) -> EvaluationSummary:
    return EvaluationSummary(dataset=dataset, views=3,
                             means={"psnr_linear": psnr, "lpips": "unavailable"},
                             lpips="unavailable: no --lpips-weights given",
                             render=RenderSpeed(fps=fps, resolution=[48, 36]),
                             training=TrainingSummary(time_s=12.0, steps=50),
                             medium_selection={"chosen": "off"})


def test_summary_table_rows_and_columns():
    records = [DatasetRecord("a", summary=_summary("a", 30.0)),
               DatasetRecord("b", status="failed", failed_step="train", error="boom",
                             train_log=pd.DataFrame({"wall_time_s": [1.0, 7.5]}))]
    table = summary_table(records)
    assert list(table["dataset"]) == ["a", "b"]
    assert "restored_psnr_linear" not in table.columns      # no dataset has it
    rows = table.set_index("dataset")
    assert rows.loc["a", "render_resolution"] == "48x36" and rows.loc["a", "medium"] == "off"
    assert rows.loc["a", "lpips"] == "unavailable"
    assert rows.loc["b", "train_time_s"] == 7.5              # from the log: no summary
    assert np.isnan(rows.loc["b", "psnr_linear"])


def test_html_escapes_names_and_messages_and_inlines_images():
    evil = "<b>dive</b>&1"
    records = [DatasetRecord(evil, summary=_summary(evil, 30.0)),
               DatasetRecord("x<y", status="failed", failed_step="ingest",
                             error="<script>alert('no')</script>")]
    page = render_html(summary_table(records), records, {"psnr_vs_time.png": PNG},
                       {evil: PNG}, "2024-01-01 00:00 UTC")
    assert "<b>dive</b>" not in page and "&lt;b&gt;dive&lt;/b&gt;&amp;1" in page
    assert "<script>" not in page and "&lt;script&gt;" in page
    assert "x&lt;y" in page and "stage <code>ingest</code>" in page
    assert "2 datasets, 1 with results; generated 2024-01-01 00:00 UTC" in page
    images = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page)
    assert [base64.b64decode(data) for data in images] == [PNG, PNG]
    assert "<td>30</td>" in page and "<td>—</td>" in page   # numbers 4 significant, gaps dashed


def test_view_means_and_lpips_status():
    table = pd.DataFrame({"dataset": ["d", "d"], "view": ["a", "b"], "psnr_linear": [30.0, 32.0],
                          "lpips": ["unavailable", "unavailable"]})
    assert dataset_summary.view_means(table) == {"psnr_linear": 31.0, "lpips": "unavailable"}
    table["lpips"] = [0.1, 0.3]
    assert dataset_summary.view_means(table)["lpips"] == pytest.approx(0.2)
    assert dataset_summary.lpips_network(None, None) == (None, "unavailable: no --lpips-weights "
                                                               "given")
    assert dataset_summary.lpips_network(None, "w.pth") == (None, "unavailable: w.pth not found")
    with pytest.raises(ValueError, match="lin0..lin4"):
        dataset_summary.lpips_network({}, "w.pth")


def test_training_summary_from_the_log():
    log = pd.DataFrame({"step": [0, 50, 100], "wall_time_s": [0.5, 20.0, 41.5],
                        "loss": [0.1, 0.01, 0.005], "test_psnr": [9.0, np.nan, np.nan]})
    training = dataset_summary.training_summary(log)
    assert training == TrainingSummary(time_s=41.5, steps=100, final_loss=0.005,
                                       final_test_psnr=9.0)
    assert dataset_summary.training_summary(None) is None
    assert dataset_summary.training_summary(pd.DataFrame({"step": [1]})) is None


# -- warnings: "needs a look" ------------------------------------------------------------------

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


def test_stopped_by_reads_the_train_log():
    lines = ["step 5: medium 'global'", "trained 300 steps in 7 s (stopped by time; 37.2 "
             "steps/s, 19066 rays/s); held-out PSNR 19.25 dB; medium global"]
    assert stopped_by(lines) == "time"
    assert stopped_by(["trained 1 steps in 1 s (stopped by steps)"]) == "steps"
    assert stopped_by(["nothing"]) is None


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


def test_summary_table_and_html_mark_datasets_with_warnings():
    look = {"step": "poses", "code": "unconfirmed_poses",
            "message": "the camera model was not confirmed <attempts 1 and 2>", "details": {}}
    records = [DatasetRecord("calm", summary=_summary("calm", 30.0)),
               DatasetRecord("doubtful", summary=_summary("doubtful", 25.0), warnings=[look])]
    table = summary_table(records).set_index("dataset")
    assert table.loc["calm", "warnings"] == 0 and pd.isna(table.loc["calm", "needs_a_look"])
    assert table.loc["doubtful", "warnings"] == 1
    assert table.loc["doubtful", "needs_a_look"] == "poses: unconfirmed_poses"
    page = render_html(summary_table(records), records, {}, {}, "now")
    assert '<tr class="warn">' in page and '<tr class="ok">' in page
    assert "1 with warnings" in page and "<h2>Needs a look</h2>" in page
    assert "&lt;attempts 1 and 2&gt;" in page and "<attempts" not in page
    row = page.split('<tr class="warn">')[1].split("</tr>")[0]
    assert "&#9888;" in row and "poses: unconfirmed_poses" in row


def test_water_plot_draws_intervals_and_marks_undetermined_values():
    from matplotlib.patches import Rectangle

    from seathru.eval.report import water_intervals
    from seathru.eval.report_plots import plot_water_parameters

    water = {"sigma_attn": [0.5, 0.2, 0.1], "sigma_bs": [0.3, 0.3, 0.2], "c_med": [0.1, 0.2, 0.3],
             "uncertainty": {"interval95": {"sigma_attn": [[0.4, 0.6]] * 3,
                                            "sigma_bs": [[0.0, None]] * 3,
                                            "c_med": [[0.05, 0.15]] * 3},
                             "determined": {"sigma_attn": [True] * 3, "sigma_bs": [False] * 3,
                                            "c_med": [True] * 3}}}
    record = DatasetRecord("reef", water=water)
    interval, determined = water_intervals(record)
    assert interval["sigma_bs"][0] == [0.0, None] and determined["sigma_bs"] == [False] * 3
    figure = plot_water_parameters([record, DatasetRecord("no_water")])
    attn, bs, colour = figure.axes
    for ax in (attn, bs, colour):
        assert len([line for line in ax.lines if len(line.get_xdata()) == 2]) == 3  # intervals
    hatched = [p for p in bs.patches if isinstance(p, Rectangle) and p.get_hatch()]
    assert len(hatched) == 3 and not [p for p in attn.patches if p.get_hatch()]


def test_water_of_a_dive_with_a_known_scale_is_shown_per_metre():
    from seathru.eval.report import water_intervals, water_values
    from seathru.io.water import WaterReport

    params = {"mode": "global", "sigma_attn": [0.8, 0.4, 0.3], "sigma_bs": [0.5, 0.25, 0.2],
              "c_med": [0.05, 0.2, 0.3]}
    half = {k: [0.01, 0.5, 0.02] for k in ("sigma_attn", "sigma_bs", "c_med")}
    assessment = {"halfwidth95": half, "determined": {k: [True, False, True] for k in half},
                  "surface_fit": {k: list(params[k]) for k in half}, "pixels": 100,
                  "groups": 10}
    scaled = WaterReport.from_parameters(params, 0.5, assessment, 0.25).to_dict()
    fitted, truth, unit = water_values(DatasetRecord("reef", water=scaled))
    assert unit == "1/m" and truth is None
    assert fitted["sigma_attn"] == scaled["per_metre"]["sigma_attn"] != scaled["sigma_attn"]
    assert fitted["c_med"] == scaled["c_med"]
    interval, _ = water_intervals(DatasetRecord("reef", water=scaled))
    assert interval["sigma_bs"] == scaled["per_metre"]["interval95"]["sigma_bs"]
    assert interval["c_med"] == scaled["uncertainty"]["interval95"]["c_med"]
    plain = WaterReport.from_parameters(params, 0.5, assessment).to_dict()
    assert water_values(DatasetRecord("reef", water=plain))[2] == "1/source unit"


# -- community protocol and colour chart -------------------------------------------------------

def _chart(measured: dict[str, np.ndarray | None], occluded=(5,), chart="macbeth-classic-24"):
    """A colour-chart result as the evaluate step writes it (``seathru.io.chart``, JSON-safe):
    per image label (stored / ingest / restored) its linear patch means, None: not measured."""
    from seathru.eval import colour_chart as cc
    from seathru.io.jsonfile import json_safe

    spec = cc.CHARTS[chart]
    use = np.ones(spec.patches, bool)
    use[list(occluded)] = False
    result = {"source": "colour_chart.json", "chart": chart, "reference": spec.source,
              "image": "IMG_7", "occluded": list(occluded), "clipped": []}
    for key, means in measured.items():
        result[key] = ({"reason": "IMG_7 is a training view and no model to render it"}
                       if means is None else
                       {**cc.chart_errors(means, spec, use), "patch_means": means.tolist()})
    return json_safe(result)


def _reference_linear(chart="macbeth-classic-24") -> np.ndarray:
    from seathru.eval import colour_chart as cc

    return cc.lab_to_linear_srgb(cc.CHARTS[chart].reference_lab)


CAST = np.array([0.45, 1.0, 1.3])   # an underwater cast: red lost, blue kept


def _protocol(psnr: float, ssim: float, lpips: float | None = None) -> dict:
    means = {"psnr": psnr, "ssim": ssim, "mae": 0.01, "mse": 0.001}
    if lpips is not None:
        means["lpips"] = lpips
    return {"protocol": "nerfbaselines", "folder": "/r/d/evaluate/nerfbaselines", "views": 4,
            "means": means, "ground_truth": "the stored 8-bit sRGB files as they are"}


def test_protocol_and_chart_columns_only_where_measured_protocol_beside_ours():
    reference = _reference_linear()
    reef, lagoon = _summary("reef", 30.0), _summary("lagoon", 25.0)
    reef.protocol = _protocol(27.5, 0.81, 0.2)
    reef.colour_chart = _chart({"stored": 0.3 * reference * CAST, "ingest": 0.5 * reference,
                                "restored": 0.4 * reference * np.sqrt(CAST)})
    lagoon.colour_chart = _chart({"ingest": 0.5 * reference * CAST, "restored": None})
    plain = _summary("plain", 28.0)
    plain.colour_chart = {"source": "none", "reason": "no annotation; OpenCV mcc found none"}
    records = [DatasetRecord("reef", summary=reef), DatasetRecord("lagoon", summary=lagoon),
               DatasetRecord("plain", summary=plain),
               DatasetRecord("broken", status="failed", failed_step="train", error="boom")]
    table = summary_table(records)
    columns = list(table.columns)
    at = columns.index("lpips")
    assert columns[at + 1:at + 4] == ["nerfbaselines_psnr", "nerfbaselines_ssim",
                                      "nerfbaselines_lpips"]
    rows = table.set_index("dataset")
    assert rows.loc["reef", "nerfbaselines_psnr"] == 27.5
    assert rows.loc["reef", "nerfbaselines_lpips"] == 0.2
    assert rows[["nerfbaselines_psnr", "chart_de00_ingest"]].loc[["plain", "broken"]].isna().all(
        axis=None)
    # the photo, white-balanced ingest and the restored render in the order of their errors:
    # exact colours (ingest) give 0, the full cast the most, half of it in between
    assert rows.loc["reef", "chart_de00_ingest"] == pytest.approx(0.0, abs=1e-6)
    assert rows.loc["reef", "chart_de00_photo"] > rows.loc["reef", "chart_de00_restored"] > 1.0
    assert rows.loc["reef", "chart_grey_deg_photo"] > rows.loc["reef", "chart_grey_deg_restored"]
    assert rows.loc["lagoon", "chart_de00_ingest"] == pytest.approx(
        rows.loc["reef", "chart_de00_photo"])            # the same cast: the same error
    assert np.isnan(rows.loc["lagoon", "chart_de00_photo"])   # a RAW source: no photo
    assert np.isnan(rows.loc["lagoon", "chart_de00_restored"])
    # none measured: no such columns at all
    bare = summary_table([DatasetRecord("plain", summary=plain), records[-1]])
    assert not [c for c in bare.columns if c.startswith(("nerfbaselines_", "chart_"))]


def test_html_labels_the_protocol_and_shows_charts_in_their_own_table():
    reference = _reference_linear()
    reef = _summary("reef", 30.0)
    reef.protocol = _protocol(27.5, 0.81)
    reef.colour_chart = _chart({"stored": 0.3 * reference * CAST,
                                "ingest": 0.5 * reference * np.sqrt(CAST), "restored": None})
    records = [DatasetRecord("reef", summary=reef), DatasetRecord("plain",
                                                                   summary=_summary("p", 20.0))]
    table = summary_table(records)
    page = render_html(table, records, {}, {}, "now", charts={"reef": PNG})
    summary = page.split('<table class="summary">')[1].split("</table>")[0]
    assert "<th>nerfbaselines_psnr</th><th>nerfbaselines_ssim</th>" in summary
    assert "<td>27.5</td><td>0.81</td>" in summary and "chart_" not in summary
    assert "nerfbaselines_lpips" not in page                 # no dataset has it
    assert "NerfBaselines&#39; default protocol" in page and "reef: 4 views" in page
    charts = page.split("<h2>Colour charts</h2>")[1].split("<h2>")[0]
    row = charts.split("<td>reef</td>")[1].split("</tr>")[0]
    cells = table.set_index("dataset").loc["reef"]
    assert (f"<td>{cells['chart_de00_photo']:.4g}</td><td>{cells['chart_de00_ingest']:.4g}</td>"
            in row) and cells["chart_de00_photo"] > cells["chart_de00_ingest"] > 1.0
    assert 'title="IMG_7 is a training view and no model to render it">—</td>' in row
    assert "<td>macbeth-classic-24</td><td>IMG_7</td><td>23</td><td>6</td>" in row
    images = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', charts)
    assert [base64.b64decode(data) for data in images] == [PNG]
    plain = render_html(summary_table(records[1:]), records[1:], {}, {}, "now")
    assert "Colour charts" not in plain and "nerfbaselines" not in plain


def test_chart_swatches_show_the_measured_colours_at_the_errors_exposure():
    from seathru.eval.report_plots import chart_swatches, plot_chart_swatches

    reference = _reference_linear()
    measured = 0.25 * reference * CAST
    measured[3] = np.nan                                       # a patch outside the image
    chart = _chart({"stored": measured, "ingest": 0.5 * reference, "restored": None},
                   occluded=(5, 7))
    rows = chart_swatches(chart)
    assert list(rows) == ["reference", "photo", "ingest"]     # restored: not measured
    ref = rows["reference"]["srgb"]
    assert ref.shape == (24, 3)
    assert np.all(ref[18] > 0.9) and np.all(ref[23] < 0.25)  # patch 19 white, 24 black
    # exact colours at another exposure: the reference's swatches again
    np.testing.assert_allclose(rows["ingest"]["srgb"], ref, atol=1e-6)
    photo = rows["photo"]["srgb"]
    assert np.isnan(photo[3]).all() and np.isnan(rows["photo"]["delta_e00"][[3, 5, 7]]).all()
    grey = photo[18:24]                                        # the cast shows: blue over red
    assert np.all(grey[:, 2] > grey[:, 0])
    assert rows["photo"]["mean_delta_e00"] == chart["stored"]["mean_delta_e00"]
    figure = plot_chart_swatches("reef", chart)
    crosses = sorted((t.get_position()[1], t.get_position()[0])
                     for t in figure.axes[0].texts if t.get_text() == "\u00d7")
    assert crosses == [(1, 3), (1, 5), (1, 7), (2, 5), (2, 7)]   # (row, patch): 4 only on photo
    numbers = [t for t in figure.axes[0].texts if t.get_text() != "\u00d7"]
    assert len(numbers) == (24 - 3) + (24 - 2)                   # each scored patch's error
    import matplotlib.pyplot as plt

    plt.close(figure)
    assert chart_swatches({**chart, "chart": "unknown-chart"}) is None
    assert plot_chart_swatches("x", {**chart, "stored": None, "ingest": None}) is None


# -- settings the train step chose: capacity level, passes, reasons ----------------------------

AUTO_CAPACITY = {"requested": "auto", "chosen": "fast", "changed": {"field.plane_res": [96, 192,
                                                                                        256]},
                 "kept_explicit": ["sampler.samples_per_ray"],
                 "scene": {"train_pixels": 20480, "images": 8, "width": 64, "height": 40,
                           "footprint_res": 180.0},
                 "device_type": "cpu", "min_passes": 1.0,
                 "levels": {"fast": {"finest_plane": 256, "expected_passes": 3.1,
                                     "fits_scene": True, "fits_budget": True}},
                 "reason": "fast: finest tri-plane 256 cells <for> a scene of 180 footprints"}


def _chosen(dataset: str, capacity: dict | None, run: dict | None, psnr: float = 25.0,
            **record) -> DatasetRecord:
    selection = {"requested": "auto", "chosen": "global", "final_mode": "global",
                 "reason": "backscatter & attenuation <measurable>"}
    if capacity is not None:
        selection["capacity"] = capacity
    return DatasetRecord(dataset, summary=_summary(dataset, psnr), selection=selection,
                         training_run=run, **record)


def test_capacity_level_and_passes_from_the_selection_and_the_model():
    from seathru.eval.report import capacity_level, training_passes

    auto = _chosen("a", AUTO_CAPACITY, {"steps": 300, "batch_rays": 1024, "preset": "auto"})
    assert capacity_level(auto) == "auto \u2192 fast"
    assert training_passes(auto) == pytest.approx(300 * 1024 / 20480)
    named = _chosen("q", {"requested": "quality", "chosen": "quality"},
                    {"steps": 300, "batch_rays": 1024, "preset": "quality"})
    assert capacity_level(named) == "quality"
    assert training_passes(named) is None                 # a named preset records no scene
    # older runs: no capacity record; the preset of model.pt's config, else nothing
    assert capacity_level(_chosen("o", None, {"steps": 10, "preset": "balanced"})) == "balanced"
    old = _chosen("o", None, None)
    assert capacity_level(old) is None and training_passes(old) is None
    for run in ({"batch_rays": 1024}, {"steps": 300}, {"steps": 0, "batch_rays": 1024}, None):
        assert training_passes(_chosen("x", AUTO_CAPACITY, run)) is None
    # the evaluation summary's copy of selection.json serves when the record has none
    copied = DatasetRecord("c", summary=_summary("c", 20.0),
                           training_run={"steps": 20, "batch_rays": 2048})
    copied.summary.medium_selection = {"chosen": "off", "capacity": AUTO_CAPACITY}
    assert capacity_level(copied) == "auto \u2192 fast"
    assert training_passes(copied) == pytest.approx(2.0)


def test_summary_table_shows_capacity_and_passes_only_where_recorded():
    records = [_chosen("auto", AUTO_CAPACITY, {"steps": 100, "batch_rays": 2048}),
               _chosen("named", {"requested": "quality", "chosen": "quality"},
                       {"steps": 100, "batch_rays": 2048}),
               DatasetRecord("broken", status="failed", failed_step="train", error="boom")]
    table = summary_table(records)
    columns = list(table.columns)
    assert columns.index("capacity") == columns.index("train_steps") + 1
    assert columns.index("passes") == columns.index("capacity") + 1
    rows = table.set_index("dataset")
    assert rows.loc["auto", "capacity"] == "auto \u2192 fast"
    assert rows.loc["auto", "passes"] == pytest.approx(10.0)
    assert rows.loc["named", "capacity"] == "quality" and pd.isna(rows.loc["named", "passes"])
    assert pd.isna(rows.loc["broken", "capacity"])
    assert rows.loc["auto", "medium"] == "global"          # from the record's selection
    old = summary_table([DatasetRecord("old", summary=_summary("old", 20.0))])
    assert "capacity" not in old.columns and "passes" not in old.columns


def test_html_says_why_each_setting_was_chosen_escaped():
    records = [_chosen("reef", AUTO_CAPACITY, {"steps": 100, "batch_rays": 2048}),
               _chosen("reef+quality", {"requested": "quality", "chosen": "quality"}, None,
                       base="reef", variant="quality"),
               DatasetRecord("pending", status="failed", error="not run")]
    page = render_html(summary_table(records), records, {}, {}, "now")
    section = page.split("<h2>Settings chosen</h2>")[1].split("<h2>")[0]
    paragraphs = re.findall(r'<p class="chosen">(.*?)</p>', section)
    assert len(paragraphs) == 2 and "pending" not in section
    reef, quality = paragraphs
    assert reef.startswith("<b>reef</b>: capacity <code>auto \u2192 fast</code>")
    assert "256 cells &lt;for&gt; a scene" in reef and "<for>" not in reef
    assert "kept as set: sampler.samples_per_ray" in reef
    assert ("Medium <code>global</code> (requested auto): backscatter &amp; attenuation "
            "&lt;measurable&gt;.") in reef
    assert "<b>reef+quality</b>: capacity <code>quality</code> (set by train.preset=quality)" \
        in quality
    assert "sampled to" not in reef                      # no far factor recorded: nothing said
    summary = page.split('<table class="summary">')[1].split("</table>")[0]
    assert "<th>capacity</th><th>passes</th>" in summary
    assert "<td>auto \u2192 fast</td><td>10</td>" in summary   # 100 x 2048 / 20480
    plain = render_html(summary_table(records[2:]), records[2:], {}, {}, "now")
    assert "Settings chosen" not in plain


def test_html_says_how_far_the_object_field_was_sampled():
    record = _chosen("survey", AUTO_CAPACITY, None)
    record.selection["far_factor"] = {"requested": "auto", "chosen": 3.0,
                                      "reason": "22.4% of the pixels are open water <one colour>"}
    page = render_html(summary_table([record]), [record], {}, {}, "now")
    chosen = re.findall(r'<p class="chosen">(.*?)</p>', page)[0]
    assert ("Object field sampled to <code>3</code>&times; the cameras' far bound: 22.4% of "
            "the pixels are open water &lt;one colour&gt;.") in chosen


def test_frontier_labels_each_run_with_its_capacity_level():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from seathru.eval.frontier import frontier_summary
    from seathru.eval.report_plots import plot_frontier

    runs = [_chosen("demo", AUTO_CAPACITY, {"steps": 100, "batch_rays": 1024}, 24.0),
            _chosen("demo+quality", {"requested": "quality", "chosen": "quality"},
                    {"steps": 100, "batch_rays": 1024}, 25.0, base="demo", variant="quality"),
            _chosen("demo+old", None, None, 23.0, base="demo", variant="old")]
    for run in runs:
        run.summary.render.seconds_per_frame = 0.5
    table = frontier_summary(runs).set_index("run")
    assert table.loc["demo", "capacity"] == "auto \u2192 fast"
    assert table.loc["demo+quality", "capacity"] == "quality"
    assert pd.isna(table.loc["demo+old", "capacity"])
    assert table.loc["demo", "passes"] == pytest.approx(5.0)
    assert pd.isna(table.loc["demo+quality", "passes"])
    figure = plot_frontier("demo", runs)
    labels = {line.get_label() for axes in figure.axes[:2] for line in axes.get_lines()}
    assert {"demo [auto \u2192 fast] (final only)", "demo+quality [quality] (final only)",
            "demo+old (final only)", "demo [auto \u2192 fast]",
            "demo+quality [quality]"} <= labels
    plt.close(figure)


# -- colour along COLMAP tracks ----------------------------------------------------------------

BETA = np.array([0.4, 0.2, 0.1])   # the water's attenuation per unit range, R G B


def _track_slope(removed: float, held_out: bool = True, seed: int = 0,
                 near_far: bool = False, followed: float = 0.5) -> dict:
    """``track_colour_slope`` as the evaluate step writes it, fitted on synthetic tracks whose
    input colour falls as exp(-BETA range) and whose restoration keeps ``1 - removed`` of that."""
    from seathru.eval.track_slope import colour_slope_summary

    rng = np.random.default_rng(seed)
    ids = np.repeat(np.arange(40), 4)
    ranges = rng.uniform(1.0, 5.0, ids.size)
    albedo = rng.uniform(0.2, 0.8, (40, 3))[ids]
    noise = np.exp(rng.normal(0.0, 0.01, (ids.size, 3)))
    observed = albedo * np.exp(-BETA * ranges[:, None]) * noise
    restored = albedo * np.exp(-(1.0 - removed) * BETA * ranges[:, None]) * noise
    rendered = observed * np.exp((1.0 - followed) * BETA * ranges[:, None])
    held = ids < 25
    far = ids >= 36
    return {"source": "/d/sparse/0", "range_units": "source units (COLMAP's)",
            "restored_from": "the trained model",
            "all_views": {**colour_slope_summary(ids, ranges, observed, restored, rendered),
                          "photographs": {**colour_slope_summary(
                              ids, ranges, observed,
                              albedo * np.exp(-0.5 * BETA * ranges[:, None]) * noise),
                              "window": 0.02}},
            **({"near_tracks": colour_slope_summary(ids[~far], ranges[~far], observed[~far],
                                                    restored[~far]),
                "far_tracks": colour_slope_summary(ids[far], ranges[far], observed[far],
                                                   restored[far])} if near_far else {}),
            "held_out_views": (colour_slope_summary(ids[held], ranges[held], observed[held],
                                                    restored[held]) if held_out else
                               {"source": "none", "reason": "3 tracks have two or more "
                                                            "observations (need 20)"})}


def _slope_records() -> list[DatasetRecord]:
    reef, lagoon, plain, untrained = (_summary(name, 25.0) for name in
                                      ("reef", "lagoon", "plain", "untrained"))
    reef.track_colour_slope = _track_slope(0.8, near_far=True)
    lagoon.track_colour_slope = _track_slope(0.4, held_out=False, seed=1)
    untrained.track_colour_slope = {"source": "none", "reason": "/d/model.pt: no trained model"}
    return [DatasetRecord("reef", summary=reef), DatasetRecord("lagoon", summary=lagoon),
            DatasetRecord("plain", summary=plain), DatasetRecord("untrained", summary=untrained),
            DatasetRecord("broken", status="failed", failed_step="train", error="boom")]


def test_followed_share_pools_the_channels_whose_input_slope_stands_out():
    from seathru.eval.report import followed_share

    assert followed_share([(0.2, 0.01), (0.0, 0.01)], [(0.05, 0.01), (0.3, 0.01)]) == \
        pytest.approx(0.25)
    # a falling input followed by a falling render counts as followed; a rising one against it
    assert followed_share([(-0.2, 0.01), (0.1, 0.01)], [(-0.2, 0.01), (-0.1, 0.01)]) == \
        pytest.approx((0.2 - 0.1) / 0.3)
    assert followed_share([(0.01, 0.01)], [(0.01, 0.01)]) is None        # within its error
    assert followed_share([(0.2, 0.01)], [(None, None)]) is None          # not measured


def test_html_says_a_reduction_says_little_where_the_full_render_does_not_follow_the_input():
    from seathru.eval.report import TRACK_SLOPE_FOLLOWED_MIN, track_slope_rows

    reef = _summary("reef", 25.0)
    reef.track_colour_slope = _track_slope(0.8, followed=0.2)
    demo = _summary("demo", 25.0)
    demo.track_colour_slope = _track_slope(0.8, seed=2, followed=0.95)
    records = [DatasetRecord("reef", summary=reef), DatasetRecord("demo", summary=demo)]
    rows = {row["dataset"]: row["parts"][0] for row in track_slope_rows(records)}
    assert rows["reef"]["followed"] == pytest.approx(0.2, abs=0.02)
    assert rows["demo"]["followed"] == pytest.approx(0.95, abs=0.02)
    assert rows["reef"]["followed"] < TRACK_SLOPE_FOLLOWED_MIN < rows["demo"]["followed"]
    page = render_html(summary_table(records), records, {}, {}, "now")
    section = page.split("<h2>Colour along COLMAP tracks</h2>")[1].split("<h2>")[0]
    reef_part = section[section.index(">reef<"):section.index(">demo<")]
    demo_part = section[section.index(">demo<"):]
    note = "of the input's slope, so the share removed says little"
    assert reef_part.count(note) == 1 and "follows only 20%" in reef_part
    assert note not in demo_part


def test_track_slope_reduction_column_only_where_fitted():
    records = _slope_records()
    table = summary_table(records)
    columns = list(table.columns)
    assert columns.index("track_slope_reduction") + 1 \
        == columns.index("photo_track_slope_reduction") == columns.index("train_time_s") - 1
    rows = table.set_index("dataset")["track_slope_reduction"]
    assert rows["reef"] == pytest.approx(0.8, abs=0.02)     # the share of the slope removed
    assert rows["lagoon"] == pytest.approx(0.4, abs=0.02)
    assert rows[["plain", "untrained", "broken"]].isna().all()
    # the restored photographs keep half of the input's slope in every fixture
    photos = table.set_index("dataset")["photo_track_slope_reduction"]
    assert photos[["reef", "lagoon"]].to_numpy() == pytest.approx([0.5, 0.5], abs=0.02)
    assert photos[["plain", "untrained", "broken"]].isna().all()
    # a fit without an input slope (null in summary.json) is a missing value, not an error
    flat = _summary("flat", 20.0)
    flat.track_colour_slope = {**_track_slope(0.5), "all_views": {
        **_track_slope(0.5)["all_views"], "reduction_overall": None}}
    both = summary_table([records[0], DatasetRecord("flat", summary=flat)])
    assert np.isnan(both.set_index("dataset").loc["flat", "track_slope_reduction"])
    bare = summary_table([r for r in records if r.dataset in ("plain", "untrained", "broken")])
    assert "track_slope_reduction" not in bare.columns


def test_html_shows_slopes_per_channel_against_the_goal_and_why_a_part_is_missing():
    from seathru.eval.report import TRACK_SLOPE_GOAL

    records = _slope_records()
    page = render_html(summary_table(records), records, {}, {}, "now")
    summary = page.split('<table class="summary">')[1].split("</table>")[0]
    assert "<th>track_slope_reduction</th>" in summary
    assert "<th>photo_track_slope_reduction</th>" in summary
    reef_all = records[0].summary.track_colour_slope["all_views"]
    assert f"<td>{100 * reef_all['reduction_overall']:.0f}%</td>" in summary
    photo_cell = f"<td>{100 * reef_all['photographs']['reduction_overall']:.0f}%</td>"
    assert photo_cell in summary and photo_cell == "<td>50%</td>"
    section = page.split("<h2>Colour along COLMAP tracks</h2>")[1].split("<h2>")[0]
    assert "plain" not in section and "broken" not in section
    assert "untrained" in section and "/d/model.pt: no trained model" in section
    reef = section[section.index(">reef<"):section.index(">lagoon<")]
    for channel, name in enumerate("RGB"):
        slope, error = reef_all["input"]["slope"][channel], reef_all["input"]["stderr"][channel]
        assert slope == pytest.approx(-BETA[channel], rel=0.05)
        assert 0 < error < 0.1 * BETA[channel]
        restored = reef_all["restored"]["slope"][channel]
        rendered = reef_all["rendered"]["slope"][channel]
        assert rendered == pytest.approx(-0.5 * BETA[channel], rel=0.05)
        assert (f"<td>{name}</td><td>{slope:.4g} &plusmn; {error:.4g}</td><td>{rendered:.4g} "
                f"&plusmn; {reef_all['rendered']['stderr'][channel]:.4g}</td><td>{restored:.4g} "
                f"&plusmn; {reef_all['restored']['stderr'][channel]:.4g}</td>"
                f"<td>{100 * reef_all['reduction'][channel]:.0f}%</td>") in reef
        photo = reef_all["photographs"]
        assert (f"<td>{photo['restored']['slope'][channel]:.4g} &plusmn; "
                f"{photo['restored']['stderr'][channel]:.4g}</td>"
                f"<td>{100 * photo['reduction'][channel]:.0f}%</td>") in reef
    assert f"<td rowspan=\"3\">{100 * photo['reduction_overall']:.0f}%</td>" in reef
    assert photo["reduction_overall"] == pytest.approx(0.5, abs=0.05)
    # parts without the full render's slope (evaluations from before it) leave its cell empty
    near = records[0].summary.track_colour_slope["near_tracks"]
    near_input = near["input"]
    assert (f"<td>{near_input['slope'][0]:.4g} &plusmn; {near_input['stderr'][0]:.4g}</td>"
            "<td>—</td>") in reef
    counts = (f'<td rowspan="3">{reef_all["input"]["tracks"]}</td>'
              f'<td rowspan="3">{reef_all["input"]["observations"]}</td>')
    assert counts in reef and reef_all["input"]["tracks"] == 40
    goal = f"{100 * TRACK_SLOPE_GOAL:.0f}%"
    # all views, held-out views, the nearest and the farthest tracks
    assert reef.count(f"(meets the {goal} goal)") == 4
    assert "nearest 90% of tracks" in reef and "farthest 10% of tracks" in reef
    lagoon = section[section.index(">lagoon<"):section.index(">untrained<")]
    assert lagoon.count(f"(below the {goal} goal)") == 1 and "meets" not in lagoon
    assert "not measured: 3 tracks have two or more observations (need 20)" in lagoon
    assert "of tracks" not in lagoon      # an evaluation from before the near/far split
    plain = render_html(summary_table(records[2:3]), records[2:3], {}, {}, "now")
    assert "COLMAP tracks" not in plain and "track_slope" not in plain


def test_brighter_near_open_water_warns_with_the_slope_beside_it():
    """d3_reef's reading (coefficients -0.33, -0.32, -0.28 at 23-32 standard errors) warns, with
    the darkening per doubling of distance (2 ** c) and the slopes with and without the term;
    the demo's (within 0.005 of 0), a loose fit or a single channel does not."""
    summary = _summary("reef", 17.0)
    summary.track_colour_slope = _track_slope(0.5)
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
    summary = _summary("phone", 25.0)
    summary.track_colour_slope = _track_slope(0.5)
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
