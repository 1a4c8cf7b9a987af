"""seathru.nerf.inference (render functions, timed renders) and nerf.rays.render_size."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from seathru.errors import PipelineError
from seathru.io.cameras import Frame
from seathru.nerf.config import TrainConfig
from seathru.nerf.inference import (RENDER_KEYS, frame_renderer, render_frame,
                                    timed_renders)
from seathru.nerf.model import SeaThruModel
from seathru.nerf.rays import frame_rays, render_size
from seathru.sim.camera_paths import look_at
from tests.test_io_model import SCENE, SMALL

FRAME = Frame(name="v", image="", width=9, height=7, fx=8.0, fy=8.0, cx=4.5, cy=3.5,
              c2w=look_at((0.0, -2.5, 0.8), (0.0, 0.0, 0.2)).tolist(), near=0.5, far=6.0)


@given(width=st.integers(1, 5000), height=st.integers(1, 5000), downscale=st.integers(1, 64))
def test_render_size_floors_each_side_and_keeps_a_pixel(width, height, downscale):
    w, h = render_size(width, height, downscale)
    assert (w, h) == (max(1, width // downscale), max(1, height // downscale))
    assert len(frame_rays(FRAME, downscale)[0]) == np.prod(render_size(9, 7, downscale))


def test_render_size_refuses_a_zero_downscale():
    with pytest.raises(ValueError, match="downscale"):
        render_size(10, 10, 0)


def test_frame_renderer_is_render_frame_with_the_chunk():
    torch.manual_seed(0)
    model = SeaThruModel(TrainConfig.from_dict(SMALL), SCENE)
    renders = frame_renderer(model, chunk=5)(FRAME, 2)
    expected = render_frame(model, FRAME, chunk=5, downscale=2)
    assert renders.keys() == set(RENDER_KEYS)
    for key, value in expected.items():
        np.testing.assert_array_equal(renders[key], value)
    assert renders["depth"].shape == (3, 4)


def test_timed_renders_yields_each_frame_in_order_with_its_time():
    calls = []

    def render_fn(frame, downscale):
        calls.append((frame.name, downscale))
        return {key: np.zeros((2, 2), np.float32) for key in RENDER_KEYS[:-1]}

    frames = [Frame(**{**FRAME.__dict__, "name": name}) for name in ("a", "b")]
    out = list(timed_renders(render_fn, frames, downscale=3))
    assert [frame.name for frame, _, _ in out] == ["a", "b"] and calls == [("a", 3), ("b", 3)]
    assert all(seconds >= 0 for _, _, seconds in out)


def test_timed_renders_refuses_a_render_without_depth():
    def render_fn(frame, downscale):
        return {"rgb": np.zeros((2, 2, 3))}

    with pytest.raises(PipelineError, match=r"render of v lacks \['restored'"):
        list(timed_renders(render_fn, [FRAME]))
