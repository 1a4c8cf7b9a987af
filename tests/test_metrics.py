"""Metrics, display transforms and the camera path: pure functions against hand-worked values and
independent float64 references."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.lib.stride_tricks import sliding_window_view
from scipy.spatial.transform import Rotation
from skimage.metrics import structural_similarity

from seathru.eval import display
from seathru.eval import metrics
from seathru.eval.camera_path import (capture_order, interpolate_poses, key_poses,
                                      smooth_camera_path)
from seathru.radiometry.colour import linear_to_srgb
from seathru.sim.camera_paths import look_at

# ------------------------------------------------------------------------------------ PSNR, SSIM


def reference_ssim(a: np.ndarray, b: np.ndarray) -> float:
    """The mip-NeRF / SeaThru-NeRF evaluation SSIM written out in float64: an 11-tap Gaussian
    (sigma 1.5) 'valid' filter, population statistics, K1 = 0.01, K2 = 0.03, data range 1."""
    x = np.arange(11) - 5.0
    g = np.exp(-0.5 * (x / 1.5) ** 2)
    window = np.outer(g, g) / g.sum() ** 2
    c1, c2 = 0.01 ** 2, 0.03 ** 2

    def blur(image):
        return np.einsum("ijkl,kl->ij", sliding_window_view(image, (11, 11)), window)

    values = []
    for channel in range(a.shape[-1]):
        p, q = a[..., channel].astype(np.float64), b[..., channel].astype(np.float64)
        mu_p, mu_q = blur(p), blur(q)
        var_p = blur(p * p) - mu_p ** 2
        var_q = blur(q * q) - mu_q ** 2
        cov = blur(p * q) - mu_p * mu_q
        ssim_map = ((2 * mu_p * mu_q + c1) * (2 * cov + c2)
                    / ((mu_p ** 2 + mu_q ** 2 + c1) * (var_p + var_q + c2)))
        values.append(ssim_map.mean())
    return float(np.mean(values))


def test_psnr_of_constant_images_matches_the_formula():
    a = np.full((8, 8, 3), 0.25)
    b = np.full((8, 8, 3), 0.5)
    # MSE = 0.0625, PSNR = 10 log10(1 / 0.0625) = 10 log10(16)
    assert metrics.psnr(a, b) == pytest.approx(10 * math.log10(16.0), abs=1e-12)
    assert metrics.psnr(a, a) == math.inf


def test_psnr_of_a_single_wrong_pixel():
    a = np.zeros((10, 10, 3))
    b = a.copy()
    b[3, 4, 1] = 1.0  # one error of 1 among 300 values: MSE = 1/300
    assert metrics.psnr(a, b) == pytest.approx(10 * math.log10(300.0), abs=1e-12)


def test_ssim_of_constant_images_is_the_luminance_term():
    # No variance: SSIM = (2 mu_a mu_b + C1) / (mu_a^2 + mu_b^2 + C1) (contrast term C2 / C2).
    a = np.full((16, 16, 3), 0.2)
    b = np.full((16, 16, 3), 0.6)
    c1 = 0.01 ** 2
    expected = (2 * 0.2 * 0.6 + c1) / (0.2 ** 2 + 0.6 ** 2 + c1)
    assert metrics.ssim(a, b) == pytest.approx(expected, abs=1e-12)


def test_ssim_of_an_image_with_itself_is_one():
    image = np.random.default_rng(0).random((20, 24, 3))
    assert metrics.ssim(image, image) == pytest.approx(1.0, abs=1e-12)


def test_ssim_of_a_step_edge_by_hand():
    # Left half 0, right half 1 against a uniform 0.5: mu_q = 0.5, var_q = 0, cov = 0, so each
    # window gives (mu_p + C1) / (mu_p^2 + 0.25 + C1) * C2 / (var_p + C2) with the window's
    # Gaussian mass w on the right half: mu_p = w, var_p = w - w^2.
    a = np.zeros((11, 12, 1))
    a[:, 6:] = 1.0
    b = np.full_like(a, 0.5)
    g = np.exp(-0.5 * ((np.arange(11) - 5.0) / 1.5) ** 2)
    g /= g.sum()
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    values = []
    for start in (0, 1):  # the two valid 11x11 window positions (columns 0-10 and 1-11)
        w = g[6 - start:].sum()
        values.append((2 * w * 0.5 + c1) / (w ** 2 + 0.25 + c1) * c2 / (w - w ** 2 + c2))
    assert metrics.ssim(a, b) == pytest.approx(np.mean(values), abs=1e-12)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2 ** 31 - 1), height=st.integers(11, 40), width=st.integers(11, 40))
def test_ssim_matches_the_float64_reference_and_skimage(seed, height, width):
    rng = np.random.default_rng(seed)
    a = rng.random((height, width, 3))
    b = np.clip(a + rng.normal(0, 0.2, a.shape), 0, 1)
    ours = metrics.ssim(a, b)
    assert ours == pytest.approx(reference_ssim(a, b), abs=1e-6)
    skimage_value = structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
                                          use_sample_covariance=False, data_range=1,
                                          channel_axis=-1)
    assert ours == pytest.approx(skimage_value, abs=1e-6)


def test_masked_psnr_and_ssim_score_only_valid_pixels():
    rng = np.random.default_rng(6)
    a = rng.random((30, 34, 3))
    b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1)
    valid = np.ones((30, 34), bool)
    valid[:12, :15] = False
    b_broken = b.copy()
    b_broken[~valid] = 1.0 - a[~valid]   # garbage where the mask is off
    assert metrics.psnr(a, b_broken, valid=valid) == pytest.approx(
        metrics.psnr(a[valid], b[valid]), abs=1e-12)
    assert metrics.ssim(a, b, valid=np.ones((30, 34), bool)) == pytest.approx(
        metrics.ssim(a, b), abs=1e-12)
    # masked SSIM: the reference map averaged over the valid window centres
    x = np.arange(11) - 5.0
    g = np.exp(-0.5 * (x / 1.5) ** 2)
    window = np.outer(g, g) / g.sum() ** 2
    blur = lambda img: np.einsum("ijkl,kl->ij", sliding_window_view(img, (11, 11)), window)  # noqa
    maps = []
    for c in range(3):
        p, q = a[..., c], b_broken[..., c]
        mp, mq = blur(p), blur(q)
        vp, vq, cov = blur(p * p) - mp ** 2, blur(q * q) - mq ** 2, blur(p * q) - mp * mq
        maps.append((2 * mp * mq + 1e-4) * (2 * cov + 9e-4)
                    / ((mp ** 2 + mq ** 2 + 1e-4) * (vp + vq + 9e-4)))
    expected = np.mean(np.stack(maps, -1)[valid[5:-5, 5:-5]])
    assert metrics.ssim(a, b_broken, valid=valid) == pytest.approx(expected, abs=1e-6)
    # image_metrics ignores NaN outside the mask
    nan_target = np.where(valid[..., None], b, np.nan)
    result = metrics.image_metrics(a, nan_target, valid=valid)
    assert all(np.isfinite(v) for v in result.values())


def test_quantisation_is_the_official_8bit_rounding():
    values = np.array([-0.1, 0.0, 0.5, 1.0 / 510.0, 0.999, 1.7])
    expected = np.array([0, 0, 128, 0, 255, 255]) / 255.0   # 127.5 rounds to even 128; 0.5 to 0
    np.testing.assert_array_equal(metrics.quantise_8bit(values), expected)


def test_image_metrics_quantise_and_encode_both_spaces():
    rng = np.random.default_rng(1)
    target = rng.random((16, 16, 3)) * 0.5
    prediction = target + 0.4 / 255.0  # below half an 8-bit step: vanishes after quantisation
    prediction[0, 0, 0] += 0.3
    result = metrics.image_metrics(prediction, target)
    q = metrics.quantise_8bit
    assert result["psnr_linear"] == pytest.approx(metrics.psnr(q(prediction), q(target)))
    srgb_p, srgb_t = q(linear_to_srgb(prediction)), q(linear_to_srgb(target))
    assert result["psnr_srgb"] == pytest.approx(metrics.psnr(srgb_p, srgb_t))
    assert result["ssim_srgb"] == pytest.approx(reference_ssim(srgb_p, srgb_t), abs=1e-6)
    assert result["psnr_linear"] != result["psnr_srgb"]


# ------------------------------------------------------------------------- gain, scale, depth

@settings(max_examples=25, deadline=None)
@given(gains=st.lists(st.floats(0.05, 20.0), min_size=3, max_size=3),
       seed=st.integers(0, 2 ** 31 - 1))
def test_channel_gain_recovers_an_exact_gain(gains, seed):
    prediction = np.random.default_rng(seed).random((12, 10, 3)) + 0.01
    target = prediction * np.asarray(gains)
    np.testing.assert_allclose(metrics.fit_channel_gain(prediction, target), gains, rtol=1e-9)


def test_channel_gain_is_least_squares_and_pools_over_views():
    rng = np.random.default_rng(2)
    views = [(rng.random((6, 7, 3)), rng.random((6, 7, 3))) for _ in range(3)]
    cross, power = np.zeros(3), np.zeros(3)
    for p, t in views:
        c, w = metrics.channel_gain_sums(p, t)
        cross, power = cross + c, power + w
    pooled = metrics.gain_from_sums(cross, power)
    p_all = np.concatenate([p.reshape(-1, 3) for p, _ in views])
    t_all = np.concatenate([t.reshape(-1, 3) for _, t in views])
    for channel in range(3):  # the 1-parameter least-squares solution, via lstsq
        solution = np.linalg.lstsq(p_all[:, channel:channel + 1], t_all[:, channel], rcond=None)
        assert pooled[channel] == pytest.approx(solution[0][0], rel=1e-12)


def test_channel_gain_ignores_invalid_pixels():
    prediction = np.ones((4, 4, 3))
    target = 2.0 * prediction
    target[0, 0] = [np.nan, 100.0, 100.0]
    valid = np.ones((4, 4), bool)
    valid[0, 0] = False
    np.testing.assert_allclose(metrics.fit_channel_gain(prediction, target, valid), [2, 2, 2])


@settings(max_examples=20, deadline=None)
@given(scale=st.floats(0.01, 100.0), seed=st.integers(0, 2 ** 31 - 1))
def test_metric_scale_recovers_the_similarity_scale(scale, seed):
    rng = np.random.default_rng(seed)
    truth = rng.normal(size=(7, 3)) * 3.0
    rotation = Rotation.random(random_state=seed % 1000).as_matrix()
    normalised = (truth @ rotation.T) / scale + rng.normal(size=3)
    result = metrics.metric_scale(normalised, truth)
    assert result["scale"] == pytest.approx(scale, rel=1e-9)
    assert result["relative_residual"] < 1e-9


def test_depth_errors_by_hand():
    truth = np.array([[1.0, 2.0], [4.0, np.inf]])
    predicted = np.array([[1.1, 1.8], [4.4, 3.0]])   # relative errors 0.1, 0.1, 0.1; inf ignored
    result = metrics.depth_errors(predicted, truth)
    assert result["depth_median_abs_rel"] == pytest.approx(0.1)
    assert result["depth_mean_abs_rel"] == pytest.approx(0.1)
    assert result["depth_rmse"] == pytest.approx(math.sqrt((0.01 + 0.04 + 0.16) / 3))
    assert result["depth_corr"] == pytest.approx(np.corrcoef([1.1, 1.8, 4.4], [1, 2, 4])[0, 1])
    empty = metrics.depth_errors(np.ones((2, 2)), np.full((2, 2), np.nan))
    assert all(math.isnan(v) for v in empty.values())


def test_relative_error_per_channel():
    np.testing.assert_allclose(metrics.relative_error([1.1, 0.5, 0.0], [1.0, 1.0, 2.0]),
                               [0.1, 0.5, 1.0])
    assert math.isnan(metrics.relative_error([1.0], [0.0])[0])


# ---------------------------------------------------------------------------------------- LPIPS

def _random_lpips_state(seed: int) -> dict:
    """Random AlexNet trunk (torchvision key layout) and LPIPS linear layers (lpips layout)."""
    generator = torch.Generator().manual_seed(seed)
    shapes = {0: (64, 3, 11, 11), 3: (192, 64, 5, 5), 6: (384, 192, 3, 3), 8: (256, 384, 3, 3),
              10: (256, 256, 3, 3)}
    state = {}
    for index, shape in shapes.items():
        fan_in = shape[1] * shape[2] * shape[3]
        state[f"features.{index}.weight"] = torch.randn(shape, generator=generator) / fan_in ** 0.5
        state[f"features.{index}.bias"] = torch.randn(shape[0], generator=generator) * 0.01
    for k, width in enumerate((64, 192, 384, 256, 256)):
        state[f"lin{k}.model.1.weight"] = torch.rand((1, width, 1, 1), generator=generator)
    return state


def reference_lpips(state: dict, a: np.ndarray, b: np.ndarray) -> float:
    """LPIPS v0.1 with an AlexNet trunk written out with torch.nn.functional."""
    import torch.nn.functional as F

    shift = torch.tensor([-0.030, -0.088, -0.188]).reshape(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450]).reshape(1, 3, 1, 1)

    def taps(image):
        x = torch.from_numpy(image.transpose(2, 0, 1)[None].astype(np.float32))
        x = ((2 * x - 1) - shift) / scale
        w = lambda i: (state[f"features.{i}.weight"], state[f"features.{i}.bias"])  # noqa: E731
        out = []
        x = F.relu(F.conv2d(x, *w(0), stride=4, padding=2)); out.append(x)
        x = F.relu(F.conv2d(F.max_pool2d(x, 3, 2), *w(3), padding=2)); out.append(x)
        x = F.relu(F.conv2d(F.max_pool2d(x, 3, 2), *w(6), padding=1)); out.append(x)
        x = F.relu(F.conv2d(x, *w(8), padding=1)); out.append(x)
        x = F.relu(F.conv2d(x, *w(10), padding=1)); out.append(x)
        return out

    total = 0.0
    for k, (fa, fb) in enumerate(zip(taps(a), taps(b))):
        fa = fa / (fa.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
        fb = fb / (fb.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
        total += float(F.conv2d((fa - fb) ** 2, state[f"lin{k}.model.1.weight"]).mean())
    return total


def test_lpips_network_matches_a_functional_reference_and_key_layouts():
    state = _random_lpips_state(0)
    rng = np.random.default_rng(3)
    a, b = rng.random((64, 80, 3)), rng.random((64, 80, 3))
    network = metrics.lpips_from_state_dict(state)
    assert network.net_name == "alex"
    value = metrics.lpips_distance(network, a, b)
    assert value == pytest.approx(reference_lpips(state, a, b), rel=1e-4)
    assert metrics.lpips_distance(network, a, a) == pytest.approx(0.0, abs=1e-7)
    # The lpips.LPIPS().state_dict() layout names the trunk net.sliceK.I.*
    slices = {0: 1, 3: 2, 6: 3, 8: 4, 10: 5}
    renamed = {(f"net.slice{slices[int(k.split('.')[1])]}.{k.split('.', 1)[1]}"
                if k.startswith("features") else k): v for k, v in state.items()}
    assert metrics.lpips_distance(metrics.lpips_from_state_dict(renamed), a, b) == \
        pytest.approx(value, rel=1e-6)


def test_lpips_rejects_incomplete_weights():
    state = _random_lpips_state(1)
    with pytest.raises(ValueError, match="trunk weights missing"):
        metrics.lpips_from_state_dict({k: v for k, v in state.items() if k.startswith("lin")})
    with pytest.raises(ValueError, match="lin0..lin4"):
        metrics.lpips_from_state_dict({k: v for k, v in state.items()
                                       if k != "lin2.model.1.weight"})


# -------------------------------------------------------------------------------------- display

def test_exposure_maps_the_percentile_to_the_target():
    image = np.linspace(0.0, 0.2, 30_000, dtype=np.float32).reshape(100, 100, 3)
    scale = display.exposure_scale([image], percentile=99.0, target=0.9)
    assert scale == pytest.approx(0.9 / np.percentile(image, 99.0), rel=1e-3)
    encoded = display.to_display(np.full((2, 2, 3), 0.9 / scale, np.float32), scale)
    np.testing.assert_allclose(encoded, linear_to_srgb(np.float32(0.9)), rtol=1e-5)
    assert display.exposure_scale([]) == 1.0
    assert display.exposure_scale([np.zeros((4, 4, 3))]) == 1.0


def test_depth_colour_map_near_warm_far_cool_invalid_black():
    import matplotlib

    depth = np.array([[1.0, 3.0], [0.5, np.nan]])
    rgb = display.colourise_depth(depth, 1.0, 3.0, "turbo")
    turbo = matplotlib.colormaps["turbo"]
    np.testing.assert_allclose(rgb[0, 0], turbo(1.0)[:3], atol=1e-6)   # nearest: top of map
    np.testing.assert_allclose(rgb[0, 1], turbo(0.0)[:3], atol=1e-6)   # farthest: bottom
    np.testing.assert_allclose(rgb[1, 0], turbo(1.0)[:3], atol=1e-6)   # clipped
    np.testing.assert_array_equal(rgb[1, 1], [0, 0, 0])
    lo, hi = display.depth_range([np.linspace(1, 2, 101).reshape(1, -1)], 1, 99)
    assert (lo, hi) == pytest.approx((1.01, 1.99))


# ---------------------------------------------------------------------------------- camera path

def _orbit(n: int, radius: float = 2.0, jitter: float = 0.0, seed: int = 0) -> np.ndarray:
    """Cameras on a circle looking at the origin (OpenCV axes), in capture order."""
    rng = np.random.default_rng(seed)
    poses = []
    for angle in np.linspace(0, 1.5 * np.pi, n):
        centre = np.array([radius * np.cos(angle), radius * np.sin(angle), 0.5])
        centre = centre + rng.normal(0, jitter, 3)
        poses.append(look_at(centre, np.zeros(3)))
    return np.stack(poses)


def test_path_interpolates_few_cameras_and_is_smooth():
    poses = _orbit(8)
    path = smooth_camera_path(poses, 400, max_keys=12)
    assert path.shape == (400, 4, 4)
    np.testing.assert_allclose(path[0], poses[0], atol=1e-9)
    np.testing.assert_allclose(path[-1], poses[-1], atol=1e-9)
    # passes through every camera (a spline through the centres, slerp through the rotations)
    for pose in poses:
        nearest = np.argmin(np.linalg.norm(path[:, :3, 3] - pose[:3, 3], axis=1))
        assert np.linalg.norm(path[nearest, :3, 3] - pose[:3, 3]) < 0.02
        angle = Rotation.from_matrix(path[nearest, :3, :3].T @ pose[:3, :3]).magnitude()
        assert angle < np.radians(2)
    rotations = path[:, :3, :3]
    np.testing.assert_allclose(rotations @ rotations.transpose(0, 2, 1),
                               np.broadcast_to(np.eye(3), rotations.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0, atol=1e-9)
    steps = np.linalg.norm(np.diff(path[:, :3, 3], axis=0), axis=1)
    assert steps.max() < 1.6 * np.median(steps)   # steady speed, no jumps


def test_path_averages_many_jittery_cameras():
    poses = _orbit(120, jitter=0.05, seed=4)
    keys = key_poses(poses, 10)
    assert keys.shape == (10, 4, 4)
    path = smooth_camera_path(poses, 200, max_keys=10)
    radii = np.linalg.norm(path[:, :2, 3], axis=1)
    assert np.all(np.abs(radii - 2.0) < 0.25)
    # smoother than the raw cameras: the path's turning is far below the jitter's
    raw_turn = np.abs(np.diff(poses[:, :3, 3], 2, axis=0)).sum()
    path_turn = np.abs(np.diff(path[:, :3, 3], 2, axis=0)).sum()
    assert path_turn < 0.2 * raw_turn


def test_capture_order_uses_names_unless_they_zigzag():
    poses = _orbit(10)
    centres = poses[:, :3, 3]
    names = [f"IMG_{i:03d}" for i in range(10)]
    np.testing.assert_array_equal(capture_order(centres, names), np.arange(10))
    shuffled = np.random.default_rng(5).permutation(10)
    order = capture_order(centres[shuffled], [names[i] for i in range(10)])
    visited = shuffled[order]   # original indices in visiting order
    assert list(visited) in (list(range(10)), list(range(9, -1, -1)))


def test_path_with_one_or_two_cameras():
    poses = _orbit(2)
    np.testing.assert_allclose(smooth_camera_path(poses[:1], 5), np.repeat(poses[:1], 5, 0))
    path = interpolate_poses(poses, 3)
    np.testing.assert_allclose(path[1, :3, 3], poses[:, :3, 3].mean(0), atol=1e-9)
    with pytest.raises(ValueError):
        smooth_camera_path(np.zeros((0, 4, 4)), 5)
