"""Where along each ray the object field is evaluated.

Every sampler returns contiguous intervals ``t_edges`` (R, S+1), non-decreasing, from the ray's
near bound to its far bound. ``seathru.nerf.rendering.render_seathru`` integrates the water in
closed form inside every interval and before/after them, so intervals may be long where there is
only water: samples are spent on surfaces only.

Candidate bins (``candidate_edges``): linear in t inside the scene box, linear in 1/t beyond it
(mip-NeRF 360's spacing for the contracted far field).

``occupancy`` sampling (the fast model): the field's own density grid is read, without
gradient, at the candidate bins (``occupancy_lookup="exact"``: trilinear, the current density,
one cheap forward pass over a 1-channel grid; ``"grid"``: nearest vertex of a cached, max-pooled
copy, a plain gather, but stale and inflated, which made training worse), turned into NeRF
weights (transmittance-aware, so surfaces behind an opaque one get few samples), mixed with a
uniform share for exploration (all uniform at first, annealed while the geometry forms), and S
intervals are drawn from that histogram by the inverse CDF (stratified, jittered in training):
many short intervals around surfaces, a few long ones in empty water. This is proposal sampling
where the proposal is the field itself, so it needs no proposal network and no
histogram loss.

``hierarchical`` sampling (paper baseline): stratified coarse intervals, then fine edges drawn
from the coarse rendering weights, merged with the coarse ones (NeRF).
"""

from __future__ import annotations

import torch
from torch import Tensor


def candidate_edges(near: Tensor, far: Tensor, t_split: Tensor, n_linear: int,
                    n_disparity: int) -> Tensor:
    """Bin edges (R, n_linear + n_disparity + 1): linear on [near, t_split], 1/t on [t_split, far].

    near, far, t_split (R,); t_split is clamped to [near, far].
    """
    near = near.clamp_min(1e-6)
    far = torch.maximum(far, near)
    t_split = torch.minimum(torch.maximum(t_split, near), far)
    s_lin = torch.linspace(0.0, 1.0, n_linear + 1, device=near.device, dtype=near.dtype)
    linear = near[:, None] + (t_split - near)[:, None] * s_lin
    if n_disparity == 0:
        return linear
    s_disp = torch.linspace(0.0, 1.0, n_disparity + 1, device=near.device, dtype=near.dtype)[1:]
    inv_split, inv_far = 1.0 / t_split, 1.0 / far
    disparity = 1.0 / (inv_split[:, None] + (inv_far - inv_split)[:, None] * s_disp)
    return torch.cat([linear, disparity], dim=-1)


def normalised_distance(t: Tensor, near: Tensor, far: Tensor, t_split: Tensor,
                        linear_share: float) -> Tensor:
    """The ray coordinate in which ``candidate_edges`` is uniform, in [0, 1]: linear up to
    t_split (reaching ``linear_share``), then linear in 1/t. t (R, K); near, far, t_split (R,)."""
    near = near.clamp_min(1e-6)[:, None]
    far = torch.maximum(far[:, None], near)
    t_split = torch.minimum(torch.maximum(t_split[:, None], near), far)
    lin = (t - near) / (t_split - near).clamp_min(1e-9) * linear_share
    inv_split, inv_far = 1.0 / t_split, 1.0 / far
    disp = linear_share + (inv_split - 1.0 / t.clamp_min(1e-9)) / (inv_split - inv_far).clamp_min(
        1e-12) * (1.0 - linear_share)
    return torch.where(t <= t_split, lin, disp).clamp(0.0, 1.0)


def stratified_edges(edges: Tensor, jitter: Tensor | None) -> Tensor:
    """Interior edges moved by jitter (R, N-1) in [0, 1) within +-half a bin; ends kept."""
    if jitter is None or edges.shape[1] <= 2:
        return edges
    mids = 0.5 * (edges[:, 1:] + edges[:, :-1])  # (R, N)
    interior = mids[:, :-1] + (mids[:, 1:] - mids[:, :-1]) * jitter
    return torch.cat([edges[:, :1], interior, edges[:, -1:]], dim=-1)


