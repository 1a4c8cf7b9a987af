"""Tests for seathru.geometry.upright: the vertical of a dive's world frame from its cameras."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from seathru.geometry.upright import estimate_up


def _camera(heading: float, pitch: float, roll: float = 0.0) -> np.ndarray:
    """Camera-to-world rotation (OpenCV axes) in a z-up world: looking along ``heading`` (rad
    from +x), ``pitch`` above the horizon, rolled by ``roll``."""
    forward = np.array([math.cos(pitch) * math.cos(heading),
                        math.cos(pitch) * math.sin(heading), math.sin(pitch)])
    right = np.array([math.sin(heading), -math.cos(heading), 0.0])
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward], axis=1)
    return rotation @ Rotation.from_rotvec(roll * np.array([0.0, 0.0, 1.0])).as_matrix()


def _angle(a, b) -> float:
    return math.degrees(math.acos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b),
                                          -1, 1)))


@pytest.mark.parametrize("arc_deg", [360.0, 60.0])
def test_level_cameras_give_the_vertical_of_a_pitched_down_orbit(arc_deg):
    rng = np.random.default_rng(0)
    world = Rotation.random(random_state=1).as_matrix()       # SfM's arbitrary orientation
    headings = np.radians(np.linspace(0.0, arc_deg, 16))
    poses = np.stack([world @ _camera(h, math.radians(-40), rng.normal(0, math.radians(2)))
                      for h in headings])
    up = estimate_up(poses)
    assert up.method == "level cameras"
    # roll jitter of 2 degrees tilts the estimate by about that over the heading spread
    assert _angle(up.vector, world @ np.array([0.0, 0.0, 1.0])) < (1.5 if arc_deg > 180 else 5.0)
    # what the cameras' mean up axis alone would give on the short arc: off by the pitch
    mean_up = -poses[:, :, 1].mean(0)
    if arc_deg < 90:
        assert _angle(mean_up, world @ np.array([0.0, 0.0, 1.0])) > 20.0


def test_cameras_facing_one_way_fall_back_to_their_mean_up_axis():
    poses = np.stack([_camera(0.01 * i, math.radians(-45)) for i in range(10)])
    up = estimate_up(poses)
    assert up.method == "mean camera up"
    assert np.allclose(up.vector, -poses[:, :, 1].mean(0) / np.linalg.norm(
        poses[:, :, 1].mean(0)))
    assert _angle(up.vector, [0.0, 0.0, 1.0]) == pytest.approx(45.0, abs=0.5)


def _posed(rotation: np.ndarray, centre) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, centre
    return pose


@pytest.mark.parametrize("slope_deg", [0.0, 10.0])
def test_a_transect_swum_at_one_depth_gives_the_vertical_of_its_path(slope_deg):
    """Cameras pitched 45 degrees down, all facing the way the diver swims: the path is a
    second horizontal direction, and the vertical comes within the path's slope of the truth
    where the mean up axis is off by the pitch."""
    rng = np.random.default_rng(0)
    world = Rotation.random(random_state=2).as_matrix()
    slope = math.radians(slope_deg)
    poses = np.stack([_posed(world @ _camera(rng.normal(0, 0.02), math.radians(-45),
                                             rng.normal(0, math.radians(1))),
                             world @ np.array([0.5 * i * math.cos(slope), 0.02 * rng.normal(),
                                               -0.5 * i * math.sin(slope)]))
                      for i in range(16)])
    up = estimate_up(poses)
    truth = world @ np.array([0.0, 0.0, 1.0])
    assert up.method == "level path"
    assert _angle(up.vector, truth) < slope_deg + 2.0
    assert _angle(-poses[:, :3, 1].mean(0), truth) > 40.0


def test_a_path_along_the_image_right_or_up_axis_is_not_taken_as_level():
    """Moving sideways leaves no second horizontal direction; sinking down a wall moves along
    the cameras' up axis: both keep the cameras' mean up axis."""
    sideways = np.stack([_posed(_camera(0.0, math.radians(-10)), [0.0, -0.4 * i, 0.0])
                         for i in range(10)])
    assert estimate_up(sideways).method == "mean camera up"
    sinking = np.stack([_posed(_camera(0.0, 0.0), [0.0, 0.0, -0.4 * i]) for i in range(10)])
    up = estimate_up(sinking)
    assert up.method == "mean camera up" and _angle(up.vector, [0.0, 0.0, 1.0]) < 1.0
    # a camera held in one place: no path at all
    still = np.stack([_posed(_camera(0.01 * i, math.radians(-45)), [0.0, 0.0, 0.0])
                      for i in range(10)])
    assert estimate_up(still).method == "mean camera up"


def test_no_cameras_is_an_error():
    with pytest.raises(ValueError, match="at least one camera"):
        estimate_up(np.zeros((0, 4, 4)))


def test_cameras_turned_every_way_have_no_common_vertical():
    rotations = Rotation.random(12, random_state=3).as_matrix()
    assert estimate_up(rotations) is None
    # landscape and portrait frames mixed: half the x axes are vertical
    mixed = np.stack([_camera(h, 0.0, math.pi / 2 if i % 2 else 0.0)
                      for i, h in enumerate(np.linspace(0, 2 * math.pi, 12, endpoint=False))])
    assert estimate_up(mixed) is None
