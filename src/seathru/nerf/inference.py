"""Rendering whole frames with a trained model, in bounded-memory ray chunks."""

from __future__ import annotations

import numpy as np
import torch

from seathru.nerf.rays import downscaled_size, frame_rays

RENDER_KEYS = ("rgb", "restored", "direct", "backscatter", "depth", "opacity")


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
                               ("depth", out.depth_mean), ("opacity", out.opacity)):
                parts[key].append(value.float().cpu())
    finally:
        model.train(was_training)
    return {k: torch.cat(v) for k, v in parts.items()}


@torch.no_grad()
def render_frame(model, frame, chunk: int = 8192, downscale: int = 1) -> dict[str, np.ndarray]:
    """Render a ``seathru.io.cameras.Frame``: "rgb" (full, with water), "restored", "direct",
    "backscatter" (H, W, 3) and "depth" (expected ray distance, normalised units), "opacity"
    (H, W), float32, at (H // downscale, W // downscale)."""
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    width, height = downscaled_size(frame.width, frame.height, downscale)
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
