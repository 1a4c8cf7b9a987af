"""Tests for seathru.nerf.water_uncertainty: how well the images determine the fitted water."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from seathru.nerf.water_fit import (WaterFit, fit_water, projected_loss, water_start,
                                    water_vector)
from seathru.nerf.water_uncertainty import (AMBIGUOUS_SPLITS, WaterUncertainty,
                                            ambiguity_halfwidths, cluster_variances,
                                            far_surface_range, group_scores,
                                            interval_determined, laplace_halfwidths,
                                            robust_halfwidths, surface_behind_open_water,
                                            veiling_beyond_surfaces, veiling_slide)
from tests.test_water_fit import (KEYS, START, TRUE, _fit_and_spread, _observations,
                                   _textured)

def test_laplace_intervals_hold_the_truth_and_flag_what_the_views_cannot_tell():
    covered = total = 0
    for seed in range(8):
        data = _observations(np.random.default_rng(seed), noise=1e-2)
        fit, spread = _fit_and_spread(*data)
        for key in ("sigma_attn", "sigma_bs", "c_med"):
            for value, half, true in zip(getattr(fit, key), spread.halfwidth[key], TRUE[key]):
                covered += abs(value - true) <= half
                total += 1
    assert covered / total >= 0.9, (covered, total)
    # one narrow band of ranges: the backscatter cannot be told from brighter surfaces
    narrow = _observations(np.random.default_rng(0), near=4.0, far=4.5, noise=1e-2)
    _, spread = _fit_and_spread(*narrow)
    assert not any(spread.determined["sigma_bs"])


def _small(seed: int, groups: int = 60, per_group: int = 6, noise: float = 0.01,
           surface_depth_error: float = 0.0, surface_colour_error: float = 0.0):
    """Surfaces at 0.5-8 m: independent pixel noise, plus optional errors shared by every
    pixel of a surface (its depth off by a relative amount, its colour off)."""
    rng = np.random.default_rng(seed)
    clean = rng.uniform(0.05, 0.9, size=(groups, 3))
    ids = np.repeat(np.arange(groups), per_group)
    ranges = rng.uniform(0.5, 8.0, size=ids.size)
    attn, bs, c_med = (np.array(TRUE[k]) for k in KEYS)
    observed = clean[ids] * np.exp(-attn * ranges[:, None]) \
        + c_med * (1 - np.exp(-bs * ranges[:, None]))
    observed += noise * rng.standard_normal(observed.shape)
    observed += surface_colour_error * rng.standard_normal((groups, 3))[ids] \
        * np.exp(-attn * ranges[:, None])
    model_ranges = ranges * (1 + surface_depth_error * rng.standard_normal(groups))[ids]
    return (torch.from_numpy(model_ranges), torch.from_numpy(observed), torch.from_numpy(ids),
            groups)


def _coverage(spreads) -> float:
    hits = [abs(v - t) <= h for fit, spread in spreads for k in KEYS
            for v, h, t in zip(getattr(fit, k), spread.halfwidth[k], TRUE[k])]
    return float(np.mean(hits))


def test_group_scores_sum_to_the_gradient_of_the_profile_loss():
    ranges, observed, ids, groups = _small(0)
    theta = torch.tensor([0.5, 0.3, 0.2, 0.4, 0.35, 0.2, 0.1, 0.25, 0.3], dtype=torch.float64,
                         requires_grad=True)
    loss = projected_loss(theta[0:3], theta[3:6], theta[6:9], ranges, observed, ids, groups)
    (gradient,) = torch.autograd.grad(loss, theta)
    scores = group_scores(theta.detach(), ranges, observed, ids, groups)
    assert scores.shape == (groups, 9)
    assert torch.allclose(scores.sum(0), gradient, rtol=1e-6, atol=1e-12)


def test_group_scores_hold_the_gradient_of_the_incidental_term_too():
    ranges, observed, ids, groups = _small(1)
    unshared = torch.from_numpy(np.random.default_rng(1).uniform(1e-4, 3e-3, observed.shape))
    weights = torch.from_numpy(np.random.default_rng(2).uniform(0.5, 1.5, (groups, 3)))
    theta = torch.tensor([0.5, 0.3, 0.2, 0.4, 0.35, 0.2, 0.1, 0.25, 0.3], dtype=torch.float64,
                         requires_grad=True)
    loss = projected_loss(theta[0:3], theta[3:6], theta[6:9], ranges, observed, ids, groups,
                          weights, unshared)
    (gradient,) = torch.autograd.grad(loss, theta)
    scores = group_scores(theta.detach(), ranges, observed, ids, groups, weights=weights,
                          unshared=unshared)
    plain = group_scores(theta.detach(), ranges, observed, ids, groups, weights=weights)
    assert torch.allclose(scores.sum(0), gradient, rtol=1e-6, atol=1e-12)
    assert not torch.allclose(plain.sum(0), gradient, rtol=1e-3, atol=1e-12)


def test_robust_refits_add_the_fits_incidental_term_back_as_it_did():
    # The parts are refitted as the whole was: a dark bound that binds nothing then moves nothing
    # (refitted without the term, its comparison was the term's own move: 10-17% of the
    # attenuation, nearly twice the red backscatter).
    data = _textured(0, groups=600)
    dark = (torch.tensor([1.0, 3.0, 5.0], dtype=torch.float64),
            torch.full((3, 3), 10.0, dtype=torch.float64))
    fit = fit_water(*data, START, dark=dark, noise_term=True)
    assert fit.unshared is not None and fit.unshared.shape == data[1].shape
    again = fit_water(*data, water_start(fit), unshared=fit.unshared)
    assert np.allclose(water_vector(again), water_vector(fit), rtol=1e-3)
    spread = robust_halfwidths(fit, *data, dark=dark)
    theta = water_vector(fit).numpy()
    assert np.all(np.array(spread.splits["dark_bound"]) < 0.01 * theta)
    parts_plain = robust_halfwidths(replace(fit, unshared=None), *data, dark=dark)
    move = np.array(parts_plain.splits["dark_bound"][:3]) / 1.96 / theta[:3]
    assert np.all(move > 0.08), move      # the term's own move in attenuation (10-17%)
    assert np.all(np.isfinite(spread.halfwidth["sigma_attn"]))


def test_cluster_variances_match_the_spread_of_fits_over_independent_noise():
    """The sandwich against the float64 reference: the empirical variance of fits."""
    fits, predicted = [], []
    for seed in range(30):
        data = _small(seed + 100, groups=200, per_group=8, noise=0.02)
        fit = fit_water(*data, START)
        fits.append([v for k in KEYS for v in getattr(fit, k)])
        predicted.append(cluster_variances(torch.tensor(fits[-1], dtype=torch.float64), *data))
    empirical = np.var(np.array(fits), axis=0, ddof=1)
    ratio = torch.stack(predicted).median(0).values.numpy() / empirical
    # 30 draws: an empirical variance is known to within -45%/+60% at 95%
    assert np.all((ratio > 0.4) & (ratio < 2.5)), ratio
    assert 0.6 < float(np.exp(np.log(ratio).mean())) < 1.5, ratio


@pytest.mark.slow  # many seeded fits (20-45 s)
def test_robust_intervals_hold_the_truth_about_95_percent_of_the_time_with_independent_noise():
    spreads = []
    for seed in range(40):
        data = _small(seed)
        fit = fit_water(*data, START)
        spreads.append((fit, robust_halfwidths(fit, *data)))
    coverage = _coverage(spreads)
    # 360 intervals from 40 seeds: 95% nominal, binomial sd ~1.2% (parameters of one fit are
    # correlated, so allow more); an interval inflated to always cover would fail the top
    assert 0.88 <= coverage <= 0.995, coverage
    assert all(spread.method == "robust" for _, spread in spreads)
    determined = np.mean([d for _, s in spreads for k in KEYS for d in s.determined[k]])
    assert determined > 0.8, determined


@pytest.mark.slow  # many seeded fits (20-45 s)
def test_robust_intervals_hold_the_truth_when_errors_are_shared_by_many_surfaces():
    """One side of the scene placed 10% too far (a NeRF's geometry errors are shared by whole
    regions, not only by a voxel's pixels), on top of 3% depth errors per surface: the
    curvature intervals, which see only the residuals, miss the truth far more often."""
    robust, curvature = [], []
    for seed in range(30):
        ranges, observed, ids, groups = _small(seed, noise=0.005, surface_depth_error=0.03)
        ranges = torch.where(ids >= groups // 2, ranges * 1.1, ranges)
        fit = fit_water(ranges, observed, ids, groups, START)
        robust.append((fit, robust_halfwidths(fit, ranges, observed, ids, groups)))
        curvature.append((fit, laplace_halfwidths(fit, ranges, observed, ids, groups)))
    assert _coverage(robust) >= 0.83, _coverage(robust)
    assert _coverage(robust) > _coverage(curvature) + 0.08, (_coverage(robust),
                                                               _coverage(curvature))


def test_robust_intervals_widen_where_parts_of_the_data_disagree():
    """Near surfaces under one water, far ones under another (a NeRF's far surfaces at the
    wrong range look like this): the systematic part holds the gap between them."""
    near = _small(0)
    far = _small(1)
    far_ranges = far[0] + 8.0
    attn = torch.tensor(TRUE["sigma_attn"], dtype=torch.float64)
    far_observed = far[1].clone()
    far_observed *= torch.exp(-0.3 * attn * far_ranges[:, None])      # more attenuation far
    ranges = torch.cat([near[0], far_ranges])
    observed = torch.cat([near[1], far_observed])
    ids = torch.cat([near[2], far[2] + near[3]])
    groups = near[3] + far[3]
    fit = fit_water(ranges, observed, ids, groups, START)
    spread = robust_halfwidths(fit, ranges, observed, ids, groups)
    assert spread.splits and "range" in spread.splits
    assert max(spread.systematic["sigma_attn"]) > 3 * max(spread.statistical["sigma_attn"])
    for k in KEYS:
        for half, stat, sys in zip(spread.halfwidth[k], spread.statistical[k],
                                   spread.systematic[k]):
            assert half == pytest.approx(float(np.hypot(stat, sys)), rel=1e-9)


@pytest.mark.slow  # many seeded fits (20-45 s)
def test_robust_intervals_allow_for_the_error_of_the_model_depth():
    """Ranges with 6% error per pixel (a NeRF's depth) bias the fit; intervals told of that
    error hold the truth where those that take the ranges as exact miss it."""
    exact, told = [], []
    for seed in range(12):
        ranges, observed, ids, groups = _small(seed, groups=200, noise=0.003)
        noise = np.random.default_rng(seed + 50).standard_normal(len(ranges))
        ranges = ranges * torch.from_numpy(np.exp(0.06 * noise))
        fit = fit_water(ranges, observed, ids, groups, START)
        exact.append((fit, robust_halfwidths(fit, ranges, observed, ids, groups)))
        told.append((fit, robust_halfwidths(fit, ranges, observed, ids, groups,
                                            range_error=0.06)))
        assert "range_error" in told[-1][1].splits and "range_error" not in exact[-1][1].splits
    assert _coverage(told) >= 0.85, (_coverage(told), _coverage(exact))
    assert _coverage(told) > _coverage(exact) + 0.1, (_coverage(told), _coverage(exact))


def test_a_trained_value_far_from_the_surface_fit_is_not_determined():
    """The interval water.json writes is the half-width plus the trained value's distance to
    the surface fit; a value is determined only where that interval is within 25% of it."""
    fit = WaterFit([1.0, 1.0, 1.0], [0.5, 0.5, 0.5], [0.2, 0.2, 0.2], 0.0, 1000, 50)
    half = {"sigma_attn": [0.05, 0.05, 0.05], "sigma_bs": [0.05, 0.05, float("inf")],
            "c_med": [0.01, 0.01, 0.01]}
    trained = {"sigma_attn": [1.1, 1.8, 0.7], "sigma_bs": [0.5, 0.45, 0.5],
               "c_med": [0.2, 0.26, 0.2]}
    flags = interval_determined(trained, fit, half)
    # 0.05 + 0.1 <= 0.275; 0.05 + 0.8 > 0.45 (80% off, narrow fit); 0.05 + 0.3 > 0.175
    assert flags["sigma_attn"] == [True, False, False]
    # 0.05 <= 0.125; 0.05 + 0.05 <= 0.1125; no finite half-width
    assert flags["sigma_bs"] == [True, True, False]
    # 0.01 <= 0.05; 0.01 + 0.06 > 0.065
    assert flags["c_med"] == [True, False, True]


def test_what_the_images_cannot_tell_apart_leaves_a_value_undetermined_however_narrow():
    """An orbit's red attenuation 9-12% off with an interval of +-18%: narrow enough to pass
    the 25% width test, but the veiling light no open water shows moves it by more than 5%."""
    fit = WaterFit([1.0, 1.0, 1.0], [0.5, 0.5, 0.5], [0.2, 0.2, 0.2], 0.0, 1000, 50)
    half = {"sigma_attn": [0.18, 0.18, 0.18], "sigma_bs": [0.05, 0.05, 0.05],
            "c_med": [0.01, 0.01, 0.01]}
    ambiguity = {"sigma_attn": [0.09, 0.04, 0.0], "sigma_bs": [0.05, 0.0, 0.02],
                 "c_med": [0.0, 0.011, 0.009]}
    trained = {k: list(getattr(fit, k)) for k in KEYS}
    width_alone = interval_determined(trained, fit, half)
    assert all(all(flags) for flags in width_alone.values())
    both = interval_determined(trained, fit, half, ambiguity=ambiguity)
    # 0.09 > 5% of 1.0; 0.04 and 0 within it
    assert both["sigma_attn"] == [False, True, True]
    assert both["sigma_bs"] == [False, True, True]      # 0.05 > 0.025; 0.02 <= 0.025
    assert both["c_med"] == [True, False, True]          # 0.011 > 0.01; 0.009 <= 0.01
    assert interval_determined(trained, fit, half, ambiguity=ambiguity,
                               max_ambiguity=1.0) == width_alone


def test_ambiguity_is_the_largest_part_from_what_the_images_cannot_tell_apart():
    splits = {"range": [0.5] * 9, "grouping": [0.4] * 9,
              AMBIGUOUS_SPLITS[0]: [0.1 * i for i in range(9)]}
    spread = WaterUncertainty({k: [1.0] * 3 for k in KEYS}, {k: [True] * 3 for k in KEYS}, 100,
                              "robust", splits=splits)
    assert ambiguity_halfwidths(spread) == {"sigma_attn": [0.0, 0.1, 0.2],
                                            "sigma_bs": pytest.approx([0.3, 0.4, 0.5]),
                                            "c_med": pytest.approx([0.6, 0.7, 0.8])}
    spread.splits[AMBIGUOUS_SPLITS[1]] = [0.25] * 9
    assert ambiguity_halfwidths(spread)["sigma_attn"] == [0.25, 0.25, 0.25]
    # data-split disagreement alone is not ambiguity: better geometry would narrow it
    spread.splits = {"range": [0.5] * 9}
    assert ambiguity_halfwidths(spread) == {k: [0.0] * 3 for k in KEYS}


def test_interval_floor_widens_only_the_narrowest_half_widths():
    ranges, observed, ids, groups = _small(5, noise=0.001)
    fit = fit_water(ranges, observed, ids, groups, START)
    plain = robust_halfwidths(fit, ranges, observed, ids, groups)
    floored = robust_halfwidths(fit, ranges, observed, ids, groups, min_relative=0.05)
    raised = 0
    for k in KEYS:
        for value, low, high in zip(getattr(fit, k), plain.halfwidth[k], floored.halfwidth[k]):
            assert high == pytest.approx(max(low, 0.05 * value), rel=1e-9)
            raised += low < 0.05 * value
    assert raised > 0, "with pixel noise of 0.001 some half-widths should be below 5%"


def test_grouping_comparison_is_the_move_of_the_fit_between_groupings():
    ranges, observed, ids, groups = _small(6, groups=80, noise=0.003)
    fit = fit_water(ranges, observed, ids, groups, START)
    same = robust_halfwidths(fit, ranges, observed, ids, groups,
                             regrouped=[(ranges, observed, ids, groups)])
    # (beyond where the fits stop: a loss change of 1e-10 of its start, water_fit's rule)
    assert max(same.splits["grouping"]) < 1e-5, "the same grouping cannot move the fit"
    # pairs of surfaces of different colours merged into one group: a coarser grouping
    merged = ids // 2
    coarse = robust_halfwidths(fit, ranges, observed, ids, groups,
                               regrouped=[(ranges, observed, merged, groups // 2)])
    moved = fit_water(ranges, observed, merged, groups // 2, {k: getattr(fit, k) for k in KEYS},
                      100)
    expected = [1.96 * abs(a - b) for k in KEYS for a, b in zip(getattr(moved, k),
                                                                 getattr(fit, k))]
    assert coarse.splits["grouping"] == pytest.approx(expected, rel=1e-3, abs=1e-9)
    assert max(coarse.splits["grouping"]) > 0.01
    for k in KEYS:
        assert all(c >= s - 1e-12 for c, s in zip(coarse.halfwidth[k], same.halfwidth[k]))


def _with_open_water(data, colour, rng: np.random.Generator, pixels: int = 300,
                     noise: float = 0.01):
    """``data`` plus ``pixels`` open-water pixels (range inf, one group) of colour ``colour``."""
    ranges, observed, ids, groups = data
    water = torch.tensor(colour, dtype=torch.float64) \
        + noise * torch.from_numpy(rng.standard_normal((pixels, 3)))
    return (torch.cat([ranges, torch.full((pixels,), float("inf"), dtype=torch.float64)]),
            torch.cat([observed, water]),
            torch.cat([ids, torch.full((pixels,), groups, dtype=ids.dtype)]), groups + 1)


@pytest.mark.parametrize("short", [0.8, 0.6])
def test_surfaces_pulling_the_veiling_light_off_the_open_water_widen_its_interval(short):
    """The open water has the true colour, the far surfaces are placed ``short`` of their
    range and pull the fit's c_med off it: the interval allows for the pull."""
    rng = np.random.default_rng(7)
    ranges, observed, ids, groups = _observations(rng, groups=300, per_group=8, near=0.5,
                                                  far=20.0, noise=0.003)
    ranges = torch.where(ranges > 10, ranges * short, ranges)
    data = _with_open_water((ranges, observed, ids, groups), TRUE["c_med"], rng, pixels=400,
                            noise=0.003)
    fit = fit_water(*data, START)
    spread = robust_halfwidths(fit, *data)
    level = data[1][~torch.isfinite(data[0])].mean(0).tolist()
    assert spread.splits["open_water_pull"][6:9] == pytest.approx(
        [1.96 * abs(c - m) for c, m in zip(fit.c_med, level)], rel=1e-6)
    assert max(abs(c / t - 1) for c, t in zip(fit.c_med, TRUE["c_med"])) > 0.01, \
        "the misplaced surfaces should pull c_med off the truth"
    for value, half, true in zip(fit.c_med, spread.halfwidth["c_med"], TRUE["c_med"]):
        assert abs(value - true) <= half


def test_surface_behind_open_water_takes_out_what_that_surface_adds():
    ranges, observed, ids, groups = _observations(np.random.default_rng(12), near=1.0, far=6.0)
    theta = torch.tensor(TRUE["sigma_attn"] + TRUE["sigma_bs"] + TRUE["c_med"],
                         dtype=torch.float64)
    attn, bs, c_med = (np.array(TRUE[k]) for k in KEYS)
    near = ranges <= ranges.median()
    clean = (observed[near].numpy() - c_med * (1 - np.exp(-bs * ranges[near, None].numpy()))) \
        * np.exp(attn * ranges[near, None].numpy())
    bright = np.quantile(clean, 0.9, axis=0)
    beyond = 8.0
    # open water that is really the bright surface 8 units away
    seabed = bright * np.exp(-attn * beyond) + c_med * (1 - np.exp(-bs * beyond))
    ranges = torch.cat([ranges, torch.full((5,), float("inf"), dtype=torch.float64)])
    observed = torch.cat([observed, torch.from_numpy(np.tile(seabed, (5, 1)))])
    as_bright, as_black = surface_behind_open_water(theta, ranges, observed, beyond)
    assert as_bright[-5:].numpy() == pytest.approx(np.tile(c_med, (5, 1)), rel=1e-9)
    assert as_black[-5:].numpy() == pytest.approx(
        np.tile(seabed + c_med * np.exp(-bs * beyond), (5, 1)), rel=1e-9)
    assert torch.equal(as_bright[:-5], observed[:-5]) and torch.equal(as_black[:-5],
                                                                     observed[:-5])
    assert far_surface_range(ranges) == pytest.approx(
        float(torch.quantile(ranges[:-5], 0.9)), rel=1e-12)


def test_far_seabed_taken_for_open_water_widens_the_interval_when_it_lies_below_the_horizon():
    """An orbit: surfaces at 2.5-6 units, and the 'open water' at the top of the frames is
    seabed 8 units away. Its colour pins c_med 3-18% off the truth with narrow intervals (they
    miss it for seeds 15-20); allowed for as a surface behind the open water, they hold it."""
    rng = np.random.default_rng(15)
    ranges, observed, ids, groups = _observations(rng, groups=200, per_group=8, near=2.5,
                                                  far=6.0, noise=0.02)
    attn, bs, c_med = (np.array(TRUE[k]) for k in KEYS)
    seabed = 0.4 * np.exp(-attn * 8.0) + c_med * (1 - np.exp(-bs * 8.0))
    data = _with_open_water((ranges, observed, ids, groups), seabed, rng, pixels=400,
                            noise=0.003)
    fit = fit_water(*data, START)
    assert max(abs(c / t - 1) for c, t in zip(fit.c_med, TRUE["c_med"])) > 0.1
    plain = robust_halfwidths(fit, *data)
    assert any(abs(v - t) > h for v, h, t in zip(fit.c_med, plain.halfwidth["c_med"],
                                                 TRUE["c_med"]))
    allowed = robust_halfwidths(fit, *data, open_water_beyond=far_surface_range(data[0]))
    assert "open_water_surface" in allowed.splits
    for key in KEYS:
        for value, half, true in zip(getattr(fit, key), allowed.halfwidth[key], TRUE[key]):
            assert abs(value - true) <= half, key
    assert not all(allowed.determined["c_med"])


def test_the_veiling_light_beyond_the_surfaces_moves_along_the_backscatter_they_show():
    """The allowance's sigma_bs move keeps the backscatter at the median range where the
    veiling light falls to the farthest surfaces' backscatter (float64), and stays finite as
    sigma_bs -> 0 (the limit of that ratio is median / far)."""
    ranges = torch.linspace(1.0, 4.0, 1001, dtype=torch.float64)
    middle, far = float(ranges.median()), float(torch.quantile(ranges, 0.9))
    bs, c_med = torch.tensor([0.41, 0.24, 0.19], dtype=torch.float64), torch.tensor(
        [0.05, 0.24, 0.34], dtype=torch.float64)
    theta = torch.cat([torch.tensor([0.5, 0.3, 0.2], dtype=torch.float64), bs, c_med])
    moves = veiling_beyond_surfaces(theta, ranges)
    assert torch.equal(moves[0:3], torch.zeros(3, dtype=torch.float64))
    assert torch.allclose(moves[6:9].sqrt(), c_med * torch.exp(-bs * far), rtol=1e-12)
    raised = bs + moves[3:6].sqrt()
    veil = c_med * (1 - torch.exp(-bs * far))
    assert torch.allclose(veil * (1 - torch.exp(-raised * middle)),
                          c_med * (1 - torch.exp(-bs * middle)), rtol=1e-9)
    for tiny in (0.0, 1e-12):
        limit = veiling_beyond_surfaces(torch.cat([theta[0:3], torch.full((3,), tiny,
                                        dtype=torch.float64), c_med]), ranges)
        assert torch.isfinite(limit).all()
        assert limit[3:6].sqrt() == pytest.approx(
            [-np.log1p(-middle / far) / middle] * 3, rel=1e-6)
        assert limit[6:9].sqrt() == pytest.approx(c_med.tolist(), rel=1e-9)
    # surfaces all at one range bound sigma_bs nowhere
    alike = veiling_beyond_surfaces(theta, torch.full((50,), 3.0, dtype=torch.float64))
    assert torch.isinf(alike[3:6]).all() and torch.isfinite(alike[6:9]).all()


def test_without_open_water_the_unseen_veiling_light_widens_the_water_intervals():
    """A transect: surfaces at 1.5-4 units with the far ones placed short (the model's range
    bent by (z / median)^-0.1). The fit slides along the backscatter curve (c_med 3-9% low,
    sigma_bs 21-43% high, green and blue sigma_attn 11% high with it) and the data-split
    intervals miss it; the allowance for the veiling light the surfaces do not show holds
    it: the attenuation's part is its move in refits with c_med held at either end of the
    slide (``veiling_slide``)."""
    rng = np.random.default_rng(0)
    ranges, observed, ids, groups = _observations(rng, groups=200, per_group=8, near=1.5,
                                                  far=4.0, noise=0.005)
    ranges = ranges * (ranges / ranges.median()) ** -0.1
    fit = fit_water(ranges, observed, ids, groups, START)
    plain = robust_halfwidths(fit, ranges, observed, ids, groups)
    allowed = robust_halfwidths(fit, ranges, observed, ids, groups, unseen_veiling=True)
    assert "veiling_beyond_surfaces" in allowed.splits
    assert "veiling_beyond_surfaces" not in plain.splits

    def misses(spread, key):
        return sum(abs(v - t) > h for v, h, t in zip(getattr(fit, key), spread.halfwidth[key],
                                                     TRUE[key]))

    assert misses(plain, "sigma_bs") + misses(plain, "c_med") >= 4
    assert misses(allowed, "sigma_bs") + misses(allowed, "c_med") == 0
    assert not any(allowed.determined["sigma_bs"])
    # what the unseen veiling light moves is ambiguity; the data splits alone are not
    assert ambiguity_halfwidths(allowed)["sigma_bs"] == \
        allowed.splits["veiling_beyond_surfaces"][3:6]
    assert ambiguity_halfwidths(plain) == {k: [0.0] * 3 for k in KEYS}
    flagged = interval_determined({k: getattr(fit, k) for k in KEYS}, fit, allowed.halfwidth,
                                  ambiguity=ambiguity_halfwidths(allowed))
    assert not any(flagged["sigma_bs"]) and not any(flagged["c_med"])
    # the attenuation slides too: green and blue held only with the refits at the ends
    held = [abs(v - t) <= h for v, h, t in zip(fit.sigma_attn, allowed.halfwidth["sigma_attn"],
                                                TRUE["sigma_attn"])]
    assert held[1:] == [True, True]
    assert misses(plain, "sigma_attn") == 3
    theta = torch.tensor(fit.sigma_attn + fit.sigma_bs + fit.c_med, dtype=torch.float64)
    ends = [fit_water(ranges, observed, ids, groups, {
        "sigma_attn": fit.sigma_attn, "sigma_bs": end[3:6].tolist(),
        "c_med": end[6:9].tolist()}, 100, fixed=("c_med",)) for end in veiling_slide(
        theta, ranges)]
    moves = allowed.splits["veiling_beyond_surfaces"][0:3]
    assert moves == pytest.approx([1.96 * max(abs(e.sigma_attn[c] - a) for e in ends)
                                   for c, a in enumerate(fit.sigma_attn)], rel=1e-3)
    # surfaces out to where the backscatter has saturated: hardly any allowance
    long = _observations(rng, groups=200, per_group=8, near=1.5, far=30.0, noise=0.005)
    fit_long = fit_water(*long, START)
    moves = robust_halfwidths(fit_long, *long, unseen_veiling=True).splits[
        "veiling_beyond_surfaces"]
    assert all(m < 0.02 * c for m, c in zip(moves[6:9], fit_long.c_med))
    # with open water in view the veiling light is seen: no allowance
    seen = _with_open_water(long, TRUE["c_med"], rng)
    assert "veiling_beyond_surfaces" not in robust_halfwidths(
        fit_water(*seen, START), *seen, unseen_veiling=True).splits
