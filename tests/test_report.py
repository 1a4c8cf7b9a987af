"""The report step, on a results tree made by the real render and evaluate steps from fabricated
datasets (a stand-in renderer, see tests/test_render_evaluate.py), plus failed datasets."""

from __future__ import annotations

import base64
import json
import os
import re
import time

import numpy as np
import pandas as pd
import pytest

from seathru.cli import main
from seathru.eval.report import camera_cells
from seathru.io.cameras import read_cameras
from seathru.io.images import read_image
from seathru.io.model import read_training_record, save_model
from seathru.io.pose_report import write_pose_report
from seathru.io.warnings import step_warning, write_warnings
from seathru.steps.render import render_dataset
from tests.test_io_pose_report import colmap_report
from tests.test_render_evaluate import RENDER_SETTINGS, make_fake_dataset

# what the train step recorded of each run: selection.json's capacity and model.pt
CAPACITY = {"sim": {"requested": "auto", "chosen": "fast", "changed": {"sampler.samples_per_ray":
                                                                       12},
                    "kept_explicit": [], "scene": {"train_pixels": 51200, "images": 8,
                                                   "width": 80, "height": 80,
                                                   "footprint_res": 150.0},
                    "device_type": "cpu", "min_passes": 1.0, "levels": {},
                    "reason": "fast: about 2.0 passes over the 51,200 training pixels"},
            "real": {"requested": "quality", "chosen": "quality"}}
MODEL_RECORD = {"sim": ({"batch_rays": 1024, "preset": "auto"},
                        {"steps": 100, "elapsed_s": 41.5, "stopped_by": "steps"}),
                "real": ({"batch_rays": 4096, "preset": "quality"},
                         {"steps": 100, "elapsed_s": 41.5, "stopped_by": "time"})}

ERROR_MESSAGE = ("results/broken/ingest/IMG_0003.NEF: the raw image data is missing "
                 "(stripped file?); remove it from the dataset")


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    base = tmp_path_factory.mktemp("report")
    results, logs = base / "results", base / "logs"
    for dataset, truth, seed in (("sim", True, 0), ("real", False, 1)):
        fake = make_fake_dataset(results / dataset, seed=seed, noise=0.002 + 0.01 * seed)
        selection = json.loads((fake["train"] / "selection.json").read_text())
        (fake["train"] / "selection.json").write_text(json.dumps(
            {**selection, "capacity": CAPACITY[dataset]}))
        config, training = MODEL_RECORD[dataset]
        save_model(fake["train"] / "model.pt", {"format": "test", "config": config,
                                                "training": training})
        render_dataset(fake["render_fn"], read_cameras(fake["poses"] / "cameras.json"),
                       results / dataset / "render", dict(RENDER_SETTINGS, path_frames=0))
        arguments = ["evaluate", "--renders", str(results / dataset / "render"),
                     "--cameras", str(fake["poses"] / "cameras.json"),
                     "--train-dir", str(fake["train"]), "--out",
                     str(results / dataset / "evaluate")]
        if truth:
            arguments += ["--truth", str(fake["truth"])]
        assert main(arguments) == 0
        (logs / dataset).mkdir(parents=True)
        # sim's log has no "stopped by": model.pt's record says
        (logs / dataset / "train.log").write_text(
            "step 100 loss 0.005\n" + ("trained 100 steps in 42 s (stopped by time; 2.4 steps/s)"
                                       "\n" if dataset == "real" else ""))
    # a camera model kept with poses.on_unconfirmed=warn, COLMAP started from the EXIF focal
    write_pose_report(results / "real" / "poses" / "report.json", {
        **colmap_report(), "gate_passed": False, "initial_focal_px": 249.6,
        "initial_focal_source": "manifest 35 mm equivalent focal length"})
    write_warnings(results / "real" / "poses" / "warnings.json", [step_warning(
        "poses", "unconfirmed_poses", "the camera model was not confirmed: attempts 1 and 2 "
        "disagree on the poses", attempt=2)])

    # failed in ingest; an older poses log from a previous run has an error line too
    (logs / "broken").mkdir(parents=True)
    (logs / "broken" / "poses.log").write_text("seathru poses: error: stale message\n")
    old = time.time() - 3600
    os.utime(logs / "broken" / "poses.log", (old, old))
    (logs / "broken" / "ingest.log").write_text(
        "INFO decoding 12 files\nseathru ingest: error: first problem\n"
        f"WARNING something\nseathru ingest: error: {ERROR_MESSAGE}\n")
    # crashed without a PipelineError (a traceback)
    (logs / "crashed").mkdir(parents=True)
    (logs / "crashed" / "train.log").write_text(
        "Traceback (most recent call last):\n  ...\nRuntimeError: CUDA out of memory\n")

    # stopped after poses (snakemake --until poses): clean logs, the poses results written;
    # "killed" has the same logs but its train step never wrote its results
    for dataset in ("stopped", "killed"):
        (logs / dataset).mkdir(parents=True)
        (logs / dataset / "ingest.log").write_text("INFO ingest: 3 images written\n")
        (logs / dataset / "poses.log").write_text("INFO poses: 3 frames written\n")
        (results / dataset / "ingest").mkdir(parents=True)
    (results / "stopped" / "poses").mkdir(parents=True)
    (results / "killed" / "poses").mkdir(parents=True)
    (logs / "killed" / "train.log").write_text("INFO step 400 loss 0.01\n")

    sheet = base / "datasets.tsv"
    sheet.write_text("dataset\tsource\tpath\toptions\n"
                     "sim\tsimulated\t\t\n"
                     "real\tsimulated\t\ttrain.max_minutes=2\n"
                     "broken\tllff\t/data/broken\t\n"
                     "crashed\tllff\t/data/crashed\t\n"
                     "pending\tllff\t/data/pending\t\n"
                     "stopped\timages\t/data/stopped\t\n"
                     "killed\timages\t/data/killed\t\n")
    out = base / "results" / "report"
    start = time.perf_counter()
    assert main(["report", "--results", str(results), "--datasets", str(sheet),
                 "--logs", str(logs), "--out", str(out)]) == 0
    return {"out": out, "seconds": time.perf_counter() - start}


