"""Camera rays and training ray batches.

Conventions (``seathru.io.cameras``): OpenCV camera axes (x right, y down, z forward), ``c2w``
maps camera to normalised world, the centre of pixel (u, v) is at (u + 0.5, v + 0.5). Ray
directions are unit vectors, so the distance ``t`` along a ray is the Euclidean range from the
camera centre (the SeaThru model's ``z``).

Downscaled rays: with ``downscale = s`` the image has ``H // s`` rows and ``W // s`` columns and
pixel (j, i) is the centre of the s x s block of full-resolution pixels it covers, at full
resolution coordinates ((j + 0.5) s, (i + 0.5) s).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from seathru.geometry.poses import pixel_of_points


def render_size(width: int, height: int, downscale: int = 1) -> tuple[int, int]:
    """(width, height) of an image rendered at ``downscale``: each side floor-divided, at least
    1 pixel (unlike ``seathru.radiometry.linearise.llff_downscaled_size``, which rounds).

    Example::

        render_size(641, 480, 2)  # (320, 240)
    """
    if downscale < 1:
        raise ValueError(f"downscale must be >= 1, got {downscale}")
    return max(1, width // downscale), max(1, height // downscale)


def camera_rays_np(c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float, width: int,
                   height: int, downscale: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Rays of every pixel, row-major, float64: origins (H*W, 3), unit directions (H*W, 3)."""
    out_w, out_h = render_size(width, height, downscale)
    u = (np.arange(out_w, dtype=np.float64) + 0.5) * downscale
    v = (np.arange(out_h, dtype=np.float64) + 0.5) * downscale
    uu, vv = np.meshgrid(u, v)  # (H, W), row-major like the image
    cam = np.stack([(uu - cx) / fx, (vv - cy) / fy, np.ones_like(uu)], axis=-1).reshape(-1, 3)
    c2w = np.asarray(c2w, dtype=np.float64)
    dirs = cam @ c2w[:3, :3].T
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    origins = np.broadcast_to(c2w[:3, 3], dirs.shape).copy()
    return origins, dirs


def frame_rays(frame, downscale: int = 1) -> tuple[Tensor, Tensor]:
    """Rays of a ``seathru.io.cameras.Frame``: origins (H*W, 3), unit directions (H*W, 3), float32.

    Row-major pixel order (reshape to (H // downscale, W // downscale, 3)).
    """
    origins, dirs = camera_rays_np(frame.c2w_array, frame.fx, frame.fy, frame.cx, frame.cy,
                                   frame.width, frame.height, downscale)
    return (torch.from_numpy(origins.astype(np.float32)),
            torch.from_numpy(dirs.astype(np.float32)))


def ray_box_intersect(origins: Tensor, dirs: Tensor, box_min: Tensor, box_max: Tensor
                      ) -> tuple[Tensor, Tensor]:
    """Slab test. origins, dirs (R, 3); box (3,). Returns t_in, t_out (R,); t_in > t_out: miss.

    Distances may be negative (box behind or around the origin).
    """
    safe = torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    inv = 1.0 / safe
    t0 = (box_min - origins) * inv
    t1 = (box_max - origins) * inv
    t_in = torch.minimum(t0, t1).amax(dim=-1)
    t_out = torch.maximum(t0, t1).amin(dim=-1)
    return t_in, t_out


