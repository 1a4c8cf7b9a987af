"""One table and plots across every dataset of the sheet; failed datasets with their error.

Reads, for each dataset id of the sheet, ``RESULTS/<dataset>/evaluate/summary.json`` and
``metrics.csv``, ``RESULTS/<dataset>/train/train_log.csv`` and ``water.json``, and the render
step's display images ``RESULTS/<dataset>/render/test/<view>/*.png``. A dataset without a
summary is listed as failed, with the stage and message of the last ``seathru <step>: error:``
line found in its logs (``LOGS/<dataset>/<step>.log``, the most recently written log that has
one), or the last line of its newest log when none has such a line.

Warnings ("needs a look"): every ``RESULTS/<dataset>/<step>/warnings.json`` the steps wrote,
and those derived from the train step's ``selection.json``, ``train_log.csv`` and log (water
model turned off; PSNR still rising by more than ``rising_psnr_db`` over the last
``rising_window`` of training: ``seathru.eval.report.training_warnings``).

Writes to ``--out``:

- ``summary.csv``: one row per dataset (status, warnings and their codes, error, held-out PSNR /
  SSIM / LPIPS, truth metrics of simulated datasets, training time, render speed, medium);
- ``summary.html``: the same table (datasets with warnings marked), each warning in full, the
  plots and image strips inlined (self-contained);
- ``psnr_vs_time.png``: held-out PSNR during training against training time, per dataset;
- ``speed_vs_error.png``: render frames per second and training time against held-out PSNR;
- ``water_parameters.png``: fitted water parameters per dataset and channel, truth markers;
- ``strips/<dataset>.png``: ground truth | full render | restored | depth | backscatter for a
  few held-out views.
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import pandas as pd

from seathru import settings
from seathru.errors import PipelineError
from seathru.eval import report_plots as plots
from seathru.eval.report import (DatasetRecord, StepLog, diagnose_failure, render_html,
                                 stopped_by, summary_table, training_warnings)
from seathru.io.atomic import atomic_dir, write_bytes, write_text
from seathru.io.evaluation import read_metrics, read_summary, read_train_log
from seathru.io.images import read_image
from seathru.io.jsonfile import read_json
from seathru.io.sheet import read_sheet
from seathru.io.warnings import read_dataset_warnings
from seathru.io.water import read_water
from seathru.settings import setting
from seathru.steps import STEP_ORDER

log = logging.getLogger(__name__)


@dataclass
class Settings:
    """The cross-dataset report: summary table, plots and image strips."""

    strip_views: int = setting(3, help="held-out views per dataset in the image strips")
    strip_height: int = setting(160, help="height in pixels of one image in the strips")
    rising_psnr_db: float = setting(
        1.0, help="warn that training is far from converged when its PSNR rose more than this "
                  "(dB) over the last rising_window of its time")
    rising_window: float = setting(0.2, help="share of the training time rising_psnr_db is over")

    def validate(self) -> None:
        if self.strip_views < 1 or self.strip_height < 16:
            raise ValueError("strip_views must be >= 1 and strip_height >= 16")
        if not 0.0 < self.rising_window <= 1.0:
            raise ValueError("rising_window must be in (0, 1]")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--results", required=True, type=Path,
                        help="results folder holding <dataset>/<step>/ outputs")
    parser.add_argument("--datasets", required=True, type=Path,
                        help="dataset sheet (TSV with at least a 'dataset' column)")
    parser.add_argument("--logs", type=Path, default=None,
                        help="logs folder (<dataset>/<step>.log): error messages of failed "
                             "datasets")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    settings.add_arguments(parser, Settings)


def run(args: argparse.Namespace) -> None:
    cfg = settings.from_namespace(Settings, args)
    import matplotlib

    matplotlib.use("Agg")
    sheet = read_sheet(args.datasets)
    records = [_collect(row, args.results, args.logs, cfg) for _, row in sheet.iterrows()]
    table = summary_table(records)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "summary.csv", table.to_csv(index=False, float_format="%.6g"))

    figures = {"psnr_vs_time.png": plots.plot_psnr_vs_time(records),
               "speed_vs_error.png": plots.plot_speed_vs_error(records),
               "water_parameters.png": plots.plot_water_parameters(records)}
    pngs = {name: plots.figure_png(figure) for name, figure in figures.items()}
    for name, png in pngs.items():
        write_bytes(out / name, png)
    strips = {}
    with atomic_dir(out / "strips") as tmp:
        for record in records:
            images = _strip_images(args.results / record.dataset, cfg.strip_views)
            figure = plots.plot_strip(record, images, cfg.strip_height)
            if figure is not None:
                strips[record.dataset] = plots.figure_png(figure)
                write_bytes(tmp / f"{record.dataset}.png", strips[record.dataset])
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    write_text(out / "summary.html", render_html(table, records, pngs, strips, stamp))
    failed = [r.dataset for r in records if r.status != "ok"]
    log.info("report: %d datasets, %d without results%s, %d with warnings", len(records),
             len(failed), f" ({', '.join(failed)})" if failed else "",
             sum(bool(r.warnings) for r in records))


def _collect(row: pd.Series, results: Path, logs: Path | None, cfg: Settings) -> DatasetRecord:
    """What the report shows about one dataset of the sheet, read from its results."""
    dataset = str(row["dataset"]).strip()
    base = Path(results) / dataset
    record = DatasetRecord(dataset, source=row.get("source", ""), options=row.get("options", ""))
    summary_path = base / "evaluate" / "summary.json"
    try:
        record.summary = read_summary(summary_path) if summary_path.is_file() else None
    except PipelineError as exc:   # a damaged summary fails this dataset, not the report
        record.status, record.failed_step, record.error = "failed", "evaluate", str(exc)
    if record.summary is None and record.status == "ok":
        record.status = "failed"
        record.failed_step, record.error = diagnose_failure(_step_logs(logs, dataset),
                                                            STEP_ORDER)
    metrics_path = base / "evaluate" / "metrics.csv"
    if record.summary is not None and metrics_path.is_file():
        record.metrics = read_metrics(metrics_path)
    record.train_log = read_train_log(base / "train" / "train_log.csv")
    water_path = base / "train" / "water.json"
    if water_path.is_file():
        try:
            record.water = read_water(water_path).to_dict()
        except PipelineError as exc:
            log.warning("%s", exc)
    selection = (record.summary.medium_selection if record.summary else None) or read_json(
        base / "train" / "selection.json", missing_ok=True)
    train_log = [s for s in _step_logs(logs, dataset) if s.step == "train"]
    record.warnings = read_dataset_warnings(base, STEP_ORDER) + training_warnings(
        selection, record.train_log, stopped_by(train_log[0].lines) if train_log else None,
        cfg.rising_psnr_db, cfg.rising_window)
    record.warnings.sort(key=lambda w: STEP_ORDER.index(w["step"]) if w["step"] in STEP_ORDER
                         else len(STEP_ORDER))
    return record


def _step_logs(logs: Path | None, dataset: str) -> list[StepLog]:
    folder = None if logs is None else Path(logs) / dataset
    if folder is None or not folder.is_dir():
        return []
    return [StepLog(path.stem, path.stat().st_mtime,
                    path.read_text(errors="replace").splitlines())
            for path in folder.glob("*.log")]


def _strip_images(base: Path, count: int) -> dict[str, dict]:
    """view -> {strip column -> display image or None} for the views shown in the strip."""
    test_dir = base / "render" / "test"
    available = [p.name for p in test_dir.iterdir() if p.is_dir()] if test_dir.is_dir() else []
    return {view: {name: read_image(path) if (path := test_dir / view / f"{name}.png").is_file()
                   else None for name, _ in plots.STRIP_COLUMNS}
            for view in plots.strip_views(available, count)}
