"""The water fitted to images of surfaces at known ranges, by variable projection.

For pixels whose surface lies at range ``z`` (the model's own depth during training, or the
simulator's true depth in the diagnostic benchmark), the SeaThru image formation is

    I = J exp(-sigma_attn z) + c_med (1 - exp(-sigma_bs z)),

per channel. Pixels are grouped by the surface point they see (one point's pixel in every
view that sees it) or by the voxel their surface point falls in
(:mod:`seathru.nerf.water_surfaces` gathers and groups them),
with one unknown clean colour ``J`` per group and channel; for given water the best
non-negative ``J`` of each voxel has a closed form, so the fit runs over the 9 water parameters
alone. The same surface seen from several ranges is what pins the attenuation down (as in
Sea-thru's regression on range); surfaces seen at one range only leave ``J`` and the water
traded against each other.

How well the images determine the water is :mod:`seathru.nerf.water_uncertainty`'s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from statistics import NormalDist
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from seathru.nerf.water_surfaces import DARK_QUANTILE, SurfaceData, without_pixels


@dataclass
class WaterFit:
    sigma_attn: list[float]     # per channel, 1 / (unit of z)
    sigma_bs: list[float]
    c_med: list[float]
    loss: float                 # mean squared (weighted) residual at the fit
    pixels: int
    groups: int
    weights: Tensor | None = None  # (groups, 3) group weights used (brightness_weights)
    unshared: Tensor | None = None  # (N, 3) variances its incidental_term used, if any


def projected_loss(sigma_attn: Tensor, sigma_bs: Tensor, c_med: Tensor, ranges: Tensor,
                   observed: Tensor, ids: Tensor, groups: int,
                   weights: Tensor | None = None, unshared: Tensor | None = None) -> Tensor:
    """Mean squared residual of the image formation with the best clean colour per group.

    Args:
        sigma_attn, sigma_bs, c_med: (3,) water parameters.
        ranges: (N,) range of each pixel's surface.
        observed: (N, 3) pixel values.
        ids: (N,) group of each pixel (``water_surfaces.voxel_groups``); groups: their number.
        weights: optional (groups, 3) weight of each group's squared residuals per channel
            (:func:`brightness_weights`); a group's clean colour does not depend on it.
        unshared: optional (N, 3) variance of what each pixel does not share with its group
            (:func:`unshared_variance`): each group's loss gets back the share of it that
            fitting the group's clean colour takes away (:func:`incidental_term`).

    Returns:
        the scalar loss (differentiable in the water parameters).
    """
    loss = (projected_residuals(sigma_attn, sigma_bs, c_med, ranges, observed, ids, groups,
                                weights)[0] ** 2).mean()
    if unshared is None:
        return loss
    term = incidental_term(sigma_attn, ranges, unshared, ids, groups, weights)
    return loss + term / observed.numel()


def incidental_term(sigma_attn: Tensor, ranges: Tensor, unshared: Tensor, ids: Tensor,
                    groups: int, weights: Tensor | None = None) -> Tensor:
    """Sum over groups (and channels) of ``f'Sf / f'f``: the part of the unshared variance that
    fitting a group's clean colour takes out of its squared residuals (``f`` the group's
    transmissions ``exp(-sigma_attn z)``, ``S`` its pixels' unshared variances).

    A group's expected squared residual is its signal misfit plus ``tr S - f'Sf / f'f``. Where
    ``S`` falls with range (the texture a pixel does not share is transmitted by the water as
    the signal is), the second term grows as ``f`` leans on the near pixels, that is with the
    attenuation, and pulls the fit there (Neyman and Scott's incidental parameters: one clean
    colour a group, so the pull does not shrink with more groups). Adding it back leaves the
    misfit's expectation alone to be minimised.

    Args:
        sigma_attn: (3,) attenuation; ranges: (N,) (inf: open water, no term).
        unshared: (N, 3) variances; ids, groups: the pixels' groups.
        weights: optional (groups, 3) group weights, as :func:`projected_loss`'s.

    Returns:
        the scalar term.

    Example::

        unshared = unshared_variance(fit, z, rgb, ids, groups)
        loss = projected_loss(attn, bs, c_med, z, rgb, ids, groups, weights, unshared)
    """
    term = _incidental_parts(sigma_attn, ranges, unshared, ids, groups)[2]
    return (term if weights is None else term * weights).sum()


def incidental_gradient(sigma_attn: Tensor, ranges: Tensor, unshared: Tensor, ids: Tensor,
                        groups: int, weights: Tensor | None = None) -> Tensor:
    """(N, 3) each pixel's share of the gradient of :func:`incidental_term` in ``sigma_attn``
    (the variances held fixed, as the fit holds them): a group's ``f'Sf / f'f`` with
    ``f_i^2 = exp(-2 sigma_attn z_i)`` has the derivative ``-2 sum_i z_i f_i^2 (S_i - term) /
    f'f``, split over its pixels."""
    f2, den, term = _incidental_parts(sigma_attn, ranges, unshared, ids, groups)
    share = -2.0 * ranges.double().clamp_max(1e6)[:, None] * f2 * (unshared - term[ids]) \
        / den[ids]
    return share if weights is None else share * weights[ids]


