"""The water fitted to images of surfaces at known ranges, by variable projection.

For pixels whose surface lies at range ``z`` (the model's own depth during training, or the
simulator's true depth in the diagnostic benchmark), the SeaThru image formation is

    I = J exp(-sigma_attn z) + c_med (1 - exp(-sigma_bs z)),

per channel. Pixels are grouped by the surface point they see (:func:`correspondence_rays`:
one point's pixel in every view that sees it) or by the voxel their surface point falls in,
with one unknown clean colour ``J`` per group and channel; for given water the best non-negative ``J`` of each
voxel has a closed form, so the fit runs over the 9 water parameters alone. The same surface
seen from several ranges is what pins the attenuation down (as in Sea-thru's regression on
range); surfaces seen at one range only leave ``J`` and the water traded against each other.

How well the images determine the water: :func:`laplace_halfwidths` (the curvature of the
loss: pixel noise only) and :func:`robust_halfwidths` (cluster-robust over voxels plus the
disagreement between parts of the data, which holds most of a NeRF geometry's error).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING
from statistics import NormalDist

import torch
import torch.nn.functional as F
from torch import Tensor

from seathru.nerf.water_interval import interval_halfwidth

if TYPE_CHECKING:
    from seathru.nerf.rays import RayBatch, RayDataset


@dataclass
class WaterFit:
    sigma_attn: list[float]     # per channel, 1 / (unit of z)
    sigma_bs: list[float]
    c_med: list[float]
    loss: float                 # mean squared (weighted) residual at the fit
    pixels: int
    groups: int
    weights: Tensor | None = None  # (groups, 3) group weights used (brightness_weights)


@dataclass
class SurfaceData:
    """Pixels of surfaces seen over a spread of ranges, grouped by voxel (float64, CPU)."""

    ranges: Tensor      # (N,)
    observed: Tensor    # (N, 3)
    ids: Tensor         # (N,) voxel group
    groups: int
    dark: tuple[Tensor, Tensor] | None = None  # (K,) range bins, (K, 3) darkest pixel values
    # the open-water pixels (range inf) look below the horizon (less than a fifth of the
    # flagged ones above): they may be far seabed
    open_water_below_horizon: bool = False


def surface_data(origins: Tensor, directions: Tensor, rgb: Tensor, depth: Tensor,
                 opacity: Tensor, voxel: float, min_opacity: float = 0.9,
                 min_pixels: int = 1000, open_water_opacity: float = 0.0,
                 open_water: Tensor | None = None, below_horizon: Tensor | None = None,
                 min_above_horizon: float = 0.2, point_ids: Tensor | None = None
                 ) -> SurfaceData | str:
    """The pixels a water fit can use, from rays rendered by the model.

    Args:
        origins, directions: (R, 3) rays; rgb: (R, 3) their pixels.
        depth: (R,) the model's median depth; opacity: (R,) its object opacity.
        voxel: side of the grouping voxels (scene units).
        min_opacity: rays below are fog, open water or unconverged, not surfaces.
        min_pixels: fewest usable pixels.
        open_water_opacity: rays whose opacity is below this meet no surface: their pixel is
            the veiling light ``c_med`` itself (range inf, one group of their own), which pins
            ``c_med`` and with it the backscatter. 0 leaves them out (use it only once the
            geometry has converged: an unfinished surface is transparent too).
        open_water: (R,) bool or None: the rays whose pixel the photographs show as open water
            (``seathru.radiometry.open_water``). Where given, these are the open-water rays
            whatever the model's opacity (a half-trained model fills open water with floaters
            and leaves dark holes elsewhere, and either pulls ``c_med`` away: on the survey demo
            0.4% of such rays, wrongly taken as open water, put ``c_med`` 27-37% low), and they
            are never surfaces; they are used whenever ``open_water_opacity`` is above 0.

            Of these, only pixels of the open water's typical colour are used
            (:func:`typical_open_water`).
        below_horizon: (R,) bool or None: the rays that look below the horizon
            (``seathru.geometry.upright``). Open water there may be a far seabed whose colour
            still holds some of its direct light (on simulated orbits, all of the flagged
            "open water" was seabed 6-11 m away, 10-23% off the veiling light). Where at least
            ``min_above_horizon`` of the open-water pixels look above the horizon, only those
            are used; otherwise all are, and the data say so
            (``SurfaceData.open_water_below_horizon``: the intervals then allow for a surface
            behind them, :func:`robust_halfwidths`).
        min_above_horizon: see ``below_horizon``.
        point_ids: (R,) long or None: rays with the same id look at the same surface point
            (:func:`correspondence_rays`); given, they are grouped by it instead of by voxel
            (``voxel`` is then unused), and rays with id -1 are no surface.

    Returns:
        the data, or a sentence saying why there is not enough of it.
    """
    keep = (opacity > min_opacity) & torch.isfinite(depth)
    if open_water is not None:
        keep &= ~open_water
    if point_ids is not None:
        keep &= point_ids.to(keep.device) >= 0
    if int(keep.sum()) < min_pixels:
        return f"only {int(keep.sum())} rays reach opaque surfaces"
    points = (origins[keep] + directions[keep] * depth[keep, None]).double().cpu()
    ranges, observed = depth[keep].double().cpu(), rgb[keep].double().cpu()
    kept_ids = None if point_ids is None else point_ids.to(keep.device)[keep].cpu()

    def grouped(which: Tensor | None = None) -> tuple[Tensor, int]:
        if kept_ids is None:
            return voxel_groups(points if which is None else points[which], voxel)
        _, ids = torch.unique(kept_ids if which is None else kept_ids[which],
                              return_inverse=True)
        return ids, int(ids.max()) + 1 if ids.numel() else 0

    ids, groups = grouped()
    ranged = ranged_groups(ranges, ids, groups)
    if int(ranged.sum()) < min_pixels:
        return f"only {int(ranged.sum())} surface pixels are seen over a spread of ranges"
    below = False
    if open_water is None:
        water = opacity < open_water_opacity
    elif open_water_opacity > 0:
        flagged = open_water
        if below_horizon is not None and bool(open_water.any()):
            above = open_water & ~below_horizon
            if int(above.sum()) >= min_above_horizon * int(open_water.sum()):
                flagged = above
            else:
                below = True
        water = flagged & typical_open_water(rgb, flagged)
    else:
        water = torch.zeros_like(open_water)
    # With open water in the data, which pins c_med and with it the backscatter, only pixels
    # of surfaces that several views place alike bound the backscatter: a dark pixel given
    # too long a range (a surface the model placed behind its true place) bounds it by the
    # lower backscatter of its true range. On the survey demo (5% of the model's surface
    # depths 30% too long or more) the bound from every pixel held blue backscatter 7-10%
    # below the fit without it; from these pixels, 0-1%. Without open water the bound is all
    # that holds the backscatter, and the tighter bound from every pixel errs the safe way:
    # backscatter left in the restored image rather than too much taken out (on a small
    # orbit, the looser bound made a restored view worse than the render with water).
    dark = dark_pixels(ranges[ranged], observed[ranged]) if bool(water.any()) \
        else dark_pixels(ranges, observed)
    ids, groups = grouped(ranged)
    ranges, observed = ranges[ranged], observed[ranged]
    if bool(water.any()):
        ranges = torch.cat([ranges, torch.full((int(water.sum()),), math.inf,
                                               dtype=ranges.dtype)])
        observed = torch.cat([observed, rgb[water].double().cpu()])
        ids = torch.cat([ids, torch.full((int(water.sum()),), groups, dtype=ids.dtype)])
        groups += 1
    return SurfaceData(ranges, observed, ids, groups, dark,
                       open_water_below_horizon=below and bool(water.any()))


@dataclass
class CorrespondenceRays:
    """Rays rendered for a water fit, grouped by the surface point they look at."""

    rays: "RayBatch"
    depth: Tensor       # (R,) the model's median depth
    opacity: Tensor     # (R,) its object opacity
    point_ids: Tensor   # (R,) long: the point each ray sees; -1 for the anchors' other rays


def correspondence_rays(dataset: "RayDataset", render, anchors: int, budget: int, seed: int,
                        min_opacity: float = 0.9, tolerance: float = 0.02
                        ) -> CorrespondenceRays:
    """Pixels of the same surface points in every training view that sees them.

    Voxel groups of randomly drawn pixels meet by chance: few pixels share a voxel, and those
    that do see neighbouring spots of texture from different views. Here ``anchors`` rays are
    drawn (``dataset.fixed_subset``) and rendered; each that reaches an opaque surface (opacity
    above ``min_opacity``, not flagged open water) gives a surface point at its median depth.
    The pixel that point falls in is taken in every training view (``dataset.rays_through``),
    at most ``budget`` of them (a random subset of the points), and rendered: a view sees the
    point where its own median depth agrees with the point's distance within ``tolerance``
    (relative) and its opacity exceeds ``min_opacity``. On the survey demo's exact images and
    ranges, with the pixels of a refit, the fit's green and blue attenuation erred by +0.6 to
    +5.2% (four draws) against +2.6 to +10.1% with voxel groups of as many pixels
    (``docs/water.md``).

    Args:
        dataset: the training rays (``seathru.nerf.rays.RayDataset``).
        render: ``render(rays) -> {"depth_median": (R,), "opacity": (R,)}``.
        anchors: rays drawn to find surface points; budget: most rays taken through them.
        seed: seeds both draws.
        min_opacity, tolerance: see above.

    Returns:
        the seeing rays (ids = their point) followed by the anchors that found no surface
        (id -1: open water and fog, which the fit may still use as open water).

    Example::

        found = correspondence_rays(trainer.data, trainer.render_batch, 16384, 65536, seed=5)
        data = surface_data(found.rays.origins, found.rays.directions, found.rays.rgb,
                            found.depth, found.opacity, voxel, point_ids=found.point_ids)
    """
    drawn = dataset.fixed_subset(anchors, seed)
    first = render(drawn)
    surface = (first["opacity"] > min_opacity) & torch.isfinite(first["depth_median"])
    if drawn.open_water is not None:
        surface &= ~drawn.open_water
    points = (drawn.origins[surface] + drawn.directions[surface]
              * first["depth_median"][surface, None]).double().cpu().numpy()
    through, owner = dataset.rays_through(points)
    if len(owner) > budget:   # whole points only: keep a random subset of them
        generator = torch.Generator().manual_seed(seed + 1)
        order = torch.randperm(len(points), generator=generator).numpy()
        rank = order.argsort()
        per_point = torch.bincount(torch.from_numpy(owner), minlength=len(points)).numpy()
        taken = per_point[order].cumsum() <= budget
        keep = taken[rank][owner]
        through, owner = through.subset(torch.from_numpy(keep).nonzero()[:, 0].to(
            through.origins.device)), owner[keep]
    second = render(through)
    owner_t = torch.from_numpy(owner).to(through.origins.device)
    point_t = torch.from_numpy(points).to(through.origins.device, through.origins.dtype)
    distance = torch.linalg.norm(point_t[owner_t] - through.origins, dim=-1)
    sees = (second["opacity"] > min_opacity) & (
        (second["depth_median"] - distance).abs() <= tolerance * distance)
    other = drawn.subset((~surface).nonzero()[:, 0])
    rays = _joined(through.subset(sees.nonzero()[:, 0]), other)
    ids = torch.cat([owner_t[sees], torch.full((len(other),), -1, dtype=torch.long,
                                               device=owner_t.device)])
    return CorrespondenceRays(rays, torch.cat([second["depth_median"][sees],
                                               first["depth_median"][~surface]]),
                              torch.cat([second["opacity"][sees], first["opacity"][~surface]]),
                              ids)


def _joined(a: "RayBatch", b: "RayBatch") -> "RayBatch":
    from seathru.nerf.rays import RayBatch

    water = None if a.open_water is None or b.open_water is None else torch.cat(
        [a.open_water, b.open_water])
    return RayBatch(*(torch.cat([getattr(a, k), getattr(b, k)]) for k in
                      ("origins", "directions", "near", "far", "rgb")), water)


DARK_QUANTILE = 0.01


def dark_pixels(ranges: Tensor, observed: Tensor, bins: int = 10,
                quantile: float = DARK_QUANTILE, min_per_bin: int = 50
                ) -> tuple[Tensor, Tensor] | None:
    """Sea-thru's dark-pixel estimate: the darkest pixels at each range bound the backscatter.

    A noise-free pixel is ``J exp(-a z) + B(z)`` with ``J >= 0`` and ``B`` grows with range, so
    the darkest pixels of a range bin are at least the backscatter at the bin's nearest range:
    the ``quantile`` of each channel per bin bounds ``B`` there from above (nearly equal to it
    where some surfaces are black or shadowed). Pixel noise puts the quantile of noisy pixels
    below that; :func:`fit_water` raises the bound by the noise it measures.

    Args:
        ranges: (N,) finite ranges; observed: (N, 3) pixels.
        bins: range bins (equal counts); quantile: the darkness quantile per bin and channel.
        min_per_bin: fewest pixels for a bin to count.

    Returns:
        (K,) nearest range of each bin and (K, 3) its dark values, or None with too few pixels.
    """
    finite = torch.isfinite(ranges)
    ranges, observed = ranges[finite], observed[finite]
    if len(ranges) < bins * min_per_bin:
        return None
    order = torch.argsort(ranges)
    centres, values = [], []
    for part in torch.tensor_split(order, bins):
        centres.append(ranges[part].min())
        values.append(torch.quantile(observed[part], quantile, dim=0))
    return torch.stack(centres), torch.stack(values)


def typical_open_water(rgb: Tensor, flagged: Tensor, spread: float = 3.0,
                       relative: float = 0.02) -> Tensor:
    """(R,) bool: the ``flagged`` pixels whose colour is the open water's own: within ``spread``
    robust standard deviations (1.4826 MAD) of the flagged pixels' median in every channel, or
    within ``relative`` of it where the water is that uniform.

    The photographs' open-water mask takes smooth regions reaching the top of the frame, and
    smooth sand or the hazy far seabed below the horizon join them: on the simulated surveys
    16% of the flagged pixels were surfaces (at 3.5-15 m), darker than the water, and their
    mean put ``c_med`` 1-4% low in G and B while its interval was +-1-2%; without the pixels
    off the median by more than 2% the mean is the truth within 0.1%. Where the veiling light
    changes with direction, the spread is wide and keeps it.

    Args:
        rgb: (R, 3) pixel colours; flagged: (R,) bool, the pixels taken as open water.
        spread, relative: the tolerance (see above).

    Returns:
        (R,) bool, a subset of ``flagged``.

    Example::

        water = open_water & typical_open_water(rgb, open_water)
    """
    if not bool(flagged.any()):
        return flagged.clone()
    colours = rgb[flagged].double()
    median = colours.median(0).values
    mad = (colours - median).abs().median(0).values * 1.4826
    tolerance = torch.maximum(spread * mad, relative * median.abs())
    near = ((rgb.double() - median).abs() <= tolerance).all(-1)
    return flagged & near


def voxel_groups(points: Tensor, voxel: float) -> tuple[Tensor, int]:
    """Group ids of points by the voxel of side ``voxel`` they fall in.

    Args:
        points: (N, 3) surface points.
        voxel: voxel side, in the units of ``points``.

    Returns:
        ids (N,) long in [0, groups) and the number of groups.
    """
    _, ids = torch.unique(torch.floor(points / voxel).long(), dim=0, return_inverse=True)
    return ids, int(ids.max()) + 1 if ids.numel() else 0


def ranged_groups(ranges: Tensor, ids: Tensor, groups: int, min_pixels: int = 3,
                  min_spread: float = 0.2) -> Tensor:
    """Which pixels belong to a group seen over a spread of ranges.

    Only a surface seen from different distances tells attenuation from a darker surface;
    groups seen at one range leave the clean colour free to absorb any water, and a fit
    dominated by them drifts to degenerate water (no attenuation).

    Args:
        ranges: (N,) ranges; ids: (N,) group ids; groups: their number.
        min_pixels: fewest pixels a group needs.
        min_spread: least (max - min) / mean range within a group.

    Returns:
        (N,) bool, True for pixels of qualifying groups.
    """
    count = torch.bincount(ids, minlength=groups)
    low = torch.full((groups,), float("inf"), dtype=ranges.dtype).scatter_reduce(
        0, ids, ranges, "amin")
    high = torch.zeros(groups, dtype=ranges.dtype).scatter_reduce(0, ids, ranges, "amax")
    mean = torch.zeros(groups, dtype=ranges.dtype).index_add_(0, ids, ranges) / count.clamp_min(1)
    good = (count >= min_pixels) & ((high - low) >= min_spread * mean)
    return good[ids]


def projected_loss(sigma_attn: Tensor, sigma_bs: Tensor, c_med: Tensor, ranges: Tensor,
                   observed: Tensor, ids: Tensor, groups: int,
                   weights: Tensor | None = None) -> Tensor:
    """Mean squared residual of the image formation with the best clean colour per group.

    Args:
        sigma_attn, sigma_bs, c_med: (3,) water parameters.
        ranges: (N,) range of each pixel's surface.
        observed: (N, 3) pixel values.
        ids: (N,) group of each pixel (``voxel_groups``); groups: their number.
        weights: optional (groups, 3) weight of each group's squared residuals per channel
            (:func:`brightness_weights`); a group's clean colour does not depend on it.

    Returns:
        the scalar loss (differentiable in the water parameters).
    """
    return (_projected_residuals(sigma_attn, sigma_bs, c_med, ranges, observed, ids, groups,
                                 weights)[0] ** 2).mean()


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


def _projected_residuals(sigma_attn: Tensor, sigma_bs: Tensor, c_med: Tensor, ranges: Tensor,
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
        (3,) float64, to add to the dark values of :func:`dark_pixels`.
    """
    theta = _theta(fit).to(ranges.device).split(3)
    residuals = _projected_residuals(*theta, ranges.double(), observed.double(), ids, groups)[0]
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
              balance_brightness: bool = True, brightness_floor: float = 1.0) -> WaterFit:
    """Fit the 9 water parameters by L-BFGS on :func:`projected_loss`, in float64.

    Nine smooth parameters and a cheap exact loss: a quasi-Newton method with a line search
    converges in a few hundred evaluations where Adam needs thousands (red attenuation, whose
    signal fades fastest with range, is the slow direction).

    Args:
        ranges: (N,) ranges; observed: (N, 3) pixels; ids, groups: from ``voxel_groups``.
        start: ``{"sigma_attn": [3] or float, "sigma_bs": ..., "c_med": ...}`` start values.
        steps: most loss evaluations of the optimiser.
        colour_max: ``c_med`` is kept in (0, colour_max).
        dark: optional dark-pixel bound (:func:`dark_pixels`): the water is first fitted
            without it, the bound is raised by the residuals' :func:`noise_allowance`, and
            backscatter above the raised bound is penalised with ``dark_weight`` times its
            mean squared excess in a second fit started from the first.
        balance_brightness: weight each group by its inverse clean colour
            (:func:`brightness_weights`, taken at an unweighted fit and once more at the
            weighted one); False fits every pixel alike.
        brightness_floor: :func:`brightness_weights`' ``floor``.

    Returns:
        the fitted water, its loss and the group weights it used.

    Example::

        ids, groups = voxel_groups(points, 0.02)
        fit = fit_water(z, rgb, ids, groups, {"sigma_attn": 0.2, "sigma_bs": 0.2, "c_med": 0.2})
    """
    weights = None
    free = _fit_water(ranges, observed, ids, groups, start, steps, colour_max)
    if balance_brightness:
        for _ in range(2):
            weights = _weights_at(free, ranges, observed, ids, groups, brightness_floor)
            free = _fit_water(ranges, observed, ids, groups, _values(free), steps, colour_max,
                              weights=weights)
    if dark is None:
        return free
    allowance = noise_allowance(free, ranges, observed, ids, groups)
    dark = (dark[0], dark[1].to(allowance) + allowance)
    return _fit_water(ranges, observed, ids, groups, _values(free), steps, colour_max, dark,
                      dark_weight, weights)


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
        fit: the water fitted to ``data``; data: its pixels (``surface_data``).
        threshold: robust standard deviations from the median.

    Returns:
        (N,) bool, True for the outliers.

    Example::

        fit = fit_water(data.ranges, data.observed, data.ids, data.groups, start)
        kept = without_pixels(data, residual_outliers(fit, data, 3.5))
    """
    theta = _theta(fit).split(3)
    residuals = _projected_residuals(*theta, data.ranges.double(), data.observed.double(),
                                     data.ids, data.groups)[0]
    surface = torch.isfinite(data.ranges)
    if int(surface.sum()) < 2:
        return torch.zeros_like(surface)
    centre = residuals[surface].median(0).values
    spread = 1.4826 * (residuals[surface] - centre).abs().median(0).values
    far = ((residuals - centre).abs() > threshold * spread.clamp_min(1e-12)).any(dim=1)
    return far & surface


def without_pixels(data: SurfaceData, drop: Tensor) -> SurfaceData | str:
    """``data`` without the pixels ``drop`` marks, less the groups no longer seen over a
    spread of ranges (:func:`ranged_groups`); the open-water group and the dark-pixel bound
    stay. A sentence saying why instead when too few surface pixels are left."""
    keep = ~drop
    surface = torch.isfinite(data.ranges)
    kept_surface = keep & surface
    ids, groups = _renumber(data.ids[kept_surface])
    ranged = ranged_groups(data.ranges[kept_surface], ids, groups)
    if int(ranged.sum()) < 3:
        return f"only {int(ranged.sum())} surface pixels left after the outliers"
    keep[kept_surface.nonzero().squeeze(1)[~ranged]] = False
    ids, groups = _renumber(data.ids[keep])
    return SurfaceData(data.ranges[keep], data.observed[keep], ids, groups, data.dark,
                       open_water_below_horizon=data.open_water_below_horizon)


def fit_surfaces(data: SurfaceData, start: dict, steps: int = 300, colour_max: float = 1.5,
                 dark_bound: bool = True, balance_brightness: bool = True,
                 trim: float = 0.0) -> tuple[WaterFit, SurfaceData]:
    """:func:`fit_water` on ``data``; with ``trim`` > 0, fitted again without the
    :func:`residual_outliers` at ``trim`` robust standard deviations, from the first fit.

    Args:
        data: surface pixels (``surface_data``): (N,) ranges, (N, 3) pixels, (N,) groups.
        start: start values, as :func:`fit_water`'s; steps, colour_max: :func:`fit_water`'s.
        dark_bound: use ``data.dark`` (the dark-pixel bound); balance_brightness: see
            :func:`fit_water`.
        trim: robust standard deviations beyond which a pixel is left out; 0 fits once.

    Returns:
        the fit and the data it was made on (``data`` itself when nothing was trimmed).

    Example::

        fit, used = fit_surfaces(data, model.water_parameters(), trim=3.5)
        spread = laplace_halfwidths(fit, used.ranges, used.observed, used.ids, used.groups)
    """
    dark = data.dark if dark_bound else None
    fit = fit_water(data.ranges, data.observed, data.ids, data.groups, start, steps,
                    colour_max, dark, balance_brightness=balance_brightness)
    if trim <= 0:
        return fit, data
    outliers = residual_outliers(fit, data, trim)
    trimmed = without_pixels(data, outliers) if bool(outliers.any()) else data
    if trimmed is data or isinstance(trimmed, str):
        return fit, data
    return fit_water(trimmed.ranges, trimmed.observed, trimmed.ids, trimmed.groups, _values(fit),
                     steps, colour_max, dark, balance_brightness=balance_brightness), trimmed


def _values(fit: WaterFit) -> dict[str, list[float]]:
    return {key: getattr(fit, key) for key in NAMES}


def _weights_at(fit: WaterFit, ranges: Tensor, observed: Tensor, ids: Tensor,
                groups: int, floor: float = 1.0) -> Tensor:
    """:func:`brightness_weights` of the clean colours at ``fit``."""
    theta = _theta(fit).to(ranges.device).split(3)
    clean = _projected_residuals(*theta, ranges.double(), observed.double(), ids, groups)[1]
    return brightness_weights(clean, theta[2], bool((~torch.isfinite(ranges)).any()), floor)


def _fit_water(ranges: Tensor, observed: Tensor, ids: Tensor, groups: int, start: dict,
               steps: int, colour_max: float, dark: tuple[Tensor, Tensor] | None = None,
               dark_weight: float = 10.0, weights: Tensor | None = None) -> WaterFit:
    """One L-BFGS fit of :func:`fit_water` with fixed group ``weights`` (or none)."""
    def triple(value) -> list[float]:
        return [float(value)] * 3 if isinstance(value, (int, float)) else [float(v) for v in value]

    colour = [min(max(c / colour_max, 1e-4), 1 - 1e-4) for c in triple(start["c_med"])]
    raw = torch.tensor([_inverse_softplus(v) for v in triple(start["sigma_attn"])]
                       + [_inverse_softplus(v) for v in triple(start["sigma_bs"])]
                       + [math.log(c / (1 - c)) for c in colour],
                       dtype=torch.float64, device=ranges.device, requires_grad=True)
    ranges, observed = ranges.double(), observed.double()
    optimiser = torch.optim.LBFGS([raw], lr=1.0, max_iter=max(1, steps), history_size=20,
                                  tolerance_grad=1e-12, tolerance_change=1e-16,
                                  line_search_fn="strong_wolfe")

    def water() -> tuple[Tensor, Tensor, Tensor]:
        return F.softplus(raw[0:3]), F.softplus(raw[3:6]), torch.sigmoid(raw[6:9]) * colour_max

    if dark is not None:
        dark = (dark[0].double().to(ranges.device), dark[1].double().to(ranges.device))

    def objective() -> Tensor:
        attn, bs, c_med = water()
        loss = projected_loss(attn, bs, c_med, ranges, observed, ids, groups, weights)
        if dark is not None:
            loss = loss + dark_weight * dark_excess(bs, c_med, dark)
        return loss

    # L-BFGS's tolerances are absolute and the loss is a small mean squared residual, so it
    # is measured relative to its start value. Unscaled, refits on the demo ran to the
    # evaluation limit (375 evaluations, 4.6 s) and ended above the scaled fit's loss (0.9 s).
    with torch.no_grad():
        scale = max(float(objective()), 1e-30)

    def closure() -> Tensor:
        optimiser.zero_grad()
        loss = objective() / scale
        loss.backward()
        return loss

    with torch.enable_grad():
        optimiser.step(closure)
    with torch.no_grad():
        attn, bs, c_med = water()
        loss = float(projected_loss(attn, bs, c_med, ranges, observed, ids, groups, weights))
    return WaterFit(attn.tolist(), bs.tolist(), c_med.tolist(), loss, int(len(ranges)), groups,
                    weights)


@dataclass
class WaterUncertainty:
    halfwidth: dict[str, list[float]]   # 95% half-width per parameter and channel (inf: none)
    determined: dict[str, list[bool]]   # half-width below ``max_relative`` of the value
    effective_samples: int              # independent units behind the spread
    method: str = "curvature"           # "curvature" (laplace_halfwidths) or "robust"
    statistical: dict[str, list[float]] | None = None  # robust: the sandwich part
    systematic: dict[str, list[float]] | None = None   # robust: the between-part part
    splits: dict[str, list[float]] | None = None       # robust: each comparison's (9,)


NAMES = ("sigma_attn", "sigma_bs", "c_med")


def laplace_halfwidths(fit: WaterFit, ranges: Tensor, observed: Tensor, ids: Tensor,
                       groups: int, max_relative: float = 0.25) -> WaterUncertainty:
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
    theta = _theta(fit)
    ranges, observed = ranges.double(), observed.double()
    hessian = profile_hessian(theta, ranges, observed, ids, groups, fit.weights)
    samples = max(1, 3 * groups)
    # information of the mean-squared loss: n / (2 sigma^2) * H, with sigma^2 = the loss; as a
    # sandwich H^-1 M H^-1 that is M = 2 sigma^2 / n * H
    meat = 2.0 * max(fit.loss, 1e-12) / samples * hessian
    half = (1.96 * sandwich_variances(hessian, meat, isolate_flat=False).sqrt()).tolist()
    return _uncertainty(fit, half, max_relative, samples, "curvature")


def robust_halfwidths(fit: WaterFit, ranges: Tensor, observed: Tensor, ids: Tensor,
                      groups: int, max_relative: float = 0.25, colour_max: float = 1.5,
                      dark: tuple[Tensor, Tensor] | None = None, steps: int = 100,
                      min_groups: int = 20, range_error: float = 0.0,
                      min_relative: float = 0.0,
                      regrouped: Sequence[tuple[Tensor, Tensor, Tensor, int]] = (),
                      open_water_beyond: float | None = None) -> WaterUncertainty:
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
    the larger move is one more ``d^2``. The interval is a prediction interval,
    ``1.96 sqrt(var + max tau^2)``: the fit's error is taken to be one more draw of the error that makes parts of the data disagree.
    With independent noise ``tau^2`` is an estimate of zero and the coverage stays near 95%
    (97% measured); on fits on trained models' own surfaces it goes from 61-72% (curvature)
    to 87-90% (``benchmarks/results/water_intervals.md``). An error every part shares alike
    (a smooth depth distortion over the whole scene, a wrong scale) is out of its reach, as
    of any measure taken from the same images.

    A direction the data do not curve gives an infinite half-width in every parameter it
    touches; a parameter whose half-width exceeds ``max_relative`` of its value is flagged as
    not determined. Costs up to 9 warm-started refits and their Hessians (1-7 s for 65k rays
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
    theta = _theta(fit)
    statistical = cluster_variances(theta, ranges, observed, ids, groups, fit.weights)
    start = _values(fit)
    balance = fit.weights is not None

    def refit(keep: Tensor) -> tuple[Tensor, Tensor] | None:
        part_ids, part_groups = _renumber(ids[keep])
        if int(torch.isfinite(ranges[keep]).sum()) == 0 or part_groups < min_groups:
            return None
        part_fit = fit_water(ranges[keep], observed[keep], part_ids, part_groups, start, steps,
                             colour_max, balance_brightness=balance)
        return _theta(part_fit), cluster_variances(_theta(part_fit), ranges[keep],
                                                   observed[keep], part_ids, part_groups,
                                                   part_fit.weights)

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
    if open_water_beyond is not None and bool(water.any()) and whole is not None:
        moves = [_theta(fit_water(ranges, shifted, ids, groups, start, steps, colour_max,
                                  balance_brightness=balance)) - whole[0]
                 for shifted in surface_behind_open_water(theta, ranges, observed,
                                                          open_water_beyond)]
        between["open_water_surface"] = _finite_variance(torch.stack(moves).pow(2).amax(0))
    if range_error > 0 and whole is not None:
        noise = torch.randn(ranges.shape, generator=torch.Generator().manual_seed(0),
                            dtype=ranges.dtype)
        noisier = torch.where(torch.isfinite(ranges), ranges * torch.exp(range_error * noise),
                              ranges)
        moved = fit_water(noisier, observed, ids, groups, start, steps, colour_max,
                          balance_brightness=balance)
        between["range_error"] = _finite_variance((_theta(moved) - whole[0]) ** 2)
    moves = [] if whole is None else [
        _theta(fit_water(*other, start, steps, colour_max, balance_brightness=balance)) - whole[0]
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
                        max_relative: float = 0.25) -> dict[str, list[bool]]:
    """Whether the views determine each trained water value, judged on the interval around it
    (``water_interval.interval_halfwidth``): determined where that half-width is finite and at most
    ``max_relative`` of the value (judged on the fit's half-width alone, values up to 81% off
    the truth on the water benchmark were flagged as determined).

    Args:
        trained: ``{"sigma_attn": [3], "sigma_bs": [3], "c_med": [3]}`` trained values.
        surface_fit: the fit on the model's surfaces the half-widths belong to.
        halfwidth: 95% half-widths per name (``WaterUncertainty.halfwidth``).
        max_relative: largest widened half-width, as a share of the value, still determined.

    Returns:
        per name, per channel, True where determined.

    Example::

        flags = interval_determined(model.water_parameters(), fit, spread.halfwidth)
    """
    return {name: [bool(math.isfinite(h) and interval_halfwidth(float(c), g, h)
                        <= max_relative * abs(float(c)))
                   for c, g, h in zip(trained[name], getattr(surface_fit, name), halfwidth[name])]
            for name in NAMES}


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
                    groups: int, weights: Tensor | None = None) -> Tensor:
    """(9, 9) Hessian of :func:`projected_loss` (with the group ``weights``, if given) at the
    water ``theta`` (symmetrised)."""
    def loss(params: Tensor) -> Tensor:
        return projected_loss(params[0:3], params[3:6], params[6:9], ranges, observed, ids,
                              groups, weights)

    with torch.enable_grad():
        hessian = torch.autograd.functional.hessian(loss, theta)
    return 0.5 * (hessian + hessian.T)


def cluster_variances(theta: Tensor, ranges: Tensor, observed: Tensor, ids: Tensor,
                      groups: int, weights: Tensor | None = None) -> Tensor:
    """(9,) variances of the water fitted at ``theta``: the sandwich ``H^-1 M H^-1`` with the
    meat summed over clusters (see :func:`robust_halfwidths`): the voxel groups, and each
    open-water pixel (range inf) on its own -- rays of many views into open water share no
    surface, and as one cluster their score would be pinned to minus the others' by the fit's
    own optimality; inf where not curved. ``weights``: the fit's group weights, if any."""
    hessian = profile_hessian(theta, ranges, observed, ids, groups, weights)
    water = ~torch.isfinite(ranges)
    clusters = ids.clone()
    clusters[water] = groups + torch.arange(int(water.sum()), device=ids.device)
    clusters, count = _renumber(clusters)
    scores = group_scores(theta, ranges, observed, ids, groups, clusters, count, weights)
    meat = scores.T @ scores * (count / max(count - 1, 1))
    return sandwich_variances(hessian, meat)


