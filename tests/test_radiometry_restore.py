"""seathru.radiometry.restore: a photograph with the water removed by the model's render."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from seathru.nerf.rendering import render_seathru
from seathru.radiometry.restore import restore_photograph

HYPOTHESIS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def render_rays(sigma, colour, edges, attn, bs, cmed) -> dict[str, np.ndarray]:
    """float64 renders of rays whose object colour is the same at every sample."""
    rays, samples = sigma.shape
    rgb = np.broadcast_to(colour[:, None, :], (rays, samples, 3))
    out = render_seathru(torch.tensor(sigma), torch.tensor(np.ascontiguousarray(rgb)),
                         torch.tensor(edges), torch.tensor(attn), torch.tensor(bs),
                         torch.tensor(cmed))
    return {"rgb": out.rgb.numpy(), "restored": out.restored.numpy(),
            "direct_share": out.direct_share.numpy(), "opacity": out.opacity.numpy()}


@st.composite
def surfaces(draw):
    """Rays with a surface somewhere along them (opaque or not), water per channel, and the
    model's and the scene's object colours."""
    rays = draw(st.integers(1, 6))
    samples = draw(st.integers(1, 12))
    rng = np.random.default_rng(draw(st.integers(0, 2**31 - 1)))
    start = rng.uniform(0.1, 3.0, (rays, 1))
    edges = start + np.concatenate([np.zeros((rays, 1)),
                                    np.cumsum(rng.uniform(0.01, 0.5, (rays, samples)), 1)], 1)
    sigma = rng.choice([0.0, 0.5, 5.0, 50.0], (rays, samples)) * rng.uniform(0.5, 1.5,
                                                                              (rays, samples))
    sigma[:, -1] = np.maximum(sigma[:, -1], 0.2)  # every ray meets some object
    attn = np.broadcast_to(rng.uniform(0.0, 0.6, 3), (rays, 3)).copy()
    bs = np.broadcast_to(rng.uniform(0.0, 0.6, 3), (rays, 3)).copy()
    cmed = np.broadcast_to(rng.uniform(0.0, 0.5, 3), (rays, 3)).copy()
    model_colour = rng.uniform(0.0, 1.0, (rays, 3))
    true_colour = rng.uniform(0.0, 1.0, (rays, 3))
    return sigma, edges, attn, bs, cmed, model_colour, true_colour


@HYPOTHESIS
@given(scene=surfaces())
def test_a_wrong_object_colour_is_undone_exactly(scene):
    """The model has the geometry and the water right and the object colour wrong: the
    photograph, divided through the model's water, gives the true colour's restored render."""
    sigma, edges, attn, bs, cmed, model_colour, true_colour = scene
    model = render_rays(sigma, model_colour, edges, attn, bs, cmed)
    photograph = render_rays(sigma, true_colour, edges, attn, bs, cmed)
    opacity = model["opacity"][:, None]
    gain = opacity / model["direct_share"]
    assert np.all(gain <= 1e6)
    restored = restore_photograph(photograph["rgb"], model, max_gain=float(gain.max()) + 1.0,
                                  detail_scale=0.0)
    # the opacity weight: at a soft surface the correction is blended in by its opacity
    expected = model["restored"] + opacity * (photograph["restored"] - model["restored"])
    np.testing.assert_allclose(restored, np.clip(expected, 0, None), rtol=1e-4, atol=1e-5)
    opaque = model["opacity"] > 1 - 1e-9
    np.testing.assert_allclose(restored[opaque], photograph["restored"][opaque],
                               rtol=1e-4, atol=1e-5)


def test_an_explained_photograph_gives_the_restored_render():
    rng = np.random.default_rng(1)
    render = {"rgb": rng.uniform(0, 1, (4, 5, 3)), "restored": rng.uniform(0, 1, (4, 5, 3)),
              "direct_share": rng.uniform(0.01, 0.5, (4, 5, 3)),
              "opacity": rng.uniform(0.5, 1, (4, 5))}
    np.testing.assert_allclose(restore_photograph(render["rgb"], render), render["restored"],
                               rtol=1e-6)


def test_open_water_stays_as_rendered_and_far_surfaces_are_capped():
    render = {"rgb": np.full((1, 3, 3), 0.3), "restored": np.array([[[0.0] * 3, [0.2] * 3,
                                                                     [0.2] * 3]]),
              "direct_share": np.array([[[0.0] * 3, [1e-4] * 3, [0.5] * 3]]),
              "opacity": np.array([[0.0, 1.0, 1.0]])}
    photograph = np.full((1, 3, 3), 0.31)
    restored = restore_photograph(photograph, render, max_gain=10.0, detail_scale=0.0)
    assert np.all(np.isfinite(restored))
    np.testing.assert_allclose(restored[0, 0], 0.0, atol=1e-7)           # open water
    np.testing.assert_allclose(restored[0, 1], 0.2 + 10.0 * 0.01, rtol=1e-5)  # capped gain
    np.testing.assert_allclose(restored[0, 2], 0.2 + 2.0 * 0.01, rtol=1e-5)   # 1 / 0.5
    assert restored.dtype == np.float32


def test_never_negative_and_checks_its_inputs():
    render = {"rgb": np.full((2, 2, 3), 0.5), "restored": np.full((2, 2, 3), 0.1),
              "direct_share": np.full((2, 2, 3), 0.1), "opacity": np.ones((2, 2))}
    assert restore_photograph(np.zeros((2, 2, 3)), render, detail_scale=0.0).min() == 0.0
    with pytest.raises(ValueError, match="differ in size"):
        restore_photograph(np.zeros((3, 2, 3)), render)
    with pytest.raises(ValueError, match="max_gain"):
        restore_photograph(np.zeros((2, 2, 3)), render, max_gain=0.5)
    with pytest.raises(ValueError, match="detail_scale"):
        restore_photograph(np.zeros((2, 2, 3)), render, detail_scale=-0.1)


def test_detail_is_carried_over_and_a_slow_colour_change_is_not():
    """A residual that changes across the frame (a colour the water model misses) is left to
    the model; fine texture the model lacks is divided out, and open water beside a surface
    does not bleed into it."""
    height, width = 48, 64
    y, x = np.mgrid[0:height, 0:width]
    opacity = np.ones((height, width))
    opacity[:8] = 0.0                                   # open water along the top
    render = {"rgb": np.full((height, width, 3), 0.3), "restored": np.full((height, width, 3), 0.5),
              "direct_share": np.full((height, width, 3), 0.5) * opacity[..., None],
              "opacity": opacity}
    trend = (0.1 * x / width)[..., None] * np.ones(3)   # brighter to the right
    texture = (0.02 * np.where((x + y) % 2 == 0, 1.0, -1.0))[..., None] * np.ones(3)
    water_above = np.where(opacity[..., None] > 0, 0.0, 0.2)
    photograph = render["rgb"] + trend + texture + water_above
    restored = restore_photograph(photograph, render, max_gain=10.0, detail_scale=0.1)
    surface = np.s_[16:-8, 8:-8]                        # away from the frame's edges
    detail = restored[surface] - 0.5
    np.testing.assert_allclose(detail, 2.0 * texture[surface], atol=0.012)
    whole = restore_photograph(photograph, render, max_gain=10.0, detail_scale=0.0)
    np.testing.assert_allclose(whole[surface], 0.5 + 2.0 * (trend + texture)[surface],
                               rtol=1e-5)
    np.testing.assert_allclose(restored[:8], 0.5, atol=1e-6)  # open water: as rendered
