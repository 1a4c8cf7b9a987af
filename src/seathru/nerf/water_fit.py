"""The water fitted to images of surfaces at known ranges, by variable projection.

For pixels whose surface lies at range ``z`` (the model's own depth during training, or the
simulator's true depth in the diagnostic benchmark), the SeaThru image formation is

    I = J exp(-sigma_attn z) + c_med (1 - exp(-sigma_bs z)),

per channel. Pixels are grouped by the voxel their surface point falls in, with one unknown
clean colour ``J`` per voxel and channel; for given water the best non-negative ``J`` of each
voxel has a closed form, so the fit runs over the 9 water parameters alone. The same surface
seen from several ranges is what pins the attenuation down (as in Sea-thru's regression on
range); surfaces seen at one range only leave ``J`` and the water traded against each other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor


@dataclass
class WaterFit:
    sigma_attn: list[float]     # per channel, 1 / (unit of z)
    sigma_bs: list[float]
    c_med: list[float]
    loss: float                 # mean squared residual at the fit
    pixels: int
    groups: int


@dataclass
class SurfaceData:
    """Pixels of surfaces seen over a spread of ranges, grouped by voxel (float64, CPU)."""

    ranges: Tensor      # (N,)
    observed: Tensor    # (N, 3)
    ids: Tensor         # (N,) voxel group
    groups: int
    dark: tuple[Tensor, Tensor] | None = None  # (K,) range bins, (K, 3) darkest pixel values


def surface_data(origins: Tensor, directions: Tensor, rgb: Tensor, depth: Tensor,
                 opacity: Tensor, voxel: float, min_opacity: float = 0.9,
                 min_pixels: int = 1000, open_water_opacity: float = 0.0) -> SurfaceData | str:
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

    Returns:
        the data, or a sentence saying why there is not enough of it.
    """
    keep = (opacity > min_opacity) & torch.isfinite(depth)
    if int(keep.sum()) < min_pixels:
        return f"only {int(keep.sum())} rays reach opaque surfaces"
    points = (origins[keep] + directions[keep] * depth[keep, None]).double().cpu()
    ranges, observed = depth[keep].double().cpu(), rgb[keep].double().cpu()
    ids, groups = voxel_groups(points, voxel)
    ranged = ranged_groups(ranges, ids, groups)
    if int(ranged.sum()) < min_pixels:
        return f"only {int(ranged.sum())} surface pixels are seen over a spread of ranges"
    dark = dark_pixels(ranges, observed)
    ids, groups = voxel_groups(points[ranged], voxel)
    ranges, observed = ranges[ranged], observed[ranged]
    water = opacity < open_water_opacity
    if bool(water.any()):
        ranges = torch.cat([ranges, torch.full((int(water.sum()),), math.inf,
                                               dtype=ranges.dtype)])
        observed = torch.cat([observed, rgb[water].double().cpu()])
        ids = torch.cat([ids, torch.full((int(water.sum()),), groups, dtype=ids.dtype)])
        groups += 1
    return SurfaceData(ranges, observed, ids, groups, dark)


