"""Tests for seathru.nerf.rendering against independent float64 references.

The references here never reuse the module's closed forms: the continuous integrals are evaluated
by composite Gauss-Legendre quadrature (16 nodes per piece) on sub-pieces graded geometrically
from each interval start (so that decay lengths down to 1e-8 are resolved), in local coordinates
u = t - s_i; the paper discretisation is re-implemented with products of per-interval factors;
the median depth is found by bisection on the optical depth.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from seathru.nerf.rendering import (
    RayRender,
    nerf_weights,
    one_minus_exp_over,
    render_general,
    render_seathru,
)

torch.set_num_threads(1)

LN2 = math.log(2.0)
GL_NODES, GL_WEIGHTS = np.polynomial.legendre.leggauss(16)
FIELDS = ("rgb", "direct", "backscatter", "restored", "direct_share", "weights", "transmittance",
          "opacity", "depth_mean", "depth_median")
HYPOTHESIS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# ----------------------------------------------------------------------------------------------
# float64 references
# ----------------------------------------------------------------------------------------------

def graded_offsets(length: float, rate: float) -> np.ndarray:
    """Sub-piece edges in [0, length]: first piece ~0.05 decay lengths, then doubling."""
    if length <= 0.0:
        return np.array([0.0, 0.0])
    if rate * length <= 0.05:
        return np.linspace(0.0, length, 3)
    first = 0.05 / rate
    edges = [0.0, first]
    while edges[-1] < length:
        edges.append(min(length, 2.0 * edges[-1]))
    return np.array(edges)


def quadrature(integrand, length: float, rate: float) -> float:
    """int_0^length integrand(u) du, integrand vectorised over u."""
    edges = graded_offsets(length, rate)
    lo, hi = edges[:-1], edges[1:]
    half = 0.5 * (hi - lo)
    nodes = (0.5 * (lo + hi))[:, None] + half[:, None] * GL_NODES[None, :]
    return float(np.sum(half[:, None] * GL_WEIGHTS[None, :] * integrand(nodes)))


def reference_seathru(sigma, rgb, edges, attn, bs, cmed, water_before=True, water_after=True,
                      t_far=None):
    """Continuous SeaThru integral per ray and channel by quadrature (float64 numpy).

    Returns a dict of the fields of RayRender (float64 arrays)."""
    rays, samples = sigma.shape
    out = {name: np.zeros((rays, 3)) for name in ("direct", "backscatter", "restored",
                                                  "direct_share")}
    out["weights"] = np.zeros((rays, samples))
    out["transmittance"] = np.zeros((rays, samples + 1))
    for r in range(rays):
        starts, lengths = edges[r, :-1], np.diff(edges[r])
        optical = np.concatenate([[0.0], np.cumsum(sigma[r] * lengths)])
        out["transmittance"][r] = np.exp(-optical)
        out["weights"][r] = np.exp(-optical[:-1]) * -np.expm1(-sigma[r] * lengths)
        out["restored"][r] = out["weights"][r] @ rgb[r]
        for c in range(3):
            a, b, m = attn[r, c], bs[r, c], cmed[r, c]
            direct = medium = share = 0.0
            for i in range(samples):
                s, sg, tau = starts[i], sigma[r, i], optical[i]
                reach = quadrature(lambda u: np.exp(-tau - sg * u - a * (s + u)) * sg,
                                   lengths[i], sg + a)
                direct += reach * rgb[r, i, c]
                share += reach
                medium += quadrature(lambda u: np.exp(-tau - sg * u - b * (s + u)) * b * m,
                                     lengths[i], sg + b)
            if water_before:
                medium += quadrature(lambda u: np.exp(-b * u) * b * m, edges[r, 0], b)
            if water_after and b > 0:
                last, tau_last = edges[r, -1], optical[-1]
                span = 60.0 / b if t_far is None else max(t_far - last, 0.0)
                medium += quadrature(lambda u: np.exp(-tau_last - b * (last + u)) * b * m, span, b)
            out["direct"][r, c], out["backscatter"][r, c] = direct, medium
            out["direct_share"][r, c] = share
    out["rgb"] = out["direct"] + out["backscatter"]
    out["opacity"] = out["weights"].sum(axis=1)
    mids = 0.5 * (edges[:, 1:] + edges[:, :-1])
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = (out["weights"] * mids).sum(axis=1) / out["opacity"]
    out["depth_mean"] = np.where(out["opacity"] > 1e-12, mean, edges[:, -1])
    out["depth_median"] = np.array([median_by_bisection(sigma[r], edges[r]) for r in range(rays)])
    return out


def optical_depth_at(t: float, sigma_row, edge_row) -> float:
    lengths = np.clip(t - edge_row[:-1], 0.0, np.diff(edge_row))
    return float(np.sum(sigma_row * lengths))


def median_by_bisection(sigma_row, edge_row) -> float:
    if optical_depth_at(edge_row[-1], sigma_row, edge_row) <= LN2:
        return float(edge_row[-1])
    lo, hi = float(edge_row[0]), float(edge_row[-1])
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if optical_depth_at(mid, sigma_row, edge_row) > LN2:
            hi = mid
        else:
            lo = mid
    return 0.5 * (lo + hi)


def reference_general(so, co, sm, cm, edges):
    """General form: int T(t) (so co + sm cm) dt with T the total transmittance (quadrature)."""
    rays, samples = so.shape
    sm = np.broadcast_to(sm[..., None], (rays, samples, 3)) if sm.ndim == 2 else sm
    out = np.zeros((rays, 3))
    for r in range(rays):
        lengths = np.diff(edges[r])
        for c in range(3):
            tau = 0.0
            for i in range(samples):
                x = so[r, i] + sm[r, i, c]
                emission = so[r, i] * co[r, i, c] + sm[r, i, c] * cm[r, i, c]
                out[r, c] += quadrature(lambda u: np.exp(-tau - x * u) * emission, lengths[i], x)
                tau += x * lengths[i]
    return out


def reference_paper(sigma, rgb, edges, attn, bs, cmed, water_before, water_after, t_far=None):
    """The paper's discrete sum, products of per-interval factors, float64."""
    rays, samples = sigma.shape
    rgb_out = np.zeros((rays, 3))
    for r in range(rays):
        starts, lengths = edges[r, :-1], np.diff(edges[r])
        transmit = 1.0
        for i in range(samples):
            alpha = 1.0 - np.exp(-sigma[r, i] * lengths[i])
            rgb_out[r] += transmit * np.exp(-attn[r] * starts[i]) * alpha * rgb[r, i]
            rgb_out[r] += transmit * np.exp(-bs[r] * starts[i]) * (1.0 - np.exp(-bs[r] * lengths[i])) * cmed[r]
            transmit *= 1.0 - alpha
        if water_before:
            rgb_out[r] += cmed[r] * (1.0 - np.exp(-bs[r] * edges[r, 0]))
        if water_after:
            far = np.exp(-bs[r] * edges[r, -1])
            if t_far is not None:
                far = far - np.exp(-bs[r] * t_far)
            rgb_out[r] += transmit * cmed[r] * np.where(bs[r] > 0, far, 0.0)
    return rgb_out


