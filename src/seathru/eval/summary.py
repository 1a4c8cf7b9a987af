"""One dataset's evaluation: per-view image metrics and the summary. Pure, no file I/O.

Per held-out view, the full-colour render is compared with the view's linear image the way the
NeRF papers do (:func:`seathru.eval.metrics.image_metrics`): PSNR and SSIM, linear (the official
SeaThru-NeRF evaluation) and after sRGB encoding; LPIPS on the linear 8-bit images when a network
is given, else ``unavailable``.

The result types defined here (:class:`ViewMetrics`, :class:`EvaluationSummary` and its parts)
are what ``seathru.io.evaluation`` writes as ``metrics.csv`` and ``summary.json``.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, NotRequired, TypedDict

import numpy as np
import pandas as pd

from seathru.eval import metrics

log = logging.getLogger(__name__)

UNAVAILABLE = "unavailable"
IMAGE_COLUMNS = ("psnr_linear", "ssim_linear", "psnr_srgb", "ssim_srgb")
VIEW_COLUMNS = ("dataset", "view", *IMAGE_COLUMNS, "lpips")
#: Columns a view has where its renders allow (the render step's ``restored_support``).
SUPPORT_COLUMNS = ("unseen_surface_share",)
#: Below this opacity a rendered pixel is open water, not a surface of the view.
SURFACE_OPACITY = 0.5
TRUTH_COLUMNS = ("restored_psnr_linear", "restored_ssim_linear", "restored_psnr_srgb",
                 "restored_ssim_srgb", "full_vs_clean_psnr_linear", "full_vs_clean_ssim_linear",
                 "full_vs_water_psnr_linear", "depth_median_abs_rel", "depth_corr",
                 "depth_rmse_m", "restored_psnr_linear_covered",
                 "full_vs_water_psnr_linear_covered", "covered_share",
                 "photo_restored_psnr_linear", "photo_restored_ssim_linear",
                 "photo_restored_psnr_linear_covered", "reprojected_restored_psnr_linear",
                 "reprojected_restored_ssim_linear", "reprojected_restored_psnr_linear_covered",
                 "reprojected_restored_psnr_linear_supported", "supported_share")


class ViewMetrics(TypedDict):
    """One held-out view's metrics (a row of ``metrics.csv``)."""

    dataset: str
    view: str
    psnr_linear: float
    ssim_linear: float
    psnr_srgb: float
    ssim_srgb: float
    lpips: float | str                          # a number or "unavailable"
    unseen_surface_share: NotRequired[float]    # of its surface, no training photograph sees
    restored_psnr_linear: NotRequired[float]    # the truth columns: simulated datasets only
    restored_ssim_linear: NotRequired[float]
    restored_psnr_srgb: NotRequired[float]
    restored_ssim_srgb: NotRequired[float]
    full_vs_clean_psnr_linear: NotRequired[float]
    full_vs_clean_ssim_linear: NotRequired[float]
    full_vs_water_psnr_linear: NotRequired[float]
    depth_median_abs_rel: NotRequired[float]
    depth_corr: NotRequired[float]
    depth_rmse_m: NotRequired[float]
    restored_psnr_linear_covered: NotRequired[float]   # on pixels 2+ training views see
    full_vs_water_psnr_linear_covered: NotRequired[float]
    covered_share: NotRequired[float]                   # of the pixels restored_* scores
    photo_restored_psnr_linear: NotRequired[float]      # the photograph restored by the model
    photo_restored_ssim_linear: NotRequired[float]
    photo_restored_psnr_linear_covered: NotRequired[float]
    reprojected_restored_psnr_linear: NotRequired[float]   # with the photographs' detail
    reprojected_restored_ssim_linear: NotRequired[float]
    reprojected_restored_psnr_linear_covered: NotRequired[float]
    reprojected_restored_psnr_linear_supported: NotRequired[float]  # the pixels it backs
    supported_share: NotRequired[float]


@dataclass(kw_only=True)
class RenderSpeed:
    """Render speed of the held-out views (from the render step's ``render_stats.json``)."""

    fps: float | None = None
    seconds_per_frame: float | None = None
    resolution: list | None = None      # [width, height], or a list of them
    device: str | None = None