def lookup_nearest(volume: Tensor, g: Tensor) -> Tensor:
    """Values of a (1, 1, D, H, W) volume at the vertices nearest to grid coords g (..., 3)."""
    depth, height, width = volume.shape[-3:]
    size = torch.tensor([width, height, depth], device=g.device, dtype=g.dtype)
    index = torch.round((g.clamp(-1.0, 1.0) + 1.0) * 0.5 * (size - 1)).long()
    flat = (index[..., 2] * height + index[..., 1]) * width + index[..., 0]
    return volume.reshape(-1)[flat]


def sample_pdf(edges: Tensor, weights: Tensor, n_samples: int, uniform_mix: float,
               jitter: Tensor | None) -> Tensor:
    """Inverse-CDF sampling of ``n_samples`` contiguous intervals from a histogram.

    edges (R, N+1), weights (R, N) >= 0; a ``uniform_mix`` share of the mass is spread evenly
    over the bins of positive length (exploration, and rays with no weight at all). jitter
    (R, n_samples - 1) in [0, 1) or None (deterministic, bin centres). Returns (R, n_samples+1)
    from edges[:, 0] to edges[:, -1], non-decreasing.
    """
    lengths = edges[:, 1:] - edges[:, :-1]
    valid = (lengths > 0).to(weights.dtype)
    weights = weights * valid
    total = weights.sum(dim=-1, keepdim=True)
    n_valid = valid.sum(dim=-1, keepdim=True).clamp_min(1.0)
    has_weight = total > 1e-12
    pdf = torch.where(has_weight, (1.0 - uniform_mix) * weights / total.clamp_min(1e-12), 0.0) \
        + torch.where(has_weight, uniform_mix, 1.0) * valid / n_valid
    pdf = pdf + 1e-12  # rays of zero length: keep the division safe
    cdf = torch.cumsum(pdf, dim=-1)
    cdf = torch.cat([torch.zeros_like(cdf[:, :1]), cdf / cdf[:, -1:]], dim=-1)
    u = torch.linspace(0.0, 1.0, n_samples + 1, device=edges.device, dtype=edges.dtype)
    u = u.expand(edges.shape[0], n_samples + 1)
    if jitter is not None and n_samples > 1:
        u = torch.cat([u[:, :1], u[:, 1:-1] + (jitter - 0.5) / n_samples, u[:, -1:]], dim=-1)
    u = u.contiguous()
    index = (torch.searchsorted(cdf, u, right=True) - 1).clamp(0, edges.shape[1] - 2)
    c0, c1 = cdf.gather(1, index), cdf.gather(1, index + 1)
    e0, e1 = edges.gather(1, index), edges.gather(1, index + 1)
    frac = ((u - c0) / (c1 - c0).clamp_min(1e-12)).clamp(0.0, 1.0)
    t = e0 + frac * (e1 - e0)
    t = torch.cat([edges[:, :1], t[:, 1:-1], edges[:, -1:]], dim=-1)
    return torch.cummax(t, dim=-1).values


def occupancy_weights(edges: Tensor, density: Tensor) -> Tensor:
    """NeRF weights (R, N) of bins with the given densities (R, N) (transmittance-aware).

    For sample placement only (no gradient): w_i = T_i - T_{i+1}, a few cheap operations.
    """
    tau = torch.cumsum(density * (edges[:, 1:] - edges[:, :-1]), dim=-1)
    transmittance = torch.exp(-tau)
    previous = torch.cat([torch.ones_like(transmittance[:, :1]), transmittance[:, :-1]], dim=-1)
    return previous - transmittance


def merge_edges(a: Tensor, b: Tensor) -> Tensor:
    """Sorted union of two edge sets with the same ends: (R, Na) + (R, Nb) -> (R, Na + Nb - 2)."""
    merged, _ = torch.sort(torch.cat([a, b[:, 1:-1]], dim=-1), dim=-1)
    return merged
