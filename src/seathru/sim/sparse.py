"""Sparse 3D points of a simulated dive as structure from motion would triangulate them, taken
from the simulator's true ranges instead of feature matches.

The water benchmark trains on the simulator's true cameras, without COLMAP; a point cloud made
here stands in for the one COLMAP would give, so that what the sparse points feed (the depth
loss, the track cue of the medium decision) is measured there too.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from seathru.geometry.poses import sees_unhidden


@dataclass
class SparsePoints:
    """Points on the true surfaces and the views that see them."""

    points: np.ndarray   # (M, 3) float64, the cameras' world frame and units
    seen: np.ndarray     # (M, V) bool: view v sees point m unhidden


def truth_sparse_points(frames: Sequence, ranges: Sequence[np.ndarray], per_view: int = 300,
                        min_views: int = 2, tolerance: float = 0.01, noise: float = 0.0,
                        seed: int = 0) -> SparsePoints:
    """Points on the surfaces the views see, each with the views that see it.

    Each view contributes ``per_view`` pixels drawn at random among those with a surface; the
    surface point behind a pixel is kept when at least ``min_views`` views (the drawing one
    included) see it: in front of the camera, inside its image, and that view's own true range
    at the pixel it falls on agrees with the point's range within ``tolerance`` (relative), so
    nothing nearer hides it. The same test as the evaluation's coverage
    (``seathru.eval.truth.training_view_coverage``).

    Args:
        frames: V cameras with ``c2w_array`` (4, 4), ``fx``, ``fy``, ``cx``, ``cy``, ``width``,
            ``height`` (``seathru.io.cameras.Frame``), OpenCV axes.
        ranges: V arrays ``(H, W)``: the true range along each pixel's ray; non-finite or <= 0
            where the pixel sees open water.
        per_view: pixels drawn in each view.
        min_views: views that must see a point for it to be kept (two to triangulate one).
        tolerance: relative range agreement for "not hidden".
        noise: triangulation error: each kept point moves by a normal draw of standard
            deviation ``noise`` times its range from the drawing view, along each axis.
        seed: seeds the pixel draw and the noise.

    Returns:
        :class:`SparsePoints` with M <= V * per_view points.

    Example::

        cloud = truth_sparse_points(cameras.frames, [read_image(d) for d in depth_paths])
        cloud.seen.sum(axis=1).min() >= 2
    """
    if len(frames) != len(ranges):
        raise ValueError(f"{len(frames)} frames but {len(ranges)} range images")
    rng = np.random.default_rng(seed)
    ranges = [np.asarray(r, dtype=np.float64) for r in ranges]
    drawn, distance_from_drawing = [], []
    for frame, view_range in zip(frames, ranges):
        surface = np.flatnonzero(np.isfinite(view_range) & (view_range > 0))
        if not surface.size:
            continue
        pick = rng.choice(surface, size=min(per_view, surface.size), replace=False)
        row, col = np.divmod(pick, view_range.shape[1])
        direction = np.stack([(col + 0.5 - frame.cx) / frame.fx,
                              (row + 0.5 - frame.cy) / frame.fy, np.ones(len(pick))], -1)
        direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
        distance = view_range[row, col]
        c2w = np.asarray(frame.c2w_array, dtype=np.float64)
        drawn.append((direction * distance[:, None]) @ c2w[:3, :3].T + c2w[:3, 3])
        distance_from_drawing.append(distance)
    if not drawn:
        return SparsePoints(np.zeros((0, 3)), np.zeros((0, len(frames)), bool))
    points = np.concatenate(drawn)
    seen = np.stack([sees_unhidden(frame, view_range, points, tolerance)
                     for frame, view_range in zip(frames, ranges)], axis=1)
    keep = seen.sum(axis=1) >= min_views
    points, seen = points[keep], seen[keep]
    if noise > 0:
        scale = noise * np.concatenate(distance_from_drawing)[keep]
        points = points + rng.normal(size=points.shape) * scale[:, None]
    return SparsePoints(points, seen)