def group_scores(theta: Tensor, ranges: Tensor, observed: Tensor, ids: Tensor,
                 groups: int, clusters: Tensor | None = None, count: int = 0,
                 weights: Tensor | None = None) -> Tensor:
    """Each group's share of the gradient of :func:`projected_loss` at the water ``theta``.

    With the clean colours at their optimum for ``theta``, the profile's gradient is the
    partial one at fixed colours (envelope theorem), a sum over pixels that splits by group.

    Args:
        theta: (9,) ``sigma_attn``, ``sigma_bs``, ``c_med`` (3 each).
        ranges, observed, ids, groups: as for :func:`projected_loss`.
        clusters, count: (N,) other units to sum the scores over, and their number
            (default: the groups).
        weights: (groups, 3) group weights of the loss, if any.

    Returns:
        (groups or count, 9) scores; they sum to the gradient (zero at an interior minimum).
    """
    attn, bs, c_med = theta[0:3], theta[3:6], theta[6:9]
    residual, clean, z = _projected_residuals(attn, bs, c_med, ranges.double(),
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


def _theta(fit: WaterFit) -> Tensor:
    return torch.tensor(fit.sigma_attn + fit.sigma_bs + fit.c_med, dtype=torch.float64)


def _by_name(values: list[float]) -> dict[str, list[float]]:
    return {n: values[3 * i:3 * i + 3] for i, n in enumerate(NAMES)}


def _used_groups(ids: Tensor, groups: int) -> int:
    return int((torch.bincount(ids, minlength=groups) > 0).sum())


def _renumber(ids: Tensor) -> tuple[Tensor, int]:
    unique, inverse = torch.unique(ids, return_inverse=True)
    return inverse, int(unique.numel())


def _uncertainty(fit: WaterFit, half: list[float], max_relative: float, samples: int,
                 method: str) -> WaterUncertainty:
    values = fit.sigma_attn + fit.sigma_bs + fit.c_med
    determined = [bool(h <= max_relative * abs(v)) for h, v in zip(half, values)]
    return WaterUncertainty(_by_name(half), _by_name(determined), samples, method)
