"""Quality against training time: the pure computations (seathru.eval.frontier), the
``frontier.csv`` contract (seathru.io.frontier), the evaluate step writing it from the train
step's snapshots of a fabricated simulated dataset, and the report's frontier figure and table
over a dataset and its sweep run."""

from __future__ import annotations

import math
import re
import shutil

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from seathru.cli import main
from seathru.errors import PipelineError
from seathru.eval import frontier
from seathru.eval.report_records import DatasetRecord
from seathru.eval.summary import EvaluationSummary, RenderSpeed, TrainingSummary
from seathru.eval.truth import compare_water, view_truth_metrics
from seathru.io.cameras import read_cameras
from seathru.radiometry.linearise import block_average
from seathru.io.frontier import frontier_table, read_frontier, write_frontier
from seathru.io.training import read_snapshot_renders, snapshot_path, write_snapshots
from seathru.steps.render import render_dataset
from tests.test_render_evaluate import (GAIN, METRES_PER_UNIT, RENDER_SETTINGS, WATER,
                                        make_fake_dataset)

# ------------------------------------------------------------------------------ pure: images

@settings(max_examples=40, deadline=None)
@given(height=st.integers(1, 9), width=st.integers(1, 9), factor=st.integers(1, 4),
       channels=st.sampled_from([None, 3]), seed=st.integers(0, 2**16))
def test_block_average_is_the_mean_of_each_block(height, width, factor, channels, seed):
    shape = (height, width) if channels is None else (height, width, channels)
    image = np.random.default_rng(seed).normal(size=shape)
    result = block_average(image, factor)
    rows, cols = height // factor, width // factor
    assert result.shape == (rows, cols, *shape[2:])
    for r in range(rows):
        for c in range(cols):
            block = image[r * factor:(r + 1) * factor, c * factor:(c + 1) * factor]
            np.testing.assert_allclose(result[r, c], block.mean(axis=(0, 1)), rtol=1e-12,
                                       atol=1e-12)


def test_block_average_keeps_open_water_undefined():
    depth = np.full((4, 4), 2.0)
    depth[0, 1] = np.inf
    averaged = block_average(depth, 2)
    assert np.isinf(averaged[0, 0]) and np.isfinite(averaged[1:, :]).all()


def test_restored_psnr_is_the_final_evaluations_restored_score():
    rng = np.random.default_rng(3)
    gain = np.array([1.5, 1.0, 0.7])
    views, expected = [], []
    for _ in range(3):
        clean = rng.uniform(0.05, 0.8, (16, 20, 3))
        depth = rng.uniform(1, 5, (16, 20))
        depth[:2, :3] = np.inf
        clean[:2, :3] = 0.0
        restored = clean / gain + rng.normal(0, 0.01, clean.shape)
        views.append((restored, clean, depth))
        expected.append(view_truth_metrics(full=restored, restored=restored, depth=depth,
                                           clean=clean, water=clean, truth_depth=depth,
                                           gain=gain, metres_per_unit=1.0)
                        ["restored_psnr_linear"])
    assert frontier.snapshot_restored_psnr(views, gain) == pytest.approx(np.mean(expected))
    assert math.isnan(frontier.snapshot_restored_psnr([], gain))
    tiny = [(view[0][:4, :5], view[1][:4, :5], view[2][:4, :5]) for view in views]
    assert np.isfinite(frontier.snapshot_restored_psnr(tiny, gain))   # smaller than SSIM's window


def _snapshot_row(step, elapsed, psnr, water=None):
    row = {"step": float(step), "elapsed_s": float(elapsed), "test_psnr_images": psnr,
           "medium": "global" if water else "off"}
    for key in ("sigma_attn", "sigma_bs", "c_med"):
        for i, c in enumerate("rgb"):
            row[f"{key}_{c}"] = None if water is None else water[key][i]
    return row