def test_summary_table_lists_every_dataset_with_status(report):
    table = pd.read_csv(report["out"] / "summary.csv")
    assert list(table["dataset"]) == ["sim", "real", "broken", "crashed", "pending",
                                      "stopped", "killed"]
    status = dict(zip(table["dataset"], table["status"]))
    assert status == {"sim": "ok", "real": "ok", "broken": "failed", "crashed": "failed",
                      "pending": "failed", "stopped": "incomplete", "killed": "failed"}
    rows = table.set_index("dataset")
    assert rows.loc["broken", "failed_step"] == "ingest"
    assert rows.loc["broken", "error"] == ERROR_MESSAGE
    assert rows.loc["crashed", "failed_step"] == "train"
    assert "CUDA out of memory" in rows.loc["crashed", "error"]
    assert "not run" in rows.loc["pending", "error"]
    assert pd.isna(rows.loc["stopped", "failed_step"])
    assert rows.loc["stopped", "error"].startswith("stopped after poses: its results are complete")
    assert rows.loc["killed", "failed_step"] == "train"
    assert "no 'error:' line; last line of train.log" in rows.loc["killed", "error"]
    evaluated = pd.read_csv(report["out"].parent / "sim" / "evaluate" / "metrics.csv")
    assert rows.loc["sim", "psnr_linear"] == pytest.approx(evaluated["psnr_linear"].mean(),
                                                           rel=1e-5)
    assert rows.loc["sim", "restored_psnr_linear"] > rows.loc["sim", "full_vs_clean_psnr_linear"]
    assert np.isnan(rows.loc["real", "restored_psnr_linear"])   # no truth for this one
    assert rows.loc["sim", "train_time_s"] == pytest.approx(41.5)
    assert rows.loc["sim", "medium"] == "seathru"
    assert rows.loc["sim", "render_fps"] > 0


def test_warnings_reach_the_needs_a_look_column(report):
    table = pd.read_csv(report["out"] / "summary.csv").set_index("dataset")
    # both fake training logs end with the held-out PSNR still rising (24 dB at 41.5 s, about
    # 21 dB at 80% of that time): far from converged
    assert table.loc["sim", "needs_a_look"] == "train: not_converged"
    assert table.loc["real", "needs_a_look"] == "poses: unconfirmed_poses; train: not_converged"
    assert table.loc["real", "warnings"] == 2
    assert pd.isna(table.loc["broken", "needs_a_look"]) and table.loc["broken", "warnings"] == 0
    page = (report["out"] / "summary.html").read_text()
    assert "<h2>Needs a look</h2>" in page and "2 with warnings" in page
    assert "attempts 1 and 2 disagree on the poses" in page
    assert "stopped at its time budget" in page   # real's train.log: stopped by time
    assert "reached train.steps" not in page.split("<b>real</b><ul>")[1].split("</ul>")[0]