# ----------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------

def to64(tensor: torch.Tensor) -> np.ndarray:
    return tensor.detach().to(torch.float64).cpu().numpy()


def assert_matches(actual, reference, name="", rel=1e-5, small=0.1, absolute=1e-6, extra_abs=None):
    """Relative error <= rel, or absolute <= absolute where |reference| < small."""
    actual = to64(actual) if isinstance(actual, torch.Tensor) else np.asarray(actual)
    reference = np.broadcast_to(np.asarray(reference, dtype=np.float64), actual.shape)
    assert np.all(np.isfinite(actual)), f"{name}: non-finite values {actual}"
    error = np.abs(actual - reference)
    ok = (error <= rel * np.abs(reference)) | ((np.abs(reference) < small) & (error <= absolute))
    if extra_abs is not None:
        ok |= error <= extra_abs
    assert ok.all(), (f"{name}: max error {error[~ok].max():.3g} at {np.argwhere(~ok)[:3].tolist()}; "
                      f"actual {actual[~ok][:3]}, reference {reference[~ok][:3]}")


def grads_of(outputs, inputs):
    loss = sum((o.double() * (k + 1.0)).sum() for k, o in enumerate(outputs))
    return torch.autograd.grad(loss, inputs, allow_unused=True)


def assert_finite_grads(outputs, inputs):
    for g in grads_of(outputs, inputs):
        assert g is None or torch.isfinite(g).all(), f"non-finite gradient {g}"


def render_fields(render: RayRender):
    return [getattr(render, name) for name in FIELDS]


def median_tolerance(sigma, edges):
    """Float32 conditioning of the median: a rounding error of the optical depth before the
    crossing interval moves the depth by that error / sigma of the crossing interval."""
    tolerance = np.zeros(sigma.shape[0])
    for r in range(sigma.shape[0]):
        optical = np.concatenate([[0.0], np.cumsum(sigma[r] * np.diff(edges[r]))])
        crossing = np.nonzero((optical[:-1] <= LN2) & (optical[1:] > LN2))[0]
        if crossing.size:
            i = crossing[0]
            tolerance[r] = 16 * 6e-8 * (optical[i] + LN2 + i) / sigma[r, i]
    return tolerance


# ----------------------------------------------------------------------------------------------
# strategies
# ----------------------------------------------------------------------------------------------

DENSITY = st.one_of(st.just(0.0), st.floats(1e-30, 1e-3), st.floats(1e-3, 50.0), st.floats(50.0, 1e8))
LENGTH = st.one_of(st.just(0.0), st.floats(1e-4, 3.0), st.floats(3.0, 1e4))
MEDIUM = st.one_of(st.just(0.0), st.floats(1e-6, 1e-2), st.floats(1e-2, 3.0))
UNIT = st.floats(0.0, 1.0)