def _incidental_parts(sigma_attn: Tensor, ranges: Tensor, unshared: Tensor, ids: Tensor,
                      groups: int) -> tuple[Tensor, Tensor, Tensor]:
    """(N, 3) squared transmissions ``f^2``, (groups, 3) their sums ``f'f`` (clamped above 0)
    and each group's ``f'Sf / f'f``."""
    f2 = torch.exp(-2.0 * sigma_attn * ranges.clamp_max(1e6)[:, None])
    den = unshared.new_zeros(groups, 3).index_add_(0, ids, f2).clamp_min(1e-300)
    return f2, den, unshared.new_zeros(groups, 3).index_add_(0, ids, f2 * unshared) / den


def unshared_variance(fit: "WaterFit", ranges: Tensor, observed: Tensor, ids: Tensor,
                      groups: int, bins: int = 12) -> Tensor:
    """(N, 3) variance of what each surface pixel does not share with its group, from the
    residuals at ``fit``: per channel, the squared residuals over one minus the pixel's leverage
    on its group's clean colour, fitted by least squares with a constant (sensor noise, which
    pulls nothing and is left out) plus a variance per quantile bin of range times the squared
    transmission ``exp(-2 sigma_attn z)``. A rough estimate (docs/water.md, "The refit adds
    the term back", for what it gets wrong and why it is kept); 0 for open water.

    Returns:
        (N, 3) float64.
    """
    if not bool(torch.isfinite(ranges).any()):
        return torch.zeros_like(observed, dtype=torch.float64)
    parts = residual_variance_design(fit, ranges, observed, ids, groups, bins)
    surface, f2, one_hot = parts.surface, parts.f2, parts.one_hot
    variance = torch.zeros(bins, 3, dtype=f2.dtype)
    for c in range(3):
        design = torch.cat([torch.ones_like(f2[:, :1]), f2[:, c:c + 1] * one_hot], 1)[surface]
        variance[:, c] = torch.linalg.lstsq(design, parts.squared[surface, c:c + 1]
                                            ).solution[1:, 0].clamp_min(0.0)
    unshared = torch.zeros_like(parts.squared)
    unshared[surface] = (f2 * (one_hot @ variance))[surface]
    return unshared


@dataclass
class ResidualVarianceDesign:
    """What :func:`unshared_variance` regresses, per pixel (N rows, float64)."""

    squared: Tensor     # (N, 3) squared residual at the fit over one minus its leverage
    clean: Tensor       # (groups, 3) the groups' clean colours at the fit
    f2: Tensor          # (N, 3) squared transmission exp(-2 sigma_attn z)
    one_hot: Tensor     # (N, bins) the pixel's range-quantile bin (zero rows: open water)
    surface: Tensor     # (N,) bool, finite range