def covisible_box(frames, min_fraction: float = 0.5, grid: tuple[int, int] = (16, 12),
                  depths: int = 32, padding: float = 0.05, depth_factor: float = 4.0
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box (min (3,), max (3,)) of the region that many cameras see, plus the cameras.

    Points on each camera's frustum (a ``grid`` of pixels, ``depths`` ranges geometric between
    the frame's near and far) count as co-visible when at least ``min_fraction`` of the cameras
    (and at least 2) see them within their own near/far. Ranges stop at ``depth_factor`` times
    the near bound (surfaces the cameras look at are rarely much farther than the nearest one,
    and beyond a few times that distance water hides them anyway). The box is where the model spends its
    full resolution; everything outside is still represented, contracted (see
    ``seathru.nerf.fields.contract``), so the box only has to cover the well-observed core.
    """
    frames = list(frames)
    if not frames:
        raise ValueError("covisible_box needs at least one frame")
    centres = np.array([f.c2w_array[:3, 3] for f in frames])
    points = []
    for f in frames:
        step_u = max(1, round(f.width / grid[0]))
        step_v = max(1, round(f.height / grid[1]))
        o, d = camera_rays_np(f.c2w_array, f.fx, f.fy, f.cx, f.cy, f.width, f.height, 1)
        d = d.reshape(f.height, f.width, 3)[step_v // 2::step_v, step_u // 2::step_u].reshape(-1, 3)
        near = max(f.near, 1e-6)
        far = max(min(f.far, depth_factor * near), near * 1.001 + 1e-6)
        ts = np.geomspace(near, far, depths)
        points.append((o[0][None, None, :] + d[:, None, :] * ts[None, :, None]).reshape(-1, 3))
    points = np.concatenate(points)
    counts = view_counts(points, frames)
    needed = max(2, int(np.ceil(min_fraction * len(frames)))) if len(frames) > 1 else 1
    core = points[counts >= needed]
    if len(core) < 16:  # too few views overlap: take the near half of every frustum instead
        core = points[np.linalg.norm(points - centres.mean(0), axis=-1)
                      <= np.median(np.linalg.norm(points - centres.mean(0), axis=-1))]
    core = np.concatenate([core, centres])
    lo, hi = core.min(axis=0), core.max(axis=0)
    size = np.maximum(hi - lo, 1e-3 * max(float(np.max(hi - lo)), 1e-6))
    pad = padding * size + 1e-6
    return lo - pad, hi + pad


def view_counts(points: np.ndarray, frames) -> np.ndarray:
    """How many frames see each point (P, 3): in front, inside the image, within near..far."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    counts = np.zeros(len(points), dtype=np.int32)
    for f in frames:
        w2c = np.linalg.inv(f.c2w_array)
        cam = points @ w2c[:3, :3].T + w2c[:3, 3]
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = f.fx * cam[:, 0] / z + f.cx
            v = f.fy * cam[:, 1] / z + f.cy
        dist = np.linalg.norm(cam, axis=-1)
        counts += (z > 0) & (u >= 0) & (u < f.width) & (v >= 0) & (v < f.height) \
            & (dist >= f.near) & (dist <= f.far)
    return counts


@dataclass
class RayBatch:
    """A batch of rays with their training targets (device tensors)."""

    origins: Tensor    # (R, 3)
    directions: Tensor  # (R, 3) unit
    near: Tensor       # (R,)
    far: Tensor        # (R,)
    rgb: Tensor        # (R, 3) linear target colour
    open_water: Tensor | None = None  # (R,) bool: the pixel shows open water (no surface)

    def __len__(self) -> int:
        return self.origins.shape[0]

    def to(self, device) -> "RayBatch":
        return RayBatch(*(getattr(self, k).to(device) for k in
                          ("origins", "directions", "near", "far", "rgb")),
                        None if self.open_water is None else self.open_water.to(device))

    def subset(self, index: Tensor) -> "RayBatch":
        return RayBatch(self.origins[index], self.directions[index], self.near[index],
                        self.far[index], self.rgb[index],
                        None if self.open_water is None else self.open_water[index])


@dataclass
class DepthRays:
    """Rays of the training views towards sparse 3D points (COLMAP's), with the range at which
    each meets its point: depth supervision (``loss.sparse_depth_weight``)."""

    rays: RayBatch   # rgb: the input colour of the point's pixel
    ranges: Tensor   # (R,) normalised units

    def __len__(self) -> int:
        return len(self.ranges)

    def sample(self, count: int, generator: torch.Generator) -> tuple[RayBatch, Tensor]:
        """``count`` rays and their ranges, drawn uniformly with replacement."""
        index = torch.randint(0, len(self), (count,), generator=generator).to(
            self.ranges.device)
        return self.rays.subset(index), self.ranges[index]


def depth_rays(frames, frame_index: np.ndarray, points: np.ndarray, colours: np.ndarray,
               device="cpu") -> DepthRays | None:
    """The rays from each frame's centre through its sparse points.

    Args:
        frames: ``seathru.io.cameras.Frame`` objects (normalised units).
        frame_index: (N,) index into ``frames`` of each observation.
        points: (N, 3) the observed 3D points, normalised units.
        colours: (N, 3) the input colour at each observation's pixel.

    Returns:
        the rays whose point lies within the frame's near..far, or None if none does.

    Example::

        rays = depth_rays(cameras.frames, obs.frames, obs.points, obs.observed)
    """
    centres = np.array([f.c2w_array[:3, 3] for f in frames], dtype=np.float64)[frame_index]
    offset = np.asarray(points, dtype=np.float64) - centres
    ranges = np.linalg.norm(offset, axis=-1)
    near = np.array([f.near for f in frames], dtype=np.float64)[frame_index]
    far = np.array([f.far for f in frames], dtype=np.float64)[frame_index]
    keep = (ranges > near) & (ranges < far) & np.isfinite(np.asarray(colours)).all(-1)
    if not keep.any():
        return None
    as_tensor = lambda a: torch.from_numpy(np.ascontiguousarray(a[keep], dtype=np.float32))  # noqa: E731
    rays = RayBatch(as_tensor(centres), as_tensor(offset / ranges[:, None]), as_tensor(near),
                    as_tensor(far), as_tensor(np.asarray(colours)))
    return DepthRays(rays.to(device), as_tensor(ranges).to(device))


class RayDataset:
    """All valid pixels of a set of frames: each pixel kept as its index and its colour, its
    ray made from the frames' cameras when a batch is drawn (:meth:`sample`, :meth:`batch`).

    A pixel costs 21 bytes (index 8, colour 12, open-water flag 1; 12 more with a deblurred
    colour); its ray is made when drawn because a stored ray would cost 65, and memory is
    what limits how many photographs at full working size one training takes
    (``benchmarks/results/train_memory.md``).

    Attributes: ``pixel_ids`` (R,) int64 on the CPU, ascending (frame offset + row * width +
    column); ``rgb`` (R, 3) the linear colours and ``open_water`` (R,) bool or None, on
    ``device``; ``deblurred_rgb`` (R, 3) on the CPU or None.

    ``images``: one (H, W, 3) float array per frame; ``masks``: (H, W) bool or None per frame.
    Pixels outside the mask or with a non-finite value are left out. ``open_water``: (H, W)
    bool per frame (``seathru.radiometry.open_water``), kept per ray, or None.
    ``deblurred``: one (H, W, 3) array per frame, the images with their processing blur taken
    out (``seathru.radiometry.deblur``), kept per ray on the CPU for the water fit
    (:meth:`fixed_subset` and :meth:`rays_through` with ``deblurred=True``), or None; an
    iterator may make them one at a time, each taken before the next is made.

    Example::

        data = RayDataset(frames, images, masks)
        batch = data.sample(1024, torch.Generator().manual_seed(0))   # a RayBatch
    """

    def __init__(self, frames, images, masks=None, device="cpu", open_water=None,
                 deblurred=None):
        self.frames = list(frames)
        self._pixel_offsets = np.cumsum([0] + [f.width * f.height for f in self.frames])
        masks = masks if masks is not None else [None] * len(frames)
        water_masks = open_water if open_water is not None else [None] * len(frames)
        self.depth_rays: DepthRays | None = None   # set by seathru.nerf.prepare
        # counted first, then filled frame by frame: no second copy of the set while gathered
        total = self.dropped_nonfinite = 0
        for frame, image, mask in zip(self.frames, images, masks):
            keep, nonfinite = self._valid_pixels(frame, image, mask)
            total, self.dropped_nonfinite = total + int(keep.sum()), \
                self.dropped_nonfinite + nonfinite
        # (R,) ascending: frame offset + row * width + column of each ray's pixel
        self.pixel_ids = torch.empty(total, dtype=torch.int64)
        self.rgb = torch.empty((total, 3), dtype=torch.float32)
        self.open_water = None if open_water is None else torch.zeros(total, dtype=torch.bool)
        self.deblurred_rgb = None if deblurred is None else torch.empty_like(self.rgb)
        sharp_images = iter(deblurred) if deblurred is not None else itertools.repeat(None)
        start = 0
        # the deblurred images first: a generator of them finishes (and logs) after the last
        for sharp, frame, image, mask, water_mask, offset in zip(
                sharp_images, self.frames, images, masks, water_masks, self._pixel_offsets):
            pixels = np.flatnonzero(self._valid_pixels(frame, image, mask)[0])
            end = start + len(pixels)
            self.pixel_ids[start:end] = torch.from_numpy(pixels + int(offset))
            self.rgb[start:end] = torch.from_numpy(
                np.asarray(image, np.float32).reshape(-1, 3)[pixels])
            if self.open_water is not None and water_mask is not None:
                self.open_water[start:end] = torch.from_numpy(
                    np.asarray(water_mask, bool).reshape(-1)[pixels])
            if self.deblurred_rgb is not None:
                self.deblurred_rgb[start:end] = torch.from_numpy(
                    np.asarray(sharp, np.float32).reshape(-1, 3)[pixels])
            start = end
        self.device = torch.device(device)
        self.rgb = self.rgb.to(self.device)
        if self.open_water is not None:
            self.open_water = self.open_water.to(self.device)
        self._cameras = _CameraTable(self.frames, self._pixel_offsets, self.device)
        self._device_ids = self.pixel_ids.to(self.device)

    @staticmethod
    def _valid_pixels(frame, image, mask) -> tuple[np.ndarray, int]:
        """(H * W,) bool: the pixels that are finite and inside the mask; and how many are not
        finite (inside the mask or not)."""
        if np.shape(image)[:2] != (frame.height, frame.width):
            raise ValueError(f"frame {frame.name}: image is {np.shape(image)[1]}x"
                             f"{np.shape(image)[0]}, cameras say {frame.width}x{frame.height}")
        keep = np.isfinite(image).all(axis=-1)
        nonfinite = int(keep.size - keep.sum())
        if mask is not None:
            keep &= np.asarray(mask, dtype=bool)
        return keep.reshape(-1), nonfinite

    def __len__(self) -> int:
        return len(self.pixel_ids)

    def batch(self, index: Tensor, deblurred: bool = False) -> RayBatch:
        """The rays at ``index`` (R,) into the dataset, with their colours; with
        ``deblurred``, the colours from the deblurred images where the dataset has them."""
        device_index = index.to(self.device)
        origins, directions, near, far = self._cameras.rays(self._device_ids[device_index])
        rgb = self.rgb[device_index]
        if deblurred and self.deblurred_rgb is not None:
            rgb = self.deblurred_rgb[index.cpu()].to(self.device)
        return RayBatch(origins, directions, near, far, rgb,
                        None if self.open_water is None else self.open_water[device_index])

    def sample(self, count: int, generator: torch.Generator) -> RayBatch:
        """``count`` rays drawn uniformly with replacement (indices from ``generator``, CPU)."""
        return self.batch(torch.randint(0, len(self), (count,), generator=generator))

    def hold_out(self, count: int, seed: int) -> RayBatch:
        """Remove a reproducible random subset of at most ``count`` rays and return it (rays
        the training never samples: a validation set drawn from the training views)."""
        generator = torch.Generator().manual_seed(seed)
        # int32: the same permutation as int64 (tested), in half the memory
        order = torch.randperm(len(self), generator=generator, dtype=torch.int32)
        chosen = order[:min(count, len(self) // 2)].long()
        del order
        held = self.batch(chosen)
        keep = torch.ones(len(self), dtype=torch.bool)
        keep[chosen] = False
        kept_here = keep.to(self.device)
        # one array at a time: the set is never held twice
        self.pixel_ids = self.pixel_ids[keep]
        self._device_ids = self.pixel_ids.to(self.device)
        self.rgb = self.rgb[kept_here]
        if self.open_water is not None:
            self.open_water = self.open_water[kept_here]
        if self.deblurred_rgb is not None:
            self.deblurred_rgb = self.deblurred_rgb[keep]
        return held

    def rays_through(self, points: np.ndarray, deblurred: bool = False
                     ) -> tuple[RayBatch, np.ndarray]:
        """The dataset's rays whose pixel each point falls in, in every frame that has the
        point in front of it and inside its image (pixels left out of the dataset, masked or
        held out, give none). Whether the frame sees the point or something in front of it is
        for the caller to judge (the model's depth).

        Args:
            points: (N, 3) world points (the frames' normalised units).
            deblurred: colour from the deblurred images (see the class), where kept.

        Returns:
            the rays (M of them) and (M,) the index into ``points`` of each.

        Example::

            rays, which = dataset.rays_through(surface_points)
        """
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        wanted, owners = [], []
        for index, frame in enumerate(self.frames):
            row, column, _, inside = pixel_of_points(frame.c2w_array, frame.fx, frame.fy,
                                                     frame.cx, frame.cy, frame.width,
                                                     frame.height, points)
            wanted.append(self._pixel_offsets[index] + row[inside] * frame.width
                          + column[inside])
            owners.append(np.flatnonzero(inside))
        wanted_t = torch.from_numpy(np.concatenate(wanted).astype(np.int64))
        owners_np = np.concatenate(owners)
        position = torch.searchsorted(self.pixel_ids, wanted_t).clamp_max(len(self.pixel_ids) - 1)
        present = (self.pixel_ids[position] == wanted_t).numpy()
        index = position[torch.from_numpy(present)]
        return self.batch(index, deblurred), owners_np[present]

    def fixed_subset(self, count: int, seed: int, deblurred: bool = False) -> RayBatch:
        """A reproducible subset of at most ``count`` rays (evaluation probes); with
        ``deblurred``, their colour from the deblurred images where kept (see the class)."""
        generator = torch.Generator().manual_seed(seed)
        count = min(count, len(self))
        index = torch.randperm(len(self), generator=generator, dtype=torch.int32)[:count].long()
        return self.batch(index, deblurred)


class _CameraTable:
    """The frames' cameras as tensors, for making the rays of pixels by their dataset index
    (frame offset + row * width + column), as :func:`camera_rays_np` makes them: in float64,
    returned in float32."""

    def __init__(self, frames, pixel_offsets: np.ndarray, device):
        as_tensor = lambda values: torch.tensor(np.asarray(values, np.float64),  # noqa: E731
                                                device=device)
        c2w = np.array([np.asarray(f.c2w_array, np.float64) for f in frames]).reshape(-1, 4, 4)
        self.rotations, self.centres = as_tensor(c2w[:, :3, :3]), as_tensor(c2w[:, :3, 3])
        self.intrinsics = as_tensor([[f.fx, f.fy, f.cx, f.cy] for f in frames]).reshape(-1, 4)
        self.bounds = as_tensor([[f.near, f.far] for f in frames]).reshape(-1, 2)
        self.widths = torch.tensor([int(f.width) for f in frames], dtype=torch.int64,
                                   device=device)
        self.offsets = torch.as_tensor(np.asarray(pixel_offsets, np.int64), device=device)

    def rays(self, pixel_ids: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Origins (R, 3), unit directions (R, 3), near (R,) and far (R,) of the pixels."""
        frame = torch.searchsorted(self.offsets, pixel_ids, right=True) - 1
        local = pixel_ids - self.offsets[frame]
        width = self.widths[frame]
        row = torch.div(local, width, rounding_mode="floor")
        fx, fy, cx, cy = self.intrinsics[frame].unbind(-1)
        cam = torch.stack([((local - row * width).double() + 0.5 - cx) / fx,
                           (row.double() + 0.5 - cy) / fy, torch.ones_like(fx)], dim=-1)
        directions = (self.rotations[frame] @ cam.unsqueeze(-1)).squeeze(-1)
        directions = directions / torch.linalg.vector_norm(directions, dim=-1, keepdim=True)
        near, far = self.bounds[frame].unbind(-1)
        return (self.centres[frame].float(), directions.float(), near.float(), far.float())
