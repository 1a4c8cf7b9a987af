"""One table and plots across every dataset of the sheet; failed datasets with their error.

Reads, for each dataset id of the sheet, ``RESULTS/<dataset>/evaluate/summary.json`` and
``metrics.csv``, ``RESULTS/<dataset>/train/train_log.csv`` and ``water.json``, and the render
step's display images ``RESULTS/<dataset>/render/test/<view>/*.png``. A dataset without a
summary is listed as failed, with the stage and message of the last ``seathru <step>: error:``
line found in its logs (``LOGS/<dataset>/<step>.log``, the most recently written log that has
one), or the last line of its newest log when none has such a line.

Writes to ``--out``:

- ``summary.csv``: one row per dataset (status, error, held-out PSNR / SSIM / LPIPS, truth
  metrics of simulated datasets, training time, render speed, medium selection);
- ``summary.html``: the same table, the plots and image strips inlined (self-contained);
- ``psnr_vs_time.png``: held-out PSNR during training against training time, per dataset;
- ``speed_vs_error.png``: render frames per second and training time against held-out PSNR;
- ``water_parameters.png``: fitted water parameters per dataset and channel, truth markers;
- ``strips/<dataset>.png``: ground truth | full render | restored | depth | backscatter for a
  few held-out views.
"""

from __future__ import annotations

import argparse
import base64
import html
import json
import logging
import re
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pandas as pd

from seathru.errors import PipelineError
from seathru.io.atomic import atomic_dir, atomic_path, write_text
from seathru.io.images import read_image
from seathru.steps import STEP_ORDER

log = logging.getLogger(__name__)

ERROR_LINE = re.compile(r"seathru (?P<step>[\w-]+): error: (?P<message>.*)")
STRIP_COLUMNS = (("gt", "ground truth"), ("full", "full render"), ("restored", "restored"),
                 ("depth", "depth"), ("backscatter", "backscatter"))
CHANNEL_COLOURS = ("#d62728", "#2ca02c", "#1f77b4")
TABLE_COLUMNS = (
    "dataset", "source", "options", "status", "failed_step", "error", "views",
    "psnr_linear", "ssim_linear", "psnr_srgb", "ssim_srgb", "lpips",
    "restored_psnr_linear", "restored_ssim_linear", "full_vs_clean_psnr_linear",
    "depth_median_abs_rel", "depth_corr", "train_time_s", "train_steps", "render_fps",
    "render_resolution", "medium")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--results", required=True, type=Path,
                        help="results folder holding <dataset>/<step>/ outputs")
    parser.add_argument("--datasets", required=True, type=Path,
                        help="dataset sheet (TSV with at least a 'dataset' column)")
    parser.add_argument("--logs", type=Path, default=None,
                        help="logs folder (<dataset>/<step>.log): error messages of failed "
                             "datasets")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--strip-views", type=int, default=3,
                        help="held-out views per dataset in the image strips (default 3)")
    parser.add_argument("--strip-height", type=int, default=160,
                        help="height in pixels of one image in the strips (default 160)")


def run(args: argparse.Namespace) -> None:
    import matplotlib

    matplotlib.use("Agg")
    if args.strip_views < 1 or args.strip_height < 16:
        raise PipelineError("--strip-views must be >= 1 and --strip-height >= 16")
    sheet = read_sheet(args.datasets)
    records = [collect_dataset(row, args.results, args.logs) for _, row in sheet.iterrows()]
    table = summary_table(records)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "summary.csv", table.to_csv(index=False, float_format="%.6g"))

    figures = {
        "psnr_vs_time.png": plot_psnr_vs_time(records),
        "speed_vs_error.png": plot_speed_vs_error(records),
        "water_parameters.png": plot_water_parameters(records),
    }
    for name, figure in figures.items():
        save_figure(figure, out / name)
    strips = {}
    with atomic_dir(out / "strips") as tmp:
        for record in records:
            figure = plot_strip(record, args.strip_views, args.strip_height)
            if figure is not None:
                save_figure(figure, tmp / f"{record['dataset']}.png")
                strips[record["dataset"]] = f"strips/{record['dataset']}.png"
    write_text(out / "summary.html", build_html(table, records, out, list(figures), strips))
    failed = [r["dataset"] for r in records if r["status"] != "ok"]
    log.info("report: %d datasets, %d without results%s", len(records), len(failed),
             f" ({', '.join(failed)})" if failed else "")