def residual_variance_design(fit: "WaterFit", ranges: Tensor, observed: Tensor, ids: Tensor,
                             groups: int, bins: int = 12) -> ResidualVarianceDesign:
    """The residuals at ``fit`` and the range-bin design :func:`unshared_variance` fits them
    with (also the start of other estimators of the unshared variance, as in
    ``benchmarks/bench_unshared_variance.py``); needs at least one surface pixel."""
    ranges, observed = ranges.double(), observed.double()
    theta = water_vector(fit).to(ranges.device).split(3)
    residuals, clean, used = projected_residuals(*theta, ranges, observed, ids, groups)
    surface = torch.isfinite(ranges)
    f2 = torch.exp(-2.0 * theta[0] * used[:, None])
    norm = observed.new_zeros(groups, 3).index_add_(0, ids, f2)
    leverage = (f2 / norm[ids].clamp_min(1e-300)).clamp_max(0.9)
    z = ranges[surface]
    edges = torch.quantile(z, torch.linspace(0.0, 1.0, bins + 1, dtype=z.dtype))[1:-1]
    which = torch.zeros_like(ranges, dtype=torch.long)
    which[surface] = torch.bucketize(z, edges)
    one_hot = F.one_hot(which, bins).to(z.dtype) * surface[:, None]
    return ResidualVarianceDesign(residuals ** 2 / (1.0 - leverage), clean, f2, one_hot, surface)


def brightness_weights(clean: Tensor, c_med: Tensor, open_water_group: bool,
                       floor: float = 1.0) -> Tensor:
    """(groups, 3) weights of each group's squared residuals: ``1 / max(J, floor median J)``
    for a group of clean colour ``J`` (the open-water group at ``c_med``), scaled to mean 1 per
    channel. Groups brighter than the median count less, in proportion; the others alike.

    A group's pull on the attenuation is its residual times the model's slope in it, and the
    slope grows with the group's brightness ``J``; residuals from what a group's pixels do not
    share (texture of a slightly different spot, a pixel footprint at a longer range averaging a
    bright speck with its darker surroundings) do not grow with it the same way. Unweighted,
    bright groups set the attenuation, and a bright speck looks darker from afar: the
    attenuation comes out high. Above the median each group pulls alike whatever its
    brightness. Below it the weight stays flat: a dark group's residual is mostly pixel noise,
    and its clean colour, kept non-negative, is biased by it (weights of ``1 / J`` down to a
    tenth of the median moved a noisy fit's backscatter 17-23% off).

    Args:
        clean: (groups, 3) clean colour of each group (the open-water group last, if any).
        c_med: (3,) veiling light, the open-water group's level.
        open_water_group: whether the last group is open water.
        floor: the share of the median below which the weight stays flat (0.3 and 0.5 were
            tried on the demo: green and blue attenuation 1-2 points lower, docs/water.md).

    Returns:
        (groups, 3) weights, mean 1 per channel.

    Example::

        weights = brightness_weights(clean, c_med, open_water_group=True)
        loss = projected_loss(attn, bs, c_med, z, rgb, ids, groups, weights)
    """
    level = clean.detach().clone()
    if open_water_group:
        level[-1] = c_med.detach()
    level = torch.maximum(level, floor * level.median(0).values.clamp_min(1e-6))
    weights = 1.0 / level
    return weights / weights.mean(0)