@st.composite
def scenes(draw, max_rays=3, max_samples=8):
    rays = draw(st.integers(1, max_rays))
    samples = draw(st.integers(0, max_samples))
    flat = lambda strat, n: np.array(draw(st.lists(strat, min_size=n, max_size=n)), dtype=np.float64)
    sigma = flat(DENSITY, rays * samples).reshape(rays, samples)
    rgb = flat(UNIT, rays * samples * 3).reshape(rays, samples, 3)
    starts = flat(st.one_of(st.just(0.0), st.floats(0.0, 20.0)), rays)
    lengths = flat(LENGTH, rays * samples).reshape(rays, samples)
    edges = np.concatenate([starts[:, None], starts[:, None] + np.cumsum(lengths, axis=1)], axis=1)
    attn = flat(MEDIUM, rays * 3).reshape(rays, 3)
    bs = flat(MEDIUM, rays * 3).reshape(rays, 3)
    cmed = flat(UNIT, rays * 3).reshape(rays, 3)
    # Round to float32 once: the references see exactly the values the renderer sees.
    f32 = lambda a: a.astype(np.float32).astype(np.float64)
    return tuple(f32(a) for a in (sigma, rgb, edges, attn, bs, cmed))


def tensors(*arrays, dtype=torch.float32, grad=True):
    return [torch.tensor(a, dtype=dtype, requires_grad=grad) for a in arrays]


# ----------------------------------------------------------------------------------------------
# one_minus_exp_over
# ----------------------------------------------------------------------------------------------

@HYPOTHESIS
@given(x=st.one_of(st.just(0.0), st.floats(1e-30, 1e-6), st.floats(1e-6, 1.0), st.floats(1.0, 2e8)),
       d=st.one_of(st.just(0.0), st.floats(1e-20, 1e-3), st.floats(1e-3, 1e4)))
def test_one_minus_exp_over_value_and_gradient(x, d):
    x32, d32 = np.float32(x), np.float32(d)
    xs, ds = torch.tensor(x32, requires_grad=True), torch.tensor(d32, requires_grad=True)
    value = one_minus_exp_over(xs, ds)
    gx, gd = torch.autograd.grad(value, (xs, ds))
    x64, d64 = float(x32), float(d32)
    y = x64 * d64
    expected = d64 if x64 == 0 else -math.expm1(-y) / x64
    # d/dx = -d^2 (1/2 - y/3 + y^2/8 - ...) near 0, (y e^-y - (1 - e^-y)) / x^2 otherwise.
    if y < 1e-2:
        expected_gx = -d64 * d64 * (0.5 - y / 3 + y * y / 8 - y ** 3 / 30)
    else:
        expected_gx = (y * math.exp(-y) + math.expm1(-y)) / (x64 * x64)
    # float32 rounding of y = x d alone moves exp(-y) by y * 6e-8 relative: allow for it.
    conditioning = 1.2e-7 * y
    assert_matches(value, expected, "value", rel=2e-6, small=0.0)
    # autograd forms (1/x) exp(-y) before multiplying by x: for large x that product can be a
    # float32 subnormal, whose absolute rounding (half of 1.4e-45) is then multiplied by x
    assert_matches(gd, math.exp(-y), "d/dd", rel=2e-6 + conditioning, small=0.0,
                   extra_abs=1e-44 + 1e-45 * x64)
    assert_matches(gx, expected_gx, "d/dx", rel=1e-5 + conditioning, small=0.0, extra_abs=1e-6 * d64 * d64 + 1e-30)


def test_one_minus_exp_over_limits():
    x = torch.tensor([0.0, 1e-30, 1e-12, 1e-4, 1e8], requires_grad=True)
    d = torch.tensor(3.0)
    value = one_minus_exp_over(x, d)
    assert torch.allclose(value[:3], torch.full((3,), 3.0), rtol=0, atol=1e-6)
    assert abs(value[-1].item() - 1e-8) < 1e-14
    (gx,) = torch.autograd.grad(value.sum(), x)
    assert torch.isfinite(gx).all()
    assert torch.allclose(gx[:3], torch.full((3,), -4.5), rtol=1e-5)


def test_gradients_stay_relatively_accurate_in_the_tail():
    # d/dd (1 - e^{-x d}) / x = e^{-x d}: tiny but relatively exact (autograd's expm1 backward,
    # expm1 + 1, would cancel to 0 in float32 here).
    d = torch.tensor([10.0, 20.0, 40.0], requires_grad=True)
    (gd,) = torch.autograd.grad(one_minus_exp_over(torch.tensor(1.0), d).sum(), d)
    assert_matches(gd, np.exp(-to64(d)), "d/dd", small=0.0)
    # Water before the first edge: d/d sigma_bs of c_med (1 - e^{-sigma_bs s_0}) = c_med s_0 e^{-sigma_bs s_0}.
    bs = torch.tensor([[1.0, 2.0, 0.5]], requires_grad=True)
    render = render_seathru(torch.zeros(1, 0), torch.zeros(1, 0, 3), torch.tensor([[15.0]]), 0.0, bs, 1.0,
                            water_after=False)
    (gbs,) = torch.autograd.grad(render.rgb.sum(), bs)
    assert_matches(gbs, 15.0 * np.exp(-15.0 * to64(bs)), "d/d sigma_bs", small=0.0)


