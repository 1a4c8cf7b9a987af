"""The report's table and page (seathru.eval.report): the summary table, the HTML template, the
water plot, protocol and chart columns, the settings chosen. The fixtures here serve the tests
of the report's other modules too."""

from __future__ import annotations

import base64
import re

import numpy as np
import pandas as pd
import pytest

from seathru.eval.report import render_html, summary_table
from seathru.eval.report_records import DatasetRecord
from seathru.eval.summary import EvaluationSummary, RenderSpeed, TrainingSummary

PNG = b"\x89PNG\r\n\x1a\n" + bytes(range(40))


def evaluation_summary(dataset: str, psnr: float, fps: float | None = 20.0) -> EvaluationSummary:
    return EvaluationSummary(dataset=dataset, views=3,
                             means={"psnr_linear": psnr, "lpips": "unavailable"},
                             lpips="unavailable: no --lpips-weights given",
                             render=RenderSpeed(fps=fps, resolution=[48, 36]),
                             training=TrainingSummary(time_s=12.0, steps=50),
                             medium_selection={"chosen": "off"})


def test_summary_table_rows_and_columns():
    records = [DatasetRecord("a", summary=evaluation_summary("a", 30.0)),
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
    records = [DatasetRecord(evil, summary=evaluation_summary(evil, 30.0)),
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


# -- "needs a look" ----------------------------------------------------------------------------


def test_summary_table_and_html_mark_datasets_with_warnings():
    look = {"step": "poses", "code": "unconfirmed_poses",
            "message": "the camera model was not confirmed <attempts 1 and 2>", "details": {}}
    records = [DatasetRecord("calm", summary=evaluation_summary("calm", 30.0)),
               DatasetRecord("doubtful", summary=evaluation_summary("doubtful", 25.0),
                             warnings=[look])]
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
    reef, lagoon = evaluation_summary("reef", 30.0), evaluation_summary("lagoon", 25.0)
    reef.protocol = _protocol(27.5, 0.81, 0.2)
    reef.colour_chart = _chart({"stored": 0.3 * reference * CAST, "ingest": 0.5 * reference,
                                "restored": 0.4 * reference * np.sqrt(CAST)})
    lagoon.colour_chart = _chart({"ingest": 0.5 * reference * CAST, "restored": None})
    plain = evaluation_summary("plain", 28.0)
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
    reef = evaluation_summary("reef", 30.0)
    reef.protocol = _protocol(27.5, 0.81)
    reef.colour_chart = _chart({"stored": 0.3 * reference * CAST,
                                "ingest": 0.5 * reference * np.sqrt(CAST), "restored": None})
    records = [DatasetRecord("reef", summary=reef),
               DatasetRecord("plain", summary=evaluation_summary("p", 20.0))]
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


def chosen_record(dataset: str, capacity: dict | None, run: dict | None, psnr: float = 25.0,
            **record) -> DatasetRecord:
    selection = {"requested": "auto", "chosen": "global", "final_mode": "global",
                 "reason": "backscatter & attenuation <measurable>"}
    if capacity is not None:
        selection["capacity"] = capacity
    return DatasetRecord(dataset, summary=evaluation_summary(dataset, psnr), selection=selection,
                         training_run=run, **record)


def test_summary_table_shows_capacity_and_passes_only_where_recorded():
    records = [chosen_record("auto", AUTO_CAPACITY, {"steps": 100, "batch_rays": 2048}),
               chosen_record("named", {"requested": "quality", "chosen": "quality"},
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
    old = summary_table([DatasetRecord("old", summary=evaluation_summary("old", 20.0))])
    assert "capacity" not in old.columns and "passes" not in old.columns


def test_html_says_why_each_setting_was_chosen_escaped():
    records = [chosen_record("reef", AUTO_CAPACITY, {"steps": 100, "batch_rays": 2048}),
               chosen_record("reef+quality", {"requested": "quality", "chosen": "quality"}, None,
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
    record = chosen_record("survey", AUTO_CAPACITY, None)
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

    runs = [chosen_record("demo", AUTO_CAPACITY, {"steps": 100, "batch_rays": 1024}, 24.0),
            chosen_record("demo+quality", {"requested": "quality", "chosen": "quality"},
                    {"steps": 100, "batch_rays": 1024}, 25.0, base="demo", variant="quality"),
            chosen_record("demo+old", None, None, 23.0, base="demo", variant="old")]
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


def track_slope_record(removed: float, held_out: bool = True, seed: int = 0,
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


def slope_records() -> list[DatasetRecord]:
    reef, lagoon, plain, untrained = (evaluation_summary(name, 25.0) for name in
                                      ("reef", "lagoon", "plain", "untrained"))
    reef.track_colour_slope = track_slope_record(0.8, near_far=True)
    lagoon.track_colour_slope = track_slope_record(0.4, held_out=False, seed=1)
    untrained.track_colour_slope = {"source": "none", "reason": "/d/model.pt: no trained model"}
    return [DatasetRecord("reef", summary=reef), DatasetRecord("lagoon", summary=lagoon),
            DatasetRecord("plain", summary=plain), DatasetRecord("untrained", summary=untrained),
            DatasetRecord("broken", status="failed", failed_step="train", error="boom")]


def test_track_slope_reduction_column_only_where_fitted():
    records = slope_records()
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
    flat = evaluation_summary("flat", 20.0)
    flat.track_colour_slope = {**track_slope_record(0.5), "all_views": {
        **track_slope_record(0.5)["all_views"], "reduction_overall": None}}
    both = summary_table([records[0], DatasetRecord("flat", summary=flat)])
    assert np.isnan(both.set_index("dataset").loc["flat", "track_slope_reduction"])
    bare = summary_table([r for r in records if r.dataset in ("plain", "untrained", "broken")])
    assert "track_slope_reduction" not in bare.columns


def test_html_shows_slopes_per_channel_against_the_goal_and_why_a_part_is_missing():
    from seathru.eval.report_tracks import TRACK_SLOPE_GOAL

    records = slope_records()
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


