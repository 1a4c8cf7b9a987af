"""Training losses (SeaThru-NeRF, Levy et al. 2023, Sec. 4).

Shapes: colours (R, 3); transmittance (R,); masks (R,) bool/float or None.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def reconstruction_loss(pred: Tensor, target: Tensor, eps: float = 1e-3,
                        mask: Tensor | None = None) -> Tensor:
    """The paper's loss on linear data: mean of ((C_hat - C) / (stopgrad(C_hat) + eps))^2.

    Dividing by the (detached) prediction approximates an L2 loss on tone-mapped (log) values,
    so dark, strongly attenuated regions count as much as bright ones (RawNeRF).
    """
    residual = (pred - target) / (pred.detach() + eps)
    squared = residual.square()
    if mask is None:
        return squared.mean()
    mask = mask.to(squared.dtype).reshape(-1, *([1] * (squared.dim() - 1)))
    return (squared * mask).sum() / (mask.sum() * squared.shape[-1]).clamp_min(1.0)


def transmittance_prior(transmittance: Tensor, scale: float = 0.1) -> Tensor:
    """-log P(T) with P a mixture of Laplacians at 0 and 1 (width ``scale``), mean over rays.

    Shifted by a constant so that the minimum, reached at T = 0 and T = 1, is exactly 0: a ray
    either hits an object or sees only water.
    """
    t = transmittance.clamp(0.0, 1.0)
    log_p = torch.logaddexp(-t / scale, -(1.0 - t) / scale)
    log_p_max = math.log1p(math.exp(-1.0 / scale))
    return (log_p_max - log_p).mean()


def mse(pred: Tensor, target: Tensor) -> Tensor:
    return (pred - target).square().mean()


def psnr_from_mse(value: float) -> float:
    """PSNR (dB) for data whose peak is 1 (linear radiance)."""
    return float("inf") if value <= 0 else -10.0 * math.log10(value)


def total_variation_3d(volume: Tensor, samples: int | None, generator: torch.Generator | None
                       = None) -> Tensor:
    """Mean squared difference between neighbouring voxels of a (1, C, D, H, W) volume.

    With ``samples``, only that many random voxels (and their +x, +y, +z neighbours) count, so
    the cost does not grow with the grid.
    """
    if samples is None:
        dz = (volume[:, :, 1:] - volume[:, :, :-1]).square().mean()
        dy = (volume[:, :, :, 1:] - volume[:, :, :, :-1]).square().mean()
        dx = (volume[..., 1:] - volume[..., :-1]).square().mean()
        return dx + dy + dz
    d, h, w = volume.shape[-3:]
    flat = volume.reshape(volume.shape[1], -1)
    index = torch.randint(0, (d - 1) * (h - 1) * (w - 1), (samples,), generator=generator)
    index = index.to(volume.device)
    x = index % (w - 1)
    y = (index // (w - 1)) % (h - 1)
    z = index // ((w - 1) * (h - 1))
    base = (z * h + y) * w + x
    centre = flat[:, base]
    return ((flat[:, base + 1] - centre).square().mean()
            + (flat[:, base + w] - centre).square().mean()
            + (flat[:, base + w * h] - centre).square().mean())


def distortion_loss(weights: Tensor, s_edges: Tensor) -> Tensor:
    """mip-NeRF 360's distortion loss, O(S): sum_ij w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 d_i.

    weights (R, S); s_edges (R, S+1) the interval edges in a normalised ray coordinate (so near
    and far intervals count alike). Pulls each ray's weight into one compact surface, which
    removes the diffuse fog that fits the training views early on. Mean over rays.
    """
    mids = 0.5 * (s_edges[:, 1:] + s_edges[:, :-1])
    lengths = s_edges[:, 1:] - s_edges[:, :-1]
    wm = weights * mids
    w_before = torch.cumsum(weights, dim=-1) - weights
    wm_before = torch.cumsum(wm, dim=-1) - wm
    inter = 2.0 * (weights * (mids * w_before - wm_before)).sum(dim=-1)
    intra = (weights.square() * lengths).sum(dim=-1) / 3.0
    return (inter + intra).mean()


def sparse_depth_loss(depth: Tensor, target: Tensor) -> Tensor:
    """Mean relative L1 error of rendered depths against the ranges of sparse 3D points.

    Relative, because a triangulated point's error grows with its range; L1, because a few
    points are mistriangulated. The expected depth (not the median) takes every sample's
    weight, so fog in front of a point is pulled onto it.

    Args:
        depth: (R,) rendered expected ray distance; target: (R,) the points' ranges (> 0).

    Returns:
        the scalar loss.

    Example::

        loss = sparse_depth_loss(render.depth_mean, ranges)
    """
    return ((depth - target).abs() / target).mean()