def test_gradcheck_one_minus_exp_over():
    for xs in ([0.0, 1e-9, 2e-5, 3e-4], [0.3, 1.7, 40.0, 900.0]):
        x = torch.tensor(xs, dtype=torch.float64, requires_grad=True)
        d = torch.tensor([2.0, 0.5, 1.3, 3.0], dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(one_minus_exp_over, (x, d))
        assert torch.autograd.gradgradcheck(one_minus_exp_over, (x, d))


# ----------------------------------------------------------------------------------------------
# render_seathru: exact form against quadrature
# ----------------------------------------------------------------------------------------------

def check_exact_against_reference(scene, water_before=True, water_after=True, t_far=None):
    sigma, rgb, edges, attn, bs, cmed = scene
    inputs = tensors(*scene)
    render = render_seathru(*inputs, water_before=water_before, water_after=water_after, t_far=t_far)
    reference = reference_seathru(sigma, rgb, edges, attn, bs, cmed, water_before, water_after, t_far)
    for name in ("rgb", "direct", "backscatter", "restored", "direct_share", "weights",
                 "transmittance", "opacity"):
        assert_matches(getattr(render, name), reference[name], name)
    opacity = reference["opacity"]
    unambiguous = (np.abs(opacity - 1e-12) > 1e-12) if opacity.size else opacity
    assert_matches(to64(render.depth_mean)[unambiguous], reference["depth_mean"][unambiguous], "depth_mean")
    total = np.array([optical_depth_at(e[-1], s, e) for s, e in zip(sigma, edges)])
    clear = np.abs(total - LN2) > 1e-5
    assert_matches(to64(render.depth_median)[clear], reference["depth_median"][clear], "depth_median",
                   extra_abs=median_tolerance(sigma, edges)[clear])
    assert_finite_grads(render_fields(render), inputs)
    return render


@HYPOTHESIS
@given(scene=scenes(), water_before=st.booleans(), water_after=st.booleans(),
       far_extra=st.one_of(st.none(), st.floats(0.0, 50.0)))
def test_exact_matches_quadrature(scene, water_before, water_after, far_extra):
    t_far = None if far_extra is None else float(scene[2][:, -1].max()) + far_extra
    check_exact_against_reference(scene, water_before, water_after, t_far)


def _scene(sigma, lengths, start=0.5, attn=(0.3, 0.2, 0.1), bs=(0.05, 0.15, 0.4), seed=0):
    """One-ray scene from per-interval densities and lengths (float32-representable arrays)."""
    rng = np.random.default_rng(seed)
    sigma = np.atleast_2d(np.asarray(sigma, dtype=np.float64))
    lengths = np.atleast_2d(np.asarray(lengths, dtype=np.float64))
    rays, samples = sigma.shape
    edges = np.concatenate([np.full((rays, 1), start), start + np.cumsum(lengths, axis=1)], axis=1)
    rgb = rng.uniform(0, 1, (rays, samples, 3))
    cmed = rng.uniform(0, 1, (rays, 3))
    attn = np.broadcast_to(np.asarray(attn, dtype=np.float64), (rays, 3)).copy()
    bs = np.broadcast_to(np.asarray(bs, dtype=np.float64), (rays, 3)).copy()
    f32 = lambda a: a.astype(np.float32).astype(np.float64)
    return tuple(f32(a) for a in (sigma, rgb, edges, attn, bs, cmed))


HARD_CASES = {
    "all densities zero (clear water)": _scene([0.0, 0.0, 0.0], [1.0, 2.0, 3.0]),
    "no water, no objects": _scene([0.0, 0.0], [1.0, 2.0], attn=0.0, bs=0.0),
    "density 1e-30": _scene([1e-30, 1e-30, 1e-30], [1.0, 0.5, 2.0], attn=1e-30, bs=1e-30),
    "opaque walls 1e8": _scene([1e8, 3.0, 1e8], [0.01, 1.0, 1e4]),
    "zero-length intervals": _scene([5.0, 1e8, 0.0, 2.0], [0.0, 0.0, 1.0, 0.0]),
    "intervals up to 1e4": _scene([1e-3, 1e-4, 2e-4], [1e4, 1e4, 1e4], attn=1e-4, bs=(1e-4, 2e-4, 3e-4)),
    "distances up to 1e4 (full attenuation)": _scene([1.0, 2.0], [1.0, 1.0], start=1e4),
    "single sample": _scene([0.7], [2.0]),
    "only water (S = 0)": _scene(np.zeros((2, 0)), np.zeros((2, 0)), start=4.0),
    "attenuation differs from backscatter": _scene([0.2, 1.5, 0.0, 4.0], [0.5, 0.3, 2.0, 1.0],
                                                   attn=(1.0, 0.01, 0.5), bs=(0.01, 1.0, 0.2)),
}


@pytest.mark.parametrize("name", list(HARD_CASES))
@pytest.mark.parametrize("t_far", [None, 2e4])
def test_exact_hard_cases(name, t_far):
    check_exact_against_reference(HARD_CASES[name], t_far=t_far)


@pytest.mark.parametrize("name", list(HARD_CASES))
def test_paper_and_general_hard_cases_finite(name):
    sigma, rgb, edges, attn, bs, cmed = HARD_CASES[name]
    inputs = tensors(*HARD_CASES[name])
    paper = render_seathru(*inputs, method="paper")
    expected = reference_paper(sigma, rgb, edges, attn, bs, cmed, True, True)
    assert_matches(paper.rgb, expected, "paper rgb")
    assert_finite_grads(render_fields(paper), inputs)
    sigma_med = np.broadcast_to(bs[:, None, :], rgb.shape).copy()
    general_inputs = tensors(sigma, rgb, sigma_med, np.broadcast_to(cmed[:, None, :], rgb.shape).copy(), edges)
    general = render_general(*general_inputs)
    assert_matches(general, reference_general(sigma, rgb, sigma_med, general_inputs[3].detach().double().numpy(),
                                              edges), "general")
    assert_finite_grads([general], general_inputs)


# ----------------------------------------------------------------------------------------------
# paper discretisation and general form
# ----------------------------------------------------------------------------------------------

@HYPOTHESIS
@given(scene=scenes(), water_before=st.booleans(), water_after=st.booleans())
def test_paper_matches_discrete_reference(scene, water_before, water_after):
    inputs = tensors(*scene)
    render = render_seathru(*inputs, method="paper", water_before=water_before, water_after=water_after)
    assert_matches(render.rgb, reference_paper(*scene, water_before, water_after), "paper rgb")
    assert_finite_grads(render_fields(render), inputs)


@HYPOTHESIS
@given(scene=scenes(), data=st.data(), per_channel=st.booleans())
def test_general_matches_quadrature(scene, data, per_channel):
    sigma, rgb, edges, _, _, _ = scene
    shape = sigma.shape + ((3,) if per_channel else ())
    size = int(np.prod(shape))
    sigma_med = np.array(data.draw(st.lists(DENSITY, min_size=size, max_size=size))).reshape(shape)
    rgb_med = np.array(data.draw(st.lists(UNIT, min_size=rgb.size, max_size=rgb.size))).reshape(rgb.shape)
    sigma_med = sigma_med.astype(np.float32).astype(np.float64)
    rgb_med = rgb_med.astype(np.float32).astype(np.float64)
    inputs = tensors(sigma, rgb, sigma_med, rgb_med, edges)
    colour = render_general(*inputs)
    assert colour.shape == (sigma.shape[0], 3)
    assert_matches(colour, reference_general(sigma, rgb, sigma_med, rgb_med, edges), "general")
    assert_finite_grads([colour], inputs)
    # Total weight <= 1, so the colour is bounded by the colours it mixes.
    bound = max(rgb.max(initial=0.0), rgb_med.max(initial=0.0))
    assert (to64(colour) <= bound * (1 + 1e-6) + 1e-7).all()


@pytest.mark.parametrize("tiny", [0.0, 1e-30])
def test_general_finite_as_total_density_vanishes(tiny):
    so = torch.full((1, 3), tiny, requires_grad=True)
    sm = torch.full((1, 3, 3), tiny, requires_grad=True)
    co, cm = torch.rand(1, 3, 3), torch.rand(1, 3, 3)
    edges = torch.tensor([[0.0, 1.0, 2.0, 3.0]])
    colour = render_general(so, co, sm, cm, edges)
    expected = (tiny * (co + cm)).sum(dim=1)   # T = 1, (1 - e^{-x d}) / x = d = 1
    assert torch.isfinite(colour).all() and torch.allclose(colour, expected, atol=1e-36)
    gso, gsm = torch.autograd.grad(colour.sum(), (so, sm))
    assert torch.isfinite(gso).all() and torch.isfinite(gsm).all()
    # d colour / d so_i = sum_c co_ic * d_i to first order.
    assert torch.allclose(gso, co.sum(-1), rtol=1e-5)


def test_general_reduces_to_nerf_without_medium():
    torch.manual_seed(1)
    sigma, rgb = torch.rand(4, 6) * 3, torch.rand(4, 6, 3)
    edges = torch.cumsum(torch.rand(4, 7), dim=1)
    general = render_general(sigma, rgb, torch.zeros(4, 6), torch.rand(4, 6, 3), edges)
    render = render_seathru(sigma, rgb, edges, 0.0, 0.0, 0.5)
    assert torch.allclose(general, render.restored, rtol=1e-6, atol=1e-7)


# ----------------------------------------------------------------------------------------------
# gradcheck (float64)
# ----------------------------------------------------------------------------------------------

def _random_inputs64(rays=2, samples=4, seed=0):
    gen = torch.Generator().manual_seed(seed)
    rand = lambda *shape: torch.rand(*shape, generator=gen, dtype=torch.float64)
    sigma = rand(rays, samples) * 2 + 0.05
    sigma[0, 1] = 1e-7  # near the series branch
    edges = 0.3 + torch.cumsum(rand(rays, samples + 1) + 0.1, dim=1)
    return sigma, rand(rays, samples, 3), edges, rand(rays, 3) * 0.5, rand(rays, 3) * 0.5, rand(rays, 3)


def test_gradcheck_nerf_weights():
    sigma, _, edges, *_ = _random_inputs64()
    deltas = (edges[:, 1:] - edges[:, :-1]).detach()
    assert torch.autograd.gradcheck(nerf_weights, (sigma.requires_grad_(), deltas.requires_grad_()))


@pytest.mark.parametrize("method", ["exact", "paper"])
@pytest.mark.parametrize("t_far", [None, 30.0])
def test_gradcheck_render_seathru(method, t_far):
    inputs = [x.requires_grad_() for x in _random_inputs64()]

    def fields(*args):
        return tuple(render_fields(render_seathru(*args, method=method, t_far=t_far)))

    assert torch.autograd.gradcheck(fields, inputs)


def test_gradcheck_render_general():
    sigma, rgb, edges, *_ = _random_inputs64()
    gen = torch.Generator().manual_seed(3)
    sigma_med = torch.rand(2, 4, 3, generator=gen, dtype=torch.float64)
    sigma_med[1, 2] = 0.0
    sigma_med[1, 2, 0] = 1e-9
    rgb_med = torch.rand(2, 4, 3, generator=gen, dtype=torch.float64)
    inputs = [x.requires_grad_() for x in (sigma, rgb, sigma_med, rgb_med, edges)]
    assert torch.autograd.gradcheck(render_general, inputs)


# ----------------------------------------------------------------------------------------------
# physical identities
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("z", [0.0, 1.5, 7.0, 40.0])
def test_opaque_surface(z):
    attn = torch.tensor([[0.4, 0.1, 0.05]])
    bs = torch.tensor([[0.1, 0.3, 0.6]])
    cmed = torch.tensor([[0.1, 0.3, 0.5]])
    surface = torch.tensor([0.9, 0.5, 0.2])
    edges = torch.tensor([[0.2 if z > 0 else 0.0, z, z + 0.01, z + 1.0]])
    sigma = torch.tensor([[0.0, 1e8, 5.0]])
    rgb = torch.stack([torch.ones(3), surface, torch.zeros(3)])[None]
    render = render_seathru(sigma, rgb, edges, attn, bs, cmed)
    z64 = torch.tensor(z, dtype=torch.float64)
    expected = surface.double() * torch.exp(-attn.double() * z64) + cmed.double() * -torch.expm1(-bs.double() * z64)
    assert_matches(render.rgb, to64(expected), "rgb")
    assert_matches(render.restored, to64(surface)[None], "restored")
    assert_matches(render.opacity, [1.0], "opacity")
    assert_matches(render.depth_median, [z + LN2 / 1e8], "median", extra_abs=1e-6)
    assert_matches(render.depth_mean, [z + 0.005], "mean")


def _plain_nerf(sigma, rgb, edges):
    """The NeRF equation written out: w_i = prod_{j<i} (1 - a_j) a_i, a = 1 - exp(-sigma d)."""
    deltas = edges[:, 1:] - edges[:, :-1]
    alpha = 1 - torch.exp(-sigma * deltas)
    transmit = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], dim=1), dim=1)
    weights = transmit * alpha
    return (weights[..., None] * rgb).sum(1), weights


