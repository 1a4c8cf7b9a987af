"""The SLURM path: `snakemake --profile workflow/profiles/slurm` on a real (single-node) cluster.

Needs a SLURM cluster answering on this machine with the profile's partitions "cpu" and "gpu"
and a filesystem shared with its node; `.ci/slurm-setup.sh` (root) makes one on Debian. Skips
when `sinfo` is missing or the cluster does not answer.

Overrides of the profile, all for a test cluster without slurmdbd and without GPUs:
- `--slurm-status-command squeue`: no accounting database, so `sacct` fails; squeue sees
  finished jobs for MinJobAge seconds (600 with the setup script).
- `--set-resources train:gpu=0 render:gpu=0` (plus the profile's other set-resources, which a
  command-line --set-resources would otherwise drop): the gpu partition has no GPU, and the
  plugin turns `gpu: N` into `sbatch --gpus=N`, which SLURM could never satisfy here.
- `--slurm-init-seconds-before-status-checks 2` (default 40) and kept SLURM logs for the asserts.

The chain up to results/<ds>/ingest always runs (about 1 minute); the whole pipeline
(train/render on the gpu partition, a few minutes) only with SEATHRU_SLURM_FULL=1.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.conftest import REPO_ROOT

pytestmark = pytest.mark.slow

PROFILE = REPO_ROOT / "workflow" / "profiles" / "slurm"
TEST_CONFIG = REPO_ROOT / ".test"
DATASET = "sim_water"  # the first row of .test/config/datasets.tsv
SNAKEMAKE_TIMEOUT_S = 600


def _run(command: list[str], timeout: float = 30, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run(command, capture_output=True, text=True, timeout=timeout, **kwargs)


@pytest.fixture(scope="module")
def slurm_cluster() -> dict[str, int]:
    """CPUs and MB of memory of the smallest node; skips when no SLURM cluster answers here."""
    if shutil.which("sinfo") is None:
        pytest.skip("SLURM not installed (no sinfo on PATH); as root: bash .ci/slurm-setup.sh")
    try:
        answer = _run(["sinfo", "-h", "-o", "%R %a %c %m"], timeout=30)
    except subprocess.TimeoutExpired:
        pytest.skip("SLURM cluster does not answer (sinfo timed out)")
    if answer.returncode != 0:
        pytest.skip(f"SLURM cluster does not answer (sinfo -h: {answer.stderr.strip()[:300]})")
    rows = [line.split() for line in answer.stdout.splitlines()]
    partitions = {row[0] for row in rows if row[1] == "up"}
    profile = yaml.safe_load((PROFILE / "config.yaml").read_text())
    wanted = {profile["default-resources"]["slurm_partition"]}
    wanted |= {res["slurm_partition"] for res in profile["set-resources"].values()
               if "slurm_partition" in res}
    missing = wanted - partitions
    if missing:
        pytest.skip(f"SLURM cluster lacks the profile's partitions {sorted(missing)} "
                    f"(has {sorted(partitions)}); .ci/slurm-setup.sh makes them")
    return {"cpus": min(int(row[2].rstrip("+")) for row in rows),
            "mem_mb": min(int(row[3].rstrip("+")) for row in rows)}


def _workdir(tmp_path: Path, node: dict[str, int]) -> Path:
    """A working directory with .test/'s configuration and its first dataset (a tiny simulated
    dive) alone, with resource requests that fit the node."""
    config = yaml.safe_load((TEST_CONFIG / "config" / "config.yaml").read_text())
    header, first_row = (TEST_CONFIG / "config" / "datasets.tsv").read_text().splitlines()[:2]
    assert first_row.split("\t")[:2] == [DATASET, "simulated"], first_row
    (tmp_path / "config").mkdir()
    sheet = tmp_path / "config" / "datasets.tsv"
    sheet.write_text(f"{header}\n{first_row}\n")
    config["datasets"] = str(sheet)
    # Small requests that fit the node (a 2-core CI machine): SLURM rejects what cannot fit.
    threads, mem_mb = min(2, node["cpus"]), min(2000, node["mem_mb"])
    config["resources"] = {
        "default": {"threads": 1, "mem_mb": min(1000, mem_mb), "runtime": 15, "gpu": 0},
        **{rule: {"threads": threads, "mem_mb": mem_mb}
           for rule in ("ingest", "poses", "train", "render")},
    }
    (tmp_path / "config" / "config.yaml").write_text(yaml.safe_dump(config))
    return tmp_path


def _profile_resources_without_gpus() -> list[str]:
    """The profile's set-resources with every gpu count 0, as --set-resources arguments.

    A --set-resources on the command line replaces the profile's whole mapping, so the other
    entries (train and render on the gpu partition) are repeated here.
    """
    profile = yaml.safe_load((PROFILE / "config.yaml").read_text())
    return [f"{rule}:{key}={0 if key == 'gpu' else value}"
            for rule, resources in profile["set-resources"].items()
            for key, value in resources.items()]


def _snakemake_on_slurm(workdir: Path, *targets: str) -> subprocess.CompletedProcess:
    venv_bin = Path(sys.executable).parent
    # sbatch --export=ALL hands this environment to the job, so `seathru` resolves on the node.
    env = dict(os.environ, PATH=f"{venv_bin}{os.pathsep}{os.environ['PATH']}", OMP_NUM_THREADS="1")
    command = [
        sys.executable, "-m", "snakemake",
        "--profile", str(PROFILE),
        "--directory", str(workdir),
        "--snakefile", str(REPO_ROOT / "workflow" / "Snakefile"),
        "--configfile", str(workdir / "config" / "config.yaml"),
        "--set-resources", *_profile_resources_without_gpus(),  # nargs="+": not last
        "--slurm-status-command", "squeue",
        "--slurm-init-seconds-before-status-checks", "2",
        "--slurm-keep-successful-logs",
        *targets,
    ]
    try:
        return _run(command, timeout=SNAKEMAKE_TIMEOUT_S, cwd=REPO_ROOT, env=env)
    except subprocess.TimeoutExpired as error:
        queue = _run(["squeue", "-h", "-o", "%i %Z"]).stdout
        _cancel_jobs_in(workdir, queue)
        stderr = error.stderr or b""
        if isinstance(stderr, bytes):
            stderr = stderr.decode(errors="replace")
        pytest.fail(f"snakemake on SLURM did not finish in {SNAKEMAKE_TIMEOUT_S} s:\n"
                    f"{stderr[-4000:]}\nsqueue:\n{queue}")


def _cancel_jobs_in(workdir: Path, queue: str) -> None:
    """Cancel the jobs left behind by a timed-out run: those whose working directory is ours."""
    ours = [line.split()[0] for line in queue.splitlines()
            if line.split()[1:] == [str(workdir)]]
    if ours:
        _run(["scancel", *ours])


def _slurm_jobs(workdir: Path) -> dict[str, list[int]]:
    """SLURM job ids per rule, from the plugin's logs .snakemake/slurm_logs/rule_R/DS/ID.log."""
    jobs: dict[str, list[int]] = {}
    for log in (workdir / ".snakemake" / "slurm_logs").glob(f"rule_*/{DATASET}/*.log"):
        jobs.setdefault(log.parent.parent.name.removeprefix("rule_"), []).append(int(log.stem))
    return jobs


