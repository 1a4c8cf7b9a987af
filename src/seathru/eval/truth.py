"""Comparison of a simulated dataset's results with the simulator's truth. Pure, no file I/O.

- colour gain: the ingest step normalises exposure and white-balances, so the pipeline's linear
  values differ from the simulator's by one gain per channel. It is measured once per dataset as
  the ratio of the truth images *with water* to the images the model was trained on (the
  camera file's linear images, sums pooled over every view, :func:`pooled_gain`), a property of
  the data and not of the model. The same gain is applied to the full and restored renders
  before comparing them with the clean truth ``J`` (and to the fitted medium colour ``c_med``),
  over the pixels where ``J`` is defined (open-water pixels, whose true range is infinite, have
  none). The full render compared with the clean truth is reported too: the restoration should
  beat it;
- metric scale (:func:`camera_metric_scale`): camera centres of the evaluated camera file
  (normalised units) are aligned to the truth centres (metres) by a similarity (Umeyama); its
  scale converts predicted depths to metres and fitted coefficients to 1/m (the camera files'
  centres come from ``seathru.io.evaluation.camera_centres``);
- water parameters (:func:`compare_water`): relative error per channel of sigma_attn, sigma_bs
  (1/m) and c_med.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from seathru.eval import metrics
from seathru.geometry.poses import sees_unhidden
from seathru.eval.summary import MetricScale, TruthSummary, WaterComparison

SIGMA_KEYS = ("sigma_attn", "sigma_bs")
WATER_KEYS = (*SIGMA_KEYS, "c_med")
COLOUR_GAIN_NOTE = ("per-channel gain: sum of the truth images with water over sum of the "
                    "camera file's linear images (every view pooled), applied to the renders "
                    "and c_med")


def camera_metric_scale(centres: Mapping[str, np.ndarray], truth_centres: Mapping[str, np.ndarray],
                        normalisation_scale: float) -> MetricScale:
    """Metres per normalised unit of the evaluated cameras, from every camera both sets know.

    Args:
        centres: camera name -> centre ``(3,)`` in the evaluated camera file (normalised units).
        truth_centres: camera name -> true centre ``(3,)`` in metres.
        normalisation_scale: the evaluated camera file's ``scale`` (normalised units per source
            unit), used alone when fewer than three cameras are shared: the source units are then
            taken to be the truth's.

    Returns:
        the scale; with three or more shared cameras from a similarity alignment of their
        centres (:func:`seathru.eval.metrics.metric_scale`), with its residuals.

    Example::

        scale = camera_metric_scale(centres, truth_centres, cameras.scale)
        depth_m = depth * scale.scale
    """
    shared = sorted(set(centres) & set(truth_centres))
    if len(shared) < 3:
        return MetricScale(scale=1.0 / normalisation_scale, rms_residual=float("nan"),
                           relative_residual=float("nan"),
                           method="camera-file normalisation only (fewer than 3 shared cameras)")
    fit = metrics.metric_scale(np.stack([centres[n] for n in shared]),
                               np.stack([truth_centres[n] for n in shared]))
    return MetricScale(scale=fit["scale"], rms_residual=fit["rms_residual"],
                       relative_residual=fit["relative_residual"],
                       method=f"similarity alignment of {len(shared)} camera centres")


def pooled_gain(pairs: Iterable[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """One colour gain ``(3,)`` over all ``(prediction, target)`` image pairs (each
    ``(H, W, 3)``; the pairs may be produced lazily, one view in memory at a time): per channel
    the target's sum over the prediction's, over the pixels where both are finite; 1 where the
    prediction sums to 0.

    Not the least-squares gain ``sum(p t) / sum(p p)``: the prediction's own error sits in its
    denominator and pulls it low (errors in the regressor). On the demo the least-squares gain
    of the linear images to the truth is 1-3% low in red; the ratio of sums agrees with the gain
    the simulator's exposure and the ingest's white balance imply to 0.2%.
    """
    target_sum, prediction_sum = np.zeros(3), np.zeros(3)
    for prediction, target in pairs:
        p = np.asarray(prediction, dtype=np.float64).reshape(-1, 3)
        t = np.asarray(target, dtype=np.float64).reshape(-1, 3)
        keep = np.all(np.isfinite(p), axis=1) & np.all(np.isfinite(t), axis=1)
        target_sum += t[keep].sum(axis=0)
        prediction_sum += p[keep].sum(axis=0)
    return np.where(prediction_sum > 0, target_sum / np.where(prediction_sum > 0,
                                                              prediction_sum, 1.0), 1.0)


def training_view_coverage(view, view_range: np.ndarray,
                           training: Iterable[tuple[object, np.ndarray]],
                           tolerance: float = 0.05) -> np.ndarray:
    """How many training views see the true surface behind each pixel of a held-out view.

    A training view sees a pixel's surface point when the point lies in front of it, inside its
    image, and that view's own true range at the pixel it projects to agrees with the point's
    range within ``tolerance`` (relative): nothing nearer hides it. Pixels no two training views
    see cannot be reconstructed by any model; scoring the restoration on them measures what was
    never photographed.

    Args:
        view: the held-out camera: ``c2w_array`` (4, 4), ``fx``, ``fy``, ``cx``, ``cy``,
            ``width``, ``height`` (a ``seathru.io.cameras.Frame``), OpenCV axes.
        view_range: ``(H, W)`` true range along each pixel's ray, in the cameras' units;
            non-finite or <= 0 where the pixel sees no surface.
        training: ``(camera, range)`` pairs of the training views, alike.
        tolerance: relative range agreement for "not hidden".

    Returns:
        ``(H, W)`` int counts; 0 where the pixel sees no surface.

    Example::

        seen = training_view_coverage(test, test_range, zip(train, train_ranges)) >= 2
    """
    view_range = np.asarray(view_range, dtype=np.float64)
    height, width = view_range.shape
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    rays = np.stack([(u - view.cx) / view.fx, (v - view.cy) / view.fy, np.ones_like(u)], -1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    c2w = np.asarray(view.c2w_array, dtype=np.float64)
    surface = np.isfinite(view_range) & (view_range > 0)
    distance = np.where(surface, view_range, 0.0)[..., None]
    points = (rays * distance) @ c2w[:3, :3].T + c2w[:3, 3]
    counts = np.zeros((height, width), dtype=np.int32)
    for camera, camera_range in training:
        counts += surface & sees_unhidden(camera, camera_range, points, tolerance)
    return counts


def view_truth_metrics(*, full: np.ndarray, restored: np.ndarray, depth: np.ndarray,
                       clean: np.ndarray, water: np.ndarray, truth_depth: np.ndarray,
                       gain: np.ndarray, metres_per_unit: float,
                       covered: np.ndarray | None = None,
                       restored_photo: np.ndarray | None = None,
                       reprojected: np.ndarray | None = None,
                       supported: np.ndarray | None = None) -> dict[str, float]:
    """The truth columns of ``metrics.csv`` for one held-out view.

    Args:
        full, restored: the renders ``(H, W, 3)``, pipeline colour scale.
        depth: rendered depth ``(H, W)``, normalised units.
        clean: the clean truth ``(H, W, 3)``; not scored where a pixel sees open water.
        water: the truth with water ``(H, W, 3)``.
        truth_depth: the true range ``(H, W)`` in metres, ``+inf`` (or NaN) where a pixel sees
            open water: those pixels have no clean truth (the simulator stores 0, older
            outputs NaN) and no depth, and are left out of the restored and depth scores.
        gain: ``(3,)`` from :func:`pooled_gain`; metres_per_unit: from
            :func:`camera_metric_scale`.
        covered: ``(H, W)`` bool or None: the pixels whose surface two or more training views
            see (:func:`training_view_coverage`); given, the restored view and the full
            render against the truth with water are also scored on those alone
            (``restored_psnr_linear_covered``, ``full_vs_water_psnr_linear_covered``: the novel
            view where a reconstruction can know it; ``covered_share`` of the scored pixels).
        restored_photo: ``(H, W, 3)`` or None: the view's photograph with the water removed
            by the model's render (``seathru.radiometry.restore``); given, scored alike
            (``photo_restored_psnr_linear``, ``..._ssim_linear``, ``..._psnr_linear_covered``).
        reprojected: ``(H, W, 3)`` or None: the restored render with the training
            photographs' restored detail reprojected into it (``seathru.nerf.reproject``);
            given, scored alike (``reprojected_restored_psnr_linear``, ...).
        supported: ``(H, W)`` bool or None: the pixels the training photographs back
            (``restored_support``); given with ``reprojected``, it is also scored on those
            alone (``reprojected_restored_psnr_linear_supported``; ``supported_share`` of the
            scored pixels).
    """
    defined = np.all(np.isfinite(clean), axis=-1) & np.isfinite(truth_depth)
    restored_m = metrics.image_metrics(gain * restored, clean, valid=defined)
    baseline = metrics.image_metrics(gain * full, clean, valid=defined)
    fit = metrics.image_metrics(gain * full, water)
    depth_m = metrics.depth_errors(depth * metres_per_unit, truth_depth)
    extra = {}

    def psnr_on(mask: np.ndarray, image: np.ndarray, reference: np.ndarray) -> float:
        return metrics.image_metrics(gain * image, reference, valid=mask)["psnr_linear"] \
            if mask.any() else float("nan")

    if covered is not None:
        seen = defined & np.asarray(covered, dtype=bool)
        extra = {"restored_psnr_linear_covered": psnr_on(seen, restored, clean),
                 "full_vs_water_psnr_linear_covered": psnr_on(seen, full, water),
                 "covered_share": float(seen.sum() / max(int(defined.sum()), 1))}
    for prefix, image in (("photo_restored", restored_photo),
                          ("reprojected_restored", reprojected)):
        if image is None:
            continue
        scores = metrics.image_metrics(gain * image, clean, valid=defined)
        extra[f"{prefix}_psnr_linear"] = scores["psnr_linear"]
        extra[f"{prefix}_ssim_linear"] = scores["ssim_linear"]
        if covered is not None:
            extra[f"{prefix}_psnr_linear_covered"] = psnr_on(seen, image, clean)
    if reprojected is not None and supported is not None:
        backed = defined & np.asarray(supported, dtype=bool)
        extra["reprojected_restored_psnr_linear_supported"] = psnr_on(backed, reprojected, clean)
        extra["supported_share"] = float(backed.sum() / max(int(defined.sum()), 1))
    return {
        "restored_psnr_linear": restored_m["psnr_linear"],
        "restored_ssim_linear": restored_m["ssim_linear"],
        "restored_psnr_srgb": restored_m["psnr_srgb"],
        "restored_ssim_srgb": restored_m["ssim_srgb"],
        "full_vs_clean_psnr_linear": baseline["psnr_linear"],
        "full_vs_clean_ssim_linear": baseline["ssim_linear"],
        "full_vs_water_psnr_linear": fit["psnr_linear"],
        "depth_median_abs_rel": depth_m["depth_median_abs_rel"],
        "depth_corr": depth_m["depth_corr"],
        "depth_rmse_m": depth_m["depth_rmse"],
        **extra,
    }


def compare_water(fitted: Mapping[str, Sequence[float]] | None,
                  truth: Mapping[str, Sequence[float]], metres_per_unit: float,
                  gain: np.ndarray,
                  halfwidth: Mapping[str, Sequence[float]] | None = None,
                  determined: Mapping[str, Sequence[bool]] | None = None) -> WaterComparison:
    """The fitted water against the truth, per channel.

    Args:
        fitted: ``sigma_attn``, ``sigma_bs`` (per normalised unit) and ``c_med`` (pipeline
            colour scale) of the trained model, each ``(3,)``; None when there is none.
        truth: the same keys in 1/m and the simulator's colour scale.
        metres_per_unit, gain: from :func:`camera_metric_scale` and :func:`pooled_gain`.

    Returns:
        the truth, the fitted values converted to 1/m (divided by ``metres_per_unit``) and to the
        truth's colour scale (c_med times ``gain``), and the relative error per channel; with
        ``halfwidth`` (the 95% half-widths of water.json's uncertainty, normalised units) and
        ``determined``, the converted intervals and whether each holds the truth.
    """
    result = WaterComparison(truth={k: [float(x) for x in truth[k]] for k in WATER_KEYS})
    if fitted is None:
        return result
    converted = {key: (np.asarray(fitted[key], dtype=np.float64) / metres_per_unit).tolist()
                 for key in SIGMA_KEYS}
    converted["c_med"] = (np.asarray(fitted["c_med"], dtype=np.float64) * gain).tolist()
    result.fitted = converted
    result.relative_error = {key: metrics.relative_error(converted[key], truth[key]).tolist()
                             for key in WATER_KEYS}
    if halfwidth is not None:
        factor = {"sigma_attn": 1.0 / metres_per_unit, "sigma_bs": 1.0 / metres_per_unit,
                  "c_med": np.asarray(gain, dtype=np.float64)}
        result.interval95, result.contains_truth = {}, {}
        for key in WATER_KEYS:
            centre = np.asarray(fitted[key], dtype=np.float64)
            half = np.asarray([np.inf if h is None else h for h in halfwidth[key]],
                              dtype=np.float64)
            low = np.maximum(0.0, centre - half) * factor[key]
            high = (centre + half) * factor[key]
            result.interval95[key] = [[float(lo), float(hi) if np.isfinite(hi) else None]
                                      for lo, hi in zip(low, high)]
            result.contains_truth[key] = [bool(lo <= tr <= hi) for lo, hi, tr in
                                          zip(low, high, truth[key])]
        result.determined = {k: [bool(v) for v in determined[k]] for k in WATER_KEYS} \
            if determined is not None else None
    return result


def truth_summary(gain: np.ndarray, scale: MetricScale, water: WaterComparison) -> TruthSummary:
    """The ``truth`` section of ``summary.json``."""
    return TruthSummary(colour_gain=np.asarray(gain, dtype=np.float64).tolist(),
                        colour_gain_note=COLOUR_GAIN_NOTE, metric_scale=scale, water=water)