@pytest.mark.parametrize("method", ["exact", "paper"])
@pytest.mark.parametrize("t_far", [None, 100.0])
def test_zero_medium_is_plain_nerf(method, t_far):
    torch.manual_seed(2)
    sigma = torch.rand(64, 16) * 4
    sigma[:, ::5] = 0.0
    sigma[:3, 7] = 1e8
    rgb = torch.rand(64, 16, 3)
    edges = torch.rand(64, 1) + torch.cumsum(torch.rand(64, 17) * 0.3, dim=1)
    cmed = torch.rand(64, 3)
    render = render_seathru(sigma, rgb, edges, 0.0, torch.zeros(64, 3), cmed, method=method, t_far=t_far)
    nerf_rgb, nerf_w = _plain_nerf(sigma.double(), rgb.double(), edges.double())
    assert torch.equal(render.rgb, render.restored)
    assert torch.equal(render.direct, render.restored)
    assert torch.equal(render.backscatter, torch.zeros_like(render.backscatter))
    assert torch.allclose(render.rgb.double(), nerf_rgb, rtol=1e-5, atol=1e-6)
    assert torch.allclose(render.weights.double(), nerf_w, rtol=1e-5, atol=1e-7)
    weights, transmittance = nerf_weights(sigma, edges[:, 1:] - edges[:, :-1])
    assert torch.equal(weights, render.weights) and torch.equal(transmittance, render.transmittance)