def test_where_the_cameras_came_from_reaches_the_table(report):
    table = pd.read_csv(report["out"] / "summary.csv").set_index("dataset")
    assert table.loc["real", "cameras"] == "COLMAP 3/3, 0.40 px, not confirmed"
    assert table.loc["real", "focal_start"] == "manifest 35 mm equivalent focal length"
    assert pd.isna(table.loc["sim", "cameras"]) and pd.isna(table.loc["broken", "cameras"])
    assert "COLMAP 3/3, 0.40 px, not confirmed" in (report["out"] / "summary.html").read_text()
    assert camera_cells({**colmap_report(), "initial_focal_px": None})["focal_start"] == \
        "none (COLMAP's own estimate)"
    assert camera_cells({"source": "llff", "frames": 20})["cameras"] == "llff (20 frames)"


def test_capacity_level_passes_and_reasons_reach_the_report(report):
    table = pd.read_csv(report["out"] / "summary.csv").set_index("dataset")
    assert table.loc["sim", "capacity"] == "auto \u2192 fast"
    assert table.loc["real", "capacity"] == "quality"
    assert table.loc["sim", "passes"] == pytest.approx(100 * 1024 / 51200)
    assert pd.isna(table.loc["real", "passes"])          # a named preset records no pixels
    assert table.loc[["broken", "pending"], "capacity"].isna().all()
    frontier = pd.read_csv(report["out"] / "frontier.csv").set_index("run")
    assert frontier.loc["sim", "capacity"] == "auto \u2192 fast"
    assert frontier.loc["real", "capacity"] == "quality"
    assert frontier.loc["sim", "passes"] == pytest.approx(2.0)
    page = (report["out"] / "summary.html").read_text()
    chosen = page.split("<h2>Settings chosen</h2>")[1].split("<h2>")[0]
    assert "<b>sim</b>: capacity <code>auto \u2192 fast</code> (fast: about 2.0 passes over " \
        "the 51,200 training pixels)" in chosen
    assert "<b>real</b>: capacity <code>quality</code> (set by train.preset=quality)" in chosen
    assert "Medium <code>seathru</code>: test." in chosen   # selection.json's reason
    assert "broken" not in chosen
    # sim's log does not say what stopped training: model.pt's record does (train.steps)
    sim = page.split("<b>sim</b><ul>")[1].split("</ul>")[0]
    assert "reached train.steps" in sim


def test_training_record_of_the_model_and_a_damaged_one(tmp_path, caplog):
    from seathru.errors import PipelineError
    from seathru.io.report_inputs import read_run_record

    save_model(tmp_path / "model.pt", {"config": {"batch_rays": 512, "preset": "fast",
                                                  "steps": 9},
                                       "state_dict": {"w": torch_zeros(3)},
                                       "training": {"steps": 7, "stopped_by": "time"}})
    assert read_training_record(tmp_path / "model.pt") == {"steps": 7, "stopped_by": "time",
                                                           "batch_rays": 512, "preset": "fast"}
    save_model(tmp_path / "old.pt", {"config": {"steps": 9}})
    assert read_training_record(tmp_path / "old.pt") == {}
    assert read_training_record(tmp_path / "absent.pt") is None
    (tmp_path / "bad.pt").write_bytes(b"not a torch file")
    with pytest.raises(PipelineError, match="bad.pt: cannot be read"):
        read_training_record(tmp_path / "bad.pt")
    assert read_run_record(tmp_path / "bad.pt") is None and "bad.pt" in caplog.text


def torch_zeros(n: int):
    import torch

    return torch.zeros(n)


def test_plots_and_strips_are_images(report):
    out = report["out"]
    for name in ("psnr_vs_time.png", "speed_vs_error.png", "water_parameters.png"):
        image = read_image(out / name)
        assert image.ndim == 3 and min(image.shape[:2]) > 200
        assert image.std() > 0.01   # something is drawn
    assert sorted(p.name for p in (out / "strips").iterdir()) == ["real.png", "sim.png"]
    strip = read_image(out / "strips" / "sim.png")
    assert strip.shape[1] > 2 * strip.shape[0]   # five columns of views, two rows


def test_html_is_self_contained_with_table_plots_and_errors(report):
    page = (report["out"] / "summary.html").read_text()
    assert "<table" in page and "sim" in page and "pending" in page
    assert ERROR_MESSAGE in page and "stage <code>ingest</code>" in page
    assert "stale message" not in page and "first problem" not in page
    images = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page)
    assert len(images) == 7   # three plots, two frontier figures (final points), two strips
    assert all(base64.b64decode(data)[:8] == b"\x89PNG\r\n\x1a\n" for data in images)
    assert 'src="http' not in page


def test_datasets_without_protocol_or_chart_add_nothing(report):
    table = pd.read_csv(report["out"] / "summary.csv")
    assert not [c for c in table.columns if c.startswith(("nerfbaselines_", "chart_"))]
    assert list((report["out"] / "charts").iterdir()) == []
    page = (report["out"] / "summary.html").read_text()
    assert "Colour charts" not in page and "nerfbaselines" not in page