def test_water_errors_convert_like_the_final_comparison():
    truth = {"sigma_attn": [0.5, 0.3, 0.2], "sigma_bs": [0.4, 0.3, 0.2],
             "c_med": [0.1, 0.2, 0.3]}
    fitted = {"sigma_attn": [1.1, 0.5, 0.5], "sigma_bs": [0.8, 0.6, 0.3],
              "c_med": [0.05, 0.2, 0.35]}
    gain, scale = np.array([2.0, 1.0, 0.8]), 2.0
    errors = frontier.snapshot_water_errors(_snapshot_row(1, 1.0, 20.0, fitted), truth, scale,
                                            gain)
    reference = compare_water(fitted, truth, scale, gain).relative_error
    for key in ("sigma_attn", "sigma_bs", "c_med"):
        for i, c in enumerate("rgb"):
            assert errors[f"{key}_rel_error_{c}"] == pytest.approx(reference[key][i])
    assert errors["sigma_attn_rel_error_r"] == pytest.approx(0.1)   # 1.1 / 2 vs 0.5
    missing = frontier.snapshot_water_errors(_snapshot_row(1, 1.0, 20.0), truth, scale, gain)
    assert all(math.isnan(v) for v in missing.values())


# ------------------------------------------------------------------------------ pure: frontier

def test_pareto_front_examples():
    assert frontier.pareto_front([1, 2, 3, 4], [10, 9, 12, 12]).tolist() == [0, 2]
    # unsorted input, a tie in time (the better one counts), NaN ignored
    assert frontier.pareto_front([4, 1, 1, 3, 2], [15, 10, 11, np.nan, 13]).tolist() == [2, 4, 0]
    assert frontier.pareto_front([], []).tolist() == []


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 20), st.integers(0, 30)), min_size=1, max_size=25))
def test_pareto_front_is_the_staircase_of_the_best_within_each_time(points):
    times = np.array([p[0] for p in points], dtype=float)
    values = np.array([p[1] for p in points], dtype=float)
    front = frontier.pareto_front(times, values)
    front_times, front_values = times[front], values[front]
    assert np.all(np.diff(front_times) > 0) and np.all(np.diff(front_values) > 0)
    for t in np.unique(times):
        best = values[times <= t].max()
        assert front_values[front_times <= t].max() == best


def test_time_to_within_half_a_db_of_the_final_psnr():
    assert frontier.time_to_within([5, 10, 20, 40], [20.0, 24.0, 25.6, 26.0]) == 20.0
    # unsorted, a dip after reaching it, NaN ignored: the first time counts
    assert frontier.time_to_within([40, 10, 5, 20, 30], [26.0, 25.7, 20.0, 25.0, np.nan]) == 10.0
    assert frontier.time_to_within([7.0], [21.0]) == 7.0
    assert frontier.time_to_within([], []) is None
    assert frontier.time_to_within([3.0, 9.0], [20.0, 21.0], margin_db=2.0) == 3.0


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(0.1, 1e3), st.floats(5, 40)), min_size=1, max_size=15,
                unique_by=lambda p: p[0]))
def test_time_to_within_against_a_direct_scan(points):
    points = sorted(points)
    final = points[-1][1]
    expected = next(t for t, v in points if v >= final - 0.5)
    times, values = zip(*points)
    rng = np.random.default_rng(len(points))
    order = rng.permutation(len(points))
    assert frontier.time_to_within(np.array(times)[order], np.array(values)[order]) == expected


def _record(dataset, variant, snapshots, psnr, time_s, s_per_frame, restored=None):
    table = pd.DataFrame([frontier.frontier_row(_snapshot_row(i, t, v), 4,
                                                None if restored is None else restored[i])
                          for i, (t, v) in enumerate(snapshots)])
    means = {"psnr_linear": psnr}
    if restored is not None:
        means["restored_psnr_linear"] = restored[-1] - 0.2
    summary = EvaluationSummary(dataset=dataset, views=3, means=means, lpips="unavailable",
                                render=RenderSpeed(seconds_per_frame=s_per_frame,
                                                   fps=1 / s_per_frame),
                                training=TrainingSummary(time_s=time_s))
    return DatasetRecord(dataset, source="simulated", summary=summary, frontier=table,
                         base=dataset.split("+")[0], variant=variant)