@HYPOTHESIS
@given(scene=scenes())
def test_colour_bounded_when_attenuation_at_least_backscatter(scene):
    sigma, rgb, edges, attn, bs, cmed = scene
    attn = np.maximum(attn, bs)   # sum of direct and medium weights <= 1 exactly when attn >= bs
    render = render_seathru(*tensors(sigma, rgb, edges, attn, bs, cmed, grad=False))
    bound = max(rgb.max(initial=0.0), cmed.max())
    colour = to64(render.rgb)
    assert (colour >= 0).all() and (colour <= bound * (1 + 1e-6) + 1e-7).all()
    assert (to64(render.restored) <= rgb.max(initial=0.0) * (1 + 1e-6) + 1e-7).all()


def test_colour_can_exceed_inputs_when_backscatter_outpaces_attenuation():
    # The SeaThru model itself: a bright surface seen through weakly attenuating but strongly
    # backscattering water reads J e^{-attn z} + c_med (1 - e^{-bs z}) > max(J, c_med).
    render = render_seathru(torch.tensor([[1e8]]), torch.ones(1, 1, 3), torch.tensor([[10.0, 11.0]]),
                            0.0, 1.0, 0.8)
    assert (render.rgb > 1.7).all()


def test_paper_converges_to_exact():
    sigma = torch.tensor([[0.0, 1.5, 0.2, 4.0]], dtype=torch.float64)
    rgb = torch.tensor([[[0.1, 0.2, 0.3], [0.9, 0.4, 0.1], [0.2, 0.8, 0.5], [0.6, 0.6, 0.9]]], dtype=torch.float64)
    coarse = torch.tensor([[0.5, 1.0, 1.8, 2.5, 4.0]], dtype=torch.float64)
    medium = dict(sigma_attn=torch.tensor([0.5, 0.2, 0.1], dtype=torch.float64),
                  sigma_bs=torch.tensor([0.1, 0.3, 0.6], dtype=torch.float64),
                  c_med=torch.tensor([0.1, 0.3, 0.5], dtype=torch.float64))
    truth = render_seathru(sigma, rgb, coarse, **medium).rgb
    errors = []
    for pieces in [1, 2, 4, 8, 16, 32, 64]:
        frac = torch.arange(pieces, dtype=torch.float64) / pieces
        starts, lengths = coarse[:, :-1, None], (coarse[:, 1:] - coarse[:, :-1])[..., None]
        fine = torch.cat([(starts + lengths * frac).reshape(1, -1), coarse[:, -1:]], dim=1)
        fine_sigma = sigma.repeat_interleave(pieces, dim=1)
        fine_rgb = rgb.repeat_interleave(pieces, dim=1)
        exact = render_seathru(fine_sigma, fine_rgb, fine, **medium).rgb
        assert torch.allclose(exact, truth, rtol=1e-12, atol=1e-14), "exact form depends on the sampling"
        errors.append((render_seathru(fine_sigma, fine_rgb, fine, method="paper", **medium).rgb - truth)
                      .abs().max().item())
    ratios = np.array(errors[1:]) / np.array(errors[:-1])
    assert errors[0] > 1e-2 and (ratios < 0.6).all() and (ratios > 0.4).all(), (errors, ratios)


