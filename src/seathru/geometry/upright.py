"""Which way is up in a dive's world frame, from its cameras alone.

SfM leaves the world frame's orientation arbitrary. A diver keeps the camera nearly level (small
roll), so each camera's x axis (image right) is nearly horizontal; the vertical is the direction
all of them are perpendicular to. When the diver looked in one direction only (a transect), the
x axes are all alike and leave the vertical free to turn about them. A diver also holds a depth
while swimming a transect, so where the cameras moved along a line across their x axes, that
line is a second horizontal direction ("level path": off by the path's slope, where the
cameras' mean up axis is off by their pitch; docs/water.md). Otherwise the cameras' mean up
axis is taken.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class UpEstimate:
    vector: tuple[float, float, float]   # unit, world frame
    method: str                          # "level cameras" or "mean camera up"


def estimate_up(c2w: np.ndarray, min_spread: float = 0.05, max_tilt_deg: float = 20.0,
                max_pitch_deg: float = 60.0) -> UpEstimate | None:
    """The vertical of the world frame, from camera-to-world poses with OpenCV axes.

    Args:
        c2w: ``(N, 3, 3)`` or ``(N, 3, 4)`` / ``(N, 4, 4)`` camera-to-world poses (x right,
            y down, z forward).
        min_spread: the x axes must span a plane for their normal to be the vertical: the
            middle eigenvalue of their second-moment matrix, over the largest, at least this
            (0.05: views about 25 degrees apart in heading or more). Below it, the mean of the
            cameras' up axes (``-y``) is returned.
        max_tilt_deg: the cameras must agree on it: the x axes' RMS angle to the horizon, or
            (mean camera up) the up axes' RMS angle to their mean, at most this. Frames shot
            in portrait and landscape mixed, or a camera turned about freely, have no common
            vertical.
        max_pitch_deg: a level path's vertical is taken only within this angle of the
            cameras' mean up axis (a diver sinking down a wall moves along the cameras' up
            axis: the path is then not level, and its vertical would lie in the horizon).

    Returns:
        the unit up vector (pointing to the side the cameras' up axes point to on average) and
        the method used ("level cameras", "level path" or "mean camera up"); None where the
        cameras do not agree on one.

    Example::

        up = np.array(estimate_up(poses).vector)
        elevation = np.degrees(np.arcsin(directions @ up))  # above the horizon > 0
    """
    rotations = np.asarray(c2w, dtype=np.float64)[:, :3, :3]
    if len(rotations) == 0:
        raise ValueError("estimate_up needs at least one camera")
    rights = rotations[:, :, 0]
    ups = -rotations[:, :, 1]
    mean_up = ups.mean(0)
    if np.linalg.norm(mean_up) < 1e-9:
        mean_up = ups[0]
    moments = rights.T @ rights / len(rights)
    values, vectors = np.linalg.eigh(moments)   # ascending
    largest_tilt = math.sin(math.radians(max_tilt_deg)) ** 2
    if values[1] >= min_spread * values[2]:
        up, method = vectors[:, 0], "level cameras"
        if up @ mean_up < 0:
            up = -up
        tilt = values[0] / max(values.sum(), 1e-12)      # mean squared sine of the x axes
    else:
        up, method = mean_up, "mean camera up"
        unit = up / np.linalg.norm(up)
        tilt = float(np.mean(1.0 - np.clip(ups @ unit, -1.0, 1.0) ** 2))
        level = _level_path_up(np.asarray(c2w, dtype=np.float64), rights.mean(0), unit,
                               max_pitch_deg)
        if level is not None:
            up, method = level, "level path"
    if tilt > largest_tilt:
        return None
    up = up / np.linalg.norm(up)
    return UpEstimate(tuple(float(v) for v in up), method)


def _level_path_up(c2w: np.ndarray, right: np.ndarray, mean_up: np.ndarray,
                   max_pitch_deg: float, max_width: float = 0.25,
                   max_along_right_deg: float = 45.0) -> np.ndarray | None:
    """The normal of the cameras' mean x axis and the line their centres lie along, or None:
    no centres (rotations only), fewer than three, a path not a line (its second spread over
    the first above ``max_width``), one running within ``max_along_right_deg`` of the x axis
    (a diver moving sideways: no second direction), or a normal further than
    ``max_pitch_deg`` from the cameras' mean up axis."""
    if c2w.shape[-1] < 4 or len(c2w) < 3:
        return None
    centres = c2w[:, :3, 3]
    values, vectors = np.linalg.eigh(np.cov(centres.T))    # ascending
    if values[2] <= 1e-12 or values[1] > max_width * values[2]:
        return None
    along, right = vectors[:, 2], right / max(np.linalg.norm(right), 1e-12)
    if abs(float(along @ right)) > math.cos(math.radians(max_along_right_deg)):
        return None
    up = np.cross(along, right)
    up /= np.linalg.norm(up)
    if up @ mean_up < 0:
        up = -up
    if float(up @ mean_up) < math.cos(math.radians(max_pitch_deg)):
        return None
    return up

