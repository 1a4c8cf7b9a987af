"""Object fields: density and colour of the scene's surfaces, in pure PyTorch (CPU or CUDA).

Space. The scene box (``SceneBox``, normalised world units) maps to ``[-1, 1]^3``; space outside
it is contracted (``contract``, the L-infinity form of mip-NeRF 360's contraction) into the
shell ``1 < |u|_inf < 2``, so a seabed that runs to the horizon is still represented, with a
resolution that falls off with distance. Grid coordinates are ``g = contract(u) / 2`` in
``[-1, 1]^3``, the ``align_corners=True`` convention of ``torch.nn.functional.grid_sample``.

``GridField`` (the default, fast model):
- density: the sum of a coarse and a fine dense 3D grid of raw values, trilinearly
  interpolated, then ``exp`` (truncated gradient), i.e. post-activation as in DVGO, so one voxel
  can hold a sharp surface; the coarse grid (each voxel crossed by many rays) finds the geometry
  in a few dozen steps, the fine one adds detail;
- colour: factorised tri-plane features (K-Planes: the Hadamard product of the xy, xz and yz
  plane features, at a coarse and a fine level, concatenated), decoded by a tiny MLP, optionally
  with the view direction (spherical harmonics, degree 3);
- coarse to fine: ``resize(density_res, plane_res)`` resamples the grids to a finer resolution
  during training (``F.interpolate`` with the same corner alignment keeps the function).

``MLPField`` is the paper-faithful baseline (positional encoding, 8 x 256 MLP with a skip).

Shapes: points ``g`` (P, 3) grid coordinates; directions (P, 3) unit; density (P,); colour (P, 3).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn


# ----------------------------------------------------------------------------------- geometry

class SceneBox(nn.Module):
    """Axis-aligned box in normalised world units; maps world points to grid coordinates."""

    def __init__(self, box_min, box_max):
        super().__init__()
        box_min = torch.as_tensor(box_min, dtype=torch.float32).reshape(3)
        box_max = torch.as_tensor(box_max, dtype=torch.float32).reshape(3)
        if not bool((box_max > box_min).all()):
            raise ValueError(f"scene box must have max > min, got {box_min} {box_max}")
        self.register_buffer("box_min", box_min)
        self.register_buffer("box_max", box_max)

    @property
    def centre(self) -> Tensor:
        return 0.5 * (self.box_min + self.box_max)

    @property
    def half_size(self) -> Tensor:
        return 0.5 * (self.box_max - self.box_min)

    def to_unit(self, points: Tensor) -> Tensor:
        """World (P, 3) -> box coordinates, the box being [-1, 1]^3."""
        return (points - self.centre) / self.half_size

    def to_grid(self, points: Tensor) -> Tensor:
        """World (P, 3) -> grid coordinates in [-1, 1]^3 (contracted outside the box)."""
        return contract(self.to_unit(points)) * 0.5


def contract(u: Tensor) -> Tensor:
    """L-infinity contraction: identity in [-1, 1]^3, the rest of space into |u|_inf < 2."""
    norm = u.abs().amax(dim=-1, keepdim=True).clamp_min(1e-9)
    scale = torch.where(norm <= 1.0, torch.ones_like(norm), (2.0 - 1.0 / norm) / norm)
    return u * scale


def uncontract(v: Tensor, max_norm: float = 1.999) -> Tensor:
    """Inverse of ``contract`` (contracted points with |v|_inf near 2 map very far away)."""
    norm = v.abs().amax(dim=-1, keepdim=True).clamp(1e-9, max_norm)
    scale = torch.where(norm <= 1.0, torch.ones_like(norm), 1.0 / ((2.0 - norm) * norm))
    return v * scale


def grid_vertices(box: "SceneBox", dims_xyz: list[int]) -> Tensor:
    """World positions of a grid's vertices, (D, H, W, 3) (x fastest, like the grid tensors)."""
    axes = [torch.linspace(-1.0, 1.0, n) for n in dims_xyz]
    z, y, x = torch.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    g = torch.stack([x, y, z], dim=-1)
    return uncontract(2.0 * g) * box.half_size.cpu() + box.centre.cpu()


