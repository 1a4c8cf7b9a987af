"""Comparison with the simulator's truth (seathru.eval.truth): hand-worked values and exact
recoveries of fabricated transforms."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from seathru.eval import metrics, truth

TRUTH = {"sigma_attn": [0.55, 0.25, 0.20], "sigma_bs": [0.45, 0.30, 0.25],
         "c_med": [0.04, 0.20, 0.28]}
GAIN = np.array([2.0, 1.25, 0.8])


def test_compare_water_converts_units_and_colour_then_takes_relative_errors():
    metres_per_unit = 2.0
    fitted = {"sigma_attn": [1.1, 0.5, 0.44],   # 1/m after / 2: 0.55, 0.25, 0.22 (B 10 % high)
              "sigma_bs": [0.9, 0.6, 0.5],
              "c_med": [0.02, 0.16, 0.35]}         # * GAIN: 0.04, 0.2, 0.28
    result = truth.compare_water(fitted, TRUTH, metres_per_unit, GAIN)
    np.testing.assert_allclose(result.fitted["sigma_attn"], [0.55, 0.25, 0.22])
    np.testing.assert_allclose(result.fitted["c_med"], TRUTH["c_med"])
    np.testing.assert_allclose(result.relative_error["sigma_attn"], [0.0, 0.0, 0.1], atol=1e-12)
    np.testing.assert_allclose(result.relative_error["sigma_bs"], [0.0, 0.0, 0.0], atol=1e-12)
    assert result.truth == TRUTH


def test_compare_water_without_a_fit_reports_the_truth_alone():
    result = truth.compare_water(None, TRUTH, 2.0, GAIN)
    assert result.fitted is None and result.relative_error is None
    assert result.truth["sigma_bs"] == TRUTH["sigma_bs"]


def test_metric_scale_undoes_a_similarity():
    rng = np.random.default_rng(3)
    metres = rng.normal(size=(5, 3)) * 3.0
    rotation = Rotation.from_euler("xyz", [10, 40, -70], degrees=True).as_matrix()
    normalised = 0.4 * metres @ rotation.T + [1.0, -2.0, 0.5]   # 0.4 units per metre
    names = [f"v{i}" for i in range(5)]
    truth_centres = dict(zip(names, metres))
    truth_centres["only_in_truth"] = np.array([100.0, 0.0, 0.0])
    scale = truth.camera_metric_scale(dict(zip(names, normalised)), truth_centres, 0.1)
    assert scale.scale == pytest.approx(2.5, rel=1e-9)
    assert scale.relative_residual < 1e-9 and "5 camera centres" in scale.method


def test_metric_scale_with_too_few_shared_cameras_uses_the_normalisation():
    centres = {name: np.zeros(3) for name in "abcd"}
    scale = truth.camera_metric_scale(centres, {"a": np.ones(3), "x": np.ones(3)}, 0.25)
    assert scale.scale == 4.0 and "fewer than 3" in scale.method


def test_pooled_gain_pools_the_views_and_ignores_undefined_pixels():
    rng = np.random.default_rng(0)
    predictions = [rng.random((6, 5, 3)) for _ in range(3)]
    targets = [p * GAIN + rng.normal(0, 0.01, p.shape) for p in predictions]
    targets[0][0, 0] = np.inf                           # open water's range: left out
    pooled = truth.pooled_gain(zip(predictions, targets))
    keep = [np.isfinite(t).all(-1) for t in targets]
    together = (sum(t[k].sum(0) for t, k in zip(targets, keep))
                / sum(p[k].sum(0) for p, k in zip(predictions, keep)))
    np.testing.assert_allclose(pooled, together, rtol=1e-12)
    np.testing.assert_allclose(pooled, GAIN, rtol=0.02)


def test_pooled_gain_is_not_pulled_low_by_the_renders_own_error():
    """A render with zero-mean error (noise, blur) against exact truth: least squares puts the
    error in its denominator and comes out low; the gain must not."""
    rng = np.random.default_rng(2)
    clean = [rng.uniform(0.05, 0.4, (128, 128, 3)) for _ in range(3)]
    renders = [c + rng.normal(0, 0.1, c.shape) for c in clean]     # 3:1 signal to error
    targets = [c * GAIN for c in clean]
    pooled = truth.pooled_gain(zip(renders, targets))
    least_squares = metrics.fit_channel_gain(np.concatenate(renders), np.concatenate(targets))
    np.testing.assert_allclose(pooled, GAIN, rtol=0.01)
    assert np.all(least_squares < 0.9 * GAIN)           # what a least-squares gain gives


def test_view_truth_metrics_scores_defined_pixels_in_metres():
    rng = np.random.default_rng(1)
    clean = rng.uniform(0.1, 0.9, (16, 16, 3))
    clean[:3, :3] = np.nan                          # open water: no clean value
    restored = np.nan_to_num(clean) / GAIN          # exact after the gain
    full = restored * 0.5 + 0.1
    truth_depth = rng.uniform(1.0, 5.0, (16, 16))
    row = truth.view_truth_metrics(full=full, restored=restored, depth=truth_depth / 3.0,
                                   clean=clean, water=full * GAIN, truth_depth=truth_depth,
                                   gain=GAIN, metres_per_unit=3.0)
    assert row["restored_psnr_linear"] == float("inf")
    assert row["full_vs_water_psnr_linear"] == float("inf")
    assert row["full_vs_clean_psnr_linear"] < 30
    assert row["depth_median_abs_rel"] == pytest.approx(0.0, abs=1e-12)
    assert row["depth_corr"] == pytest.approx(1.0)


def test_water_intervals_are_converted_like_the_values_and_checked_against_the_truth():
    from seathru.eval.truth import compare_water

    fitted = {"sigma_attn": [0.2, 0.1, 0.1], "sigma_bs": [0.1, 0.1, 0.1], "c_med": [0.1, 0.2, 0.3]}
    truth = {"sigma_attn": [0.1, 0.07, 0.5], "sigma_bs": [0.05, 0.05, 0.07],
             "c_med": [0.2, 0.4, 0.6]}
    half = {"sigma_attn": [0.02, 0.02, 0.02], "sigma_bs": [0.1, None, 0.01],
            "c_med": [0.01, 0.01, 0.01]}
    determined = {k: [True, False, True] for k in half}
    result = compare_water(fitted, truth, metres_per_unit=2.0, gain=np.array([2.0, 2.0, 2.0]),
                           halfwidth=half, determined=determined)
    assert result.fitted["sigma_attn"] == [0.1, 0.05, 0.05]
    assert np.allclose(result.interval95["sigma_attn"][0], [0.09, 0.11])
    assert result.contains_truth["sigma_attn"] == [True, False, False]
    assert result.interval95["sigma_bs"][1] == [0.0, None]          # unbounded above
    assert result.contains_truth["sigma_bs"] == [True, True, False]
    assert np.allclose(result.interval95["c_med"][2], [0.58, 0.62])
    assert result.contains_truth["c_med"] == [True, True, True]
    assert result.determined == determined


class _Camera:
    """A pinhole looking along +z (OpenCV axes) from ``centre``."""

    def __init__(self, centre, width=40, height=30, focal=30.0):
        self.c2w_array = np.eye(4)
        self.c2w_array[:3, 3] = centre
        self.width, self.height, self.fx, self.fy = width, height, focal, focal
        self.cx, self.cy = width / 2, height / 2

    def range_to_plane(self, plane_z: float) -> np.ndarray:
        """True range of every pixel to the plane z = plane_z (in front of the camera)."""
        u, v = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        rays = np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy,
                         np.ones_like(u)], -1)
        unit = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
        return (plane_z - self.c2w_array[2, 3]) / unit[..., 2]


def test_training_view_coverage_counts_the_views_that_see_each_surface_point_unhidden():
    test = _Camera((0.0, 0.0, 0.0))
    view_range = test.range_to_plane(5.0)
    view_range[:4, :4] = np.inf                              # open water: no surface
    shifted = _Camera((1.5, 0.0, 0.0))                       # sees the left part of the view
    away = _Camera((100.0, 0.0, 0.0))                        # sees none of it
    hidden = _Camera((0.0, 0.2, 0.0))                        # a nearer surface hides the wall
    counts = truth.training_view_coverage(
        test, view_range, [(shifted, shifted.range_to_plane(5.0)),
                           (away, away.range_to_plane(5.0)),
                           (hidden, np.full((30, 40), 2.0)),
                           (test, view_range)])
    # the wall point of pixel column i lies at x = 5 (i + 0.5 - 20) / 30, which the shifted
    # camera sees where 30 (x - 1.5) / 5 + 20 >= 0, i.e. for i + 0.5 >= 9
    expected = np.ones((30, 40), dtype=int)                  # the test view itself
    expected[:, 9:] += 1
    expected[:4, :4] = 0
    np.testing.assert_array_equal(counts, expected)


def test_view_truth_metrics_scores_the_covered_pixels_apart():
    rng = np.random.default_rng(2)
    clean = rng.uniform(0.1, 0.9, (16, 16, 3))
    restored = clean / GAIN
    restored[:, :4] = 0.0                                   # never seen: restored wrong
    covered = np.ones((16, 16), dtype=bool)
    covered[:, :4] = False
    truth_depth = rng.uniform(1.0, 5.0, (16, 16))
    water = clean * 0.8
    full = water / GAIN
    full[:, :4] = 0.0                                       # and the novel view wrong there
    common = dict(full=full, restored=restored, depth=truth_depth, clean=clean,
                  water=water, truth_depth=truth_depth, gain=GAIN, metres_per_unit=1.0)
    row = truth.view_truth_metrics(**common, covered=covered)
    assert row["restored_psnr_linear_covered"] == float("inf")
    assert row["full_vs_water_psnr_linear_covered"] == float("inf")
    assert row["full_vs_water_psnr_linear"] < 20
    assert row["restored_psnr_linear"] < 20
    assert row["covered_share"] == pytest.approx(0.75)
    without = truth.view_truth_metrics(**common)
    assert "restored_psnr_linear_covered" not in without
    assert "full_vs_water_psnr_linear_covered" not in without


def test_the_restored_photograph_and_the_reprojected_view_are_scored_alike():
    rng = np.random.default_rng(3)
    clean = rng.uniform(0.1, 0.9, (16, 16, 3))
    truth_depth = rng.uniform(1.0, 5.0, (16, 16))
    covered = np.ones((16, 16), dtype=bool)
    covered[:, :4] = False
    exact = clean / GAIN
    off = exact.copy()
    off[:, :4] *= 0.5                                       # wrong only where nothing sees
    common = dict(full=exact, restored=exact, depth=truth_depth, clean=clean, water=clean,
                  truth_depth=truth_depth, gain=GAIN, metres_per_unit=1.0, covered=covered)
    row = truth.view_truth_metrics(**common, restored_photo=exact, reprojected=off)
    assert row["photo_restored_psnr_linear"] == float("inf")
    assert row["reprojected_restored_psnr_linear"] < 30
    assert row["reprojected_restored_ssim_linear"] < row["photo_restored_ssim_linear"]
    assert row["reprojected_restored_psnr_linear_covered"] == float("inf")
    assert not any(key.startswith("reprojected") for key in truth.view_truth_metrics(**common))

    supported = np.zeros((16, 16), dtype=bool)
    supported[:, 2:] = True                                 # half the wrong columns backed
    backed = truth.view_truth_metrics(**common, reprojected=off, supported=supported)
    expected = metrics.image_metrics(GAIN * off, clean, valid=supported)["psnr_linear"]
    assert backed["reprojected_restored_psnr_linear_supported"] == pytest.approx(expected)
    assert row["reprojected_restored_psnr_linear"] < expected < float("inf")
    assert backed["supported_share"] == pytest.approx(14 / 16)
    assert "supported_share" not in truth.view_truth_metrics(**common, supported=supported)