# ----------------------------------------------------------------------------------------------
# water before/after, t_far, empty rays
# ----------------------------------------------------------------------------------------------

def test_empty_rays_are_exact_without_samples():
    bs = torch.tensor([[0.2, 0.5, 1e-3], [1e-30, 2.0, 0.7]])
    cmed = torch.tensor([[0.1, 0.4, 0.6], [0.3, 0.3, 0.3]])
    edges = torch.tensor([[3.0], [0.0]])
    render = render_seathru(torch.zeros(2, 0), torch.zeros(2, 0, 3), edges, 0.7, bs, cmed)
    assert torch.allclose(render.rgb, cmed, rtol=1e-6)
    assert render.weights.shape == (2, 0) and torch.equal(render.transmittance, torch.ones(2, 1))
    assert torch.equal(render.depth_mean, edges[:, 0]) and torch.equal(render.depth_median, edges[:, 0])
    finite = render_seathru(torch.zeros(2, 0), torch.zeros(2, 0, 3), edges, 0.7, bs, cmed, t_far=10.0)
    assert torch.allclose(finite.rgb, cmed * -torch.expm1(-bs * 10.0), rtol=1e-6, atol=1e-30)
    # Zero object density along sampled intervals gives the same numbers as no samples at all.
    sampled = render_seathru(torch.zeros(2, 5), torch.rand(2, 5, 3), edges + torch.arange(6.0), 0.7, bs, cmed)
    assert torch.allclose(sampled.rgb, render.rgb, rtol=1e-6)


