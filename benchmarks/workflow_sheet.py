"""Benchmarks that run the workflow over a sheet of their own: the working folder, the sheet,
the Snakemake call and the command line they share."""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHEET_HEADER = "dataset\tsource\tpath\toptions\tsweep"


def run_sheet(work: Path, rows: list[str], cores: int, targets: tuple[str, ...] = ()) -> None:
    """Run the workflow in ``work`` over ``rows`` (the sheet's lines after its header) with
    the project's config, one dataset's failure not stopping the others; ``targets``: what
    to make (default: everything)."""
    (work / "config").mkdir(parents=True, exist_ok=True)
    shutil.copy(REPO / "config" / "config.yaml", work / "config" / "config.yaml")
    (work / "config" / "datasets.tsv").write_text("\n".join([SHEET_HEADER, *rows]) + "\n")
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}"}
    subprocess.run([sys.executable, "-m", "snakemake", "--snakefile",
                    str(REPO / "workflow" / "Snakefile"), "--directory", str(work),
                    "--configfile", "config/config.yaml", "--cores", str(cores),
                    "--keep-going", *targets], check=False, env=env, cwd=work)


def sheet_arguments(description: str, work: Path, out: Path) -> argparse.Namespace:
    """``--work`` (the working folder), ``--cores``, ``--summarise-only`` (tabulate a
    finished ``--work``) and ``--out`` (the results file)."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--work", type=Path, default=work)
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument("--summarise-only", action="store_true")
    parser.add_argument("--out", type=Path, default=out)
    return parser.parse_args()
