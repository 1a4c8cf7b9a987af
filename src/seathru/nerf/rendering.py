"""Medium-aware volume rendering for SeaThru-NeRF (Levy et al., CVPR 2023).

Along a ray, ``t`` is the Euclidean distance from the camera centre (unit ray directions). The
object density ``sigma_obj`` and colour ``c_obj`` are piecewise constant on contiguous intervals
``[s_i, s_{i+1})`` given by ``t_edges`` of shape (R, S+1). Per ray and RGB channel the water has
an attenuation ``sigma_attn``, a backscatter coefficient ``sigma_bs`` and a colour ``c_med``. The
SeaThru continuous model is::

    C = int_0^inf T(t) exp(-sigma_attn t) sigma_obj(t) c_obj(t) dt          (direct)
      + int_0^inf T(t) exp(-sigma_bs t) sigma_bs c_med dt                   (backscatter)
    T(t) = exp(-int_0^t sigma_obj)                                          (object transmittance)

``render_seathru(method="exact")`` integrates every interval in closed form, so the result is
exact for piecewise-constant fields whatever the sample count; water before the first edge
(``water_before``) and after the last edge (``water_after``) are closed-form terms too, so a ray
through empty water needs no samples at all (S = 0 is allowed). ``method="paper"`` is the
paper's discretisation (object weight T_i exp(-sigma_attn s_i) (1 - exp(-sigma_i d_i)), medium
weight T_i exp(-sigma_bs s_i) (1 - exp(-sigma_bs d_i))), which converges to the exact form as
intervals shrink. The water before/after flags apply to both methods; pass
``water_before=False, water_after=False`` for the paper's rendering with water only between the
samples.

Water after the last edge: with ``t_far=None`` (default) the water extends to infinity and
contributes ``T_S c_med exp(-sigma_bs s_S)`` when ``sigma_bs > 0``, and exactly 0 when
``sigma_bs == 0`` (infinitely deep water saturates to ``c_med`` for any positive backscatter, so
the limit sigma_bs -> 0 is discontinuous; this is the physics, kept explicit). With a finite
``t_far`` the water stops there and the tail ``T_S c_med (exp(-sigma_bs s_S) -
exp(-sigma_bs t_far))`` is continuous in ``sigma_bs``; edges are assumed to be <= ``t_far`` (the
tail length is clamped at 0 otherwise).

``render_general`` is the appendix's general form with per-interval object and medium densities
and colours, sharing one total transmittance.

Outputs: ``restored`` is J = sum_i w_i c_i (the object without water, black where nothing is
hit; not normalised by the opacity). ``depth_mean`` = sum_i w_i mid_i / opacity (the last edge
where opacity <= 1e-12); ``depth_median`` is where the object opacity 1 - T(t) reaches 0.5,
solved exactly inside the crossing interval (T is exponential there), the last edge if it never
does. The colour is bounded by max(c_obj, c_med) whenever sigma_attn >= sigma_bs per channel (the
weights then sum to <= 1); with sigma_attn < sigma_bs the SeaThru model itself can exceed it
(e.g. J exp(-sigma_attn z) + c_med (1 - exp(-sigma_bs z)) with sigma_attn = 0).

Numerics: transmittance is exp(-cumulative optical depth) (log space, never products); every
``(1 - exp(-x d)) / x`` goes through one stable helper (expm1, with a Taylor series and a safe
denominator below ``x d < 0.1``, and 1 - exp(-y) differentiated as exp(-y) rather than
autograd's expm1 + 1) so values and gradients stay finite, and relatively accurate, for
densities from 0 and 1e-30 up to 1e8, intervals of length 0 to 1e4 and distances up to 1e4.
With zero medium parameters the same code yields plain NeRF exactly: ``rgb == direct ==
restored`` bit for bit and ``backscatter == 0``. Nothing is clamped in the normal range.

Dtypes and devices: the code is device-agnostic (CPU/CUDA). float32 and float64 are computed in
their own precision (mixed inputs promote). float16/bfloat16 inputs are upcast and computed in
float32, and the outputs are float32 (their exponent range and 8-11 bit mantissas cannot hold
the transmittance products or the 1e-5 accuracy); gradients flow back to the half-precision
inputs. Non-floating inputs raise TypeError. Input values (non-negative densities,
non-decreasing edges) are preconditions and are not checked, to avoid device synchronisation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = [
    "RayRender",
    "render_seathru",
    "render_general",
    "one_minus_exp_over",
    "nerf_weights",
]

# Below this optical thickness y = x*d a Taylor series replaces expm1(-y) / x: that division (and
# its gradient -num/x^2) is unsafe as x -> 0, and its autograd gradient in x loses digits to
# cancellation ~ 2/y for small y (40x at y = 0.1; 2000x at 1e-3, too much for float32).
_SERIES_LIMIT = 0.1
_LN2 = math.log(2.0)
# Rays whose total object opacity is below this get the far depth (last edge) as depth_mean.
_OPACITY_FLOOR = 1e-12


@dataclass
class RayRender:
    """Per-ray rendering outputs (every field a tensor; R rays, S intervals)."""

    rgb: Tensor            # (R, 3) full colour with water: direct + backscatter
    direct: Tensor         # (R, 3) attenuated object component
    backscatter: Tensor    # (R, 3) water component
    restored: Tensor       # (R, 3) object colour without water: sum_i w_i c_i
    direct_weights: Tensor  # (R, S, 3) each interval's share of its object colour in direct
    weights: Tensor        # (R, S) object weights w_i = T_i (1 - exp(-sigma_i d_i))
    transmittance: Tensor  # (R, S+1) object transmittance at each edge, T_0 = 1
    opacity: Tensor        # (R,) sum_i w_i
    depth_mean: Tensor     # (R,) sum_i w_i mid_i / opacity; last edge where opacity ~ 0
    depth_median: Tensor   # (R,) where object opacity 1 - T(t) crosses 0.5; last edge if never

    @property
    def direct_share(self) -> Tensor:
        """(R, 3) what of a uniform object colour c reaches the camera: direct =
        direct_share * c, restored = opacity * c (summed only when asked: inference)."""
        return self.direct_weights.sum(dim=1)


class _OneMinusExpNeg(torch.autograd.Function):
    """1 - exp(-y) via expm1, with the derivative exp(-y) evaluated directly: autograd's expm1
    backward forms expm1(-y) + 1, which cancels to a relative error ~u / exp(-y) for large y."""

    @staticmethod
    def forward(ctx, y: Tensor) -> Tensor:
        ctx.save_for_backward(y)
        return -torch.expm1(-y)

    @staticmethod
    def backward(ctx, grad: Tensor) -> Tensor:
        (y,) = ctx.saved_tensors
        return grad * torch.exp(-y)


def _one_minus_exp_neg(y: Tensor) -> Tensor:
    """1 - exp(-y), accurate in value and gradient for all y."""
    return _OneMinusExpNeg.apply(y)


def _series_one_minus_exp_over_y(y: Tensor) -> Tensor:
    """(1 - exp(-y)) / y = sum_k (-y)^k / (k+1)! for |y| <= _SERIES_LIMIT, Horner form.

    6 terms reach float32 rounding at |y| = 0.1 (truncation 1.4e-8), 10 terms float64 (2.8e-16).
    """
    terms = 6 if torch.finfo(y.dtype).eps > 1e-10 else 10
    one = torch.ones((), dtype=y.dtype, device=y.device)
    result = torch.addcmul(one, y, one, value=-1.0 / terms)
    for k in range(terms - 2, 0, -1):
        result = torch.addcmul(one, y, result, value=-1.0 / (k + 1))
    return result


def one_minus_exp_over(x: Tensor, d: Tensor) -> Tensor:
    """``(1 - exp(-x d)) / x``, stable, tending to ``d`` as ``x -> 0`` (values and gradients).

    ``x`` and ``d`` broadcast together. Exact at x = 0, finite gradients everywhere on x >= 0.
    """
    x, d = torch.as_tensor(x), torch.as_tensor(d)
    return _absorbed_fraction(torch.ones((), dtype=x.dtype, device=x.device), x, d, total_given=True)


def _absorbed_fraction(a: Tensor, b: Tensor, d: Tensor, total_given: bool = False) -> Tensor:
    """``a / (a+b) * (1 - exp(-(a+b) d))`` = a * one_minus_exp_over(a+b, d), stable.

    The share of the light that component ``a`` (a density) contributes over an interval of
    length d in which the total density is a+b (``total_given``: b already is the total). With
    b = 0 it is the same expression as the NeRF alpha, which is what makes "medium off" plain
    NeRF bit for bit.
    """
    x = b if total_given else a + b
    y = x * d
    small = y.abs() < _SERIES_LIMIT
    # Both torch.where branches are differentiated: each must stay finite where it is not used.
    # The series gets |y| clamped to its range; the closed form a safe denominator (expm1 itself
    # is harmless for small y).
    series = a * d * _series_one_minus_exp_over_y(y.clamp(-_SERIES_LIMIT, _SERIES_LIMIT))
    closed = a / torch.where(small, 1.0, x) * _one_minus_exp_neg(y)
    return torch.where(small, series, closed)


def _optical_depth(sigma: Tensor, deltas: Tensor) -> Tensor:
    """Cumulative optical depth at each edge (..., S+1), starting at 0."""
    return torch.nn.functional.pad(torch.cumsum(sigma * deltas, dim=-1), (1, 0))


def _nerf(sigma: Tensor, deltas: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    tau = _optical_depth(sigma, deltas)
    transmittance = torch.exp(-tau)
    alpha = _absorbed_fraction(sigma, torch.zeros_like(sigma), deltas)
    return transmittance[..., :-1] * alpha, transmittance, tau


def nerf_weights(sigma: Tensor, deltas: Tensor) -> tuple[Tensor, Tensor]:
    """Plain NeRF weights for piecewise-constant density.

    sigma, deltas: (..., S). Returns ``(weights (..., S), transmittance (..., S+1))`` with
    ``T_i = exp(-sum_{j<i} sigma_j delta_j)`` (T_0 = 1) and ``w_i = T_i (1 - exp(-sigma_i
    delta_i))``.
    """
    dtype = _compute_dtype(sigma, deltas)
    sigma, deltas = sigma.to(dtype), deltas.to(dtype)
    weights, transmittance, _ = _nerf(sigma, deltas)
    return weights, transmittance


def _compute_dtype(*values) -> torch.dtype:
    dtype = None
    for value in values:
        if isinstance(value, Tensor):
            if not value.is_floating_point():
                raise TypeError(f"rendering inputs must be floating point tensors, got {value.dtype}")
            dtype = value.dtype if dtype is None else torch.promote_types(dtype, value.dtype)
    if dtype is None:
        dtype = torch.get_default_dtype()
    if dtype in (torch.float16, torch.bfloat16):
        dtype = torch.float32
    return dtype


def _per_ray_rgb(value, name: str, rays: int, dtype: torch.dtype, device) -> Tensor:
    tensor = torch.as_tensor(value, device=device).to(dtype)
    try:
        return torch.broadcast_to(tensor, (rays, 3))
    except RuntimeError as error:
        raise ValueError(f"{name} of shape {tuple(tensor.shape)} does not broadcast to ({rays}, 3)") from error


def _check_fields(sigma_obj: Tensor, rgb_obj: Tensor, t_edges: Tensor) -> tuple[int, int]:
    if sigma_obj.dim() != 2:
        raise ValueError(f"sigma_obj must be (R, S), got shape {tuple(sigma_obj.shape)}")
    rays, samples = sigma_obj.shape
    if tuple(rgb_obj.shape) != (rays, samples, 3):
        raise ValueError(f"rgb_obj must be (R, S, 3) = ({rays}, {samples}, 3), got {tuple(rgb_obj.shape)}")
    if tuple(t_edges.shape) != (rays, samples + 1):
        raise ValueError(f"t_edges must be (R, S+1) = ({rays}, {samples + 1}), got {tuple(t_edges.shape)}")
    return rays, samples


def _median_depth(tau: Tensor, sigma: Tensor, t_edges: Tensor) -> Tensor:
    """Distance where 1 - T(t) crosses 0.5, i.e. the optical depth crosses ln 2 (exact inside the
    interval, T being exponential there); the last edge where it never does."""
    far = t_edges[:, -1]
    samples = sigma.shape[1]
    if samples == 0:
        return far
    # tau is non-decreasing, tau_0 = 0 <= ln 2, so the crossing interval is count(tau <= ln2) - 1.
    count = (tau <= _LN2).sum(dim=-1, keepdim=True)
    crosses = count <= samples
    index = torch.clamp(count - 1, max=samples - 1)
    tau_i = torch.gather(tau, 1, index)
    sigma_i = torch.gather(sigma, 1, index)
    start = torch.gather(t_edges, 1, index)
    length = torch.gather(t_edges, 1, index + 1) - start
    # Crossing implies sigma_i * d_i > 0, so sigma_i > 0 there; elsewhere keep the division safe.
    sigma_safe = torch.where(crosses, sigma_i, torch.ones_like(sigma_i))
    offset = torch.minimum((_LN2 - tau_i) / sigma_safe, length)
    return torch.where(crosses, start + offset, far[:, None]).squeeze(1)


def render_seathru(sigma_obj: Tensor, rgb_obj: Tensor, t_edges: Tensor, sigma_attn, sigma_bs, c_med, *,
                   method: str = "exact", water_before: bool = True, water_after: bool = True,
                   t_far: float | None = None) -> RayRender:
    """Render R rays through water with piecewise-constant object fields.

    sigma_obj (R, S) >= 0; rgb_obj (R, S, 3); t_edges (R, S+1) non-decreasing, >= 0 (S may be 0);
    sigma_attn, sigma_bs, c_med: tensors or numbers broadcastable to (R, 3).
    method: "exact" (closed form per interval) or "paper" (the paper's discretisation).
    water_before / water_after: include the water in [0, s_0) / after s_S (closed form).
    t_far: where the water ends (None = infinity; see the module docstring).
    """
    if method not in ("exact", "paper"):
        raise ValueError(f"method must be 'exact' or 'paper', got {method!r}")
    dtype = _compute_dtype(sigma_obj, rgb_obj, t_edges, sigma_attn, sigma_bs, c_med)
    device = sigma_obj.device
    sigma_obj, rgb_obj, t_edges = sigma_obj.to(dtype), rgb_obj.to(dtype), t_edges.to(dtype)
    rays, _ = _check_fields(sigma_obj, rgb_obj, t_edges)
    attn = _per_ray_rgb(sigma_attn, "sigma_attn", rays, dtype, device)
    bs = _per_ray_rgb(sigma_bs, "sigma_bs", rays, dtype, device)
    medium_rgb = _per_ray_rgb(c_med, "c_med", rays, dtype, device)

    starts = t_edges[:, :-1]
    deltas = t_edges[:, 1:] - starts
    weights, transmittance, tau = _nerf(sigma_obj, deltas)

    sigma3, start3, delta3 = sigma_obj[..., None], starts[..., None], deltas[..., None]
    neg_tau3 = -tau[:, :-1, None]
    attn3, bs3 = attn[:, None, :], bs[:, None, :]
    # Transmittance through objects and water combined in log space: one exp per term.
    direct_reach = torch.exp(torch.addcmul(neg_tau3, attn3, start3, value=-1.0))   # (R, S, 3)
    medium_reach = torch.exp(torch.addcmul(neg_tau3, bs3, start3, value=-1.0))
    if method == "exact":
        direct_weights = direct_reach * _absorbed_fraction(sigma3, attn3, delta3)
        medium_weights = medium_reach * _absorbed_fraction(bs3, sigma3, delta3)
    else:
        alpha = _absorbed_fraction(sigma_obj, torch.zeros_like(sigma_obj), deltas)
        direct_weights = direct_reach * alpha[..., None]
        medium_weights = medium_reach * _absorbed_fraction(bs3, torch.zeros_like(bs3), delta3)
    direct = (direct_weights * rgb_obj).sum(dim=1)

    medium_share = medium_weights.sum(dim=1)            # (R, 3)
    if water_before:
        medium_share = medium_share + _one_minus_exp_neg(bs * t_edges[:, :1])
    if water_after:
        last_edge = t_edges[:, -1:]
        reach_last = torch.exp(-(tau[:, -1:] + bs * last_edge))
        if t_far is None or math.isinf(float(t_far)):
            tail = torch.where(bs > 0, reach_last, torch.zeros_like(reach_last))
        else:
            water_left = torch.clamp(torch.as_tensor(t_far, dtype=dtype, device=device) - last_edge, min=0)
            tail = reach_last * _one_minus_exp_neg(bs * water_left)
        medium_share = medium_share + tail
    backscatter = medium_share * medium_rgb

    restored = (weights[..., None] * rgb_obj).sum(dim=1)
    opacity = weights.sum(dim=-1)
    far = t_edges[:, -1]
    visible = opacity > _OPACITY_FLOOR
    midpoints = starts + 0.5 * deltas
    depth_mean = torch.where(
        visible, (weights * midpoints).sum(dim=-1) / torch.where(visible, opacity, torch.ones_like(opacity)), far)
    return RayRender(
        rgb=direct + backscatter,
        direct=direct,
        backscatter=backscatter,
        restored=restored,
        direct_weights=direct_weights,
        weights=weights,
        transmittance=transmittance,
        opacity=opacity,
        depth_mean=depth_mean,
        depth_median=_median_depth(tau, sigma_obj, t_edges),
    )


def render_general(sigma_obj: Tensor, rgb_obj: Tensor, sigma_med: Tensor, rgb_med: Tensor,
                   t_edges: Tensor) -> Tensor:
    """The appendix's general form: per-interval object and medium densities and colours.

    C = sum_i T(s_i) (1 - exp(-(so+sm) d_i)) (so co + sm cm) / (so+sm), with T the total
    (object + medium) transmittance, finite as so+sm -> 0.
    sigma_obj (R, S); rgb_obj (R, S, 3); sigma_med (R, S) or (R, S, 3) per channel;
    rgb_med (R, S, 3); t_edges (R, S+1). Returns (R, 3).
    """
    dtype = _compute_dtype(sigma_obj, rgb_obj, sigma_med, rgb_med, t_edges)
    sigma_obj, rgb_obj, t_edges = sigma_obj.to(dtype), rgb_obj.to(dtype), t_edges.to(dtype)
    sigma_med, rgb_med = sigma_med.to(dtype), rgb_med.to(dtype)
    rays, samples = _check_fields(sigma_obj, rgb_obj, t_edges)
    if tuple(rgb_med.shape) != (rays, samples, 3):
        raise ValueError(f"rgb_med must be (R, S, 3) = ({rays}, {samples}, 3), got {tuple(rgb_med.shape)}")
    if tuple(sigma_med.shape) == (rays, samples):
        sigma_med = sigma_med[..., None]
    elif tuple(sigma_med.shape) != (rays, samples, 3):
        raise ValueError(f"sigma_med must be (R, S) or (R, S, 3), got {tuple(sigma_med.shape)}")
    sigma_obj = sigma_obj[..., None]
    deltas = (t_edges[:, 1:] - t_edges[:, :-1])[..., None]
    # Optical depth per channel along the interval axis (dim 1).
    total = (sigma_obj + sigma_med) * deltas
    tau = torch.nn.functional.pad(torch.cumsum(total, dim=1), (0, 0, 1, 0))[:, :-1]
    reach = torch.exp(-tau)
    colour = (_absorbed_fraction(sigma_obj, sigma_med, deltas) * rgb_obj
              + _absorbed_fraction(sigma_med, sigma_obj, deltas) * rgb_med)
    return (reach * colour).sum(dim=1)
