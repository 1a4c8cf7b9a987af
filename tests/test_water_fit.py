"""Tests for seathru.nerf.water_fit: the water recovered from surfaces seen at several ranges."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from seathru.nerf.water_fit import (WaterFit, brightness_weights, fit_surfaces, fit_water,
                                    incidental_term, projected_loss, projected_residuals,
                                    residual_outliers, unshared_variance)
from seathru.nerf.water_surfaces import SurfaceData, dark_pixels, surface_data
from seathru.nerf.water_uncertainty import group_scores, laplace_halfwidths

TRUE = {"sigma_attn": [0.55, 0.25, 0.20], "sigma_bs": [0.45, 0.30, 0.25],
        "c_med": [0.08, 0.20, 0.30]}


def _observations(rng: np.random.Generator, groups: int = 400, per_group: int = 12,
                  near: float = 0.5, far: float = 12.0, noise: float = 0.0):
    clean = rng.uniform(0.05, 0.9, size=(groups, 3))
    ids = np.repeat(np.arange(groups), per_group)
    ranges = rng.uniform(near, far, size=ids.size)
    attn, bs, c_med = (np.array(TRUE[k]) for k in ("sigma_attn", "sigma_bs", "c_med"))
    observed = clean[ids] * np.exp(-attn * ranges[:, None]) \
        + c_med * (1 - np.exp(-bs * ranges[:, None]))
    observed += noise * rng.standard_normal(observed.shape)
    return (torch.from_numpy(ranges), torch.from_numpy(observed), torch.from_numpy(ids),
            groups)


KEYS = ("sigma_attn", "sigma_bs", "c_med")
START = {"sigma_attn": 0.3, "sigma_bs": 0.3, "c_med": 0.3}


def _fit_and_spread(ranges, observed, ids, groups):
    fit = fit_water(ranges, observed, ids, groups,
                    {"sigma_attn": 0.3, "sigma_bs": 0.3, "c_med": 0.5})
    return fit, laplace_halfwidths(fit, ranges, observed, ids, groups)


def test_projected_loss_is_zero_at_the_true_water_and_positive_elsewhere():
    ranges, observed, ids, groups = _observations(np.random.default_rng(0))
    truth = [torch.tensor(TRUE[k], dtype=torch.float64) for k in ("sigma_attn", "sigma_bs",
                                                                  "c_med")]
    assert float(projected_loss(*truth, ranges, observed, ids, groups)) < 1e-16
    wrong = [truth[0] * 0.5, truth[1], truth[2]]
    assert float(projected_loss(*wrong, ranges, observed, ids, groups)) > 1e-6


@pytest.mark.parametrize("start", [0.05, 1.0])
def test_fit_recovers_the_water_from_surfaces_seen_over_a_range_of_distances(start):
    ranges, observed, ids, groups = _observations(np.random.default_rng(1), noise=1e-3)
    fit = fit_water(ranges, observed, ids, groups,
                    {"sigma_attn": start, "sigma_bs": start, "c_med": 0.5})
    for key in ("sigma_attn", "sigma_bs", "c_med"):
        assert np.allclose(getattr(fit, key), TRUE[key], rtol=0.05), (key, getattr(fit, key))
    assert fit.pixels == len(ranges) and fit.groups == groups


def test_a_fit_with_fixed_parameters_profiles_the_loss_along_them():
    """``fixed`` keeps those values at their start exactly while the rest is fitted: at the true
    veiling light the noise-free fit returns the true water; at a wrong one the other values
    move to the best fit there (a lower loss than where they started, a higher one than the
    free fit's); every name fixed, or an unknown one, is refused."""
    ranges, observed, ids, groups = _observations(np.random.default_rng(3), near=1.0, far=6.0)
    held = fit_water(ranges, observed, ids, groups, {**START, "c_med": TRUE["c_med"]},
                     balance_brightness=False, fixed=("c_med",))
    assert held.c_med == TRUE["c_med"]
    for key in ("sigma_attn", "sigma_bs"):
        assert getattr(held, key) == pytest.approx(TRUE[key], rel=1e-4)
    wrong = [0.8 * c for c in TRUE["c_med"]]
    start = {**START, "c_med": wrong}
    slid = fit_water(ranges, observed, ids, groups, start, balance_brightness=False,
                     fixed=("c_med",))
    assert slid.c_med == pytest.approx(wrong, rel=1e-15)

    def loss(water) -> float:
        return float(projected_loss(*(torch.tensor(w, dtype=torch.float64) for w in (
            water["sigma_attn"], water["sigma_bs"], water["c_med"])), ranges.double(),
            observed.double(), ids, groups))

    at_start = loss({"sigma_attn": [START["sigma_attn"]] * 3,
                     "sigma_bs": [START["sigma_bs"]] * 3, "c_med": wrong})
    assert 1e-12 < slid.loss < 0.5 * at_start
    assert max(abs(a - t) for a, t in zip(slid.sigma_bs, TRUE["sigma_bs"])) > 0.01
    for names in (("c_med", "sigma_attn", "sigma_bs"), ("veiling",)):
        with pytest.raises(ValueError, match="fixed"):
            fit_water(ranges, observed, ids, groups, START, fixed=names)


def test_fit_converges_alike_whatever_the_brightness_of_the_images(monkeypatch):
    # a dim exposure scales the loss by its square: the fit must end at the same water, in
    # about as many loss evaluations (absolute tolerances used to run dim fits to the limit)
    import seathru.nerf.water_fit as water_fit

    ranges, observed, ids, groups = _observations(np.random.default_rng(2), noise=1e-3)
    calls = []
    real = water_fit.projected_loss
    monkeypatch.setattr(water_fit, "projected_loss", lambda *a: calls.append(1) or real(*a))
    fits, evaluations = [], []
    for gain in (1.0, 0.02):
        scaled = {"sigma_attn": 0.3, "sigma_bs": 0.3, "c_med": 0.5 * gain}
        calls.clear()
        fit = fit_water(ranges, observed * gain, ids, groups, scaled)
        fits.append(fit)
        evaluations.append(len(calls))
    for key in ("sigma_attn", "sigma_bs"):
        assert np.allclose(getattr(fits[1], key), getattr(fits[0], key), rtol=1e-4), key
    assert np.allclose(np.array(fits[1].c_med) / 0.02, fits[0].c_med, rtol=1e-4)
    assert evaluations[1] < 2 * evaluations[0] + 20, evaluations


def test_a_fit_started_at_its_optimum_stops_there(monkeypatch):
    # the later rounds of a refit start where the one before ended; they used to run to the
    # evaluation limit (375) without moving the loss
    import seathru.nerf.water_fit as water_fit

    ranges, observed, ids, groups = _observations(np.random.default_rng(3), noise=1e-3)
    first = fit_water(ranges, observed, ids, groups, START, balance_brightness=False)
    calls = []
    real = water_fit.projected_loss
    monkeypatch.setattr(water_fit, "projected_loss", lambda *a: calls.append(1) or real(*a))
    again = fit_water(ranges, observed, ids, groups, water_fit.water_start(first),
                      balance_brightness=False)
    assert len(calls) < 60, len(calls)
    for key in KEYS:
        assert np.allclose(getattr(again, key), getattr(first, key), rtol=1e-4), key


def test_brightness_weights_count_groups_above_the_median_less_in_proportion():
    rng = np.random.default_rng(4)
    clean = torch.from_numpy(rng.uniform(0.0, 1.0, size=(201, 3)))
    c_med = torch.tensor([0.9, 0.05, 0.5], dtype=torch.float64)
    weights = brightness_weights(clean, c_med, open_water_group=True)
    assert torch.allclose(weights.mean(0), torch.ones(3, dtype=torch.float64))
    level = clean.clone()
    level[-1] = c_med                      # the open-water group is weighed at its veiling light
    median = level.median(0).values
    product = weights * torch.maximum(level, median)
    assert torch.allclose(product, product[0].expand_as(product))  # 1 / max(J, median), scaled
    for channel in range(3):
        above = level[:, channel] > median[channel]
        at_most = weights[~above, channel]
        assert torch.allclose(at_most, at_most.max().expand_as(at_most))   # dark groups alike
        assert bool((weights[above, channel] < at_most.max()).all())
    # a lower floor: flat below that share of the median, in proportion above it
    lowered = brightness_weights(clean, c_med, open_water_group=True, floor=0.3)
    product = lowered * torch.maximum(level, 0.3 * median)
    assert torch.allclose(product, product[0].expand_as(product))


def test_a_balanced_fit_is_a_minimum_of_the_loss_it_weights():
    # the weights travel with the fit into the intervals: at the balanced fit the weighted
    # scores cancel; the unweighted ones need not
    ranges, observed, ids, groups = _observations(np.random.default_rng(5), noise=0.02)
    fit = fit_water(ranges, observed, ids, groups, START)
    plain = fit_water(ranges, observed, ids, groups, START, balance_brightness=False)
    assert fit.weights is not None and fit.weights.shape == (groups, 3) and plain.weights is None
    theta = torch.tensor(fit.sigma_attn + fit.sigma_bs + fit.c_med, dtype=torch.float64)
    weighted = group_scores(theta, ranges, observed, ids, groups, weights=fit.weights).sum(0)
    unweighted = group_scores(theta, ranges, observed, ids, groups).sum(0)
    assert float(weighted.abs().max()) < 0.05 * float(unweighted.abs().max()), \
        (weighted, unweighted)
    assert np.allclose(fit.sigma_attn, TRUE["sigma_attn"], rtol=0.1)
    spread = laplace_halfwidths(fit, ranges, observed, ids, groups)
    assert all(np.isfinite(spread.halfwidth["sigma_attn"]))


def test_open_water_pixels_pin_the_veiling_light():
    rng = np.random.default_rng(3)
    ranges, observed, ids, groups = _observations(rng, near=4.0, far=4.5, noise=1e-2)
    _, without = _fit_and_spread(ranges, observed, ids, groups)
    water = torch.tensor(TRUE["c_med"], dtype=torch.float64) \
        + 1e-2 * torch.from_numpy(rng.standard_normal((500, 3)))
    ranges = torch.cat([ranges, torch.full((500,), float("inf"), dtype=torch.float64)])
    ids = torch.cat([ids, torch.full((500,), groups, dtype=ids.dtype)])
    fit, with_water = _fit_and_spread(ranges, torch.cat([observed, water]), ids, groups + 1)
    assert np.allclose(fit.c_med, TRUE["c_med"], rtol=0.05)
    assert all(with_water.determined["c_med"])
    assert all(np.isfinite(fit.sigma_attn + fit.sigma_bs))
    for before, after in zip(without.halfwidth["c_med"], with_water.halfwidth["c_med"]):
        assert after < before


def test_noisy_dark_pixels_do_not_pull_the_backscatter_below_the_truth():
    # The darkest 1% of noisy pixels lie ~2.3 noise deviations below the backscatter itself;
    # taken as the bound unraised, it held red backscatter at half the truth on the survey demo.
    rng = np.random.default_rng(8)
    ranges, observed, ids, groups = _observations(rng, groups=1500, per_group=8, far=8.0,
                                                  noise=0.02)
    black = torch.from_numpy(rng.random(groups) < 0.1)[ids]        # one surface in ten
    attn, bs, c_med = (torch.tensor(TRUE[k], dtype=torch.float64) for k in KEYS)
    backscatter = c_med * (1 - torch.exp(-bs * ranges[:, None]))
    noise = observed - _observations(np.random.default_rng(8), groups=1500, per_group=8,
                                     far=8.0)[1]
    observed = torch.where(black[:, None], backscatter + noise, observed)
    bound = dark_pixels(ranges, observed)
    fit = fit_water(ranges, observed, ids, groups, START, dark=bound)
    error = np.abs(np.array(fit.sigma_bs) / np.array(TRUE["sigma_bs"]) - 1)
    assert np.all(error < 0.2), fit.sigma_bs          # the unraised bound: 99%, 30%, 31%


def test_balanced_refit_is_nearer_the_simulated_water_than_the_plain_one():
    # The simulator's survey with its photographic textures, on its exact ranges: the image
    # formation holds in every pixel, yet the surfaces of one voxel differ in texture and in
    # pixel footprint from view to view. Unweighted, the bright ones set the attenuation high.
    from seathru.io.textures import load_sample_textures
    from seathru.sim import dive as dive_mod
    from seathru.sim import sensor
    from seathru.sim.water import water_params

    spec = dive_mod.DiveSpec(views=10, width=160, height=120, path="survey",
                             water=water_params("default"), seed=0, fov_deg=65.0,
                             supersample=2, seabed_amplitude=0.08)
    plan = dive_mod.plan_dive(spec, load_sample_textures())
    origins, directions, ranges, observed = [], [], [], []
    for view in dive_mod.render_views(spec, plan):
        origin, rays = sensor.pixel_rays(plan.camera, view.c2w, 1)
        directions.append(rays.reshape(-1, 3))
        origins.append(np.broadcast_to(origin, directions[-1].shape))
        ranges.append(view.range_m.reshape(-1).astype(np.float64))
        observed.append(view.water.reshape(-1, 3).astype(np.float64))
    origins, directions, ranges, observed = (torch.from_numpy(np.concatenate(a)) for a in
                                             (origins, directions, ranges, observed))
    water = ~torch.isfinite(ranges)
    data = surface_data(origins, directions, observed, torch.where(water, torch.nan, ranges),
                        (~water).double(), 0.05, 0.9, open_water_opacity=0.5, open_water=water)
    truth = np.array(spec.water.sigma_attn)
    errors = {}
    for balance in (False, True):
        fit = fit_water(data.ranges, data.observed, data.ids, data.groups, START, dark=data.dark,
                        balance_brightness=balance)
        errors[balance] = np.abs(np.array(fit.sigma_attn) / truth - 1)
    assert errors[True].max() < 0.8 * errors[False].max(), errors


def _misplaced(rng: np.random.Generator, share: float = 0.05, texture: float = 0.03,
               noise: float = 0.002):
    """Surfaces under TRUE water, with ``share`` of their pixels replaced by a surface only one
    view sees, 0.5-1 m away and bright, that the model put onto the group behind it: its
    pixel keeps the group's range. Each pixel differs from its group's colour by ``texture``
    (relative) and ``noise`` (absolute). Returns the data and which pixels were misplaced."""
    ranges, observed, ids, groups = _observations(rng, groups=300, per_group=12, near=1.5,
                                                  far=10.0)
    observed = observed * (1 + texture * torch.from_numpy(rng.standard_normal(observed.shape))) \
        + noise * torch.from_numpy(rng.standard_normal(observed.shape))
    misplaced = torch.from_numpy(rng.random(len(ranges)) < share)
    true_range = torch.from_numpy(rng.uniform(0.5, 1.0, int(misplaced.sum())))
    clean = torch.from_numpy(rng.uniform(0.5, 0.9, (int(misplaced.sum()), 3)))
    attn, bs, c_med = (torch.tensor(TRUE[k], dtype=torch.float64)
                       for k in ("sigma_attn", "sigma_bs", "c_med"))
    observed = observed.clone()
    observed[misplaced] = clean * torch.exp(-attn * true_range[:, None]) \
        + c_med * (1 - torch.exp(-bs * true_range[:, None]))
    return SurfaceData(ranges, observed, ids, groups), misplaced


def _errors(fit) -> list[float]:
    return [abs(v / t - 1) for k in ("sigma_attn", "sigma_bs") for v, t in
            zip(getattr(fit, k), TRUE[k])]


def test_residual_outliers_are_the_pixels_placed_at_the_wrong_range():
    data, misplaced = _misplaced(np.random.default_rng(21))
    fit = fit_water(data.ranges, data.observed, data.ids, data.groups, START)
    outliers = residual_outliers(fit, data, 3.5)
    assert float(outliers[misplaced].float().mean()) > 0.8
    # bright textured pixels carry larger residuals: some of them go too, at little cost
    assert float(outliers[~misplaced].float().mean()) < 0.15


def test_a_trimmed_fit_recovers_the_water_that_misplaced_pixels_pull_away():
    data, _ = _misplaced(np.random.default_rng(22))
    plain, same = fit_surfaces(data, START, trim=0.0)
    trimmed, used = fit_surfaces(data, START, trim=3.5)
    assert same is data and len(used.ranges) < len(data.ranges)
    assert max(_errors(plain)) > 0.1, _errors(plain)
    assert max(_errors(trimmed)) < 0.05, _errors(trimmed)


def test_trimming_leaves_clean_data_and_open_water_alone():
    rng = np.random.default_rng(23)
    ranges, observed, ids, groups = _observations(rng, groups=200, noise=1e-3)
    data = SurfaceData(torch.cat([ranges, torch.full((50,), torch.inf, dtype=ranges.dtype)]),
                       torch.cat([observed, torch.tensor(TRUE["c_med"]).double()
                                  * (1 + 0.02 * torch.from_numpy(rng.standard_normal((50, 3))))]),
                       torch.cat([ids, torch.full((50,), groups)]), groups + 1)
    fit, used = fit_surfaces(data, START, trim=3.5)
    assert int((~torch.isfinite(used.ranges)).sum()) == 50
    assert len(used.ranges) > 0.95 * len(data.ranges)
    assert int(used.ids.max()) + 1 == used.groups
    assert max(_errors(fit)) < 0.05


def _textured(seed: int, groups: int = 1500, per_group: int = 6, texture: float = 0.3,
              open_water: int = 500):
    """Groups whose pixels each see their own spot: clean colour times (1 + texture noise),
    transmitted by the water like the signal; plus open-water pixels at ``c_med``."""
    rng = np.random.default_rng(seed)
    clean = rng.uniform(0.05, 0.9, size=(groups, 3))
    ids = np.repeat(np.arange(groups), per_group)
    ranges = rng.uniform(0.5, 6.0, ids.size)
    attn, bs, c_med = (np.array(TRUE[k]) for k in KEYS)
    spots = clean[ids] * (1.0 + texture * rng.standard_normal((ids.size, 3)))
    observed = spots * np.exp(-attn * ranges[:, None]) + c_med * (1 - np.exp(-bs * ranges[:, None]))
    ranges = np.r_[ranges, np.full(open_water, np.inf)]
    observed = np.r_[observed, np.tile(c_med, (open_water, 1))]
    ids = np.r_[ids, np.full(open_water, groups)]
    return (torch.from_numpy(ranges), torch.from_numpy(observed), torch.from_numpy(ids),
            groups + 1)


def test_incidental_term_is_what_fitting_a_groups_colour_takes_out_of_its_residuals():
    # One group, float64 reference by simulation: E[RSS] = tr S - f'Sf / f'f at the true water.
    rng = np.random.default_rng(3)
    ranges = torch.from_numpy(rng.uniform(0.5, 8.0, 7))
    attn = torch.tensor(TRUE["sigma_attn"], dtype=torch.float64)
    bs = torch.tensor(TRUE["sigma_bs"], dtype=torch.float64)
    c_med = torch.tensor(TRUE["c_med"], dtype=torch.float64)
    unshared = torch.from_numpy(rng.uniform(1e-4, 4e-3, (7, 3)))
    ids = torch.zeros(7, dtype=torch.long)
    transmission = torch.exp(-attn * ranges[:, None])
    signal = 5.0 * transmission + c_med * (1 - torch.exp(-bs * ranges[:, None]))
    draws = 20000  # each draw of the noise its own group
    noise = torch.from_numpy(rng.standard_normal((draws, 7, 3))) * unshared.sqrt()
    observed = (signal + noise).reshape(-1, 3)
    residuals = projected_residuals(attn, bs, c_med, ranges.repeat(draws), observed,
                                    torch.arange(draws).repeat_interleave(7), draws)[0]
    expected = unshared.sum() - incidental_term(attn, ranges, unshared, ids, 1)
    assert float((residuals ** 2).sum() / draws) == pytest.approx(float(expected), rel=0.02)


def test_unshared_variance_follows_the_texture_variance_near_and_leaves_open_water_out():
    rng = np.random.default_rng(4)
    groups, per_group = 3000, 8
    ids = np.repeat(np.arange(groups), per_group)
    ranges = rng.uniform(0.5, 6.0, ids.size)
    variance = np.where(ranges < 3.0, 4e-3, 1e-3)[:, None] * np.ones(3)
    attn, bs, c_med = (np.array(TRUE[k]) for k in KEYS)
    transmission = np.exp(-attn * ranges[:, None])
    spots = rng.uniform(0.2, 0.8, (groups, 3))[ids] + np.sqrt(variance) * rng.standard_normal(
        (ids.size, 3))
    observed = spots * transmission + c_med * (1 - np.exp(-bs * ranges[:, None]))
    ranges, observed = np.r_[ranges, np.inf, np.inf], np.r_[observed, [c_med, c_med]]
    ids = np.r_[ids, groups, groups]
    fit = WaterFit(TRUE["sigma_attn"], TRUE["sigma_bs"], TRUE["c_med"], 0.0, ids.size, groups + 1)
    estimated = unshared_variance(fit, torch.from_numpy(ranges), torch.from_numpy(observed),
                                  torch.from_numpy(ids), groups + 1, bins=6).numpy()
    assert np.all(estimated[-2:] == 0.0)
    near = ranges[:-2] < 2.5
    ratio = estimated[:-2][near] / (variance[near] * transmission[near] ** 2)
    # a rough estimate (docs/water.md): the near bins within 30%, every channel
    assert np.all((np.median(ratio, axis=0) > 0.65) & (np.median(ratio, axis=0) < 1.15))


def test_the_noise_term_takes_away_the_pull_of_texture_that_fades_with_range():
    data = _textured(0)
    plain = fit_water(*data, START)
    termed = fit_water(*data, START, noise_term=True)

    def attenuation_error(fit) -> float:
        return float(np.abs(np.array(fit.sigma_attn) / TRUE["sigma_attn"] - 1).mean())

    red_bs = [abs(fit.sigma_bs[0] / TRUE["sigma_bs"][0] - 1) for fit in (plain, termed)]
    assert attenuation_error(plain) > 0.06 and attenuation_error(termed) < 0.03
    assert red_bs[1] < 0.25 * red_bs[0], red_bs
