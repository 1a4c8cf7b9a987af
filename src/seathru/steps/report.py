"""One table and plots across every dataset of the sheet; failed datasets with their error.

Reads, for each dataset id of the sheet and each of its sweep runs ``<dataset>+<variant>`` (the
sheet's ``sweep`` column; ``--variants`` gives the configuration's variants:
``seathru.io.sheet.expand_sweeps``), ``RESULTS/<dataset>/evaluate/summary.json``,
``metrics.csv`` and ``frontier.csv``, ``RESULTS/<dataset>/train/train_log.csv``,
``water.json``, ``selection.json`` and ``model.pt``'s training record, and the render step's
display images
``RESULTS/<dataset>/render/test/<view>/*.png`` (``seathru.io.report_inputs``). A dataset without
a summary is listed as failed, with the stage and message of the last ``seathru <step>: error:``
line found in its logs (``LOGS/<dataset>/<step>.log``, the most recently written log that has
one), or the last line of its newest log when none has such a line.

Warnings ("needs a look"): every ``RESULTS/<dataset>/<step>/warnings.json`` the steps wrote,
and those derived from the train step's ``selection.json``, ``train_log.csv`` and log (water
model turned off; PSNR still rising by more than ``rising_psnr_db`` over the last
``rising_window`` of training: ``seathru.eval.report_warnings.training_warnings``).

Writes to ``--out``:

- ``summary.csv``: one row per dataset (status, warnings and their codes, error, held-out PSNR /
  SSIM / LPIPS, truth metrics of simulated datasets, training time, capacity level (``auto →
  fast``, ``quality``) and passes over the training pixels, render speed, medium);
- ``summary.html``: the same table (datasets with warnings marked), each warning in full, why
  the capacity level and the medium model were chosen ("Settings chosen"), the plots and image
  strips inlined (self-contained);
- ``psnr_vs_time.png``: held-out PSNR during training against training time, per dataset;
- ``speed_vs_error.png``: render frames per second and training time against held-out PSNR;
- ``water_parameters.png``: fitted water parameters per dataset and channel, truth markers;
- ``frontier/<dataset>.png``: per sheet dataset, its runs (the row and its sweep variants) on
  the same axes: snapshot PSNR against training time and final PSNR against render time, with
  the Pareto fronts (``seathru.eval.frontier``), each run labelled with its capacity level;
  ``frontier.csv``: one row per run, with its capacity level and passes and the time it needed
  to get within 0.5 dB of its own final PSNR;
- ``strips/<dataset>.png``: ground truth | full render | restored | depth | backscatter for a
  few held-out views;
- ``charts/<dataset>.png``: for a dataset whose evaluation measured a colour chart, its
  patches: reference, photo, ingest image and restored render.
- the page's "Colour along COLMAP tracks": for a dataset whose evaluation fitted the colour's
  slope against range along COLMAP tracks, per channel the input's and the restored render's
  slope and the share removed (``track_slope_reduction`` in the table; for the restored
  photographs ``photo_track_slope_reduction``), against the 70% goal.

Datasets evaluated with ``evaluate.protocol=nerfbaselines`` get that protocol's means beside
ours (``nerfbaselines_psnr``, ``_ssim``, ``_lpips``), datasets with a colour chart its mean
CIEDE2000 and grey angular error per image (``chart_*``; a table of their own on the page).
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from seathru import settings
from seathru.eval import report_plots as plots
from seathru.eval.frontier import frontier_summary, runs_by_dataset
from seathru.eval.report import measured_chart, render_html, summary_table
from seathru.io.atomic import atomic_dir, write_bytes, write_text
from seathru.io.report_inputs import collect_record, read_strip_images
from seathru.io.sheet import expand_sweeps, read_sheet, variant_options
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
    parser.add_argument("--variants", nargs="+", default=None, metavar="NAME=OPTIONS",
                        help="the sweep variants the sheet's 'sweep' column names (the "
                             "configuration's 'sweep', passed by the workflow)")
    settings.add_arguments(parser, Settings)


def run(args: argparse.Namespace) -> None:
    cfg = settings.from_namespace(Settings, args)
    import matplotlib

    matplotlib.use("Agg")
    sheet = expand_sweeps(read_sheet(args.datasets), variant_options(args.variants),
                          args.datasets)
    records = [collect_record(row, args.results, args.logs, STEP_ORDER, cfg.rising_psnr_db,
                              cfg.rising_window) for _, row in sheet.iterrows()]
    table, frontier = summary_table(records), frontier_summary(records)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "summary.csv", table.to_csv(index=False, float_format="%.6g"))
    write_text(out / "frontier.csv", frontier.to_csv(index=False, float_format="%.6g"))

    figures = {"psnr_vs_time.png": plots.plot_psnr_vs_time(records),
               "speed_vs_error.png": plots.plot_speed_vs_error(records),
               "water_parameters.png": plots.plot_water_parameters(records)}
    pngs = {name: plots.figure_png(figure) for name, figure in figures.items()}
    for name, png in pngs.items():
        write_bytes(out / name, png)
    fronts = {}
    with atomic_dir(out / "frontier") as tmp:
        for dataset, runs in runs_by_dataset(records).items():
            if (figure := plots.plot_frontier(dataset, runs)) is not None:
                fronts[dataset] = plots.figure_png(figure)
                write_bytes(tmp / f"{dataset}.png", fronts[dataset])
    strips = {}
    with atomic_dir(out / "strips") as tmp:
        for record in records:
            images = read_strip_images(args.results / record.dataset, cfg.strip_views)
            figure = plots.plot_strip(record, images, cfg.strip_height)
            if figure is not None:
                strips[record.dataset] = plots.figure_png(figure)
                write_bytes(tmp / f"{record.dataset}.png", strips[record.dataset])
    charts = {}
    with atomic_dir(out / "charts") as tmp:
        for record in records:
            chart = measured_chart(record.summary)
            if chart is not None and (figure := plots.plot_chart_swatches(record.dataset,
                                                                          chart)) is not None:
                charts[record.dataset] = plots.figure_png(figure)
                write_bytes(tmp / f"{record.dataset}.png", charts[record.dataset])
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    write_text(out / "summary.html", render_html(table, records, pngs, strips, stamp,
                                                 frontier, fronts, charts))
    failed = [r.dataset for r in records if r.status != "ok"]
    log.info("report: %d datasets, %d without results%s, %d with warnings", len(records),
             len(failed), f" ({', '.join(failed)})" if failed else "",
             sum(bool(r.warnings) for r in records))