# ------------------------------------------------------------------------------------- gathering

def read_sheet(path: Path) -> pd.DataFrame:
    if not Path(path).is_file():
        raise PipelineError(f"{path}: dataset sheet not found")
    try:
        sheet = pd.read_csv(path, sep="\t", dtype=str, keep_default_na=False, comment="#")
    except (pd.errors.ParserError, pd.errors.EmptyDataError) as exc:
        raise PipelineError(f"{path}: cannot be read as a tab-separated sheet ({exc})") from None
    if "dataset" not in sheet.columns:
        raise PipelineError(f"{path}: no 'dataset' column; the sheet is tab-separated with a "
                            f"header row (found columns {list(sheet.columns)})")
    return sheet[sheet["dataset"].str.strip() != ""]


def _read_json(path: Path):
    try:
        return json.loads(Path(path).read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def find_failure(logs: Path | None, dataset: str) -> dict:
    """The failing stage and message of a dataset, from its step logs."""
    folder = None if logs is None else Path(logs) / dataset
    if folder is None or not folder.is_dir():
        return {"failed_step": None, "error": "no results and no logs (not run yet?)"}
    candidates = []
    for path in folder.glob("*.log"):
        lines = path.read_text(errors="replace").splitlines()
        errors = [m for m in map(ERROR_LINE.search, lines) if m]
        last_line = next((line.strip() for line in reversed(lines) if line.strip()), "")
        candidates.append((path.stat().st_mtime, path.stem, errors[-1] if errors else None,
                           last_line))
    if not candidates:
        return {"failed_step": None, "error": "no results and no logs (not run yet?)"}
    with_errors = [c for c in candidates if c[2] is not None]
    if with_errors:
        _, stem, match, _ = max(with_errors, key=lambda c: (c[0], _step_rank(c[1])))
        return {"failed_step": match["step"] if match["step"] in STEP_ORDER else stem,
                "error": match["message"].strip()}
    _, stem, _, last_line = max(candidates, key=lambda c: (c[0], _step_rank(c[1])))
    return {"failed_step": stem,
            "error": f"no 'error:' line; last line of {stem}.log: {last_line or '(empty)'}"}


def _step_rank(stem: str) -> int:
    return STEP_ORDER.index(stem) if stem in STEP_ORDER else -1


def collect_dataset(row: pd.Series, results: Path, logs: Path | None) -> dict:
    """Everything the report shows about one dataset of the sheet."""
    dataset = str(row["dataset"]).strip()
    base = Path(results) / dataset
    record = {"dataset": dataset, "source": row.get("source", ""),
              "options": row.get("options", ""), "base": base}
    summary = _read_json(base / "evaluate" / "summary.json")
    record["summary"] = summary
    if summary is None:
        record.update(status="failed", **find_failure(logs, dataset))
    else:
        record.update(status="ok", failed_step=None, error=None)
    metrics_path = base / "evaluate" / "metrics.csv"
    record["metrics"] = pd.read_csv(metrics_path) if summary and metrics_path.is_file() else None
    log_path = base / "train" / "train_log.csv"
    record["train_log"] = pd.read_csv(log_path) if log_path.is_file() else None
    record["water_json"] = _read_json(base / "train" / "water.json")
    return record


def _medium(selection) -> str | None:
    if not isinstance(selection, dict):
        return None
    for key in ("final_mode", "chosen", "mode", "medium", "selected"):
        if key in selection:
            return str(selection[key])
    return json.dumps(selection)[:80]


def summary_table(records: list[dict]) -> pd.DataFrame:
    rows = []
    for record in records:
        row = {key: record.get(key) for key in ("dataset", "source", "options", "status",
                                                "failed_step", "error")}
        summary = record["summary"] or {}
        means = summary.get("means") or {}
        row["views"] = summary.get("views")
        for key in TABLE_COLUMNS:
            if key in means:
                row[key] = means[key]
        training = summary.get("training") or {}
        render = summary.get("render") or {}
        row["train_time_s"] = training.get("time_s")
        row["train_steps"] = training.get("steps")
        if row["train_time_s"] is None and record["train_log"] is not None \
                and "wall_time_s" in record["train_log"]:
            row["train_time_s"] = float(record["train_log"]["wall_time_s"].max())
        row["render_fps"] = render.get("fps")
        resolution = render.get("resolution")
        row["render_resolution"] = ("x".join(map(str, resolution))
                                    if isinstance(resolution, list) and len(resolution) == 2
                                    and not isinstance(resolution[0], list) else None)
        row["medium"] = _medium(summary.get("medium_selection"))
        rows.append(row)
    table = pd.DataFrame(rows)
    columns = [c for c in TABLE_COLUMNS if c in table.columns and
               (c in ("dataset", "status", "error", "failed_step") or table[c].notna().any())]
    return table[columns]


# ---------------------------------------------------------------------------------------- plots

def save_figure(figure, path: Path) -> None:
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        figure.savefig(tmp, dpi=110, bbox_inches="tight")
    plt.close(figure)


def _empty_axes(axes, text: str) -> None:
    axes.text(0.5, 0.5, text, ha="center", va="center", transform=axes.transAxes,
              color="0.4")
    axes.set_xticks([])
    axes.set_yticks([])


def plot_psnr_vs_time(records: list[dict]):
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(7, 4.5))
    drawn = False
    for index, record in enumerate(records):
        table = record["train_log"]
        colour = f"C{index % 10}"
        if table is not None and {"wall_time_s", "test_psnr"} <= set(table.columns):
            curve = table[["wall_time_s", "test_psnr"]].apply(pd.to_numeric, errors="coerce")
            curve = curve.dropna()
            if len(curve):
                axes.plot(curve["wall_time_s"], curve["test_psnr"], "-o", ms=3, color=colour,
                          label=record["dataset"])
                drawn = True
        summary = record["summary"] or {}
        psnr = (summary.get("means") or {}).get("psnr_linear")
        time_s = (summary.get("training") or {}).get("time_s")
        if psnr is not None and time_s is not None:
            axes.plot([time_s], [psnr], "*", ms=12, color=colour,
                      label=None if drawn else record["dataset"])
            drawn = True
    if not drawn:
        _empty_axes(axes, "no training logs")
    else:
        axes.set_xlabel("training time (s)")
        axes.set_ylabel("held-out PSNR, linear (dB)")
        axes.set_title("Held-out PSNR during training (star: final evaluation)")
        axes.grid(alpha=0.3)
        axes.legend(fontsize=8)
    return figure