def axis_resolution(resolution: int, extent: Tensor | list, minimum: int = 8) -> list[int]:
    """Per-axis cell counts: ``resolution`` along the longest box axis, proportional elsewhere.

    Returned in (x, y, z) order.
    """
    extent = [float(e) for e in extent]
    longest = max(extent)
    return [max(minimum, int(round(resolution * e / longest))) for e in extent]


class _TruncExp(torch.autograd.Function):
    """exp with its gradient clamped (instant-NGP), so a large raw density cannot blow up."""

    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return torch.exp(x)

    @staticmethod
    def backward(ctx, grad):
        (x,) = ctx.saved_tensors
        return grad * torch.exp(x.clamp(max=15.0))


def trunc_exp(x: Tensor) -> Tensor:
    return _TruncExp.apply(x)


def spherical_harmonics(dirs: Tensor, degree: int = 3) -> Tensor:
    """Real SH basis up to ``degree`` (1, 4, 9 or 16 values) of unit directions (P, 3)."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, 0.28209479177387814)]
    if degree >= 1:
        out += [-0.48860251190291987 * y, 0.48860251190291987 * z, -0.48860251190291987 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [1.0925484305920792 * xy, -1.0925484305920792 * yz,
                0.31539156525252005 * (2 * zz - xx - yy), -1.0925484305920792 * xz,
                0.5462742152960396 * (xx - yy)]
    if degree >= 3:
        out += [-0.5900435899266435 * y * (3 * xx - yy), 2.890611442640554 * xy * z,
                -0.4570457994644658 * y * (4 * zz - xx - yy),
                0.3731763325901154 * z * (2 * zz - 3 * xx - 3 * yy),
                -0.4570457994644658 * x * (4 * zz - xx - yy),
                1.445305721320277 * z * (xx - yy), -0.5900435899266435 * x * (xx - 3 * yy)]
    return torch.stack(out, dim=-1)


def positional_encoding(x: Tensor, frequencies: int, include_input: bool = True) -> Tensor:
    """NeRF's encoding: [x, sin(2^k pi x), cos(2^k pi x)] for k < frequencies. (P, D) -> (P, D')."""
    scales = (2.0 ** torch.arange(frequencies, device=x.device, dtype=x.dtype)) * math.pi
    angles = (x[..., None, :] * scales[:, None]).flatten(-2)
    parts = [x] if include_input else []
    return torch.cat(parts + [torch.sin(angles), torch.cos(angles)], dim=-1)


# ------------------------------------------------------------------------------ grid field

def _resize_volume(volume: Tensor, dims_xyz: list[int]) -> Tensor:
    """(1, C, D, H, W) volume resampled to (W, H, D) = dims_xyz, corner-aligned trilinear."""
    return F.interpolate(volume, size=(dims_xyz[2], dims_xyz[1], dims_xyz[0]), mode="trilinear",
                         align_corners=True)


def _resize_plane(plane: Tensor, size_hw: tuple[int, int]) -> Tensor:
    return F.interpolate(plane, size=size_hw, mode="bilinear", align_corners=True)


# (first axis, second axis) of each plane; a plane is stored (1, C, n_second, n_first).
PLANE_AXES = ((0, 1), (0, 2), (1, 2))


_GRID_SAMPLE_3D = dict(mode="bilinear", padding_mode="border", align_corners=True)
_BORDER, _BILINEAR = 1, 0  # aten's enum values of padding_mode="border", mode="bilinear"


def _split_for_threads(volume: Tensor, g: Tensor) -> tuple[Tensor, Tensor, int]:
    # PyTorch's CPU kernel of grid_sample in 3D runs one thread per batch item, so a single
    # volume read at many points uses one core: the points are split into one batch item per
    # thread, reading the same (expanded, not copied) volume. Small reads stay whole: there
    # the threads' start-up costs more than the work they share.
    parts = torch.get_num_threads() if g.device.type == "cpu" and g.shape[0] >= 4096 else 1
    pad = (-g.shape[0]) % parts
    if pad:
        g = torch.cat([g, g.new_zeros(pad, 3)])
    return volume.expand(parts, *volume.shape[1:]), g.reshape(parts, -1, 1, 1, 3), pad


class _TrilinearLookup(torch.autograd.Function):
    """``grid_sample`` of a volume at points, forward on all threads; gradient for the volume
    only (the points are sample positions, never trained)."""

    @staticmethod
    def forward(ctx, volume: Tensor, g: Tensor) -> Tensor:
        batched, grid, pad = _split_for_threads(volume, g)
        values = F.grid_sample(batched, grid, **_GRID_SAMPLE_3D)  # (parts, C, P/parts, 1, 1)
        values = values.reshape(batched.shape[0], volume.shape[1], -1).permute(0, 2, 1)
        values = values.reshape(-1, volume.shape[1])
        ctx.save_for_backward(volume, g)
        return values[:g.shape[0]] if pad else values

    @staticmethod
    def backward(ctx, grad: Tensor):
        volume, g = ctx.saved_tensors
        grad_volume, _ = torch.ops.aten.grid_sampler_3d_backward(
            grad.t().reshape(1, volume.shape[1], -1, 1, 1).contiguous(), volume,
            g.reshape(1, -1, 1, 1, 3), _BILINEAR, _BORDER, True, [True, False])
        return grad_volume, None


def trilinear_lookup(volume: Tensor, g: Tensor) -> Tensor:
    """Trilinear values of a volume at grid coordinates, with border padding.

    The same values as ``F.grid_sample(volume, g.reshape(1, -1, 1, 1, 3), mode="bilinear",
    padding_mode="border", align_corners=True)``, but on every CPU thread (PyTorch's CPU
    kernel parallelises over the batch only), and differentiable in ``volume`` only.

    Args:
        volume: (1, C, D, H, W) values at the grid vertices (x along W).
        g: (P, 3) grid coordinates (x, y, z) in [-1, 1] (clamped to the border outside).

    Returns:
        (P, C) values.

    Example:
        >>> volume = torch.arange(8.0).reshape(1, 1, 2, 2, 2)
        >>> trilinear_lookup(volume, torch.zeros(1, 3))  # the centre: the mean of the corners
        tensor([[3.5000]])
    """
    g = g.to(volume.dtype)
    if g.requires_grad:
        values = F.grid_sample(volume, g.reshape(1, -1, 1, 1, 3), **_GRID_SAMPLE_3D)
        return values.reshape(volume.shape[1], -1).t()
    return _TrilinearLookup.apply(volume, g)


class DensityGrid(nn.Module):
    """Raw density = coarse grid + fine grid (trilinear); density = exp(raw).

    The coarse grid (few voxels, each crossed by many rays) finds the geometry within a few
    dozen steps; the fine grid (zero at first, resampled finer during training) adds detail.
    """

    def __init__(self, coarse_dims_xyz: list[int], dims_xyz: list[int], init_density: float):
        super().__init__()
        coarse = torch.full((1, 1, coarse_dims_xyz[2], coarse_dims_xyz[1], coarse_dims_xyz[0]),
                            math.log(init_density))
        self.coarse = nn.Parameter(coarse)
        self.raw = nn.Parameter(torch.zeros(1, 1, dims_xyz[2], dims_xyz[1], dims_xyz[0]))

    @property
    def dims_xyz(self) -> list[int]:
        return [self.raw.shape[4], self.raw.shape[3], self.raw.shape[2]]

    def raw_at(self, g: Tensor) -> Tensor:
        return (trilinear_lookup(self.raw, g) + trilinear_lookup(self.coarse, g)).reshape(-1)

    def forward(self, g: Tensor) -> Tensor:
        return trunc_exp(self.raw_at(g))

    def resized(self, dims_xyz: list[int]) -> Tensor:
        return _resize_volume(self.raw.detach(), dims_xyz)

    def vertex_raw(self) -> Tensor:
        """Raw density at the fine grid's vertices (1, 1, D, H, W)."""
        d, h, w = self.raw.shape[-3:]
        coarse = F.interpolate(self.coarse.detach(), size=(d, h, w), mode="trilinear",
                               align_corners=True)
        return self.raw.detach() + coarse