def test_frontier_summary_has_one_row_per_run_with_its_time_to_within():
    records = [
        _record("demo+fast", "fast", [(5, 18.0), (10, 21.0), (20, 22.1), (31, 22.4)], 23.0,
                31.0, 0.5, restored=[10.0, 12.0, 13.0, 13.5]),
        _record("demo", "", [(5, 15.0), (10, 19.0), (20, 22.0), (40, 24.0), (62, 24.3)], 25.0,
                62.0, 1.0),
        DatasetRecord("other", status="failed", error="boom"),
    ]
    table = frontier.frontier_summary(records)
    assert table["run"].tolist() == ["demo", "demo+fast", "other"]   # the sheet's row first
    demo, fast, other = (table.iloc[i] for i in range(3))
    assert demo["variant"] == frontier.SHEET_ROW and fast["variant"] == "fast"
    assert demo[frontier.WITHIN_COLUMN] == 40.0 and fast[frontier.WITHIN_COLUMN] == 20.0
    assert fast["within_share_of_training"] == pytest.approx(20.0 / 31.0)
    assert fast["snapshot_final_psnr"] == 22.4 and fast["psnr_linear"] == 23.0
    assert fast["snapshot_final_restored_psnr"] == 13.5 and pd.isna(demo["restored_psnr_linear"])
    assert fast["render_s_per_frame"] == 0.5 and fast["snapshots"] == 4
    assert other["status"] == "failed" and other["snapshots"] == 0
    assert pd.isna(other[frontier.WITHIN_COLUMN])


def test_frontier_figure_draws_every_run_and_the_fronts():
    import matplotlib

    matplotlib.use("Agg")
    from seathru.eval.report_plots import figure_png, plot_frontier

    runs = [_record("demo", "", [(5, 15.0), (10, 19.0), (40, 24.0)], 25.0, 40.0, 1.0,
                    restored=[9.0, 11.0, 12.0]),
            _record("demo+fast", "fast", [(5, 18.0), (20, 22.0)], 23.0, 20.0, 0.5)]
    figure = plot_frontier("demo", runs)
    left, right = figure.axes[:2]
    labels = [line.get_label() for line in left.get_lines()]
    assert {"demo", "demo+fast", "demo: restored vs clean", "Pareto front (held-out)",
            "Pareto front (restored)"} <= set(labels)
    front = next(line for line in left.get_lines() if line.get_label() == "Pareto front (held-out)")
    # the staircase: 18 @ 5 s (fast), 19 @ 10 s, 22 @ 20 s (fast), 24 @ 40 s
    assert list(front.get_ydata()) == [18.0, 19.0, 22.0, 24.0, 24.0]
    assert {line.get_label() for line in right.get_lines()} >= {"demo", "demo+fast",
                                                                  "Pareto front"}
    assert figure_png(figure)[:8] == b"\x89PNG\r\n\x1a\n"
    assert plot_frontier("none", [DatasetRecord("none", status="failed")]) is None


# ------------------------------------------------------------------------------ frontier.csv

def test_frontier_csv_round_trip(tmp_path):
    rows = [frontier.frontier_row(_snapshot_row(10, 5.0, 18.25), 4, 11.5,
                                  {"sigma_attn_rel_error_r": 0.25}),
            frontier.frontier_row(_snapshot_row(20, 10.5, None), 4)]
    table = pd.DataFrame(rows)
    write_frontier(tmp_path / "frontier.csv", table)
    back = read_frontier(tmp_path / "frontier.csv")
    assert list(back.columns) == list(frontier.FRONTIER_COLUMNS)
    pd.testing.assert_frame_equal(back, table[list(frontier.FRONTIER_COLUMNS)],
                                  check_dtype=False)
    assert back["medium"].tolist() == ["off", "off"]


