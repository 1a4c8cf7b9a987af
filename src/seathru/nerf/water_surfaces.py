"""The surface pixels a water fit rests on (:mod:`seathru.nerf.water_fit`): gathered from a
model's render (:func:`surface_data`, :func:`correspondence_rays`), grouped by the surface
point they see (:func:`voxel_groups`, :func:`ranged_groups`), with the open water
(:func:`typical_open_water`) and the dark-pixel bound (:func:`dark_pixels`) beside them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

if TYPE_CHECKING:
    from seathru.nerf.rays import RayBatch, RayDataset


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
                 min_above_horizon: float = 0.2, point_ids: Tensor | None = None,
                 open_water_surface_within: Tensor | None = None) -> SurfaceData | str:
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
            are no surfaces unless ``open_water_surface_within`` says so; they are used
            whenever ``open_water_opacity`` is above 0.

            Of these, only pixels of the open water's typical colour are used
            (:func:`typical_open_water`).
        below_horizon: (R,) bool or None: the rays that look below the horizon
            (``seathru.geometry.upright``). Open water there may be a far seabed whose colour
            still holds some of its direct light (on simulated orbits, all of the flagged
            "open water" was seabed 6-11 m away, 10-23% off the veiling light). Where at least
            ``min_above_horizon`` of the open-water pixels look above the horizon, only those
            are used; otherwise all are, and the data say so
            (``SurfaceData.open_water_below_horizon``: the intervals then allow for a surface
            behind them, :func:`~seathru.nerf.water_uncertainty.robust_halfwidths`).
        min_above_horizon: see ``below_horizon``.
        point_ids: (R,) long or None: rays with the same id look at the same surface point
            (:func:`correspondence_rays`); given, they are grouped by it instead of by voxel
            (``voxel`` is then unused), and rays with id -1 are no surface.
        open_water_surface_within: (R,) ranges or None: given, a ray of the photographs' open
            water that the model renders as an opaque surface (``opacity`` above
            ``min_opacity``) nearer than its range here is that surface, not open water. In
            turbid water far seabed is smooth and fills the top of the frame: on the
            simulator's turbid transects and orbits every such pixel had seabed 3-11 m away,
            which a converged model places where the truth has it (95-96% opaque; on the
            surveys the opaque share matched the truth's seabed share within 2 points).

    Returns:
        the data, or a sentence saying why there is not enough of it.
    """
    keep = (opacity > min_opacity) & torch.isfinite(depth)
    if open_water is not None and open_water_surface_within is not None:
        open_water = open_water & ~(keep & (depth < open_water_surface_within))
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
                        min_opacity: float = 0.9, tolerance: float = 0.02,
                        deblurred: bool = False) -> CorrespondenceRays:
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
        deblurred: the rays' colour from the dataset's deblurred images, where it keeps them.

    Returns:
        the seeing rays (ids = their point) followed by the anchors that found no surface
        (id -1: open water and fog, which the fit may still use as open water).

    Example::

        found = correspondence_rays(trainer.data, trainer.render_batch, 16384, 65536, seed=5)
        data = surface_data(found.rays.origins, found.rays.directions, found.rays.rgb,
                            found.depth, found.opacity, voxel, point_ids=found.point_ids)
    """
    drawn = dataset.fixed_subset(anchors, seed, deblurred)
    first = render(drawn)
    surface = (first["opacity"] > min_opacity) & torch.isfinite(first["depth_median"])
    if drawn.open_water is not None:
        surface &= ~drawn.open_water
    points = (drawn.origins[surface] + drawn.directions[surface]
              * first["depth_median"][surface, None]).double().cpu().numpy()
    through, owner = dataset.rays_through(points, deblurred)
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
    below that; :func:`~seathru.nerf.water_fit.fit_water` raises the bound by the noise it
    measures.

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


def without_pixels(data: SurfaceData, drop: Tensor) -> SurfaceData | str:
    """``data`` without the pixels ``drop`` marks, less the groups no longer seen over a
    spread of ranges (:func:`ranged_groups`); the open-water group and the dark-pixel bound
    stay. A sentence saying why instead when too few surface pixels are left."""
    keep = ~drop
    surface = torch.isfinite(data.ranges)
    kept_surface = keep & surface
    ids, groups = renumbered_groups(data.ids[kept_surface])
    ranged = ranged_groups(data.ranges[kept_surface], ids, groups)
    if int(ranged.sum()) < 3:
        return f"only {int(ranged.sum())} surface pixels left after the outliers"
    keep[kept_surface.nonzero().squeeze(1)[~ranged]] = False
    ids, groups = renumbered_groups(data.ids[keep])
    return SurfaceData(data.ranges[keep], data.observed[keep], ids, groups, data.dark,
                       open_water_below_horizon=data.open_water_below_horizon)


def renumbered_groups(ids: Tensor) -> tuple[Tensor, int]:
    """Group ids renumbered 0..G-1 over the groups present, and G."""
    unique, inverse = torch.unique(ids, return_inverse=True)
    return inverse, int(unique.numel())