def dark_pixels(ranges: Tensor, observed: Tensor, bins: int = 10, quantile: float = 0.01,
                min_per_bin: int = 50) -> tuple[Tensor, Tensor] | None:
    """Sea-thru's dark-pixel estimate: the darkest pixels at each range bound the backscatter.

    A pixel is ``J exp(-a z) + B(z)`` with ``J >= 0`` and ``B`` grows with range, so the
    darkest pixels of a range bin are at least the backscatter at the bin's nearest range: the
    ``quantile`` of each channel per bin bounds ``B`` there from above (nearly equal to it
    where some surfaces are black or shadowed).

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
                   observed: Tensor, ids: Tensor, groups: int) -> Tensor:
    """Mean squared residual of the image formation with the best clean colour per group.

    Args:
        sigma_attn, sigma_bs, c_med: (3,) water parameters.
        ranges: (N,) range of each pixel's surface.
        observed: (N, 3) pixel values.
        ids: (N,) group of each pixel (``voxel_groups``); groups: their number.

    Returns:
        the scalar loss (differentiable in the water parameters).
    """
    # open water (range inf) as a very long finite range: same values, finite gradients
    ranges = ranges.clamp_max(1e6)
    attenuation = torch.exp(-sigma_attn * ranges[:, None])
    backscatter = c_med * (1.0 - torch.exp(-sigma_bs * ranges[:, None]))
    num = observed.new_zeros(groups, 3).index_add_(0, ids, attenuation * (observed - backscatter))
    den = observed.new_zeros(groups, 3).index_add_(0, ids, attenuation * attenuation)
    clean = (num / den.clamp_min(1e-12)).clamp_min(0.0)
    return ((observed - clean[ids] * attenuation - backscatter) ** 2).mean()


def _inverse_softplus(value: float) -> float:
    value = max(value, 1e-6)
    return value + math.log(-math.expm1(-value)) if value < 20 else value


def dark_excess(sigma_bs: Tensor, c_med: Tensor, dark: tuple[Tensor, Tensor]) -> Tensor:
    """Mean squared excess of the modelled backscatter over the dark-pixel bound (0 if below)."""
    centres, values = dark
    backscatter = c_med * (1.0 - torch.exp(-sigma_bs * centres[:, None]))
    return (torch.relu(backscatter - values) ** 2).mean()


def fit_water(ranges: Tensor, observed: Tensor, ids: Tensor, groups: int, start: dict,
              steps: int = 300, colour_max: float = 1.5,
              dark: tuple[Tensor, Tensor] | None = None, dark_weight: float = 10.0) -> WaterFit:
    """Fit the 9 water parameters by L-BFGS on :func:`projected_loss`, in float64.

    Nine smooth parameters and a cheap exact loss: a quasi-Newton method with a line search
    converges in a few hundred evaluations where Adam needs thousands (red attenuation, whose
    signal fades fastest with range, is the slow direction).

    Args:
        ranges: (N,) ranges; observed: (N, 3) pixels; ids, groups: from ``voxel_groups``.
        start: ``{"sigma_attn": [3] or float, "sigma_bs": ..., "c_med": ...}`` start values.
        steps: most loss evaluations of the optimiser.
        colour_max: ``c_med`` is kept in (0, colour_max).
        dark: optional dark-pixel bound (:func:`dark_pixels`): backscatter above it is
            penalised with ``dark_weight`` times its mean squared excess.

    Returns:
        the fitted water and its loss.

    Example::

        ids, groups = voxel_groups(points, 0.02)
        fit = fit_water(z, rgb, ids, groups, {"sigma_attn": 0.2, "sigma_bs": 0.2, "c_med": 0.2})
    """
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

    def closure() -> Tensor:
        optimiser.zero_grad()
        attn, bs, c_med = water()
        loss = projected_loss(attn, bs, c_med, ranges, observed, ids, groups)
        if dark is not None:
            loss = loss + dark_weight * dark_excess(bs, c_med, dark)
        loss.backward()
        return loss

    with torch.enable_grad():
        optimiser.step(closure)
    with torch.no_grad():
        attn, bs, c_med = water()
        loss = float(projected_loss(attn, bs, c_med, ranges, observed, ids, groups))
    return WaterFit(attn.tolist(), bs.tolist(), c_med.tolist(), loss, int(len(ranges)), groups)


@dataclass
class WaterUncertainty:
    halfwidth: dict[str, list[float]]   # 95% half-width per parameter and channel (inf: none)
    determined: dict[str, list[bool]]   # half-width below ``max_relative`` of the value
    effective_samples: int


def laplace_halfwidths(fit: WaterFit, ranges: Tensor, observed: Tensor, ids: Tensor,
                       groups: int, max_relative: float = 0.25) -> WaterUncertainty:
    """95% intervals of the fitted water from the curvature of the profile loss (Laplace).

    The loss of :func:`projected_loss` is already minimised over every clean colour, so its
    Hessian in the 9 water parameters is that of the profile likelihood: flat directions (water
    traded against brighter surfaces) give wide intervals. Residuals are treated as Gaussian
    with the fit's own variance, but pixels of one surface voxel share the model's errors, so
    the sample count is the number of voxels times 3 channels, not of pixels: intervals from
    pixel counts would be far too narrow for a NeRF's geometry errors. A parameter whose
    half-width exceeds ``max_relative`` of its value is flagged as not determined.

    Args:
        fit: the result of :func:`fit_water` on the same data.
        ranges, observed, ids, groups: the data of that fit.
        max_relative: relative half-width above which a parameter counts as undetermined.

    Returns:
        half-widths and flags per parameter (``sigma_attn``, ``sigma_bs``, ``c_med``) and channel.
    """
    theta = torch.tensor(fit.sigma_attn + fit.sigma_bs + fit.c_med, dtype=torch.float64)
    ranges, observed = ranges.double(), observed.double()

    def loss(params: Tensor) -> Tensor:
        return projected_loss(params[0:3], params[3:6], params[6:9], ranges, observed, ids,
                              groups)

    with torch.enable_grad():
        hessian = torch.autograd.functional.hessian(loss, theta)
    samples = max(1, 3 * groups)
    variance = max(fit.loss, 1e-12)
    # information of the mean-squared loss: n / (2 sigma^2) * H, with sigma^2 = the loss
    information = samples / (2.0 * variance) * hessian
    eigenvalues, vectors = torch.linalg.eigh(0.5 * (information + information.T))
    floor = float(eigenvalues.abs().max()) * 1e-12 + 1e-300
    inverse = torch.where(eigenvalues > floor, 1.0 / eigenvalues.clamp_min(floor),
                          torch.full_like(eigenvalues, float("inf")))
    # a direction the data do not curve gets infinite variance in every parameter it touches
    variance_diag = ((vectors ** 2) * inverse).sum(-1)
    variance_diag = torch.where(torch.isnan(variance_diag), torch.full_like(variance_diag,
                                float("inf")), variance_diag)
    half = (1.96 * variance_diag.sqrt()).tolist()
    values = fit.sigma_attn + fit.sigma_bs + fit.c_med
    names = ("sigma_attn", "sigma_bs", "c_med")
    halfwidth = {n: half[3 * i:3 * i + 3] for i, n in enumerate(names)}
    determined = {n: [bool(h <= max_relative * abs(v)) for h, v in
                      zip(half[3 * i:3 * i + 3], values[3 * i:3 * i + 3])]
                  for i, n in enumerate(names)}
    return WaterUncertainty(halfwidth, determined, samples)