def projected_residuals(sigma_attn: Tensor, sigma_bs: Tensor, c_med: Tensor, ranges: Tensor,
                         observed: Tensor, ids: Tensor, groups: int,
                         weights: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """(N, 3) residuals at the best non-negative clean colour per group (times the square root
    of their group's weight, where given), that (groups, 3) colour and the (N,) ranges as used
    (open water, range inf, as a very long finite range: same values, finite gradients)."""
    ranges = ranges.clamp_max(1e6)
    attenuation = torch.exp(-sigma_attn * ranges[:, None])
    backscatter = c_med * (1.0 - torch.exp(-sigma_bs * ranges[:, None]))
    num = observed.new_zeros(groups, 3).index_add_(0, ids, attenuation * (observed - backscatter))
    den = observed.new_zeros(groups, 3).index_add_(0, ids, attenuation * attenuation)
    clean = (num / den.clamp_min(1e-12)).clamp_min(0.0)
    residuals = observed - clean[ids] * attenuation - backscatter
    if weights is not None:
        residuals = residuals * weights.sqrt()[ids]
    return residuals, clean, ranges


def _inverse_softplus(value: float) -> float:
    value = max(value, 1e-6)
    return value + math.log(-math.expm1(-value)) if value < 20 else value


def noise_allowance(fit: "WaterFit", ranges: Tensor, observed: Tensor, ids: Tensor,
                    groups: int, quantile: float = DARK_QUANTILE) -> Tensor:
    """How far below the noise-free backscatter the dark-pixel ``quantile`` of noisy pixels
    falls: the normal quantile times the robust spread (1.4826 MAD) of each channel's residuals
    at ``fit``. The residuals also hold texture and geometry error, so the allowance errs large
    (a looser bound), never small (a bound below the truth biases the backscatter low).

    Returns:
        (3,) float64, to add to the dark values of ``water_surfaces.dark_pixels``.
    """
    theta = water_vector(fit).to(ranges.device).split(3)
    residuals = projected_residuals(*theta, ranges.double(), observed.double(), ids, groups)[0]
    centred = residuals - residuals.median(dim=0).values
    spread = 1.4826 * centred.abs().median(dim=0).values
    return NormalDist().inv_cdf(1.0 - quantile) * spread


def dark_excess(sigma_bs: Tensor, c_med: Tensor, dark: tuple[Tensor, Tensor]) -> Tensor:
    """Mean squared excess of the modelled backscatter over the dark-pixel bound (0 if below)."""
    centres, values = dark
    backscatter = c_med * (1.0 - torch.exp(-sigma_bs * centres[:, None]))
    return (torch.relu(backscatter - values) ** 2).mean()


def fit_water(ranges: Tensor, observed: Tensor, ids: Tensor, groups: int, start: dict,
              steps: int = 300, colour_max: float = 1.5,
              dark: tuple[Tensor, Tensor] | None = None, dark_weight: float = 10.0,
              balance_brightness: bool = True, brightness_floor: float = 1.0,
              noise_term: bool = False, unshared: Tensor | None = None,
              fixed: Sequence[str] = ()) -> WaterFit:
    """Fit the 9 water parameters by L-BFGS on :func:`projected_loss`, in float64.

    Nine smooth parameters and a cheap exact loss: a quasi-Newton method with a line search
    converges in a few hundred evaluations where Adam needs thousands (red attenuation, whose
    signal fades fastest with range, is the slow direction).

    Args:
        ranges: (N,) ranges; observed: (N, 3) pixels; ids, groups: from ``water_surfaces.voxel_groups``.
        start: ``{"sigma_attn": [3] or float, "sigma_bs": ..., "c_med": ...}`` start values.
        steps: most loss evaluations of the optimiser.
        colour_max: ``c_med`` is kept in (0, colour_max).
        dark: optional dark-pixel bound (``water_surfaces.dark_pixels``): the water is first fitted
            without it, the bound is raised by the residuals' :func:`noise_allowance`, and
            backscatter above the raised bound is penalised with ``dark_weight`` times its
            mean squared excess in a second fit started from the first.
        balance_brightness: weight each group by its inverse clean colour
            (:func:`brightness_weights`, taken at an unweighted fit and once more at the
            weighted one); False fits every pixel alike.
        brightness_floor: :func:`brightness_weights`' ``floor``.
        noise_term: add back what fitting each group's clean colour takes out of its
            residuals (:func:`incidental_term`, with :func:`unshared_variance` taken at the fit
            without it and once more at the fit with it).
        unshared: (N, 3) variances for that term, given (as another fit's ``unshared``, to
            refit part of its data alike) instead of estimated; implies the term.
        fixed: names (``sigma_attn``, ``sigma_bs``, ``c_med``) kept at their ``start``
            values while the rest is fitted: a profile of the loss along them.

    Returns:
        the fitted water, its loss and the group weights it used.

    Example::

        ids, groups = water_surfaces.voxel_groups(points, 0.02)
        fit = fit_water(z, rgb, ids, groups, {"sigma_attn": 0.2, "sigma_bs": 0.2, "c_med": 0.2})
    """
    unknown = set(fixed) - set(NAMES)
    if unknown or set(fixed) == set(NAMES):
        raise ValueError(f"fixed: {list(fixed)}: name some of the water parameters {NAMES}, "
                         "not all")
    weights = None
    free = _fit_water(ranges, observed, ids, groups, start, steps, colour_max, fixed=fixed)
    if balance_brightness:
        for _ in range(2):
            weights = _weights_at(free, ranges, observed, ids, groups, brightness_floor)
            free = _fit_water(ranges, observed, ids, groups, water_start(free), steps, colour_max,
                              weights=weights, fixed=fixed)
    if unshared is not None:
        free = _fit_water(ranges, observed, ids, groups, water_start(free), steps, colour_max,
                          weights=weights, unshared=unshared, fixed=fixed)
    elif noise_term:
        for _ in range(2):
            unshared = unshared_variance(free, ranges, observed, ids, groups)
            free = _fit_water(ranges, observed, ids, groups, water_start(free), steps, colour_max,
                              weights=weights, unshared=unshared, fixed=fixed)
    if dark is None:
        return free
    allowance = noise_allowance(free, ranges, observed, ids, groups)
    dark = (dark[0], dark[1].to(allowance) + allowance)
    return _fit_water(ranges, observed, ids, groups, water_start(free), steps, colour_max, dark,
                      dark_weight, weights, unshared, fixed)


def residual_outliers(fit: WaterFit, data: SurfaceData, threshold: float) -> Tensor:
    """Surface pixels the image formation at ``fit`` explains far worse than the rest.

    A pixel's residual (with its group's best clean colour) is an outlier where it lies more
    than ``threshold`` robust standard deviations (1.4826 times the median absolute
    deviation) from the median, in any channel. Open-water pixels (range inf) are never
    outliers.

    What this removes is pixels placed at the wrong range: a surface only one training view
    sees, which the model puts onto the background other views see behind it, joins the
    background's voxel with a colour the background's range does not explain (on simulated
    surveys 3-4% of the surface pixels; they raised green and blue attenuation by 10-15
    points, ``docs/water.md``). Residuals relative to the predicted value were tried: they
    also drop the far, dark pixels whose noise is large against their value, and the red
    attenuation rose.

    Args:
        fit: the water fitted to ``data``; data: its pixels (``water_surfaces.surface_data``).
        threshold: robust standard deviations from the median.

    Returns:
        (N,) bool, True for the outliers.

    Example::

        fit = fit_water(data.ranges, data.observed, data.ids, data.groups, start)
        kept = without_pixels(data, residual_outliers(fit, data, 3.5))
    """
    theta = water_vector(fit).split(3)
    residuals = projected_residuals(*theta, data.ranges.double(), data.observed.double(),
                                     data.ids, data.groups)[0]
    surface = torch.isfinite(data.ranges)
    if int(surface.sum()) < 2:
        return torch.zeros_like(surface)
    centre = residuals[surface].median(0).values
    spread = 1.4826 * (residuals[surface] - centre).abs().median(0).values
    far = ((residuals - centre).abs() > threshold * spread.clamp_min(1e-12)).any(dim=1)
    return far & surface


def fit_surfaces(data: SurfaceData, start: dict, steps: int = 300, colour_max: float = 1.5,
                 dark_bound: bool = True, balance_brightness: bool = True,
                 trim: float = 0.0, noise_term: bool = False) -> tuple[WaterFit, SurfaceData]:
    """:func:`fit_water` on ``data``; with ``trim`` > 0, fitted again without the
    :func:`residual_outliers` at ``trim`` robust standard deviations, from the first fit.

    Args:
        data: surface pixels (``water_surfaces.surface_data``): (N,) ranges, (N, 3) pixels, (N,) groups.
        start: start values, as :func:`fit_water`'s; steps, colour_max: :func:`fit_water`'s.
        dark_bound: use ``data.dark`` (the dark-pixel bound); balance_brightness: see
            :func:`fit_water`.
        trim: robust standard deviations beyond which a pixel is left out; 0 fits once.
        noise_term: :func:`fit_water`'s.

    Returns:
        the fit and the data it was made on (``data`` itself when nothing was trimmed).

    Example::

        fit, used = fit_surfaces(data, model.water_parameters(), trim=3.5)
        spread = water_uncertainty.robust_halfwidths(fit, used.ranges, used.observed, used.ids,
                                                     used.groups)
    """
    dark = data.dark if dark_bound else None
    fit = fit_water(data.ranges, data.observed, data.ids, data.groups, start, steps,
                    colour_max, dark, balance_brightness=balance_brightness,
                    noise_term=noise_term)
    if trim <= 0:
        return fit, data
    outliers = residual_outliers(fit, data, trim)
    trimmed = without_pixels(data, outliers) if bool(outliers.any()) else data
    if trimmed is data or isinstance(trimmed, str):
        return fit, data
    return fit_water(trimmed.ranges, trimmed.observed, trimmed.ids, trimmed.groups,
                     water_start(fit), steps, colour_max, dark,
                     balance_brightness=balance_brightness, noise_term=noise_term), trimmed


def water_start(fit: WaterFit) -> dict[str, list[float]]:
    """The fit's water by name, as :func:`fit_water` takes its ``start``."""
    return {key: getattr(fit, key) for key in NAMES}


def _weights_at(fit: WaterFit, ranges: Tensor, observed: Tensor, ids: Tensor,
                groups: int, floor: float = 1.0) -> Tensor:
    """:func:`brightness_weights` of the clean colours at ``fit``."""
    theta = water_vector(fit).to(ranges.device).split(3)
    clean = projected_residuals(*theta, ranges.double(), observed.double(), ids, groups)[1]
    return brightness_weights(clean, theta[2], bool((~torch.isfinite(ranges)).any()), floor)


# Stopping rule of every fit, on the loss relative to its start value. A fit started at its
# optimum (the later rounds of brightness weights, the dark-bound fit where the bound does not
# bind) ran to the evaluation limit under 1e-16 / 1e-12, changing the loss by under 1e-9: on
# the demo 5.8 of a refit's 7.5 s (a one-off count). These stop it there; the water moves by
# under 0.5% (benchmarks/results/refit_tolerance.md).
LBFGS_TOLERANCE_CHANGE = 1e-10
LBFGS_TOLERANCE_GRAD = 1e-9


def water_raw(start: dict, colour_max: float, device=None) -> Tensor:
    """(9,) float64 unconstrained parameters of the water ``start`` (values per channel or one
    for all): softplus for the two coefficients, a logistic in (0, colour_max) for ``c_med``;
    :func:`water_of_raw` inverts it."""
    colour = [min(max(c / colour_max, 1e-4), 1 - 1e-4) for c in _triple(start["c_med"])]
    return torch.tensor([_inverse_softplus(v) for v in _triple(start["sigma_attn"])]
                        + [_inverse_softplus(v) for v in _triple(start["sigma_bs"])]
                        + [math.log(c / (1 - c)) for c in colour],
                        dtype=torch.float64, device=device, requires_grad=True)


def _triple(value) -> list[float]:
    """A start value per channel (one number: the same for all three)."""
    return [float(value)] * 3 if isinstance(value, (int, float)) else [float(v) for v in value]


def water_of_raw(raw: Tensor, colour_max: float) -> tuple[Tensor, Tensor, Tensor]:
    """``sigma_attn``, ``sigma_bs``, ``c_med`` (3 each) of :func:`water_raw`'s parameters."""
    return F.softplus(raw[0:3]), F.softplus(raw[3:6]), torch.sigmoid(raw[6:9]) * colour_max


def minimise_relative(raw: Tensor, objective, steps: int,
                      tolerance_change: float | None = None,
                      tolerance_grad: float | None = None) -> None:
    """Minimise ``objective()`` over ``raw`` in place by L-BFGS, on the loss relative to its
    start value (default tolerances: ``LBFGS_TOLERANCE_CHANGE`` and ``_GRAD``).

    L-BFGS's tolerances are absolute and the loss is a small mean squared residual, so it is
    measured relative to its start value. Unscaled, refits on the demo ran to the evaluation
    limit (375 evaluations, 4.6 s) and ended above the scaled fit's loss (0.9 s).
    """
    optimiser = torch.optim.LBFGS(
        [raw], lr=1.0, max_iter=max(1, steps), history_size=20,
        tolerance_grad=LBFGS_TOLERANCE_GRAD if tolerance_grad is None else tolerance_grad,
        tolerance_change=LBFGS_TOLERANCE_CHANGE if tolerance_change is None
        else tolerance_change, line_search_fn="strong_wolfe")
    with torch.no_grad():
        scale = max(float(objective()), 1e-30)

    def closure() -> Tensor:
        optimiser.zero_grad()
        loss = objective() / scale
        loss.backward()
        return loss

    with torch.enable_grad():
        optimiser.step(closure)


def _fit_water(ranges: Tensor, observed: Tensor, ids: Tensor, groups: int, start: dict,
               steps: int, colour_max: float, dark: tuple[Tensor, Tensor] | None = None,
               dark_weight: float = 10.0, weights: Tensor | None = None,
               unshared: Tensor | None = None, fixed: Sequence[str] = ()) -> WaterFit:
    """One L-BFGS fit of :func:`fit_water` with given group ``weights`` (or none),
    :func:`incidental_term` variances ``unshared`` (or none) and the ``fixed`` parameters at
    their ``start`` values (their raw values then take no gradient and stay put)."""
    raw = water_raw(start, colour_max, ranges.device)
    ranges, observed = ranges.double(), observed.double()
    if dark is not None:
        dark = (dark[0].double().to(ranges.device), dark[1].double().to(ranges.device))
    held = {name: torch.tensor(_triple(start[name]), dtype=torch.float64, device=ranges.device)
            for name in fixed}

    def water() -> tuple[Tensor, Tensor, Tensor]:
        values = dict(zip(NAMES, water_of_raw(raw, colour_max)))
        values.update(held)
        return values["sigma_attn"], values["sigma_bs"], values["c_med"]

    def objective() -> Tensor:
        attn, bs, c_med = water()
        loss = projected_loss(attn, bs, c_med, ranges, observed, ids, groups, weights, unshared)
        if dark is not None:
            loss = loss + dark_weight * dark_excess(bs, c_med, dark)
        return loss

    minimise_relative(raw, objective, steps)
    with torch.no_grad():
        attn, bs, c_med = water()
        loss = float(projected_loss(attn, bs, c_med, ranges, observed, ids, groups, weights))
    return WaterFit(attn.tolist(), bs.tolist(), c_med.tolist(), loss, int(len(ranges)), groups,
                    weights, unshared)


NAMES = ("sigma_attn", "sigma_bs", "c_med")


def water_vector(fit: WaterFit) -> Tensor:
    """The fit's 9 water parameters (sigma_attn, sigma_bs, c_med; R G B each), float64."""
    return torch.tensor(fit.sigma_attn + fit.sigma_bs + fit.c_med, dtype=torch.float64)
