"""End to end through the real Snakemake API: the tiny configuration of .test/.

Two simulated dives (one with water, one clear) and one dataset made of corrupt raw files
(.test/bad_raw/), run from a copy of .test/ (`snakemake --directory .test` runs the same). The
good ones must produce metrics and the report; the bad one must fail with its clear message and
appear in the report; a rerun has nothing to do for the good ones; changing one dataset's option
reruns only that dataset's affected stages; a training job killed with SIGKILL resumes from its
checkpoint when the workflow is rerun.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import psutil
import pytest
import yaml
from snakemake.api import SnakemakeApi
from snakemake.settings.types import (ConfigSettings, DAGSettings, ExecutionSettings,
                                      OutputSettings, ResourceSettings)

from seathru.io.cameras import read_cameras
from tests.conftest import REPO_ROOT

pytestmark = pytest.mark.slow

SNAKEFILE = REPO_ROOT / "workflow" / "Snakefile"
BIN = Path(sys.executable).parent
TEST_CONFIG = REPO_ROOT / ".test"


def write_bad_raw(folder: Path) -> None:
    """The corrupt RAW files of the ``bad_raw`` dataset (see .test/bad_raw/README.md)."""
    import numpy as np

    from seathru.io.dng import write_dng

    folder.mkdir(parents=True, exist_ok=True)
    whole = folder / "whole.dng"
    mosaic = np.random.default_rng(0).integers(2000, 15000, size=(48, 64), dtype=np.uint16)
    write_dng(whole, mosaic, black_level=1024, white_level=16383, exposure_time_s=0.01, iso=200,
              f_number=4.0)
    data = whole.read_bytes()
    (folder / "truncated.dng").write_bytes(data[:len(data) // 2])
    whole.unlink()
    (folder / "not_a_raw.nef").write_text("this is not a raw file\n")
    (folder / "empty.cr2").write_bytes(b"")


def _copy_test_configuration(workdir: Path) -> None:
    """.test/ (config, sheet) copied into ``workdir`` with the corrupt RAW files written."""
    shutil.copytree(TEST_CONFIG, workdir, dirs_exist_ok=True,
                    ignore=shutil.ignore_patterns("results", "logs", ".snakemake", "report.html"))
    write_bad_raw(workdir / "bad_raw")


def run_workflow(workdir: Path, targets: tuple[str, ...] = (), dryrun: bool = False) -> bool:
    """Run the workflow in-process through the Snakemake API; True when every job succeeded."""
    os.environ["PATH"] = f"{BIN}{os.pathsep}{os.environ['PATH']}"
    cwd = os.getcwd()
    try:
        with SnakemakeApi(OutputSettings(quiet=None, printshellcmds=True)) as api:
            workflow = api.workflow(
                resource_settings=ResourceSettings(cores=2),
                config_settings=ConfigSettings(configfiles=[workdir / "config" / "config.yaml"]),
                snakefile=SNAKEFILE, workdir=workdir)
            dag = workflow.dag(DAGSettings(targets=set(targets)))
            dag.execute_workflow(executor="dryrun" if dryrun else "local",
                                 execution_settings=ExecutionSettings(keep_going=True))
        return True
    except Exception:  # the API raises when a job failed (after the others finished)
        return False
    finally:
        os.chdir(cwd)


def planned_jobs(workdir: Path, *extra: str) -> list[tuple[str, str]]:
    """(rule, dataset) pairs a dry run of the CLI would execute."""
    result = subprocess.run(
        [sys.executable, "-m", "snakemake", "-n", "--cores", "1", "--snakefile", str(SNAKEFILE),
         "--directory", str(workdir), "--configfile", str(workdir / "config" / "config.yaml"),
         *extra], capture_output=True, text=True, env=_env(), timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    jobs = re.findall(r"^rule (\w+):\n(?:    .*\n)*?    wildcards: dataset=(\S+)", result.stdout,
                      re.M)
    if re.search(r"^rule report:", result.stdout, re.M):
        jobs.append(("report", "*"))
    return jobs


def _env() -> dict:
    return dict(os.environ, PATH=f"{BIN}{os.pathsep}{os.environ['PATH']}")


@pytest.fixture(scope="module")
def finished_collection(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("collection")
    _copy_test_configuration(workdir)
    succeeded = run_workflow(workdir)
    return workdir, succeeded


def test_good_datasets_finish_and_the_bad_one_fails_clearly(finished_collection):
    workdir, succeeded = finished_collection
    assert not succeeded, "the bad raw dataset should have failed the run"
    for dataset in ("sim_water", "sim_clear"):
        metrics = pd.read_csv(workdir / "results" / dataset / "evaluate" / "metrics.csv")
        assert len(metrics) >= 1 and metrics["psnr_linear"].notna().all()
        summary = json.loads((workdir / "results" / dataset / "evaluate" / "summary.json")
                             .read_text())
        assert summary
    # the simulated RAW files were demosaiced and undistorted here: each training image
    # carries that blur, and the water fit works on images with it taken out
    cameras = read_cameras(workdir / "results" / "sim_water" / "poses" / "cameras.json")
    assert all(f.blur_px is not None and f.blur_px[0] > f.blur_px[1] > 0 for f in cameras.frames)
    assert "blur taken out" in (workdir / "logs" / "sim_water" / "train.log").read_text()
    selection = json.loads((workdir / "results" / "sim_water" / "train" / "selection.json")
                           .read_text())
    refits = selection["water_refits"]
    assert refits and all(r["colours"] == "deblurred" for r in refits)
    # the RAW files were developed with one white balance: no frame has a cast to correct
    change = (selection.get("statistics") or {}).get("track_colour_change") or {}
    cast = change.get("frame_colour")
    assert cast is None or (cast["one_white_balance"] and not cast["varies"])
    assert selection["frame_colour_correction"] is None
    log = (workdir / "logs" / "bad_raw" / "ingest.log").read_text()
    assert re.search(r"seathru ingest: error: .*usable image", log), log[-2000:]
    assert not (workdir / "results" / "bad_raw" / "ingest").exists()


def test_report_lists_every_dataset_and_the_failure(finished_collection):
    workdir, _ = finished_collection
    report = workdir / "results" / "report"
    table = pd.read_csv(report / "summary.csv")
    assert set(table["dataset"]) == {"sim_water", "sim_clear", "bad_raw"}
    html = (report / "summary.html").read_text()
    assert "bad_raw" in html and "usable image" in html
    assert (report / "psnr_vs_time.png").stat().st_size > 1000


def test_rerun_has_nothing_to_do_for_the_finished_datasets(finished_collection):
    workdir, _ = finished_collection
    jobs = planned_jobs(workdir)
    assert {dataset for _, dataset in jobs} <= {"bad_raw", "*"}, jobs


def test_changing_one_option_reruns_only_that_datasets_affected_stages(finished_collection):
    workdir, _ = finished_collection
    sheet = workdir / "config" / "datasets.tsv"
    original = sheet.read_text()
    try:
        sheet.write_text(original.replace("simulate.water=clear", "simulate.water=clear; "
                                          "render.path_frames=3"))
        jobs = set(planned_jobs(workdir))
        good_jobs = {job for job in jobs if job[1] not in ("bad_raw", "*")}
        assert good_jobs == {("render", "sim_clear"), ("evaluate", "sim_clear")}, jobs
    finally:
        sheet.write_text(original)


def test_killed_training_resumes_from_its_checkpoint(finished_collection):
    workdir, _ = finished_collection
    checkpoints = workdir / "results" / "sim_water" / "checkpoints"
    shutil.rmtree(checkpoints, ignore_errors=True)
    target = "results/sim_water/train/model.pt"
    # --configfile and --forcerun take several values: each is followed by another option.
    base = [sys.executable, "-m", "snakemake", "--snakefile", str(SNAKEFILE), "--directory",
            str(workdir), "--configfile", str(workdir / "config" / "config.yaml")]
    process = subprocess.Popen(base + ["--forcerun", "train", "--cores", "2", target],
                               env=_env(), start_new_session=True,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 300
        # "[!.]": not the atomic writer's hidden temporary file
        while time.time() < deadline and not any(checkpoints.glob("[!.]*.pt")):
            time.sleep(0.2)
        assert any(checkpoints.glob("[!.]*.pt")), "no checkpoint appeared"
        trainers = [child for child in psutil.Process(process.pid).children(recursive=True)
                    if "train" in child.cmdline() and "seathru" in " ".join(child.cmdline())]
        assert trainers, "the training job is not running"
        for trainer in trainers:
            trainer.send_signal(signal.SIGKILL)
        assert process.wait(timeout=120) != 0, "Snakemake should report the killed job"
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    assert not (workdir / "results" / "sim_water" / "train" / "model.pt").exists()
    rerun = subprocess.run(base + ["--cores", "2", target], env=_env(),
                           capture_output=True, text=True, timeout=600)
    assert rerun.returncode == 0, rerun.stdout[-3000:] + rerun.stderr[-3000:]
    train_log = (workdir / "logs" / "sim_water" / "train.log").read_text()
    assert re.search(r"[Rr]esum", train_log), train_log[-3000:]
    log = pd.read_csv(workdir / "results" / "sim_water" / "train" / "train_log.csv")
    config = yaml.safe_load((workdir / "config" / "config.yaml").read_text())
    assert log["step"].max() == config["train"]["steps"]