@dataclass(kw_only=True)
class TrainingSummary:
    """Training time and last logged values (from ``train_log.csv``)."""

    time_s: float
    steps: int | None = None
    final_loss: float | None = None
    final_test_psnr: float | None = None


@dataclass(kw_only=True)
class MetricScale:
    """Truth units (metres) per normalised unit and how it was found."""

    scale: float
    rms_residual: float | None = None
    relative_residual: float | None = None
    method: str = ""


@dataclass(kw_only=True)
class WaterComparison:
    """Fitted water (1/m, c_med after the colour gain) against the truth, per channel."""

    truth: dict[str, list[float]]
    fitted: dict[str, list[float]] | None = None
    relative_error: dict[str, list[float | None]] | None = None
    interval95: dict[str, list[list[float | None]]] | None = None  # converted like ``fitted``
    contains_truth: dict[str, list[bool]] | None = None
    determined: dict[str, list[bool]] | None = None   # from water.json's uncertainty


@dataclass(kw_only=True)
class TruthSummary:
    """Comparison with the simulator's truth (simulated datasets)."""

    colour_gain: list[float]
    colour_gain_note: str
    metric_scale: MetricScale
    water: WaterComparison


@dataclass(kw_only=True)
class EvaluationSummary:
    """One dataset's evaluation (``summary.json``)."""

    dataset: str
    views: int
    means: dict[str, float | str]       # column of metrics.csv -> mean ("lpips" may be a note)
    lpips: str                          # "available (net, path)" or "unavailable: why"
    render: RenderSpeed = field(default_factory=RenderSpeed)
    training: TrainingSummary | None = None
    water_fitted: dict | None = None    # the train step's water.json content
    medium_selection: dict | None = None
    truth: TruthSummary | None = None
    protocol: dict | None = None        # NerfBaselines' protocol: means, views, folder
    colour_chart: dict | None = None    # seathru.io.chart's measurement, or why there is none
    track_colour_slope: dict | None = None  # seathru.io.tracks: colour vs range along tracks


def lpips_network(state: Mapping | None, source: str | os.PathLike | None):
    """(network or None, status line of ``summary.json``) from LPIPS weights.

    Args:
        state: the weights (``seathru.io.evaluation.read_lpips_weights``), None when absent.
        source: where they were looked for, None when not configured.

    Raises:
        ValueError: the weights exist but are not LPIPS v0.1 AlexNet / VGG weights.
    """
    if source is None:
        return None, f"{UNAVAILABLE}: no --lpips-weights given"
    if state is None:
        log.warning("LPIPS weights %s not found: LPIPS unavailable", source)
        return None, f"{UNAVAILABLE}: {source} not found"
    network = metrics.lpips_from_state_dict(state)
    return network, f"available ({network.net_name}, {source})"


def view_metrics(dataset: str, view: str, full: np.ndarray, target: np.ndarray,
                 lpips_network=None) -> ViewMetrics:
    """The image columns of one held-out view's metrics.

    Args:
        full: the full render ``(H, W, 3)``, linear; target: the held-out image, same shape.
        lpips_network: from :func:`lpips_network`, or None.
    """
    row: dict[str, Any] = {"dataset": dataset, "view": view,
                           **metrics.image_metrics(full, target), "lpips": UNAVAILABLE}
    if lpips_network is not None:
        try:
            row["lpips"] = metrics.lpips_distance(lpips_network, metrics.quantise_8bit(full),
                                                  metrics.quantise_8bit(target))
        except ValueError as exc:
            log.warning("%s: LPIPS unavailable (%s)", view, exc)
    return row  # type: ignore[return-value]


def metrics_table(rows: list[ViewMetrics]) -> pd.DataFrame:
    """The views' metrics as a table: :data:`VIEW_COLUMNS`, then the truth columns present."""
    table = pd.DataFrame(rows)
    missing = [c for c in VIEW_COLUMNS if c not in table.columns]
    if missing:
        raise ValueError(f"metrics rows lack the columns {missing}")
    return table[[*VIEW_COLUMNS, *(c for c in (*SUPPORT_COLUMNS, *TRUTH_COLUMNS)
                                   if c in table.columns)]]