def plot_speed_vs_error(records: list[dict]):
    import matplotlib.pyplot as plt

    figure, (left, right) = plt.subplots(1, 2, figsize=(10, 4.2))
    points = []
    for record in records:
        summary = record["summary"] or {}
        psnr = (summary.get("means") or {}).get("psnr_linear")
        if psnr is None:
            continue
        label = record["dataset"] + (f"\n{record['options']}" if record.get("options") else "")
        points.append((label, (summary.get("render") or {}).get("fps"),
                       (summary.get("training") or {}).get("time_s"), psnr))
    for axes, column, xlabel in ((left, 1, "render speed (frames per second, held-out views)"),
                                 (right, 2, "training time (s)")):
        usable = [p for p in points if p[column] is not None and p[column] > 0]
        if not usable:
            _empty_axes(axes, "no finished datasets")
            continue
        for index, point in enumerate(usable):
            axes.scatter(point[column], point[3], color=f"C{index % 10}", s=40)
            axes.annotate(point[0], (point[column], point[3]), fontsize=7,
                          xytext=(4, 4), textcoords="offset points")
        values = [p[column] for p in usable]
        if max(values) > 10 * min(values):   # a log axis only pays off over a decade or more
            axes.set_xscale("log")
        axes.set_xlabel(xlabel)
        axes.set_ylabel("held-out PSNR, linear (dB)")
        axes.grid(alpha=0.3, which="both")
    figure.suptitle("Speed against quality across datasets and settings")
    return figure


def _water_values(record: dict) -> tuple[dict | None, dict | None, str]:
    """(fitted, truth, unit note): fitted in 1/m against the truth where known, else as trained."""
    truth_part = ((record["summary"] or {}).get("truth") or {}).get("water") or {}
    if truth_part.get("fitted"):
        return truth_part["fitted"], truth_part.get("truth"), "1/m"
    water = record["water_json"]
    if not isinstance(water, dict):
        return None, None, ""
    for section in (water.get("source_units"), water.get("per_source_unit"), water):
        if isinstance(section, dict) and "sigma_attn" in section:
            return {k: section.get(k, water.get(k)) for k in ("sigma_attn", "sigma_bs", "c_med")
                    if section.get(k, water.get(k)) is not None}, None, "1/source unit"
    return None, None, ""


