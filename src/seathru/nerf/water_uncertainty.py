"""How well the images determine a water fitted to surfaces (:mod:`seathru.nerf.water_fit`).

:func:`laplace_halfwidths` takes the curvature of the profile loss (pixel noise only);
:func:`robust_halfwidths` is cluster-robust over surface groups and adds how much parts of the
data disagree, which holds most of a NeRF geometry's error. :func:`interval_determined` flags
the parameters a trained water's interval leaves undetermined, or that alternatives the images
cannot tell apart (:data:`AMBIGUOUS_SPLITS`) move beyond the goal's tolerance.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from seathru.nerf.water_fit import (NAMES, WaterFit, fit_water, incidental_gradient,
                                    projected_loss, projected_residuals, water_start,
                                    water_vector)
from seathru.nerf.water_interval import DETERMINED_MAX_RELATIVE, interval_halfwidth
from seathru.nerf.water_surfaces import renumbered_groups


# comparisons of robust_halfwidths that no amount of data of the same kind narrows: the veiling
# light beyond the farthest surfaces where no open water is in view, and open water that may be
# far seabed; the others measure how well the data pin the water, these what they cannot say
AMBIGUOUS_SPLITS = ("veiling_beyond_surfaces", "open_water_surface")


@dataclass
class WaterUncertainty:
    halfwidth: dict[str, list[float]]   # 95% half-width per parameter and channel (inf: none)
    determined: dict[str, list[bool]]   # half-width below ``max_relative`` of the value
    effective_samples: int              # independent units behind the spread
    method: str = "curvature"           # "curvature" (laplace_halfwidths) or "robust"
    statistical: dict[str, list[float]] | None = None  # robust: the sandwich part
    systematic: dict[str, list[float]] | None = None   # robust: the between-part part
    splits: dict[str, list[float]] | None = None       # robust: each comparison's (9,)


def laplace_halfwidths(fit: WaterFit, ranges: Tensor, observed: Tensor, ids: Tensor,
                       groups: int, max_relative: float = DETERMINED_MAX_RELATIVE
                       ) -> WaterUncertainty:
    """95% intervals of the fitted water from the curvature of the profile loss (Laplace).

    The loss of :func:`projected_loss` is already minimised over every clean colour, so its
    Hessian in the 9 water parameters is that of the profile likelihood: flat directions (water
    traded against brighter surfaces) give wide intervals. Residuals are treated as Gaussian
    with the fit's own variance and one sample per surface voxel and channel. This sees only
    the noise of the pixels: fits on a NeRF's own surfaces are off by far more than these
    intervals (biased geometry: :func:`robust_halfwidths` holds that error); it stays as the
    cheap curvature the training's refit acceptance was tuned on.

    Args:
        fit: the result of :func:`fit_water` on the same data.
        ranges, observed, ids, groups: the data of that fit.
        max_relative: relative half-width above which a parameter counts as undetermined.

    Returns:
        half-widths and flags per parameter (``sigma_attn``, ``sigma_bs``, ``c_med``) and channel.
    """
    theta = water_vector(fit)
    ranges, observed = ranges.double(), observed.double()
    hessian = profile_hessian(theta, ranges, observed, ids, groups, fit.weights, fit.unshared)
    samples = max(1, 3 * groups)
    # information of the mean-squared loss: n / (2 sigma^2) * H, with sigma^2 = the loss; as a
    # sandwich H^-1 M H^-1 that is M = 2 sigma^2 / n * H
    meat = 2.0 * max(fit.loss, 1e-12) / samples * hessian
    half = (1.96 * sandwich_variances(hessian, meat, isolate_flat=False).sqrt()).tolist()
    return _uncertainty(fit, half, max_relative, samples, "curvature")


def robust_halfwidths(fit: WaterFit, ranges: Tensor, observed: Tensor, ids: Tensor,
                      groups: int, max_relative: float = DETERMINED_MAX_RELATIVE,
                      colour_max: float = 1.5,
                      dark: tuple[Tensor, Tensor] | None = None, steps: int = 100,
                      min_groups: int = 20, range_error: float = 0.0,
                      min_relative: float = 0.0,
                      regrouped: Sequence[tuple[Tensor, Tensor, Tensor, int]] = (),
                      open_water_beyond: float | None = None,
                      unseen_veiling: bool = False) -> WaterUncertainty:
    """95% intervals of the fitted water that hold model error: a cluster-robust statistical
    part and a systematic part from how much parts of the data disagree.

    Statistical part: the fit is an M-estimator over surface-voxel groups (the clean colours
    are profiled out), ``theta - theta_true ~ -H^-1 sum_g s_g`` with ``s_g`` a group's score
    (:func:`group_scores`), so ``cov = H^-1 (G / (G - 1) sum_g s_g s_g^T) H^-1``
    (:func:`cluster_variances`). It holds whatever the pixels of one voxel share (its depth off
    by some amount, texture, a floater in front) with no noise model and no guess of a sample
    count; with independent pixel noise it is the usual covariance.

    Systematic part: on a NeRF's own surfaces the fits are biased by errors common to many
    voxels -- far surfaces placed short, which pixels count as opaque, misplaced surfaces taken
    for open water -- and there the truth fits the data markedly worse than the fit: no spread
    within the data sees that. What the data do show is that parts those errors affect
    differently disagree. The water is refitted (warm start, ``steps`` iterations, no dark
    bound: the bound is the same for every part and would pin them all alike) on the near and
    the far half of the voxels by range and on the two sides of the scene
    (:func:`data_splits`); without the open-water pixels; and, when the fit used the dark-pixel
    bound, without it (the bound is a heuristic, not data); with ``range_error``, on ranges
    given that much more relative error (log-normal per pixel, fixed seed). Error in the ranges
    biases the fit (the attenuation up: on the simulator's exact ranges of the survey demo
    +2 to +5%, with 5% error +18 to +39%), and adding as much again moves it by about as much as
    the error already there did (the first step of SIMEX, Cook and Stefanski 1994): that move
    is taken as a between-part variance ``d^2``. With ``regrouped``, the same pixels grouped at
    other voxel sizes are refitted too, and the largest move is another ``d^2``: which pixels
    count as one surface is a modelling choice, and where surfaces are placed inconsistently
    between views (no open water, surfaces at a narrow spread of ranges) the answer depends on
    it. Each comparison gives a
    between-part variance by the method of moments (as in a random-effects meta-analysis):
    ``tau^2 = max(0, d^2 - var_a - var_b) / 2`` for two disjoint halves differing by ``d``,
    ``max(0, d^2 - (var_part - var_whole))`` for a part against the whole, ``d^2`` for the
    bound. With open water, how far the fit's ``c_med`` lies from the open-water pixels' mean
    colour is one more ``d^2`` (surfaces placed at the wrong range pull it off the water's own
    colour). With ``open_water_beyond``, the open-water pixels may instead be surfaces at that
    range or farther (:func:`surface_behind_open_water`): the fit is redone on their colour
    less what such a surface would add, as bright as the scene's bright surfaces or black, and
    the larger move is one more ``d^2``. With ``unseen_veiling`` and no open-water pixels, the
    veiling light the farthest surfaces do not yet show is one more
    (:func:`veiling_beyond_surfaces`), with the attenuation's move from refits with ``c_med``
    held at either end of that slide (:func:`veiling_slide`). The interval is a prediction interval,
    ``1.96 sqrt(var + max tau^2)``: the fit's error is taken to be one more draw of the error
    that makes parts of the data disagree. A fit made with the incidental term
    (``fit.unshared``) is refitted with it: the parts with the fit's own variances, the other
    groupings with theirs estimated anew; the scores and Hessian include it.
    With independent noise ``tau^2`` is an estimate of zero and the coverage stays near 95%
    (97% measured); on fits on trained models' own surfaces it goes from 61-72% (curvature)
    to 87-90% (``benchmarks/results/water_intervals.md``; 86% around the trained values of the
    24 models of ``water_intervals_s44.md``). An error every part shares alike
    (a smooth depth distortion over the whole scene, a wrong scale) is out of its reach, as
    of any measure taken from the same images.

    A direction the data do not curve gives an infinite half-width in every parameter it
    touches; a parameter whose half-width exceeds ``max_relative`` of its value is flagged as
    not determined. Costs up to 11 warm-started refits and their Hessians (1-7 s for 65k rays
    on one CPU thread).

    Args:
        fit: the result of :func:`fit_water` on the same data.
        ranges, observed, ids, groups: the data of that fit.
        max_relative: relative half-width above which a parameter counts as undetermined.
        colour_max, dark: as given to :func:`fit_water` for ``fit``.
        steps: most L-BFGS iterations of each refit.
        min_groups: a part with fewer voxel groups is not refitted (its comparison is left out).
        range_error: relative error of the ranges (a NeRF's depth: 3-5% robust spread against
            the truth on the demo); 0 leaves the comparison out (exact ranges).
        min_relative: least half-width, as a share of the value. Thousands of open-water pixels
            give ``c_med`` a statistical half-width of 0.01%, far below what the image values
            themselves are known to (black level, linearisation, the colour gain that relates
            them to another measurement: of the order of 1%).
        regrouped: ``(ranges, observed, ids, groups)`` of the same rays grouped at other voxel
            sizes (:func:`surface_data`); empty leaves the comparison out.
        open_water_beyond: where the open-water pixels may be a far surface (they look below
            the horizon: ``SurfaceData.open_water_below_horizon``), the least range of that
            surface (:func:`far_surface_range`); None leaves the comparison out.
        unseen_veiling: without open-water pixels, allow for the veiling light beyond the
            surfaces (:func:`veiling_beyond_surfaces`); False leaves the comparison out.

    Returns:
        half-widths and flags per parameter and channel; ``statistical`` and ``systematic``
        half-widths (1.96 sqrt(var), 1.96 sqrt(max tau^2)) and ``splits``, each comparison's
        systematic half-widths (9,).

    Example::

        fit = fit_water(z, rgb, ids, groups, start, dark=dark)
        spread = robust_halfwidths(fit, z, rgb, ids, groups, dark=dark)
        low = [v - h for v, h in zip(fit.sigma_attn, spread.halfwidth["sigma_attn"])]
    """
    ranges, observed = ranges.double(), observed.double()
    theta = water_vector(fit)
    statistical = cluster_variances(theta, ranges, observed, ids, groups, fit.weights,
                                    fit.unshared)
    start = water_start(fit)
    balance = fit.weights is not None
    unshared = fit.unshared     # the refits add the fit's incidental_term back as it did

    def refit(keep: Tensor) -> tuple[Tensor, Tensor] | None:
        part_ids, part_groups = renumbered_groups(ids[keep])
        if int(torch.isfinite(ranges[keep]).sum()) == 0 or part_groups < min_groups:
            return None
        part_fit = fit_water(ranges[keep], observed[keep], part_ids, part_groups, start, steps,
                             colour_max, balance_brightness=balance,
                             unshared=None if unshared is None else unshared[keep])
        return water_vector(part_fit), cluster_variances(
            water_vector(part_fit), ranges[keep], observed[keep], part_ids, part_groups,
            part_fit.weights, part_fit.unshared)

    everything = torch.ones_like(ranges, dtype=torch.bool)
    whole = (theta, statistical) if dark is None else refit(everything)
    between: dict[str, Tensor] = {}
    for name, keeps in data_splits(ranges, ids, groups).items():
        a, b = (refit(keeps[0]), refit(keeps[1])) if len(keeps) == 2 \
            else (refit(keeps[0]), whole)
        if a is None or b is None:
            continue
        if len(keeps) == 2:
            tau2 = ((a[0] - b[0]) ** 2 - a[1] - b[1]) / 2
        else:
            tau2 = (a[0] - b[0]) ** 2 - (a[1] - b[1]).clamp_min(0.0)
        between[name] = _finite_variance(tau2)
    water = ~torch.isfinite(ranges)
    if bool(water.any()):
        # what the surfaces pull c_med away from the open water's own colour
        pull = torch.zeros_like(theta)
        pull[6:9] = (theta[6:9] - observed[water].mean(0)) ** 2
        between["open_water_pull"] = pull
    if dark is not None and whole is not None:
        between["dark_bound"] = (whole[0] - theta) ** 2
    if unseen_veiling and not bool(water.any()) and bool(torch.isfinite(ranges).any()):
        moves = veiling_beyond_surfaces(theta, ranges)
        if whole is not None:
            # the attenuation slides with the veiling light: refitted at each end of its move
            slid = [water_vector(fit_water(ranges, observed, ids, groups, {
                "sigma_attn": start["sigma_attn"], "sigma_bs": end[3:6].tolist(),
                "c_med": end[6:9].clamp(1e-6, colour_max).tolist()}, steps, colour_max,
                balance_brightness=balance, unshared=unshared, fixed=("c_med",))) - whole[0]
                    for end in veiling_slide(theta, ranges) if bool(torch.isfinite(end).all())]
            if slid:
                moves = torch.maximum(moves, _finite_variance(torch.stack(slid).pow(2).amax(0)))
        between["veiling_beyond_surfaces"] = moves
    if open_water_beyond is not None and bool(water.any()) and whole is not None:
        moves = [water_vector(fit_water(ranges, shifted, ids, groups, start, steps, colour_max,
                                        balance_brightness=balance, unshared=unshared))
                 - whole[0]
                 for shifted in surface_behind_open_water(theta, ranges, observed,
                                                          open_water_beyond)]
        between["open_water_surface"] = _finite_variance(torch.stack(moves).pow(2).amax(0))
    if range_error > 0 and whole is not None:
        noise = torch.randn(ranges.shape, generator=torch.Generator().manual_seed(0),
                            dtype=ranges.dtype)
        noisier = torch.where(torch.isfinite(ranges), ranges * torch.exp(range_error * noise),
                              ranges)
        moved = fit_water(noisier, observed, ids, groups, start, steps, colour_max,
                          balance_brightness=balance, unshared=unshared)
        between["range_error"] = _finite_variance((water_vector(moved) - whole[0]) ** 2)
    moves = [] if whole is None else [
        water_vector(fit_water(*other, start, steps, colour_max, balance_brightness=balance,
                               noise_term=unshared is not None)) - whole[0]
        for other in regrouped if other[3] >= min_groups]
    if moves:
        between["grouping"] = _finite_variance(torch.stack(moves).pow(2).amax(0))
    tau2 = torch.stack(list(between.values())).amax(0) if between \
        else torch.zeros_like(statistical)
    half = [max(h, min_relative * abs(v)) for h, v in
            zip((1.96 * (statistical + tau2).sqrt()).tolist(), theta.tolist())]
    result = _uncertainty(fit, half, max_relative, _used_groups(ids, groups), "robust")
    result.statistical = _by_name((1.96 * statistical.sqrt()).tolist())
    result.systematic = _by_name((1.96 * tau2.sqrt()).tolist())
    result.splits = {name: (1.96 * value.sqrt()).tolist() for name, value in between.items()}
    return result


def veiling_beyond_surfaces(theta: Tensor, ranges: Tensor, quantile: float = 0.9) -> Tensor:
    """Squared moves (9,) of ``sigma_bs`` and ``c_med`` allowed for where no open water is in
    view (to the ends of :func:`veiling_slide`): the veiling light is then seen only through
    the surfaces' backscatter,
    ``c_med (1 - exp(-sigma_bs z))``, up to the farthest surface, and the part those surfaces
    do not yet show, ``c_med exp(-sigma_bs z_far)``, rests on the curvature of that curve
    over the ranges in view, which a NeRF's depth and colour errors bend: the fit slides along
    the curve, and the data splits slide with it (docs/water.md). That part is taken as the
    move of ``c_med``; ``sigma_bs`` moves along the curve that keeps the backscatter at the
    median range: up to where the veiling light is no more than the farthest surfaces'
    backscatter, down to where it is that much more. Ranges all alike bound nothing: the move
    of ``sigma_bs`` is then infinite.

    Args:
        theta: (9,) the water (``sigma_attn``, ``sigma_bs``, ``c_med``).
        ranges: (N,) ranges (inf: open water, left out).
        quantile: which range counts as the farthest surfaces' (:func:`far_surface_range`).

    Returns:
        (9,) squared moves: zero for ``sigma_attn`` (:func:`robust_halfwidths` refits it at
        each end), inf where unbounded.

    Example::

        moves = veiling_beyond_surfaces(water_vector(fit), z)
        halfwidth_c_med = 1.96 * moves[6:9].sqrt()   # the allowance alone
    """
    theta = theta.double()
    moves = torch.stack(veiling_slide(theta, ranges, quantile)).sub(theta).pow(2).amax(0)
    moves[0:3] = 0.0
    return torch.nan_to_num(moves, nan=math.inf, posinf=math.inf)


def veiling_slide(theta: Tensor, ranges: Tensor, quantile: float = 0.9
                  ) -> tuple[Tensor, Tensor]:
    """The two ends (9,) of the water's slide along the backscatter the surfaces show when
    no open water is in view (:func:`veiling_beyond_surfaces`): the veiling light down by the
    part ``c_med exp(-sigma_bs z_far)`` the farthest surfaces do not show, with the
    ``sigma_bs`` that keeps the backscatter at the median range; and up by as much, with the
    lower ``sigma_bs``. ``sigma_attn`` as in ``theta``; non-finite where the ranges bound
    nothing (all alike)."""
    theta = theta.double()
    far = far_surface_range(ranges, quantile)
    middle = float(ranges[torch.isfinite(ranges)].double().median())
    bs, c_med = theta[3:6].clamp_min(0.0), theta[6:9]
    unseen = c_med * torch.exp(-bs * far)
    # backscatter at the median range over the veiling light, at the two ends of the move;
    # the first as sigma_bs -> 0 tends to middle / far
    tiny = bs * far < 1e-9
    saturated = torch.where(tiny, torch.full_like(bs, middle / far),
                            torch.expm1(-bs * middle) / torch.expm1(-bs * far).where(~tiny, -1.0))
    diluted = -torch.expm1(-bs * middle) / (1.0 + torch.exp(-bs * far))
    high = -torch.log1p(-saturated) / middle
    low = -torch.log1p(-diluted) / middle
    return (torch.cat([theta[0:3], high, c_med - unseen]),
            torch.cat([theta[0:3], low, c_med + unseen]))


def far_surface_range(ranges: Tensor, quantile: float = 0.9) -> float:
    """The range beyond which the model places few surfaces: ``quantile`` of the finite
    ``ranges`` (N,). Open water below the horizon lies behind the surfaces the views show, so
    a seabed behind it is at least about this far (on simulated orbits the 0.9 quantile was
    3.7-4.2 m, the seabed taken for open water 6-11 m)."""
    finite = ranges[torch.isfinite(ranges)]
    return float(torch.quantile(finite.double(), quantile)) if finite.numel() else math.inf


def surface_behind_open_water(theta: Tensor, ranges: Tensor, observed: Tensor, beyond: float,
                              bright_quantile: float = 0.9) -> list[Tensor]:
    """The open-water pixels' colours (range inf) as they would be without a surface at range
    ``beyond`` behind them: two copies of ``observed`` (N, 3), one for a surface as bright as
    the scene's bright surfaces and one for a black one.

    A surface of clean colour ``J`` at range ``z`` shows ``J exp(-sigma_attn z) + c_med (1 -
    exp(-sigma_bs z))``, which differs from the veiling light by ``J exp(-sigma_attn z) - c_med
    exp(-sigma_bs z)``; the difference shrinks with range, so ``beyond`` (the least range such
    a surface could be at) bounds it. ``J`` of the bright surfaces: the ``bright_quantile`` of
    the clean colours the water ``theta`` implies for the nearer half of the surface pixels
    (farther ones amplify the range error).

    Args:
        theta: (9,) the water (``sigma_attn``, ``sigma_bs``, ``c_med``).
        ranges: (N,) ranges, inf for open water; observed: (N, 3) pixel colours.
        beyond: least range of a surface behind the open water.
        bright_quantile: which clean colour counts as bright.

    Returns:
        [bright, black]: (N, 3) each, ``observed`` with the open water's colours changed.

    Example::

        for shifted in surface_behind_open_water(theta, z, rgb, far_surface_range(z)):
            moved = fit_water(z, shifted, ids, groups, start)
    """
    theta = theta.double()
    attn, bs, c_med = theta[0:3], theta[3:6], theta[6:9]
    finite = torch.isfinite(ranges)
    near = finite & (ranges <= ranges[finite].median())
    z = ranges[near, None].double()
    clean = (observed[near].double() - c_med * (1 - torch.exp(-bs * z))) * torch.exp(attn * z)
    bright = torch.quantile(clean, bright_quantile, dim=0).clamp_min(0.0)
    veil_left = c_med * torch.exp(-bs * beyond)
    shifts = [bright * torch.exp(-attn * beyond) - veil_left, -veil_left]
    out = []
    for shift in shifts:
        shifted = observed.double().clone()
        shifted[~finite] = (shifted[~finite] - shift).clamp_min(1e-6)
        out.append(shifted)
    return out


def interval_determined(trained: dict, surface_fit: WaterFit, halfwidth: dict[str, list[float]],
                        max_relative: float = DETERMINED_MAX_RELATIVE,
                        ambiguity: dict[str, list[float]] | None = None,
                        max_ambiguity: float = 0.05) -> dict[str, list[bool]]:
    """Whether the views determine each trained water value, judged on the interval around it
    (``water_interval.interval_halfwidth``): determined where that half-width is finite and at most
    ``max_relative`` of the value (judged on the fit's half-width alone, values up to 81% off
    the truth on the water benchmark were flagged as determined), and where the part of it that
    comes from alternatives the images cannot tell apart (``ambiguity``,
    :func:`ambiguity_halfwidths`) is at most ``max_ambiguity`` of the value. The second test
    is what the width cannot be: a 20% interval that holds the truth is honest, but where it
    is 20% because no open water shows the veiling light, no better geometry would narrow it,
    and the value is not known to the 5% the water benchmark asks of a determined one
    (orbits' red attenuation, 8-12% off with 16-22% intervals: ``determined.md``).

    Args:
        trained: ``{"sigma_attn": [3], "sigma_bs": [3], "c_med": [3]}`` trained values.
        surface_fit: the fit on the model's surfaces the half-widths belong to.
        halfwidth: 95% half-widths per name (``WaterUncertainty.halfwidth``).
        max_relative: largest widened half-width, as a share of the value, still determined.
        ambiguity: per name, the half-widths' part from what the images cannot tell apart;
            None judges on the half-width alone.
        max_ambiguity: largest such part, as a share of the value, still determined.

    Returns:
        per name, per channel, True where determined.

    Example::

        flags = interval_determined(model.water_parameters(), fit, spread.halfwidth,
                                    ambiguity=ambiguity_halfwidths(spread))
    """
    flags = {}
    for name in NAMES:
        unsure = ambiguity[name] if ambiguity is not None else [0.0] * 3
        flags[name] = [bool(math.isfinite(h) and interval_halfwidth(float(c), g, h)
                            <= max_relative * abs(float(c))
                            and a <= max_ambiguity * abs(float(c)))
                       for c, g, h, a in zip(trained[name], getattr(surface_fit, name),
                                             halfwidth[name], unsure)]
    return flags


def ambiguity_halfwidths(spread: WaterUncertainty) -> dict[str, list[float]]:
    """The part of each robust 95% half-width that comes from the comparisons in
    :data:`AMBIGUOUS_SPLITS` (the largest of those present; 0 where none is), per name and
    channel, in the units of the half-widths.

    Example::

        spread = robust_halfwidths(fit, z, rgb, ids, groups, unseen_veiling=True)
        ambiguity_halfwidths(spread)["sigma_attn"]    # [r, g, b]
    """
    parts = [spread.splits[name] for name in AMBIGUOUS_SPLITS
             if spread.splits and name in spread.splits]
    largest = [max((part[i] for part in parts), default=0.0) for i in range(3 * len(NAMES))]
    return _by_name(largest)


def data_splits(ranges: Tensor, ids: Tensor, groups: int) -> dict[str, tuple[Tensor, ...]]:
    """Masks (N,) of the parts of the data :func:`robust_halfwidths` compares.

    ``range``: voxels nearer / farther than the median voxel range; ``side``: the lower /
    upper half of voxel ids (one side of the scene along the first axis); open-water pixels
    (range inf) go with both halves. ``open_water`` (only with such pixels): one mask, the
    data without them, compared with the whole.
    """
    finite = torch.isfinite(ranges)
    count = torch.bincount(ids[finite], minlength=groups)
    mean = torch.zeros(groups, dtype=ranges.dtype).index_add_(0, ids[finite], ranges[finite]) \
        / count.clamp_min(1)
    median = mean[count > 0].median() if bool((count > 0).any()) else mean.new_tensor(0.0)
    water = ~finite
    near, low_side = mean[ids] <= median, ids < groups // 2
    splits: dict[str, tuple[Tensor, ...]] = {
        "range": (water | (finite & near), water | (finite & ~near)),
        "side": (water | (finite & low_side), water | (finite & ~low_side))}
    if bool(water.any()):
        splits["open_water"] = (finite,)
    return splits


def profile_hessian(theta: Tensor, ranges: Tensor, observed: Tensor, ids: Tensor,
                    groups: int, weights: Tensor | None = None,
                    unshared: Tensor | None = None) -> Tensor:
    """(9, 9) Hessian of :func:`projected_loss` (with the group ``weights`` and the
    incidental term's ``unshared`` variances, if given) at the water ``theta`` (symmetrised)."""
    def loss(params: Tensor) -> Tensor:
        return projected_loss(params[0:3], params[3:6], params[6:9], ranges, observed, ids,
                              groups, weights, unshared)

    with torch.enable_grad():
        hessian = torch.autograd.functional.hessian(loss, theta)
    return 0.5 * (hessian + hessian.T)


def cluster_variances(theta: Tensor, ranges: Tensor, observed: Tensor, ids: Tensor,
                      groups: int, weights: Tensor | None = None,
                      unshared: Tensor | None = None) -> Tensor:
    """(9,) variances of the water fitted at ``theta``: the sandwich ``H^-1 M H^-1`` with the
    meat summed over clusters (see :func:`robust_halfwidths`): the voxel groups, and each
    open-water pixel (range inf) on its own -- rays of many views into open water share no
    surface, and as one cluster their score would be pinned to minus the others' by the fit's
    own optimality; inf where not curved. ``weights``, ``unshared``: the fit's group weights
    and incidental-term variances, if any."""
    hessian = profile_hessian(theta, ranges, observed, ids, groups, weights, unshared)
    water = ~torch.isfinite(ranges)
    clusters = ids.clone()
    clusters[water] = groups + torch.arange(int(water.sum()), device=ids.device)
    clusters, count = renumbered_groups(clusters)
    scores = group_scores(theta, ranges, observed, ids, groups, clusters, count, weights,
                          unshared)
    meat = scores.T @ scores * (count / max(count - 1, 1))
    return sandwich_variances(hessian, meat)


def group_scores(theta: Tensor, ranges: Tensor, observed: Tensor, ids: Tensor,
                 groups: int, clusters: Tensor | None = None, count: int = 0,
                 weights: Tensor | None = None, unshared: Tensor | None = None) -> Tensor:
    """Each group's share of the gradient of :func:`projected_loss` at the water ``theta``.

    With the clean colours at their optimum for ``theta``, the profile's gradient is the
    partial one at fixed colours (envelope theorem), a sum over pixels that splits by group.

    Args:
        theta: (9,) ``sigma_attn``, ``sigma_bs``, ``c_med`` (3 each).
        ranges, observed, ids, groups: as for :func:`projected_loss`.
        clusters, count: (N,) other units to sum the scores over, and their number
            (default: the groups).
        weights: (groups, 3) group weights of the loss, if any.
        unshared: (N, 3) variances of the loss's incidental term, if any (its gradient in the
            attenuation splits by group too).

    Returns:
        (groups or count, 9) scores; they sum to the gradient (zero at an interior minimum).
    """
    attn, bs, c_med = theta[0:3], theta[3:6], theta[6:9]
    residual, clean, z = projected_residuals(attn, bs, c_med, ranges.double(),
                                              observed.double(), ids, groups, weights)
    z = z[:, None]
    bs_decay = torch.exp(-bs * z)
    # d residual / d theta per pixel and channel (a channel's water touches that channel only)
    d_attn = clean[ids] * z * torch.exp(-attn * z)
    d_bs = -c_med * z * bs_decay
    d_c = -(1.0 - bs_decay)
    scale = 2.0 / residual.numel()
    if weights is not None:     # the residuals are weighted: so is their slope
        residual = residual * weights.sqrt()[ids]
    per_pixel = torch.cat([residual * d_attn, residual * d_bs, residual * d_c], dim=1) * scale
    if unshared is not None:
        per_pixel[:, 0:3] += incidental_gradient(attn, ranges, unshared, ids, groups,
                                                 weights) / residual.numel()
    if clusters is None:
        clusters, count = ids, groups
    return residual.new_zeros(count, 9).index_add_(0, clusters, per_pixel)


def sandwich_variances(hessian: Tensor, meat: Tensor, isolate_flat: bool = True) -> Tensor:
    """diag(H^-1 M H^-1) (9,); infinite for parameters along a direction H does not curve
    (eigenvalue below 1e-12 of the largest), or for all of them when one direction is flat
    and not ``isolate_flat`` (what :func:`laplace_halfwidths` has always done)."""
    eigenvalues, vectors = torch.linalg.eigh(hessian)
    floor = float(eigenvalues.abs().max()) * 1e-12 + 1e-300
    flat = eigenvalues <= floor
    inverse = torch.where(flat, torch.zeros_like(eigenvalues), 1.0 / eigenvalues.clamp_min(floor))
    half_inverse = vectors * inverse                     # V diag(1/lambda)
    variance = ((half_inverse @ (vectors.T @ meat @ vectors)) * half_inverse).sum(-1)
    touched = ((vectors ** 2) * flat).sum(-1) > 1e-12 if isolate_flat \
        else flat.any().expand(variance.shape)
    return torch.where(touched | ~torch.isfinite(variance),
                       torch.full_like(variance, float("inf")), variance.clamp_min(0.0))


def _finite_variance(value: Tensor) -> Tensor:
    return torch.nan_to_num(value, nan=0.0, posinf=0.0).clamp_min(0.0)


def _by_name(values: list[float]) -> dict[str, list[float]]:
    return {n: values[3 * i:3 * i + 3] for i, n in enumerate(NAMES)}


def _used_groups(ids: Tensor, groups: int) -> int:
    return int((torch.bincount(ids, minlength=groups) > 0).sum())


def _uncertainty(fit: WaterFit, half: list[float], max_relative: float, samples: int,
                 method: str) -> WaterUncertainty:
    values = fit.sigma_attn + fit.sigma_bs + fit.c_med
    determined = [bool(h <= max_relative * abs(v)) for h, v in zip(half, values)]
    return WaterUncertainty(_by_name(half), _by_name(determined), samples, method)