class TriPlanes(nn.Module):
    """K-Planes features: per level, product of the xy, xz, yz plane features (C each)."""

    def __init__(self, levels_dims: list[list[int]], channels: int, init_range=(0.5, 1.0)):
        super().__init__()
        self.channels = channels
        self.planes = nn.ParameterList()
        for dims in levels_dims:
            for a, b in PLANE_AXES:
                plane = torch.empty(1, channels, dims[b], dims[a]).uniform_(*init_range)
                self.planes.append(nn.Parameter(plane))

    @property
    def levels(self) -> int:
        return len(self.planes) // 3

    @property
    def out_features(self) -> int:
        return self.levels * self.channels

    def level_dims(self, level: int) -> list[int]:
        xy, xz = self.planes[3 * level], self.planes[3 * level + 1]
        return [xy.shape[3], xy.shape[2], xz.shape[2]]

    def forward(self, g: Tensor) -> Tensor:
        features = []
        for level in range(self.levels):
            product = None
            for k, (a, b) in enumerate(PLANE_AXES):
                plane = self.planes[3 * level + k]
                coords = torch.stack([g[:, a], g[:, b]], dim=-1).reshape(1, -1, 1, 2)
                value = F.grid_sample(plane, coords.to(plane.dtype), mode="bilinear",
                                      padding_mode="border", align_corners=True)
                value = value.reshape(self.channels, -1)
                product = value if product is None else product * value
            features.append(product)
        return torch.cat(features, dim=0).t()

    def resized(self, level: int, dims_xyz: list[int]) -> list[Tensor]:
        return [_resize_plane(self.planes[3 * level + k].detach(), (dims_xyz[b], dims_xyz[a]))
                for k, (a, b) in enumerate(PLANE_AXES)]


