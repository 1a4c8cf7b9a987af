"""The report's plots, as matplotlib figures (the caller saves them; :func:`figure_png` renders
one to PNG bytes and closes it). No file I/O.

- :func:`plot_psnr_vs_time`: held-out PSNR during training against training time, per dataset;
- :func:`plot_speed_vs_error`: render frames per second and training time against held-out PSNR;
- :func:`plot_water_parameters`: fitted water parameters per dataset and channel, truth markers;
- :func:`plot_frontier`: one dataset's runs (its sheet row and sweep variants), each labelled
  with its capacity level: held-out PSNR (and restored-vs-clean) of every snapshot against
  training time, and the final PSNR against render time per frame, each with its Pareto front;
- :func:`plot_strip`: ground truth | full render | restored | photograph restored | depth |
  backscatter for a few held-out views of one dataset;
- :func:`plot_chart_swatches`: a measured colour chart's patches, reference against the photo,
  the ingest image and the restored render (:func:`chart_swatches`).

Call ``matplotlib.use("Agg")`` first on machines without a display.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd

from seathru.eval.colour_chart import CHARTS, lab_to_linear_srgb
from seathru.eval.frontier import final_point, pareto_front, snapshot_curve
from seathru.eval.report import CHART_IMAGES, water_intervals, water_values
from seathru.eval.report_records import DatasetRecord, capacity_level
from seathru.eval.truth import WATER_KEYS
from seathru.radiometry.colour import linear_to_srgb

STRIP_COLUMNS = (("gt", "ground truth"), ("full", "full render"), ("restored", "restored"),
                 ("restored_reprojected", "restored + photos' detail"),
                 ("restored_support", "support (white: backed)"),
                 ("restored_photo", "photograph restored"), ("depth", "depth"),
                 ("backscatter", "backscatter"))
CHANNEL_COLOURS = ("#d62728", "#2ca02c", "#1f77b4")
WATER_TITLES = {"sigma_attn": "attenuation sigma_attn", "sigma_bs": "backscatter sigma_bs",
                "c_med": "medium colour c_med"}


def figure_png(figure, dpi: int = 110) -> bytes:
    """The figure as PNG bytes (tight bounding box); the figure is closed."""
    import matplotlib.pyplot as plt

    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(figure)
    return buffer.getvalue()


def _empty_axes(axes, text: str) -> None:
    axes.text(0.5, 0.5, text, ha="center", va="center", transform=axes.transAxes, color="0.4")
    axes.set_xticks([])
    axes.set_yticks([])


def _final_psnr_and_time(record: DatasetRecord) -> tuple[float | None, float | None]:
    summary = record.summary
    if summary is None:
        return None, None
    psnr = summary.means.get("psnr_linear")
    return psnr, summary.training.time_s if summary.training else None


def plot_psnr_vs_time(records: Sequence[DatasetRecord]):
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(7, 4.5))
    drawn = False
    for index, record in enumerate(records):
        table = record.train_log
        colour = f"C{index % 10}"
        if table is not None and {"wall_time_s", "test_psnr"} <= set(table.columns):
            curve = table[["wall_time_s", "test_psnr"]].apply(pd.to_numeric, errors="coerce")
            curve = curve.dropna()
            if len(curve):
                axes.plot(curve["wall_time_s"], curve["test_psnr"], "-o", ms=3, color=colour,
                          label=record.dataset)
                drawn = True
        psnr, time_s = _final_psnr_and_time(record)
        if psnr is not None and time_s is not None:
            axes.plot([time_s], [psnr], "*", ms=12, color=colour,
                      label=None if drawn else record.dataset)
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


def plot_speed_vs_error(records: Sequence[DatasetRecord]):
    import matplotlib.pyplot as plt

    figure, (left, right) = plt.subplots(1, 2, figsize=(10, 4.2))
    points = []
    for record in records:
        psnr, time_s = _final_psnr_and_time(record)
        if psnr is None:
            continue
        label = record.dataset + (f"\n{record.options}" if record.options else "")
        points.append((label, record.summary.render.fps, time_s, psnr))
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


def plot_water_parameters(records: Sequence[DatasetRecord]):
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 3, figsize=(12, 4))
    entries = [(r.dataset, *water_values(r), *water_intervals(r)) for r in records]
    entries = [e for e in entries if e[1]]
    first_truth = next((i for i, e in enumerate(entries) if e[2]), -1)
    width = 0.8 / 3
    for key, ax in zip(WATER_KEYS, axes):
        if not entries:
            _empty_axes(ax, "no fitted water parameters")
            ax.set_title(key)
            continue
        for d, (dataset, fitted, truth, unit, interval, determined) in enumerate(entries):
            values = fitted.get(key)
            if values is None:
                continue
            for c, value in enumerate(np.ravel(values)[:3]):
                x = d + (c - 1) * width
                sure = determined is None or determined[key][c]
                ax.bar(x, value, width, color=CHANNEL_COLOURS[c], alpha=1.0 if sure else 0.35,
                       hatch=None if sure else "//",
                       label=("R", "G", "B")[c] if d == 0 else None)
                if interval is not None:
                    low, high = interval[key][c]
                    top = high if high is not None else ax.get_ylim()[1]
                    ax.plot([x, x], [low, top], color="0.25", linewidth=1.2,
                            linestyle="-" if high is not None else ":")
                if truth and truth.get(key) is not None:
                    ax.plot([x], [np.ravel(truth[key])[c]], marker="_", color="black",
                            markersize=14, markeredgewidth=2.5,
                            label="truth" if (d, c) == (first_truth, 0) else None)
        ax.set_xticks(range(len(entries)))
        ax.set_xticklabels([f"{e[0]}\n({e[3]})" if key != "c_med" else e[0] for e in entries],
                           fontsize=8, rotation=0)
        ax.set_title(WATER_TITLES[key])
        ax.grid(alpha=0.3, axis="y")
    if entries:
        axes[0].legend(fontsize=8)
    figure.suptitle("Fitted water per channel: grey lines 95% intervals, hatched bars not "
                    "determined by the views, black ticks the simulation truth (1/m where known)")
    figure.tight_layout()
    return figure


def _front_line(axes, times, values, x_end, **style) -> None:
    """The Pareto front of ``(times, values)`` as a staircase held to ``x_end``."""
    front = pareto_front(times, values)
    if len(front):
        xs, ys = np.asarray(times)[front], np.asarray(values)[front]
        axes.step([*xs, max(x_end, xs[-1])], [*ys, ys[-1]], where="post", **style)


def _log_if_wide(axes, values) -> None:
    values = [v for v in values if v is not None and v > 0]
    if values and max(values) > 10 * min(values):   # a log axis pays off over a decade or more
        axes.set_xscale("log")


def plot_frontier(dataset: str, runs: Sequence[DatasetRecord]):
    """One dataset's runs on the same axes, or None when none has a snapshot or a final point.
    Each run is labelled ``<run> [<capacity level>]`` where its level is known
    (``seathru.eval.report_records.capacity_level``: ``auto → fast``, ``quality``).

    Left: held-out PSNR on whole images (snapshots, ``frontier.csv``) against training time, per
    run, with restored-vs-clean where the truth is known (dashed); a run without snapshots shows
    its final evaluation (star); black: the Pareto front of the held-out PSNR (the best any run
    reached within that time), grey dashed: that of restored-vs-clean. Right: final held-out PSNR
    (full resolution) against render time per frame, restored-vs-clean hollow, with the front.
    """
    import matplotlib.pyplot as plt

    curves = [(r, *snapshot_curve(r), snapshot_curve(r, "restored_psnr_linear"), final_point(r))
              for r in runs]
    if not any(len(c[1]) or c[4]["psnr_linear"] is not None for c in curves):
        return None
    figure, (left, right) = plt.subplots(1, 2, figsize=(11.5, 4.4))
    points = {"held": ([], []), "restored": ([], [])}
    for index, (record, times, psnr, (r_times, restored), final) in enumerate(curves):
        level = capacity_level(record)
        colour, label = f"C{index % 10}", record.dataset + (f" [{level}]" if level else "")
        if len(times):
            left.plot(times, psnr, "-o", ms=4, color=colour, label=label)
            points["held"][0].extend(times)
            points["held"][1].extend(psnr)
        elif final["psnr_linear"] is not None and final["train_time_s"]:
            left.plot([final["train_time_s"]], [final["psnr_linear"]], "*", ms=11,
                      color=colour, label=f"{label} (final only)")
        if len(r_times):
            left.plot(r_times, restored, "--^", ms=4, color=colour, alpha=0.7,
                      label=f"{label}: restored vs clean")
            points["restored"][0].extend(r_times)
            points["restored"][1].extend(restored)
        if final["psnr_linear"] is not None and final["render_s_per_frame"]:
            right.plot([final["render_s_per_frame"]], [final["psnr_linear"]], "o", ms=8,
                       color=colour, label=label)
            if final["restored_psnr_linear"] is not None:
                right.plot([final["render_s_per_frame"]], [final["restored_psnr_linear"]], "^",
                           ms=8, mfc="none", color=colour)
    x_end = max([max(xs) for xs, _ in points.values() if xs] or [1.0])
    _front_line(left, *points["held"], x_end, color="black", lw=1.5, alpha=0.8,
                label="Pareto front (held-out)")
    _front_line(left, *points["restored"], x_end, color="0.5", lw=1.2, ls="--",
                label="Pareto front (restored)")
    _log_if_wide(left, [*points["held"][0], *points["restored"][0]])
    left.set_xlabel("training time (s)")
    left.set_ylabel("PSNR, linear (dB)")
    left.set_title("Snapshots: held-out whole images (solid), restored vs clean (dashed)",
                   fontsize=9)
    left.grid(alpha=0.3, which="both")
    left.legend(fontsize=7)
    finals = [(c[4]["render_s_per_frame"], c[4]["psnr_linear"]) for c in curves
              if c[4]["psnr_linear"] is not None and c[4]["render_s_per_frame"]]
    if finals:
        xs, ys = zip(*finals)
        _front_line(right, xs, ys, max(xs), color="black", lw=1.5, alpha=0.8,
                    label="Pareto front")
        _log_if_wide(right, xs)
        right.set_xlabel("render time per frame (s, held-out views)")
        right.set_ylabel("final held-out PSNR, linear (dB)")
        right.set_title("Final evaluation (restored vs clean: hollow)", fontsize=9)
        right.grid(alpha=0.3, which="both")
        right.legend(fontsize=7)
    else:
        _empty_axes(right, "no render times")
    figure.suptitle(f"{dataset}: quality against time ({len(runs)} run"
                    f"{'s' if len(runs) != 1 else ''})")
    figure.tight_layout()
    return figure


def strip_views(views: Sequence[str], count: int) -> list[str]:
    """At most ``count`` of the (sorted) held-out views, spread evenly over them."""
    views = sorted(views)
    if len(views) <= count:
        return views
    return [views[i] for i in np.linspace(0, len(views) - 1, count).round().astype(int)]


def plot_strip(record: DatasetRecord,
               images: Mapping[str, Mapping[str, np.ndarray | None]], height: int):
    """Rows of held-out views: ground truth | full | restored | photograph restored | depth |
    backscatter, or None when there is no image.

    Args:
        images: view -> {column name of :data:`STRIP_COLUMNS` -> display image (H, W, 3) in
            [0, 1], or None when missing}.
        height: height in pixels of one image.
    """
    import matplotlib.pyplot as plt

    views = list(images)
    first = next((image for view in views for name, _ in STRIP_COLUMNS
                  if (image := images[view].get(name)) is not None), None)
    if first is None:
        return None
    psnr = {}
    if record.metrics is not None and "psnr_linear" in record.metrics:
        psnr = dict(zip(record.metrics["view"].astype(str), record.metrics["psnr_linear"]))
    aspect = first.shape[1] / first.shape[0]
    inches = height / 100
    figure, axes = plt.subplots(len(views), len(STRIP_COLUMNS), squeeze=False,
                                figsize=(len(STRIP_COLUMNS) * inches * aspect + 0.6,
                                         len(views) * inches + 0.5))
    for r, view in enumerate(views):
        for c, (name, title) in enumerate(STRIP_COLUMNS):
            ax = axes[r, c]
            image = images[view].get(name)
            if image is not None:
                ax.imshow(np.clip(image, 0, 1))
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
    figure.suptitle(f"{record.dataset}: held-out views", fontsize=10)
    figure.subplots_adjust(wspace=0.02, hspace=0.05)
    return figure


def _floats(values) -> np.ndarray:
    """A JSON list (of lists) of numbers with nulls as a float array, nulls as NaN."""
    array = np.asarray(values, dtype=object)
    return np.array([np.nan if v is None else v for v in array.ravel()],
                    dtype=np.float64).reshape(array.shape)


def chart_swatches(chart: Mapping) -> dict[str, dict] | None:
    """The colours to draw of a measured chart (the evaluate step's ``colour_chart``), by row:
    ``reference`` and, for each image of ``CHART_IMAGES`` measured, its label.

    Returns:
        label -> ``{"srgb": (patches, 3) display colours in [0, 1] (NaN: not measured),
        "delta_e00": (patches,) (NaN: not scored), "mean_delta_e00"}``; measured patches at the
        exposure scale the error uses (one scalar: a colour cast stays visible). None for a
        chart type this version does not know or without a measured image.

    Example::

        rows = chart_swatches(summary.colour_chart)   # {"reference": ..., "photo": ...}
    """
    spec = CHARTS.get(chart.get("chart")) if isinstance(chart, Mapping) else None
    if spec is None:
        return None
    reference = lab_to_linear_srgb(spec.reference_lab)
    rows = {"reference": {"srgb": linear_to_srgb(np.clip(reference, 0.0, 1.0)),
                          "delta_e00": np.full(spec.patches, np.nan), "mean_delta_e00": None}}
    for key, label in CHART_IMAGES:
        part = chart.get(key)
        if not isinstance(part, Mapping) or part.get("patch_means") is None:
            continue
        means = _floats(part["patch_means"])
        scale = part.get("exposure_scale")
        if means.shape != (spec.patches, 3) or scale is None or not np.isfinite(scale):
            continue
        delta = _floats(part.get("delta_e00") or [None] * spec.patches)
        rows[label] = {"srgb": linear_to_srgb(np.clip(scale * means, 0.0, 1.0)),
                       "delta_e00": delta, "mean_delta_e00": part.get("mean_delta_e00")}
    return rows if len(rows) > 1 else None


def plot_chart_swatches(dataset: str, chart: Mapping):
    """One row of swatches per image (:func:`chart_swatches`), patches left to right in the
    chart's order; excluded patches crossed, each measured patch labelled with its CIEDE2000.
    None when there is nothing to draw."""
    import matplotlib.pyplot as plt

    rows = chart_swatches(chart)
    if rows is None:
        return None
    labels = list(rows)
    colours = np.stack([rows[label]["srgb"] for label in labels])
    patches = colours.shape[1]
    excluded = {int(i) for i in (*chart.get("occluded", []), *chart.get("clipped", []))}
    figure, axes = plt.subplots(figsize=(max(4.0, 0.42 * patches + 1.6), 0.5 * len(labels) + 0.9))
    axes.imshow(np.where(np.isfinite(colours), colours, 1.0), aspect="equal",
                interpolation="nearest")
    for r, label in enumerate(labels):
        for c in range(patches):
            if r and (c in excluded or not np.isfinite(colours[r, c]).all()):
                axes.text(c, r, "\u00d7", ha="center", va="center", fontsize=12, color="0.3")
            elif np.isfinite(delta := rows[label]["delta_e00"][c]):
                light = float(colours[r, c] @ [0.2126, 0.7152, 0.0722]) > 0.55
                axes.text(c, r, f"{delta:.0f}", ha="center", va="center", fontsize=6,
                          color="black" if light else "white")
    axes.set_yticks(range(len(labels)))
    axes.set_yticklabels([label if rows[label]["mean_delta_e00"] is None else
                          f"{label}  \u0394E00 {rows[label]['mean_delta_e00']:.1f}"
                          for label in labels], fontsize=8)
    axes.set_xticks(range(patches))
    axes.set_xticklabels([str(c + 1) for c in range(patches)], fontsize=6)
    axes.tick_params(length=0)
    axes.set_title(f"{dataset}: {chart.get('chart')} in {chart.get('image')}", fontsize=9)
    return figure