def unseen_surface_share(support: np.ndarray, opacity: np.ndarray) -> float | None:
    """The share of a held-out view's surface that no training photograph sees.

    A held-out view at the end of a camera path can show surfaces no training view does (the
    foreground in front of the path's first frame); its scores there measure the model's guess,
    not the reconstruction. Found with the model's own depth, so it works without a truth.

    Args:
        support: ``(H, W)`` the render step's ``restored_support``: how much the training
            photographs back each pixel (``seathru.nerf.reproject``; 0 where no training view
            sees the pixel's surface unhidden).
        opacity: ``(H, W)`` the rendered object opacity; the view's surface is where it is at
            least :data:`SURFACE_OPACITY`.

    Returns:
        the share in [0, 1], or None where the view shows no surface.

    Example::

        unseen_surface_share(read_image(".../restored_support.tiff"),
                             read_image(".../opacity.tiff"))   # 0.16 for the demo's first view
    """
    surface = np.nan_to_num(np.asarray(opacity, dtype=np.float64)) >= SURFACE_OPACITY
    if not surface.any():
        return None
    unseen = surface & ~(np.nan_to_num(np.asarray(support, dtype=np.float64)) > 0.0)
    return float(unseen.sum() / surface.sum())


def view_means(table: pd.DataFrame) -> dict[str, float | str]:
    """Mean of every numeric column of the metrics table (not dataset / view); ``lpips`` is
    ``unavailable`` when no view has a number."""
    numeric = table.drop(columns=["dataset", "view"]).apply(pd.to_numeric, errors="coerce")
    means: dict[str, float | str] = {column: float(numeric[column].mean())
                                     for column in numeric.columns
                                     if numeric[column].notna().any()}
    if "lpips" not in means:
        means["lpips"] = UNAVAILABLE
    return means


def training_summary(train_log: pd.DataFrame | None) -> TrainingSummary | None:
    """Training time and the last logged loss and test PSNR (None without a usable log)."""
    if train_log is None or train_log.empty or "wall_time_s" not in train_log:
        return None
    last = train_log.iloc[-1]
    test_psnr = train_log["test_psnr"].dropna() if "test_psnr" in train_log else pd.Series([])
    return TrainingSummary(
        time_s=float(train_log["wall_time_s"].max()),
        steps=int(last["step"]) if "step" in train_log else None,
        final_loss=float(last["loss"]) if "loss" in train_log else None,
        final_test_psnr=float(test_psnr.iloc[-1]) if len(test_psnr) else None)


def render_speed(render_stats: dict | None) -> RenderSpeed:
    """The headline speed of the render step's ``render_stats.json`` content."""
    stats = render_stats or {}
    return RenderSpeed(fps=stats.get("fps"), seconds_per_frame=stats.get("seconds_per_frame"),
                       resolution=stats.get("resolution"),
                       device=(stats.get("settings") or {}).get("device"))


def build_summary(dataset: str, table: pd.DataFrame, *, lpips_status: str,
                  render_stats: dict | None = None, train_log: pd.DataFrame | None = None,
                  water: dict | None = None, selection: dict | None = None,
                  truth: TruthSummary | None = None, protocol: dict | None = None,
                  colour_chart: dict | None = None,
                  track_colour_slope: dict | None = None) -> EvaluationSummary:
    """One dataset's summary from its metrics table and the other steps' records.

    Args:
        table: from :func:`metrics_table`.
        render_stats, water, selection: the content of the render step's
            ``render_stats.json`` and the train step's ``water.json`` and ``selection.json``.
        train_log: the train step's ``train_log.csv``.
        protocol: ``seathru.io.nerfbaselines.evaluate_nerfbaselines``'s summary part.
        colour_chart: ``seathru.io.chart.evaluate_colour_chart``'s result.
        track_colour_slope: ``seathru.io.tracks.track_colour_slope``'s result.
    """
    return EvaluationSummary(dataset=dataset, views=len(table), means=view_means(table),
                             lpips=lpips_status, render=render_speed(render_stats),
                             training=training_summary(train_log), water_fitted=water,
                             medium_selection=selection, truth=truth, protocol=protocol,
                             colour_chart=colour_chart, track_colour_slope=track_colour_slope)
