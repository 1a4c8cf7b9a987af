"""Camera paths of the simulated dives: a diver circling the scene's target (orbit) and one
swimming a straight line over the seabed with the camera pitched down (transect); the reef
survey's path is in ``seathru.sim.reef``. Poses are camera-to-world (4, 4), OpenCV axes
(x right, y down, z forward), world z up. No file I/O.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from seathru.sim.scene import Scene


def look_at(eye: Sequence[float], target: Sequence[float], roll: float = 0.0) -> np.ndarray:
    """Camera-to-world (4, 4), OpenCV axes (x right, y down, z forward), world z up."""
    eye = np.asarray(eye, np.float64)
    forward = np.asarray(target, np.float64) - eye
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-9:  # looking straight up or down: any right vector will do
        right = np.array([1.0, 0.0, 0.0]) - forward[0] * forward
    right = right / np.linalg.norm(right)
    down = np.cross(forward, right)
    c, s = math.cos(roll), math.sin(roll)
    right, down = c * right + s * down, -s * right + c * down
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, eye
    return c2w


def orbit_path(scene: Scene, views: int, rng: np.random.Generator, radius: float = 2.5,
               height: float = 2.2, height_variation: float = 0.2) -> np.ndarray:
    """Diver circling ``scene.target`` once at ``radius`` m, ``height`` m above the seabed
    (varying by +-``height_variation``), looking at the target with small aim and roll jitter.
    Returns (views, 4, 4) camera-to-world."""
    target = np.asarray(scene.target)
    poses = []
    for i in range(views):
        angle = 2.0 * math.pi * i / views + rng.uniform(-0.03, 0.03)
        x = target[0] + radius * math.cos(angle)
        y = target[1] + radius * math.sin(angle)
        ground = float(scene.seabed.height(np.array(x), np.array(y)))
        z = ground + height + height_variation * math.sin(2.0 * angle + 0.4)
        aim = target + rng.normal(0.0, 0.05, 3)
        poses.append(look_at((x, y, z), aim, roll=rng.normal(0.0, math.radians(2.0))))
    return np.stack(poses)


def transect_path(scene: Scene, views: int, rng: np.random.Generator, length: float = 6.0,
                  height: float = 1.6, pitch_deg: float = 45.0) -> np.ndarray:
    """Diver swimming along +x at ``height`` m above the seabed (bobbing +-0.1 m), camera
    pitched ``pitch_deg`` below the horizon; the footprint centre sweeps ``length`` m across the
    scene centre with a slow lateral sway, while the diver looks around a little (yaw +-6 deg,
    pitch +-4 deg): pure forward motion over a plane would leave the focal length ambiguous to
    self-calibrating SfM. Returns (views, 4, 4) camera-to-world."""
    reach = height / math.tan(math.radians(pitch_deg))
    poses = []
    for i in range(views):
        frac = i / max(views - 1, 1)
        look_x = scene.target[0] - 0.5 * length + frac * length
        x = look_x - reach
        y = scene.target[1] + 0.3 * math.sin(2.0 * math.pi * frac) + rng.normal(0.0, 0.02)
        ground = float(scene.seabed.height(np.array(x), np.array(y)))
        z = ground + height + 0.1 * math.sin(3.0 * math.pi * frac) + rng.normal(0.0, 0.02)
        yaw = math.radians(6.0) * math.sin(2.0 * math.pi * frac) + rng.normal(0.0, 0.02)
        pitch = math.radians(pitch_deg + 4.0 * math.cos(3.0 * math.pi * frac)) + rng.normal(
            0.0, 0.02)
        forward = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw),
                            -math.sin(pitch)])
        poses.append(look_at((x, y, z), np.array([x, y, z]) + forward,
                             roll=rng.normal(0.0, math.radians(2.0))))
    return np.stack(poses)