def plot_water_parameters(records: list[dict]):
    import matplotlib.pyplot as plt

    keys = ("sigma_attn", "sigma_bs", "c_med")
    figure, axes = plt.subplots(1, 3, figsize=(12, 4))
    entries = [(r["dataset"], *_water_values(r)) for r in records]
    entries = [e for e in entries if e[1]]
    for key, ax in zip(keys, axes):
        if not entries:
            _empty_axes(ax, "no fitted water parameters")
            ax.set_title(key)
            continue
        width = 0.8 / 3
        for d, (dataset, fitted, truth, unit) in enumerate(entries):
            values = fitted.get(key)
            if values is None:
                continue
            for c, value in enumerate(np.ravel(values)[:3]):
                x = d + (c - 1) * width
                ax.bar(x, value, width, color=CHANNEL_COLOURS[c],
                       label=("R", "G", "B")[c] if d == 0 else None)
                if truth and truth.get(key) is not None:
                    ax.plot([x], [np.ravel(truth[key])[c]], marker="_", color="black",
                            markersize=14, markeredgewidth=2.5,
                            label="truth" if (d, c) == (_first_truth(entries), 0) else None)
        ax.set_xticks(range(len(entries)))
        ax.set_xticklabels([f"{e[0]}\n({e[3]})" if key != "c_med" else e[0] for e in entries],
                           fontsize=8, rotation=0)
        ax.set_title({"sigma_attn": "attenuation sigma_attn", "sigma_bs": "backscatter sigma_bs",
                      "c_med": "medium colour c_med"}[key])
        ax.grid(alpha=0.3, axis="y")
    if entries:
        axes[0].legend(fontsize=8)
    figure.suptitle("Fitted water parameters per channel (black: simulation truth; 1/m where "
                    "the truth is known)")
    figure.tight_layout()
    return figure


def _first_truth(entries) -> int:
    return next((i for i, e in enumerate(entries) if e[2]), -1)


def _strip_views(record: dict, count: int) -> list[str]:
    test_dir = record["base"] / "render" / "test"
    if not test_dir.is_dir():
        return []
    views = sorted(p.name for p in test_dir.iterdir() if p.is_dir())
    if len(views) <= count:
        return views
    return [views[i] for i in np.linspace(0, len(views) - 1, count).round().astype(int)]


def plot_strip(record: dict, count: int, height: int):
    """Rows of held-out views: ground truth | full | restored | depth | backscatter, or None."""
    import matplotlib.pyplot as plt

    views = _strip_views(record, count)
    if not views:
        return None
    psnr = {}
    if record["metrics"] is not None and "psnr_linear" in record["metrics"]:
        psnr = dict(zip(record["metrics"]["view"].astype(str), record["metrics"]["psnr_linear"]))
    first = None
    for view in views:
        for name, _ in STRIP_COLUMNS:
            path = record["base"] / "render" / "test" / view / f"{name}.png"
            if path.is_file():
                first = read_image(path)
                break
        if first is not None:
            break
    if first is None:
        return None
    aspect = first.shape[1] / first.shape[0]
    inches = height / 100
    figure, axes = plt.subplots(len(views), len(STRIP_COLUMNS), squeeze=False,
                                figsize=(len(STRIP_COLUMNS) * inches * aspect + 0.6,
                                         len(views) * inches + 0.5))
    for r, view in enumerate(views):
        for c, (name, title) in enumerate(STRIP_COLUMNS):
            ax = axes[r, c]
            path = record["base"] / "render" / "test" / view / f"{name}.png"
            if path.is_file():
                ax.imshow(np.clip(read_image(path), 0, 1))
            else:
                _empty_axes(ax, "missing")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(title, fontsize=9)
            if c == 0:
                label = view + (f"\n{psnr[view]:.2f} dB" if view in psnr
                                and pd.notna(psnr[view]) else "")
                ax.set_ylabel(label, fontsize=8)
    figure.suptitle(f"{record['dataset']}: held-out views", fontsize=10)
    figure.subplots_adjust(wspace=0.02, hspace=0.05)
    return figure


# ----------------------------------------------------------------------------------------- HTML

def _image_tag(path: Path, alt: str) -> str:
    data = base64.b64encode(Path(path).read_bytes()).decode("ascii")
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


def _format_cell(value) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "—"
    if isinstance(value, float):
        return f"{value:.4g}"
    return html.escape(str(value))