def test_infinite_tail_is_discontinuous_at_zero_backscatter_and_finite_far_is_not():
    edges, cmed = torch.tensor([[0.0, 1.0]]), torch.tensor([[0.5, 0.5, 0.5]])
    tiny = torch.tensor([[0.0, 1e-30, 1e-6]])
    infinite = render_seathru(torch.zeros(1, 1), torch.zeros(1, 1, 3), edges, 0.0, tiny, cmed)
    assert infinite.rgb[0, 0] == 0 and torch.allclose(infinite.rgb[0, 1:], torch.tensor([0.5, 0.5]), rtol=1e-5)
    finite = render_seathru(torch.zeros(1, 1), torch.zeros(1, 1, 3), edges, 0.0, tiny, cmed, t_far=1e3)
    assert torch.allclose(finite.rgb, torch.tensor([[0.0, 5e-28, 0.5 * -math.expm1(-1e-3)]]), rtol=1e-5, atol=0)


def test_water_flags_add_exactly_the_closed_form_terms():
    sigma, rgb, edges, attn, bs, cmed = (torch.tensor(a, dtype=torch.float64) for a in HARD_CASES[
        "attenuation differs from backscatter"])
    both = render_seathru(sigma, rgb, edges, attn, bs, cmed)
    none = render_seathru(sigma, rgb, edges, attn, bs, cmed, water_before=False, water_after=False)
    before = cmed * -torch.expm1(-bs * edges[:, :1])
    after = cmed * torch.exp(-bs * edges[:, -1:]) * both.transmittance[:, -1:]
    assert torch.allclose(both.backscatter - none.backscatter, before + after, rtol=1e-12)
    assert torch.equal(both.direct, none.direct)


# ----------------------------------------------------------------------------------------------
# dtypes, devices, input errors
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_is_computed_in_float32(dtype):
    sigma, rgb, edges, attn, bs, cmed = HARD_CASES["attenuation differs from backscatter"]
    low = [torch.tensor(a).to(dtype).requires_grad_() for a in (sigma, rgb, edges, attn, bs, cmed)]
    render = render_seathru(*low)
    assert all(f.dtype == torch.float32 for f in render_fields(render))
    single = render_seathru(*[x.detach().float() for x in low])
    for name in FIELDS:
        assert torch.equal(getattr(render, name), getattr(single, name)), name
    grads = grads_of([render.rgb], low)
    assert all(g is not None and g.dtype == dtype and torch.isfinite(g.float()).all() for g in grads)
    general = render_general(low[0], low[1], low[0], low[1], low[2])
    assert general.dtype == torch.float32


def test_float64_is_kept():
    render = render_seathru(*[torch.tensor(a) for a in HARD_CASES["single sample"]])
    assert all(f.dtype == torch.float64 for f in render_fields(render))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
def test_cuda_matches_cpu():
    inputs = [torch.tensor(a, dtype=torch.float32) for a in HARD_CASES["attenuation differs from backscatter"]]
    cpu = render_seathru(*inputs)
    gpu = render_seathru(*[x.cuda() for x in inputs])
    for name in FIELDS:
        assert torch.allclose(getattr(gpu, name).cpu(), getattr(cpu, name), rtol=1e-5, atol=1e-6), name
    general = render_general(inputs[0].cuda(), inputs[1].cuda(), inputs[0].cuda(), inputs[1].cuda(),
                             inputs[2].cuda())
    assert general.is_cuda


def test_bad_inputs_raise_clear_errors():
    sigma, rgb, edges = torch.rand(2, 3), torch.rand(2, 3, 3), torch.cumsum(torch.rand(2, 4), 1)
    with pytest.raises(ValueError, match="t_edges"):
        render_seathru(sigma, rgb, edges[:, :3], 0.1, 0.1, 0.1)
    with pytest.raises(ValueError, match="rgb_obj"):
        render_seathru(sigma, rgb[..., :2], edges, 0.1, 0.1, 0.1)
    with pytest.raises(ValueError, match="sigma_bs"):
        render_seathru(sigma, rgb, edges, 0.1, torch.rand(3, 3), 0.1)
    with pytest.raises(ValueError, match="method"):
        render_seathru(sigma, rgb, edges, 0.1, 0.1, 0.1, method="trapezoid")
    with pytest.raises(TypeError, match="floating point"):
        render_seathru(sigma, rgb, edges.long(), 0.1, 0.1, 0.1)
    with pytest.raises(ValueError, match="sigma_med"):
        render_general(sigma, rgb, torch.rand(2, 3, 2), rgb, edges)
