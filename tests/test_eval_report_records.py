"""What the report knows of a dataset (seathru.eval.report_records): why a dataset failed, what
ended its training, the medium, capacity level and passes its train step chose."""

from __future__ import annotations

import pytest

from seathru.eval.report_records import (NOT_RUN, DatasetRecord, StepLog, capacity_level,
                                         diagnose_failure, medium_name, stopped_by,
                                         training_passes)
from seathru.steps import STEP_ORDER
from tests.test_eval_report import AUTO_CAPACITY, chosen_record, evaluation_summary


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


def test_stopped_by_reads_the_train_log():
    lines = ["step 5: medium 'global'", "trained 300 steps in 7 s (stopped by time; 37.2 "
             "steps/s, 19066 rays/s); held-out PSNR 19.25 dB; medium global"]
    assert stopped_by(lines) == "time"
    assert stopped_by(["trained 1 steps in 1 s (stopped by steps)"]) == "steps"
    assert stopped_by(["nothing"]) is None


def test_capacity_level_and_passes_from_the_selection_and_the_model():
    auto = chosen_record("a", AUTO_CAPACITY, {"steps": 300, "batch_rays": 1024, "preset": "auto"})
    assert capacity_level(auto) == "auto \u2192 fast"
    assert training_passes(auto) == pytest.approx(300 * 1024 / 20480)
    named = chosen_record("q", {"requested": "quality", "chosen": "quality"},
                    {"steps": 300, "batch_rays": 1024, "preset": "quality"})
    assert capacity_level(named) == "quality"
    assert training_passes(named) is None                 # a named preset records no scene
    # older runs: no capacity record; the preset of model.pt's config, else nothing
    older = chosen_record("o", None, {"steps": 10, "preset": "balanced"})
    assert capacity_level(older) == "balanced"
    old = chosen_record("o", None, None)
    assert capacity_level(old) is None and training_passes(old) is None
    for run in ({"batch_rays": 1024}, {"steps": 300}, {"steps": 0, "batch_rays": 1024}, None):
        assert training_passes(chosen_record("x", AUTO_CAPACITY, run)) is None
    # the evaluation summary's copy of selection.json serves when the record has none
    copied = DatasetRecord("c", summary=evaluation_summary("c", 20.0),
                           training_run={"steps": 20, "batch_rays": 2048})
    copied.summary.medium_selection = {"chosen": "off", "capacity": AUTO_CAPACITY}
    assert capacity_level(copied) == "auto \u2192 fast"
    assert training_passes(copied) == pytest.approx(2.0)
