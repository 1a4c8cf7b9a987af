"""The water: per ray and RGB channel attenuation ``sigma_attn``, backscatter ``sigma_bs`` (both
per normalised unit of distance, >= 0, by softplus) and veiling-light colour ``c_med`` (in (0, 1)
times ``colour_max``, by sigmoid).

Modes (``MEDIUM_MODES``):
- ``off``: all zeros, the renderer then is plain NeRF (clear water, air);
- ``global``: one value per channel for the whole scene;
- ``view``: a small MLP of the encoded view direction (spherical harmonics, degree 3), as the
  paper's medium network; it starts equal to the global values (zero last layer);
- ``veiling``: global attenuation and backscatter, the veiling light ``c_med`` by direction (the
  same MLP's colour outputs): open water is brighter towards the surface and the sun, while
  attenuation and backscatter are properties of the water that do not depend on where one
  looks.

The mode lives in a buffer, so a state dict carries it and it can change during training
(``medium.mode=auto``). Shapes: directions (R, 3) -> each parameter (R, 3).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from seathru.nerf.fields import spherical_harmonics

MEDIUM_MODES = ("off", "global", "view", "veiling")  # appended: stored indices stay valid
DIRECTIONAL_MODES = ("view", "veiling")


def inverse_softplus(y: float) -> float:
    y = max(y, 1e-6)  # softplus never reaches 0
    return y + math.log(-math.expm1(-y)) if y < 20 else y


def logit(p: float) -> float:
    p = min(max(p, 1e-4), 1 - 1e-4)
    return math.log(p / (1 - p))


class Medium(nn.Module):
    def __init__(self, mode: str = "global", sigma_init: float = 0.2,
                 c_med_init=(0.1, 0.2, 0.3), colour_max: float = 1.0, hidden: int = 64):
        super().__init__()
        self.colour_max = colour_max
        self.register_buffer("mode_index", torch.tensor(MEDIUM_MODES.index(mode)))
        c_med_init = torch.as_tensor(c_med_init, dtype=torch.float32).reshape(3) / colour_max
        raw_sigma = inverse_softplus(sigma_init)
        self.raw_attn = nn.Parameter(torch.full((3,), raw_sigma))
        self.raw_bs = nn.Parameter(torch.full((3,), raw_sigma))
        self.raw_colour = nn.Parameter(torch.tensor([logit(float(c)) for c in c_med_init]))
        self.view_net = nn.Sequential(nn.Linear(16, hidden), nn.ReLU(inplace=True),
                                      nn.Linear(hidden, hidden), nn.ReLU(inplace=True),
                                      nn.Linear(hidden, 9))
        nn.init.zeros_(self.view_net[-1].weight)
        nn.init.zeros_(self.view_net[-1].bias)

    @property
    def mode(self) -> str:
        return MEDIUM_MODES[int(self.mode_index)]

    def set_mode(self, mode: str) -> None:
        """Switch mode; entering a directional mode starts the direction MLP at the global
        values."""
        if mode not in MEDIUM_MODES:
            raise ValueError(f"medium mode must be one of {MEDIUM_MODES}, got {mode!r}")
        if mode in DIRECTIONAL_MODES and self.mode not in DIRECTIONAL_MODES:
            with torch.no_grad():
                nn.init.zeros_(self.view_net[-1].weight)
                nn.init.zeros_(self.view_net[-1].bias)
        self.mode_index.fill_(MEDIUM_MODES.index(mode))

    @torch.no_grad()
    def set_global(self, sigma_attn, sigma_bs, c_med=None) -> None:
        """Set the global water (per channel, normalised units; ``c_med`` below colour_max;
        None keeps the veiling light)."""
        self.raw_attn.copy_(torch.tensor([inverse_softplus(float(v)) for v in sigma_attn]))
        self.raw_bs.copy_(torch.tensor([inverse_softplus(float(v)) for v in sigma_bs]))
        if c_med is not None:
            self.raw_colour.copy_(torch.tensor([logit(float(v) / self.colour_max)
                                                for v in c_med]))

    def global_parameters(self) -> list[nn.Parameter]:
        return [self.raw_attn, self.raw_bs, self.raw_colour]

    def network_parameters(self) -> list[nn.Parameter]:
        return list(self.view_net.parameters())

    def forward(self, dirs: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(sigma_attn, sigma_bs, c_med), each (R, 3)."""
        rays = dirs.shape[0]
        mode = self.mode
        if mode == "off":
            zeros = dirs.new_zeros(rays, 3)
            return zeros, zeros, zeros
        raw = torch.cat([self.raw_attn, self.raw_bs, self.raw_colour]).to(dirs.dtype)
        raw = raw.expand(rays, 9)
        if mode == "view":
            raw = raw + self.view_net(spherical_harmonics(dirs, 3))
        elif mode == "veiling":
            offset = self.view_net(spherical_harmonics(dirs, 3))[:, 6:9]
            raw = torch.cat([raw[:, :6], raw[:, 6:9] + offset], dim=-1)
        attn = F.softplus(raw[:, 0:3])
        bs = F.softplus(raw[:, 3:6])
        colour = torch.sigmoid(raw[:, 6:9]) * self.colour_max
        return attn, bs, colour
