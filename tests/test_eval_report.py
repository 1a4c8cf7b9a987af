"""The report's domain code (seathru.eval.report) and the per-dataset summary
(seathru.eval.summary): failure diagnosis, the summary table, the HTML template."""

from __future__ import annotations

import base64
import re

import numpy as np
import pandas as pd
import pytest

from seathru.eval import summary as dataset_summary
from seathru.eval.report import (NOT_RUN, DatasetRecord, StepLog, diagnose_failure, medium_name,
                                 render_html, summary_table)
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
