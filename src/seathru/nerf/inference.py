"""Rendering whole frames with a trained model, in bounded-memory ray chunks.

A *render function* ``render_fn(frame, downscale) -> dict`` maps a ``seathru.io.cameras.Frame``
to float32 images keyed as :data:`RENDER_KEYS` (:func:`frame_renderer` makes one from a model;
tests pass stand-ins); :func:`timed_renders` runs one over frames, timing each.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any

import numpy as np
import torch

from seathru.errors import PipelineError
from seathru.nerf.rays import frame_rays, render_size

RENDER_KEYS = ("rgb", "restored", "direct", "backscatter", "depth", "opacity", "direct_share")
REQUIRED_KEYS = RENDER_KEYS[:-2]  # opacity and direct_share are optional for stand-in renderers

RenderFn = Callable[[Any, int], dict]


@torch.no_grad()
def render_rays(model, origins: torch.Tensor, directions: torch.Tensor, near: torch.Tensor,
                far: torch.Tensor, chunk: int = 8192) -> dict[str, torch.Tensor]:
    """Render rays (R, 3) / (R,) in chunks; returns CPU tensors keyed as ``RENDER_KEYS``
    (colours (R, 3); depth = expected ray distance in normalised units, opacity (R,))."""
    device = next(model.parameters()).device
    was_training = model.training
    model.eval()
    parts: dict[str, list[torch.Tensor]] = {k: [] for k in RENDER_KEYS}
    try:
        for start in range(0, origins.shape[0], chunk):
            sl = slice(start, start + chunk)
            out = model(origins[sl].to(device), directions[sl].to(device), near[sl].to(device),
                        far[sl].to(device)).render
            for key, value in (("rgb", out.rgb), ("restored", out.restored),
                               ("direct", out.direct), ("backscatter", out.backscatter),
                               ("depth", out.depth_mean), ("opacity", out.opacity),
                               ("direct_share", out.direct_share)):
                parts[key].append(value.float().cpu())
    finally:
        model.train(was_training)
    return {k: torch.cat(v) for k, v in parts.items()}


@torch.no_grad()
def render_frame(model, frame, chunk: int = 8192, downscale: int = 1) -> dict[str, np.ndarray]:
    """Render a ``seathru.io.cameras.Frame``: "rgb" (full, with water), "restored", "direct",
    "backscatter", "direct_share" (H, W, 3: ``seathru.nerf.rendering.RayRender``) and "depth"
    (expected ray distance, normalised units), "opacity" (H, W), float32, at
    (H // downscale, W // downscale)."""
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    width, height = render_size(frame.width, frame.height, downscale)
    origins, directions = frame_rays(frame, downscale)
    count = origins.shape[0]
    near = torch.full((count,), float(frame.near))
    far = torch.full((count,), float(frame.far))
    flat = render_rays(model, origins, directions, near, far, chunk)
    out = {}
    for key, value in flat.items():
        shape = (height, width, 3) if value.dim() == 2 else (height, width)
        out[key] = value.reshape(shape).numpy().astype(np.float32, copy=False)
    return out


def frame_renderer(model, chunk: int = 8192) -> RenderFn:
    """The render function of a model: ``render_fn(frame, downscale)`` is :func:`render_frame`."""
    def render_fn(frame, downscale: int) -> dict[str, np.ndarray]:
        return render_frame(model, frame, chunk=chunk, downscale=downscale)

    return render_fn


def timed_renders(render_fn: RenderFn, frames: Iterable, downscale: int = 1
                  ) -> Iterator[tuple[Any, dict[str, np.ndarray], float]]:
    """``(frame, images, seconds)`` for each frame, rendered one at a time.

    Args:
        render_fn: ``render_fn(frame, downscale) -> dict`` (see the module docstring).
        frames: ``Frame`` objects (anything with the camera fields of one).
        downscale: resolution divisor.

    Raises:
        PipelineError: a render lacks one of :data:`REQUIRED_KEYS`.

    Example::

        for frame, images, seconds in timed_renders(frame_renderer(model), frames): ...
    """
    for frame in frames:
        start = time.perf_counter()
        images = render_fn(frame, downscale)
        seconds = time.perf_counter() - start
        missing = [key for key in REQUIRED_KEYS if key not in images]
        if missing:
            raise PipelineError(f"the model's render of {frame.name} lacks {missing}; the model "
                                "and the render step disagree on the inference contract")
        yield frame, images, seconds