class ColourDecoder(nn.Module):
    """Tiny MLP: features (+ SH of the view direction) -> linear RGB in (0, colour_max).

    The direction enters through its own first-layer weights (``view``), started at zero: a
    view-dependent decoder starts from view-independent colours. ``view_dependent="auto"``
    builds it switched off; switching it on (:meth:`set_view_enabled`) starts from the same
    colours and lets the direction's weights train from there (the decision is
    ``Trainer.select_view_dependence``). The switch is a buffer, so checkpoints keep it.
    """

    def __init__(self, in_features: int, hidden: int, view_dependent: bool | str,
                 colour_max: float):
        super().__init__()
        self.view_dependent = view_dependent in (True, "on", "auto")
        self.colour_max = colour_max
        self.net = nn.Sequential(nn.Linear(in_features, hidden), nn.ReLU(inplace=True),
                                 nn.Linear(hidden, 3))
        if self.view_dependent:
            self.view = nn.Linear(16, hidden, bias=False)
            nn.init.zeros_(self.view.weight)
        if view_dependent == "auto":
            self.register_buffer("view_enabled", torch.tensor(False))

    @property
    def uses_view(self) -> bool:
        """Whether the colour currently depends on the view direction."""
        enabled = getattr(self, "view_enabled", None)
        return self.view_dependent and (enabled is None or bool(enabled))

    def set_view_enabled(self, enabled: bool) -> None:
        """Switch the view input of an ``auto`` decoder on or off."""
        if not hasattr(self, "view_enabled"):
            raise ValueError("only a decoder built with view_dependent='auto' can be switched")
        self.view_enabled.fill_(bool(enabled))

    def view_parameters(self) -> list[nn.Parameter]:
        return list(self.view.parameters()) if self.view_dependent else []

    def init_colour(self, rgb) -> None:
        """Start every point at colour ``rgb`` (3,), e.g. the images' mean colour."""
        rgb = torch.as_tensor(rgb, dtype=torch.float32).reshape(3) / self.colour_max
        rgb = rgb.clamp(1e-3, 1 - 1e-3)
        with torch.no_grad():
            self.net[-1].bias.copy_(torch.log(rgb / (1 - rgb)))
            self.net[-1].weight.mul_(0.5)

    def forward(self, features: Tensor, dirs: Tensor | None) -> Tensor:
        hidden = self.net[0](features)
        if self.uses_view:
            hidden = hidden + self.view(spherical_harmonics(dirs, 3))
        return torch.sigmoid(self.net[2](self.net[1](hidden))) * self.colour_max