def build_html(table: pd.DataFrame, records: list[dict], out: Path, figures: list[str],
               strips: dict[str, str]) -> str:
    """A self-contained page: the summary table, failures, plots and strips inlined."""
    header = "".join(f"<th>{html.escape(c)}</th>" for c in table.columns)
    body = []
    for _, row in table.iterrows():
        css = "ok" if row["status"] == "ok" else "failed"
        cells = "".join(f"<td>{_format_cell(None if pd.isna(v) else v)}</td>"
                        if not isinstance(v, str) else f"<td>{html.escape(v)}</td>"
                        for v in row.tolist())
        body.append(f'<tr class="{css}">{cells}</tr>')
    failures = [r for r in records if r["status"] != "ok"]
    def failure_item(record: dict) -> str:
        stage = (f"stage <code>{html.escape(str(record['failed_step']))}</code>: "
                 if record["failed_step"] else "")
        return (f"<li><b>{html.escape(record['dataset'])}</b>: {stage}"
                f"<span class=\"error\">{html.escape(str(record['error']))}</span></li>")

    failure_items = "".join(failure_item(r) for r in failures)
    water_rows = []
    for record in records:
        water = ((record["summary"] or {}).get("truth") or {}).get("water") or {}
        if not water.get("fitted"):
            continue
        for key in ("sigma_attn", "sigma_bs", "c_med"):
            fitted = water["fitted"].get(key)
            truth = (water.get("truth") or {}).get(key)
            error = (water.get("relative_error") or {}).get(key)
            water_rows.append(
                f"<tr><td>{html.escape(record['dataset'])}</td><td>{key}</td>"
                f"<td>{_triple(fitted)}</td><td>{_triple(truth)}</td>"
                f"<td>{_triple(error)}</td></tr>")
    sections = [
        "<h2>Summary</h2>",
        f'<table class="summary"><thead><tr>{header}</tr></thead><tbody>{"".join(body)}'
        "</tbody></table>",
        "<p>PSNR / SSIM: held-out views, 8-bit quantised, linear (official) and sRGB-encoded. "
        "restored_*: restored render against the simulation's clean image after one colour "
        "gain per channel (fitted between the full render and the truth with water); "
        "full_vs_clean: the full render against the clean image (what no restoration gives). "
        "Depth: median absolute relative error and correlation against the simulated range "
        "after a similarity alignment of camera centres.</p>",
    ]
    if failures:
        sections += ["<h2>Datasets without results</h2>", f"<ul>{failure_items}</ul>"]
    if water_rows:
        sections += ["<h2>Water parameters against the truth (1/m; c_med after the colour "
                     "gain)</h2>",
                     "<table><thead><tr><th>dataset</th><th>parameter</th><th>fitted (R, G, B)"
                     "</th><th>truth</th><th>relative error</th></tr></thead><tbody>"
                     + "".join(water_rows) + "</tbody></table>"]
    sections.append("<h2>Plots</h2>")
    sections += [f"<figure>{_image_tag(out / name, name)}<figcaption>{html.escape(name)}"
                 "</figcaption></figure>" for name in figures]
    if strips:
        sections.append("<h2>Held-out views</h2>")
        sections += [f"<figure>{_image_tag(out / path, dataset)}<figcaption>"
                     f"{html.escape(dataset)}</figcaption></figure>"
                     for dataset, path in strips.items()]
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>SeaThru-NeRF pipeline report</title>
<style>
body {{ font-family: sans-serif; margin: 2em; color: #222; }}
table {{ border-collapse: collapse; font-size: 0.85em; margin-bottom: 1em; }}
th, td {{ border: 1px solid #ccc; padding: 0.25em 0.5em; text-align: right; }}
th {{ background: #f0f0f0; }}
td:first-child {{ text-align: left; font-weight: bold; }}
tr.failed td {{ background: #fde8e8; }}
.error {{ color: #a00; font-family: monospace; }}
img {{ max-width: 100%; }}
figure {{ margin: 1em 0; }}
</style></head><body>
<h1>SeaThru-NeRF pipeline report</h1>
<p>{len(records)} datasets, {len(records) - len(failures)} with results; generated {stamp}.</p>
{chr(10).join(sections)}
</body></html>
"""


def _triple(values) -> str:
    if values is None:
        return "—"
    return ", ".join(_format_cell(None if v is None else float(v)) for v in np.ravel(values))