@pytest.mark.parametrize(("content", "expected"), [
    ("step,elapsed_s\n1,2\n", r"missing columns \['test_psnr_images'"),
    (None, "not a number"),
    ("", "cannot be read as a table"),
    (b"\xff\xfe\x00garbage\x00\x81", "cannot be read|missing columns"),
])
def test_malformed_frontier_csv_is_refused_naming_the_file(tmp_path, content, expected):
    path = tmp_path / "frontier.csv"
    if content is None:
        row = frontier.frontier_row(_snapshot_row(1, 2.0, 20.0), 4)
        pd.DataFrame([row]).to_csv(path, index=False)
        path.write_text(path.read_text().replace("2.0,20.0", "2.0,soon"))
    elif isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    with pytest.raises(PipelineError, match=re.escape(str(path))) as caught:
        read_frontier(path)
    assert re.search(expected, str(caught.value)), caught.value
    with pytest.raises(PipelineError, match="frontier.csv: file not found"):
        read_frontier(tmp_path / "missing" / "frontier.csv")


def test_a_damaged_snapshot_archive_is_refused_naming_it(tmp_path):
    path = snapshot_path(tmp_path, 40)
    path.parent.mkdir(parents=True)
    path.write_bytes(b"not a zip")
    with pytest.raises(PipelineError, match=re.escape(str(path))):
        read_snapshot_renders(tmp_path, 40)
    assert read_snapshot_renders(tmp_path, 41) is None


# -------------------------------------------------------------- evaluate: a fabricated dataset

DOWNSCALE = 2


def _write_fake_snapshots(fake: dict, noises: list[float], times: list[float],
                          water_scale: float = 1.0) -> None:
    """Snapshots of the fabricated dataset: its exact renders block-averaged, plus noise that
    falls with training time; the water the truth's (normalised units) times ``water_scale``."""
    rng = np.random.default_rng(7)
    rows, renders = [], {}
    water = {"sigma_attn": np.asarray(WATER["sigma_attn"]) * METRES_PER_UNIT * water_scale,
             "sigma_bs": np.asarray(WATER["sigma_bs"]) * METRES_PER_UNIT * water_scale,
             "c_med": np.asarray(WATER["c_med"]) / GAIN}
    for index, (noise, elapsed) in enumerate(zip(noises, times)):
        step = 10 * (index + 1)
        arrays = {}
        for view in fake["test_views"]:
            for key, source in (("rgb", "full"), ("restored", "restored")):
                image = block_average(fake["data"][view][source], DOWNSCALE)
                arrays[f"{view}.{key}"] = (image + rng.normal(0, noise, image.shape)
                                           ).astype(np.float16)
        renders[step] = arrays
        rows.append({"step": step, "elapsed_s": elapsed, "test_psnr_images": 20.0 + index,
                     "medium": "global", **{f"{k}_{c}": float(water[k][i]) for k in water
                                            for i, c in enumerate("rgb")}})
    write_snapshots(fake["train"], rows, renders, DOWNSCALE)


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    root = tmp_path_factory.mktemp("frontier") / "results" / "sim"
    fake = make_fake_dataset(root)
    render_dataset(fake["render_fn"], read_cameras(fake["poses"] / "cameras.json"),
                   root / "render", dict(RENDER_SETTINGS, path_frames=0))
    _write_fake_snapshots(fake, [0.05, 0.01, 0.002], [1.5, 3.0, 4.2])
    assert main(["evaluate", "--renders", str(root / "render"), "--cameras",
                 str(fake["poses"] / "cameras.json"), "--train-dir", str(fake["train"]),
                 "--truth", str(fake["truth"]), "--out", str(root / "evaluate")]) == 0
    return fake


def test_evaluate_writes_the_frontier_of_the_snapshots(evaluated):
    table = read_frontier(evaluated["root"] / "evaluate" / "frontier.csv")
    assert table["step"].tolist() == [10, 20, 30]
    assert table["elapsed_s"].tolist() == [1.5, 3.0, 4.2]
    assert table["test_psnr_images"].tolist() == [20.0, 21.0, 22.0]   # the train step's
    assert (table["downscale"] == DOWNSCALE).all()
    restored = table["restored_psnr_linear"].to_numpy()
    assert np.all(np.isfinite(restored)) and np.all(np.diff(restored) > 3), restored
    assert restored[-1] > 35   # the exact restoration, 8-bit quantised, float16, tiny noise
    # the truth's water, converted as the final comparison does: tiny relative errors
    errors = table[list(frontier.WATER_ERROR_COLUMNS)].to_numpy()
    assert np.all(errors < 5e-3), errors


