"""Which way is up in a dive's world frame, from its cameras alone.

SfM leaves the world frame's orientation arbitrary. A diver keeps the camera nearly level (small
roll), so each camera's x axis (image right) is nearly horizontal; the vertical is the direction
all of them are perpendicular to. When the diver looked in one direction only (a transect), the
x axes are all alike and leave the vertical free to turn about them; then the cameras' mean up
axis is taken, which is off by the dive's mean pitch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class UpEstimate:
    vector: tuple[float, float, float]   # unit, world frame
    method: str                          # "level cameras" or "mean camera up"


def estimate_up(c2w: np.ndarray, min_spread: float = 0.05, max_tilt_deg: float = 20.0
                ) -> UpEstimate | None:
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

    Returns:
        the unit up vector (pointing to the side the cameras' up axes point to on average) and
        the method used; None where the cameras do not agree on one.

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
    if tilt > largest_tilt:
        return None
    up = up / np.linalg.norm(up)
    return UpEstimate(tuple(float(v) for v in up), method)

