"""A smooth camera path through the training poses, for fly-through videos.

The path visits the training cameras in capture order: positions follow a cubic spline
(``scipy.interpolate.CubicSpline``, natural end conditions) through key positions, rotations are
spherically interpolated (``scipy.spatial.transform.Slerp``) between key rotations, and both are
parameterised by arc length (chord length between keys) so the camera moves at a steady speed.
With many training images, neighbouring poses are first averaged into at most ``max_keys`` key
poses, which removes the hand-held jitter of a dive.

Poses are ``(N, 4, 4)`` camera-to-world matrices (any convention: the rotation is interpolated
as a whole). Pure numpy / scipy, no file I/O.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, Slerp

DEFAULT_MAX_KEYS = 12


def path_length(centres: np.ndarray) -> float:
    """Sum of the distances between consecutive ``(N, 3)`` points."""
    return float(np.linalg.norm(np.diff(centres, axis=0), axis=1).sum()) if len(centres) > 1 \
        else 0.0


def nearest_neighbour_chain(centres: np.ndarray) -> np.ndarray:
    """Indices visiting every point once, greedily stepping to the nearest unvisited one.

    Starts from the point farthest from the centroid, which tends to be one end of the sweep.
    """
    centres = np.asarray(centres, dtype=np.float64)
    n = len(centres)
    if n == 0:
        return np.zeros(0, dtype=int)
    current = int(np.argmax(np.linalg.norm(centres - centres.mean(axis=0), axis=1)))
    order, visited = [current], np.zeros(n, dtype=bool)
    visited[current] = True
    for _ in range(n - 1):
        distances = np.linalg.norm(centres - centres[current], axis=1)
        distances[visited] = np.inf
        current = int(np.argmin(distances))
        order.append(current)
        visited[current] = True
    return np.asarray(order)


def capture_order(centres: np.ndarray, names: list[str] | None = None,
                  tolerance: float = 1.5) -> np.ndarray:
    """The order to visit the cameras in.

    Image names usually follow the capture sequence, which is the natural path. When the path in
    name order is more than ``tolerance`` times longer than the greedy nearest-neighbour chain
    (names that are not sequential, or grid-like forward-facing captures), the chain is used.
    """
    centres = np.asarray(centres, dtype=np.float64)
    by_name = (np.argsort(np.asarray(names), kind="stable") if names is not None
               else np.arange(len(centres)))
    chain = nearest_neighbour_chain(centres)
    if path_length(centres[by_name]) > tolerance * path_length(centres[chain]):
        return chain
    return by_name


def key_poses(c2w: np.ndarray, max_keys: int = DEFAULT_MAX_KEYS) -> np.ndarray:
    """At most ``max_keys`` poses, each the mean of a run of consecutive poses.

    ``c2w``: ``(N, 4, 4)`` in visiting order. The first and last keys average the first and
    last runs; rotations are averaged with ``Rotation.mean`` (chordal L2 mean).
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    n = len(c2w)
    if n <= max_keys:
        return c2w.copy()
    bounds = np.linspace(0, n, max_keys + 1).round().astype(int)
    keys = []
    for start, stop in zip(bounds[:-1], bounds[1:]):
        run = c2w[start:stop]
        key = np.eye(4)
        key[:3, :3] = Rotation.from_matrix(run[:, :3, :3]).mean().as_matrix()
        key[:3, 3] = run[:, :3, 3].mean(axis=0)
        keys.append(key)
    return np.stack(keys)


def interpolate_poses(keys: np.ndarray, n_frames: int) -> np.ndarray:
    """``n_frames`` poses along a cubic spline / slerp through the ``(K, 4, 4)`` key poses.

    The first and last output poses equal the first and last keys.
    """
    keys = np.asarray(keys, dtype=np.float64)
    if n_frames <= 0:
        return np.zeros((0, 4, 4))
    if len(keys) == 1:
        return np.repeat(keys, n_frames, axis=0)
    centres = keys[:, :3, 3]
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    rotations = Rotation.from_matrix(keys[:, :3, :3])
    angles = (rotations[:-1].inv() * rotations[1:]).magnitude()
    # Parameter: arc length, with turning in place counted too so keys never coincide in time.
    scene_size = max(float(np.ptp(centres, axis=0).max()), 1e-12)
    steps = steps + angles * scene_size * 0.1 + 1e-9 * scene_size
    knots = np.concatenate([[0.0], np.cumsum(steps)])
    times = np.linspace(0.0, knots[-1], n_frames)
    positions = CubicSpline(knots, centres, bc_type="natural")(times)
    out = np.tile(np.eye(4), (n_frames, 1, 1))
    out[:, :3, :3] = Slerp(knots, rotations)(times).as_matrix()
    out[:, :3, 3] = positions
    return out


def smooth_camera_path(c2w: np.ndarray, n_frames: int, names: list[str] | None = None,
                       max_keys: int = DEFAULT_MAX_KEYS) -> np.ndarray:
    """A smooth ``(n_frames, 4, 4)`` path through ``(N, 4, 4)`` training poses.

    Orders the cameras (:func:`capture_order`), reduces them to key poses (:func:`key_poses`) and
    interpolates (:func:`interpolate_poses`).
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.ndim != 3 or c2w.shape[1:] != (4, 4) or len(c2w) == 0:
        raise ValueError(f"expected (N, 4, 4) poses with N >= 1, got {c2w.shape}")
    order = capture_order(c2w[:, :3, 3], names)
    return interpolate_poses(key_poses(c2w[order], max_keys), n_frames)


def path_frames(cameras, n_frames: int, max_keys: int = DEFAULT_MAX_KEYS) -> list:
    """``n_frames`` camera frames along the smooth path through the training cameras of a
    ``seathru.io.cameras.CameraSet``: named ``path_0000``, ..., split ``path``, with the first
    training frame's intrinsics and the scene-wide near/far bounds (no image)."""
    train = sorted(cameras.split("train"), key=lambda f: f.name)
    poses = smooth_camera_path(np.stack([f.c2w_array for f in train]), n_frames,
                               names=[f.name for f in train], max_keys=max_keys)
    return [replace(train[0], name=f"path_{i:04d}", image="", mask=None, split="path",
                    c2w=pose.tolist(), near=float(cameras.near), far=float(cameras.far))
            for i, pose in enumerate(poses)]