def test_restored_score_matches_a_direct_computation(evaluated):
    """One snapshot scored by hand: truth block-averaged, the summary's gain."""
    import json

    from seathru.io.images import read_image

    summary = json.loads((evaluated["root"] / "evaluate" / "summary.json").read_text())
    gain = np.asarray(summary["truth"]["colour_gain"])
    renders = read_snapshot_renders(evaluated["train"], 20)
    scores = []
    for view in sorted(renders):
        clean = block_average(read_image(evaluated["truth"] / "clean" /
                                                  f"{view}.tiff"), DOWNSCALE)
        depth = block_average(read_image(evaluated["truth"] / "depth" /
                                                  f"{view}.tiff"), DOWNSCALE)
        scores.append(view_truth_metrics(
            full=renders[view]["rgb"], restored=renders[view]["restored"], depth=depth,
            clean=clean, water=clean, truth_depth=depth, gain=gain,
            metres_per_unit=1.0)["restored_psnr_linear"])
    table = read_frontier(evaluated["root"] / "evaluate" / "frontier.csv")
    assert table["restored_psnr_linear"][1] == pytest.approx(np.mean(scores), abs=1e-4)


def test_frontier_without_truth_or_snapshots(evaluated, tmp_path):
    table = frontier_table(evaluated["train"])       # not simulated: the train step's PSNR only
    assert len(table) == 3 and table["restored_psnr_linear"].isna().all()
    assert table[list(frontier.WATER_ERROR_COLUMNS)].isna().all().all()
    empty = frontier_table(tmp_path)                 # no snapshots.csv: no rows, same columns
    assert empty.empty and list(empty.columns) == list(frontier.FRONTIER_COLUMNS)


def test_missing_snapshot_renders_leave_their_restored_score_empty(evaluated, tmp_path):
    train = tmp_path / "train"
    shutil.copytree(evaluated["train"], train)
    snapshot_path(train, 10).unlink()     # taken before a resumed run's restart
    from seathru.io.evaluation import read_summary

    truth = read_summary(evaluated["root"] / "evaluate" / "summary.json").truth
    table = frontier_table(train, evaluated["truth"], truth)
    assert math.isnan(table["restored_psnr_linear"][0])
    assert np.isfinite(table["restored_psnr_linear"][1:]).all()


# ------------------------------------------------------------------- report: a run and a sweep

def test_report_draws_the_frontier_of_a_dataset_and_its_sweep_run(evaluated, tmp_path):
    results = tmp_path / "results"
    shutil.copytree(evaluated["root"], results / "sim")
    fast = results / "sim+fast"
    for stage in ("train", "render"):
        shutil.copytree(evaluated["root"] / stage, fast / stage)
    fake = dict(evaluated, train=fast / "train")
    _write_fake_snapshots(fake, [0.03, 0.004], [1.0, 2.0])
    assert main(["evaluate", "--renders", str(fast / "render"), "--cameras",
                 str(evaluated["poses"] / "cameras.json"), "--train-dir", str(fast / "train"),
                 "--truth", str(evaluated["truth"]), "--out", str(fast / "evaluate")]) == 0
    sheet = tmp_path / "datasets.tsv"
    sheet.write_text("dataset\tsource\tpath\toptions\tsweep\nsim\tsimulated\t\t\tfast\n")
    out = results / "report"
    assert main(["report", "--results", str(results), "--datasets", str(sheet), "--out",
                 str(out), "--variants", "fast=train.preset=fast", "quality=x"]) == 0
    assert sorted(p.name for p in (out / "frontier").iterdir()) == ["sim.png"]
    table = pd.read_csv(out / "frontier.csv")
    assert table["run"].tolist() == ["sim", "sim+fast"]
    assert table[frontier.WITHIN_COLUMN].tolist() == [4.2, 2.0]   # 22 dB of 22; 21 of 21
    summary = pd.read_csv(out / "summary.csv")
    assert summary["dataset"].tolist() == ["sim", "sim+fast"]
    assert summary["options"].fillna("").tolist() == ["", "train.preset=fast"]
    page = (out / "summary.html").read_text()
    assert 'alt="frontier sim"' in page and "Quality against time" in page