def _slurm_record(job_id: int) -> dict[str, str]:
    """What the controller remembers of a job (squeue keeps finished jobs for MinJobAge)."""
    answer = _run(["squeue", "--states=all", "-h", "-j", str(job_id), "-o", "%T|%P|%k|%j|%N"])
    fields = answer.stdout.strip().split("|") if answer.returncode == 0 else []
    if len(fields) != 5:  # forgotten already: ask the accounting database if there is one
        answer = _run(["sacct", "-X", "-n", "-P", "-j", str(job_id),
                       "-o", "State,Partition,Comment,JobName,NodeList"])
        fields = answer.stdout.strip().split("|") if answer.returncode == 0 else []
    if len(fields) != 5:
        return {}
    return dict(zip(("state", "partition", "comment", "name", "nodes"), fields))


def _assert_ran_on_slurm(workdir: Path, result: subprocess.CompletedProcess,
                         expected: dict[str, str]) -> None:
    """Every rule of `expected` ran as one SLURM job that completed on the expected partition."""
    jobs = _slurm_jobs(workdir)
    assert set(jobs) == set(expected), (
        f"SLURM jobs per rule {jobs}, expected one for each of {sorted(expected)}\n"
        f"{result.stderr[-3000:]}")
    run_names = set()
    for rule, partition in expected.items():
        assert len(jobs[rule]) == 1, f"rule {rule} ran as SLURM jobs {jobs[rule]}"
        job_id = jobs[rule][0]
        record = _slurm_record(job_id)
        assert record, f"SLURM does not know job {job_id} of rule {rule}"
        assert record["state"] == "COMPLETED", f"job {job_id} ({rule}): {record}"
        assert record["partition"] == partition, f"job {job_id} ({rule}): {record}"
        assert record["comment"] == f"rule_{rule}_wildcards_{DATASET}", record
        run_names.add(record["name"])
        log = (workdir / ".snakemake" / "slurm_logs" / f"rule_{rule}" / DATASET
               / f"{job_id}.log").read_text()
        assert f"rule {rule}:" in log and "Finished jobid" in log, log[-2000:]
        assert f"SLURM jobid {job_id}" in result.stderr, "job not submitted by this run"
    assert len(run_names) == 1, f"jobs of one run carry one job name (the run id): {run_names}"


def test_chain_to_ingest_runs_as_slurm_jobs(slurm_cluster, tmp_path):
    workdir = _workdir(tmp_path, slurm_cluster)
    result = _snakemake_on_slurm(workdir, f"results/{DATASET}/ingest")
    assert result.returncode == 0, result.stderr[-6000:]
    ingest = workdir / "results" / DATASET / "ingest"
    assert ingest.is_dir() and any(ingest.iterdir()), f"{ingest} empty"
    _assert_ran_on_slurm(workdir, result, {"simulate": "cpu", "ingest": "cpu"})


def _train_step_exists() -> bool:
    answer = _run([str(Path(sys.executable).parent / "seathru"), "train", "--help"])
    return answer.returncode == 0


@pytest.mark.skipif(os.environ.get("SEATHRU_SLURM_FULL") != "1",
                    reason="whole pipeline on SLURM takes minutes: set SEATHRU_SLURM_FULL=1")
def test_whole_pipeline_runs_as_slurm_jobs(slurm_cluster, tmp_path):
    if not _train_step_exists():
        pytest.skip("'seathru train' does not exist yet")
    workdir = _workdir(tmp_path, slurm_cluster)
    result = _snakemake_on_slurm(workdir)
    assert result.returncode == 0, result.stderr[-6000:]
    assert (workdir / "results" / "report" / "summary.csv").is_file()
    _assert_ran_on_slurm(workdir, result, {
        "simulate": "cpu", "ingest": "cpu", "poses": "cpu", "train": "gpu", "render": "gpu",
        "evaluate": "cpu", "export": "cpu"})