class GridField(nn.Module):
    """Dense density grid + tri-plane colour features; see the module docstring."""

    def __init__(self, box_extent, density_res: int, plane_res: int, plane_coarse_res: int,
                 channels: int, hidden: int, view_dependent: bool | str, colour_max: float,
                 init_density: float, density_coarse_res: int = 32):
        super().__init__()
        # Grid coordinates span the box plus the contracted shell: twice the box per axis.
        self.extent = [float(e) for e in box_extent]
        self.density = DensityGrid(axis_resolution(density_coarse_res, self.extent, 4),
                                   axis_resolution(density_res, self.extent), init_density)
        self.planes = TriPlanes([axis_resolution(plane_coarse_res, self.extent),
                                 axis_resolution(plane_res, self.extent)], channels)
        self.decoder = ColourDecoder(self.planes.out_features, hidden, view_dependent, colour_max)

    def density_at(self, g: Tensor) -> Tensor:
        return self.density(g)

    @property
    def uses_view(self) -> bool:
        return self.decoder.uses_view

    def colour_at(self, g: Tensor, dirs: Tensor | None) -> Tensor:
        return self.decoder(self.planes(g), dirs)

    def resize(self, density_res: int, plane_res: int) -> dict[str, Tensor]:
        """Resampled values of the grids at a new resolution: {parameter name: tensor}."""
        out = {"density.raw": self.density.resized(axis_resolution(density_res, self.extent))}
        fine = self.planes.levels - 1
        for k, plane in enumerate(self.planes.resized(fine, axis_resolution(plane_res,
                                                                            self.extent))):
            out[f"planes.planes.{3 * fine + k}"] = plane
        return out

    def grid_parameters(self) -> list[nn.Parameter]:
        return [self.density.coarse, self.density.raw]

    def feature_parameters(self) -> list[nn.Parameter]:
        return list(self.planes.parameters())

    def network_parameters(self) -> list[nn.Parameter]:
        return list(self.decoder.net.parameters())   # the direction's weights: view_parameters

    def view_parameters(self) -> list[nn.Parameter]:
        return self.decoder.view_parameters()

    @torch.no_grad()
    def occupancy_density(self, dilate: int = 1) -> Tensor:
        """Density on the grid vertices, max-pooled over ``dilate`` voxels: (1, 1, D, H, W)."""
        density = torch.exp(self.density.vertex_raw().clamp(max=30.0))
        if dilate > 0:
            density = F.max_pool3d(density, 2 * dilate + 1, stride=1, padding=dilate)
        return density


# ------------------------------------------------------------------------- paper baseline

class MLPField(nn.Module):
    """NeRF MLP: PE(10) of grid coordinates -> 8 x 256 (skip at 4) -> density and feature;
    feature + PE(4) of the direction -> 128 -> RGB. Density: softplus."""

    def __init__(self, width: int = 256, depth: int = 8, pos_freqs: int = 10,
                 dir_freqs: int = 4, colour_max: float = 1.0, view_dependent: bool = True):
        super().__init__()
        self.pos_freqs, self.dir_freqs = pos_freqs, dir_freqs
        self.view_dependent = view_dependent
        self.colour_max = colour_max
        in_pos = 3 + 6 * pos_freqs
        self.skip = depth // 2
        layers = []
        for i in range(depth):
            fan_in = in_pos if i == 0 else width + (in_pos if i == self.skip else 0)
            layers.append(nn.Linear(fan_in, width))
        self.layers = nn.ModuleList(layers)
        self.density_head = nn.Linear(width, 1)
        self.feature = nn.Linear(width, width)
        in_dir = (3 + 6 * dir_freqs) if view_dependent else 0
        self.colour = nn.Sequential(nn.Linear(width + in_dir, width // 2), nn.ReLU(inplace=True),
                                    nn.Linear(width // 2, 3))

    def _trunk(self, g: Tensor) -> Tensor:
        x = encoded = positional_encoding(g, self.pos_freqs)
        for i, layer in enumerate(self.layers):
            if i == self.skip:
                x = torch.cat([x, encoded], dim=-1)
            x = F.relu(layer(x))
        return x

    def density_and_colour(self, g: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
        h = self._trunk(g)
        density = F.softplus(self.density_head(h).squeeze(-1) - 1.0)
        feature = self.feature(h)
        if self.view_dependent:
            feature = torch.cat([feature, positional_encoding(dirs, self.dir_freqs)], dim=-1)
        return density, torch.sigmoid(self.colour(feature)) * self.colour_max

    def grid_parameters(self) -> list[nn.Parameter]:
        return []

    def feature_parameters(self) -> list[nn.Parameter]:
        return []

    def network_parameters(self) -> list[nn.Parameter]:
        return list(self.parameters())

    def view_parameters(self) -> list[nn.Parameter]:
        return []
