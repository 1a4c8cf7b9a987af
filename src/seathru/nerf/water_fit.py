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
    attenuation = torch.exp(-sigma_attn * ranges[:, None])
    backscatter = c_med * (1.0 - torch.exp(-sigma_bs * ranges[:, None]))
    num = observed.new_zeros(groups, 3).index_add_(0, ids, attenuation * (observed - backscatter))
    den = observed.new_zeros(groups, 3).index_add_(0, ids, attenuation * attenuation)
    clean = (num / den.clamp_min(1e-12)).clamp_min(0.0)
    return ((observed - clean[ids] * attenuation - backscatter) ** 2).mean()


def _inverse_softplus(value: float) -> float:
    value = max(value, 1e-6)
    return value + math.log(-math.expm1(-value)) if value < 20 else value


def fit_water(ranges: Tensor, observed: Tensor, ids: Tensor, groups: int, start: dict,
              steps: int = 300, colour_max: float = 1.5) -> WaterFit:
    """Fit the 9 water parameters by L-BFGS on :func:`projected_loss`, in float64.

    Nine smooth parameters and a cheap exact loss: a quasi-Newton method with a line search
    converges in a few hundred evaluations where Adam needs thousands (red attenuation, whose
    signal fades fastest with range, is the slow direction).

    Args:
        ranges: (N,) ranges; observed: (N, 3) pixels; ids, groups: from ``voxel_groups``.
        start: ``{"sigma_attn": [3] or float, "sigma_bs": ..., "c_med": ...}`` start values.
        steps: most loss evaluations of the optimiser.
        colour_max: ``c_med`` is kept in (0, colour_max).

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

    def closure() -> Tensor:
        optimiser.zero_grad()
        loss = projected_loss(*water(), ranges, observed, ids, groups)
        loss.backward()
        return loss

    with torch.enable_grad():
        optimiser.step(closure)
    with torch.no_grad():
        attn, bs, c_med = water()
        loss = float(projected_loss(attn, bs, c_med, ranges, observed, ids, groups))
    return WaterFit(attn.tolist(), bs.tolist(), c_med.tolist(), loss, int(len(ranges)), groups)