@pytest.fixture(scope="module")
def chart_report(tmp_path_factory):
    """A dataset of stored 8-bit photos with an annotated chart (tests/test_colour_chart.py),
    evaluated with the NerfBaselines protocol, beside one that has not run."""
    from tests.test_colour_chart import _dataset

    base = tmp_path_factory.mktemp("chart_report")
    data = _dataset(base / "results" / "reef", chart_view=0)
    annotation = {"format": "seathru-colour-chart/1", "chart": "macbeth-classic-24",
                  "image": "view_00.png", "corners": data["corners"].tolist(), "occluded": [5]}
    (data["source"] / "colour_chart.json").write_text(json.dumps(annotation))
    root = data["root"]
    assert main(["evaluate", "--renders", str(root / "render"), "--cameras",
                 str(root / "poses" / "cameras.json"), "--train-dir", str(root / "train"),
                 "--out", str(root / "evaluate"), "--no-chart-detect",
                 "--protocol", "nerfbaselines"]) == 0
    sheet = base / "datasets.tsv"
    sheet.write_text("dataset\tsource\nreef\tllff\npending\tllff\n")
    out = base / "report"
    assert main(["report", "--results", str(base / "results"), "--datasets", str(sheet),
                 "--out", str(out)]) == 0
    return {"out": out, "summary": json.loads((root / "evaluate" / "summary.json").read_text())}


def test_report_shows_the_evaluations_protocol_and_chart(chart_report):
    out, summary = chart_report["out"], chart_report["summary"]
    table = pd.read_csv(out / "summary.csv").set_index("dataset")
    columns = list(table.columns)
    assert columns.index("nerfbaselines_psnr") == columns.index("lpips") + 1
    protocol, chart = summary["protocol"]["means"], summary["colour_chart"]
    assert table.loc["reef", "nerfbaselines_psnr"] == pytest.approx(protocol["psnr"], rel=1e-5)
    assert table.loc["reef", "nerfbaselines_ssim"] == pytest.approx(protocol["ssim"], rel=1e-5)
    for label, key in (("photo", "stored"), ("ingest", "ingest"), ("restored", "restored")):
        assert table.loc["reef", f"chart_de00_{label}"] == pytest.approx(
            chart[key]["mean_delta_e00"], rel=1e-5)
        assert table.loc["reef", f"chart_grey_deg_{label}"] == pytest.approx(
            chart[key]["mean_grey_angular_error_deg"], rel=1e-5)
    assert table.loc[["pending"], ["nerfbaselines_psnr", "chart_de00_photo"]].isna().all(axis=None)
    swatches = read_image(out / "charts" / "reef.png")
    assert swatches.shape[1] > 3 * swatches.shape[0] and swatches.std() > 0.05
    page = (out / "summary.html").read_text()
    assert "<h2>Colour charts</h2>" in page and "charts/reef.png" in page
    assert "reef: 2 views, ground truth the stored 8-bit sRGB files as they are" in page


def test_report_runtime_is_small(report):
    assert report["seconds"] < 60


def test_report_rejects_a_sheet_without_dataset_column(tmp_path, capsys):
    sheet = tmp_path / "sheet.tsv"
    sheet.write_text("name\tsource\nx\tllff\n")
    assert main(["report", "--results", str(tmp_path), "--datasets", str(sheet),
                 "--out", str(tmp_path / "out")]) == 2
    assert "no 'dataset' column" in capsys.readouterr().err


def test_report_rejects_bad_strip_settings(tmp_path, capsys):
    sheet = tmp_path / "sheet.tsv"
    sheet.write_text("dataset\nx\n")
    assert main(["report", "--results", str(tmp_path), "--datasets", str(sheet),
                 "--out", str(tmp_path / "out"), "--strip-views", "0"]) == 2
    assert "strip_views must be >= 1" in capsys.readouterr().err


def test_a_damaged_summary_fails_its_dataset_not_the_report(tmp_path):
    (tmp_path / "results" / "bad" / "evaluate").mkdir(parents=True)
    (tmp_path / "results" / "bad" / "evaluate" / "summary.json").write_text('{"format": 1}')
    sheet = tmp_path / "sheet.tsv"
    sheet.write_text("dataset\nbad\n")
    assert main(["report", "--results", str(tmp_path / "results"), "--datasets", str(sheet),
                 "--out", str(tmp_path / "out")]) == 0
    row = pd.read_csv(tmp_path / "out" / "summary.csv").iloc[0]
    assert row["status"] == "failed" and row["failed_step"] == "evaluate"
    assert "summary.json: expected format 'seathru-evaluation/1'" in row["error"]
