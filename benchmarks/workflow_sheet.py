"""Benchmarks that run the workflow over a sheet of their own: the working folder, the sheet,
the Snakemake call and the command line they share."""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
SHEET_HEADER = "dataset\tsource\tpath\toptions\tsweep"


def run_sheet(work: Path, rows: list[str], cores: int, targets: tuple[str, ...] = (),
              sweep: dict[str, str] | None = None) -> None:
    """Run the workflow in ``work`` over ``rows`` (the sheet's lines after its header) with
    the project's config, one dataset's failure not stopping the others; ``targets``: what
    to make (default: everything); ``sweep``: the config's sweep variants instead of the
    project's (variant name -> options)."""
    (work / "config").mkdir(parents=True, exist_ok=True)
    if sweep is None:
        shutil.copy(REPO / "config" / "config.yaml", work / "config" / "config.yaml")
    else:
        config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
        config["sweep"] = sweep
        (work / "config" / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    (work / "config" / "datasets.tsv").write_text("\n".join([SHEET_HEADER, *rows]) + "\n")
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}"}
    subprocess.run([sys.executable, "-m", "snakemake", "--snakefile",
                    str(REPO / "workflow" / "Snakefile"), "--directory", str(work),
                    "--configfile", "config/config.yaml", "--cores", str(cores),
                    "--keep-going", *targets], check=False, env=env, cwd=work)


def sheet_arguments(description: str, work: Path, out: Path,
                    extra: dict[str, dict] | None = None) -> argparse.Namespace:
    """``--work`` (the working folder), ``--cores``, ``--summarise-only`` (tabulate a
    finished ``--work``) and ``--out`` (the results file); ``extra``: a benchmark's own
    options (flag -> ``add_argument`` keywords)."""
    parser = argparse.ArgumentParser(description=description)
    for flag, keywords in (extra or {}).items():
        parser.add_argument(flag, **keywords)
    parser.add_argument("--work", type=Path, default=work)
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument("--summarise-only", action="store_true")
    parser.add_argument("--out", type=Path, default=out)
    return parser.parse_args()


def water_cells(water: dict) -> list[str]:
    """The evaluate step's ``truth.water`` as three table cells (``sigma_attn``, ``sigma_bs``,
    ``c_med``): signed error against the truth per channel, %, ``?`` where flagged as not
    determined, ``!`` where the interval misses the truth."""
    cells = []
    for key in ("sigma_attn", "sigma_bs", "c_med"):
        values = []
        for fitted, true, determined, holds in zip(water["fitted"][key], water["truth"][key],
                                                   water["determined"][key],
                                                   water["contains_truth"][key]):
            mark = ("" if determined else "?") + ("" if holds else "!")
            values.append(f"{100 * (fitted - true) / true:+.0f}{mark}")
        cells.append(", ".join(values) + "%")
    return cells


def unseen_cell(rows: list[dict]) -> str:
    """Each held-out view's ``unseen_surface_share`` with its held-out PSNR in brackets
    (``0.16 (25.5), ...``), ``-`` where the evaluation has no such column."""
    if not rows or not rows[0].get("unseen_surface_share"):
        return "-"
    return ", ".join(f"{float(row['unseen_surface_share']):.2f} "
                     f"({float(row['psnr_linear']):.1f})" for row in rows)


def metric_mean(rows: list[dict], key: str) -> str:
    """The mean of a ``metrics.csv`` column over its views, two decimals, ``-`` if none."""
    values = [float(row[key]) for row in rows if row.get(key)]
    return f"{statistics.mean(values):.2f}" if values else "-"


def read_run(work: Path, run: str) -> tuple[dict, list[dict]] | None:
    """A finished run's evaluation in ``work``: its ``summary.json`` and the rows of its
    ``metrics.csv``; None where the run did not get that far."""
    evaluate = work / "results" / run / "evaluate"
    if not (evaluate / "summary.json").is_file():
        return None
    return (json.loads((evaluate / "summary.json").read_text()),
            list(csv.DictReader((evaluate / "metrics.csv").open())))
