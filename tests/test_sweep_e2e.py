"""End to end through the Snakemake API: a sweep on the tiny configuration of .test/.

One simulated dive (`sim_water`) whose sheet row asks for the sweep variant `fast` (defined in
.test/config/config.yaml): the workflow runs it as `sim_water` and `sim_water+fast`, the latter
from train on, on `sim_water`'s simulate / ingest / poses outputs; each evaluation writes the
frontier of its quality snapshots, and the report draws both runs on one frontier figure.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import torch

from seathru.eval.frontier import WITHIN_COLUMN
from seathru.io.frontier import read_frontier
from tests.test_pipeline_e2e import _copy_test_configuration, planned_jobs, run_workflow

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def swept(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("sweep")
    _copy_test_configuration(workdir)
    (workdir / "config" / "datasets.tsv").write_text(
        "dataset\tsource\tpath\toptions\tsweep\nsim_water\tsimulated\t\t\tfast\n")
    return workdir, run_workflow(workdir)


def test_the_sweep_run_finishes_in_its_own_folder_on_the_datasets_poses(swept):
    workdir, succeeded = swept
    assert succeeded
    results = workdir / "results"
    summary = json.loads((results / "sim_water+fast" / "evaluate" / "summary.json").read_text())
    assert summary["dataset"] == "sim_water+fast"
    for stage in ("simulate", "ingest", "poses", "export"):
        assert (results / "sim_water" / stage).is_dir()
        assert not (results / "sim_water+fast" / stage).exists(), stage
    assert (workdir / "logs" / "sim_water+fast" / "train.log").is_file()
    models = {run: torch.load(results / run / "train" / "model.pt", map_location="cpu",
                              weights_only=True)["config"] for run in ("sim_water",
                                                                       "sim_water+fast")}
    assert models["sim_water+fast"]["preset"] == "fast"
    assert models["sim_water"]["preset"] == "auto"  # the default
    from seathru.nerf.config import TRAIN_PRESETS
    assert models["sim_water+fast"]["field"]["density_res"] == \
        TRAIN_PRESETS["fast"]["field"]["density_res"]
    capacity = json.loads((results / "sim_water" / "train" / "selection.json").read_text())[
        "capacity"]
    assert capacity["requested"] == "auto" and capacity["chosen"] in TRAIN_PRESETS


@pytest.mark.parametrize("run", ["sim_water", "sim_water+fast"])
def test_each_run_writes_its_frontier(swept, run):
    workdir, _ = swept
    table = read_frontier(workdir / "results" / run / "evaluate" / "frontier.csv")
    assert len(table) >= 2, table
    assert table["elapsed_s"].is_monotonic_increasing
    assert table["test_psnr_images"].notna().all()
    assert table["restored_psnr_linear"].notna().all()      # simulated: against the truth
    last = table.iloc[-1]
    errors = [last[f"{key}_rel_error_{c}"] for key in ("sigma_attn", "sigma_bs", "c_med")
              for c in "rgb"]
    assert np.isfinite(errors).all() or last["medium"] == "off"
    if last["medium"] == "global":
        # the last snapshot is the final model, one water for every view: its errors are the
        # final evaluation's (water.json; a view-dependent water is averaged there instead)
        summary = json.loads((workdir / "results" / run / "evaluate" / "summary.json")
                             .read_text())
        final = summary["truth"]["water"]["relative_error"]
        np.testing.assert_allclose(errors, [v for key in ("sigma_attn", "sigma_bs", "c_med")
                                            for v in final[key]], rtol=1e-4)


def test_the_report_draws_both_runs_on_one_frontier(swept):
    workdir, _ = swept
    report = workdir / "results" / "report"
    assert [p.name for p in (report / "frontier").glob("*.png")] == ["sim_water.png"]
    assert (report / "frontier" / "sim_water.png").stat().st_size > 5000
    table = pd.read_csv(report / "frontier.csv")
    assert table["run"].tolist() == ["sim_water", "sim_water+fast"]
    assert table[WITHIN_COLUMN].notna().all() and (table["snapshots"] >= 2).all()
    assert set(pd.read_csv(report / "summary.csv")["dataset"]) == {"sim_water",
                                                                   "sim_water+fast"}
    html = (report / "summary.html").read_text()
    assert 'alt="frontier sim_water"' in html


def test_a_rerun_has_nothing_to_do(swept):
    workdir, _ = swept
    assert planned_jobs(workdir) == []
