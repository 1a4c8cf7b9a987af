"""seathru.sim.sparse: points on the true surfaces with the views that see them unhidden, against
a scene whose ranges are known in closed form (a wall behind a nearer panel)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from seathru.sim.sparse import truth_sparse_points

WALL_Z, PANEL_Z = 6.0, 2.0
PANEL_X = (-0.2, 0.4)   # the panel covers this strip of x at z = PANEL_Z, every y
WIDTH, HEIGHT, FOCAL = 40, 30, 30.0


def _camera(x: float) -> SimpleNamespace:
    c2w = np.eye(4)
    c2w[0, 3] = x
    return SimpleNamespace(c2w_array=c2w, fx=FOCAL, fy=FOCAL, cx=WIDTH / 2, cy=HEIGHT / 2,
                           width=WIDTH, height=HEIGHT)


def _ranges(camera: SimpleNamespace) -> np.ndarray:
    """Exact range along each pixel's ray: the panel where the ray crosses it, else the wall."""
    u, v = np.meshgrid(np.arange(WIDTH) + 0.5, np.arange(HEIGHT) + 0.5)
    direction = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy,
                          np.ones_like(u)], -1)
    length = np.linalg.norm(direction, axis=-1)
    x_at_panel = camera.c2w_array[0, 3] + direction[..., 0] * PANEL_Z
    on_panel = (x_at_panel >= PANEL_X[0]) & (x_at_panel <= PANEL_X[1])
    return np.where(on_panel, PANEL_Z, WALL_Z) * length


def _on_a_surface(points: np.ndarray) -> np.ndarray:
    on_panel = (np.abs(points[:, 2] - PANEL_Z) < 1e-6) & (points[:, 0] >= PANEL_X[0] - 1e-6) \
        & (points[:, 0] <= PANEL_X[1] + 1e-6)
    return on_panel | (np.abs(points[:, 2] - WALL_Z) < 1e-6)


def _hidden_by_panel(camera: SimpleNamespace, points: np.ndarray) -> np.ndarray:
    """Wall points whose segment to the camera crosses the panel."""
    centre = camera.c2w_array[:3, 3]
    t = (PANEL_Z - centre[2]) / (points[:, 2] - centre[2])
    x = centre[0] + t * (points[:, 0] - centre[0])
    return (points[:, 2] > PANEL_Z + 1e-6) & (x >= PANEL_X[0]) & (x <= PANEL_X[1])


CAMERAS = [_camera(x) for x in (-1.03, -0.51, 0.02, 0.47, 0.98)]
RANGES = [_ranges(c) for c in CAMERAS]


def test_points_lie_on_the_surfaces_and_are_seen_exactly_where_nothing_hides_them():
    cloud = truth_sparse_points(CAMERAS, RANGES, per_view=200, min_views=2, seed=1)
    assert len(cloud.points) > 500
    assert _on_a_surface(cloud.points).all()
    assert (cloud.seen.sum(axis=1) >= 2).all()
    for view, camera in enumerate(CAMERAS):
        local = cloud.points - camera.c2w_array[:3, 3]
        column = FOCAL * local[:, 0] / local[:, 2] + WIDTH / 2
        row = FOCAL * local[:, 1] / local[:, 2] + HEIGHT / 2
        inside = (column >= 0) & (column < WIDTH) & (row >= 0) & (row < HEIGHT)
        # within a pixel or so of the panel's silhouette, or on a pixel border, the pixel
        # grid decides; everywhere else the exact geometry does
        silhouette = FOCAL * (np.asarray(PANEL_X) - camera.c2w_array[0, 3]) / PANEL_Z + WIDTH / 2
        edge = (np.abs(column[:, None] - silhouette[None, :]) < 1.5).any(axis=1)
        edge |= (np.abs(column - np.round(column)) < 0.01) | (np.abs(row - np.round(row)) < 0.01)
        expected = inside & ~_hidden_by_panel(camera, cloud.points)
        clear = ~edge & (column > 1) & (column < WIDTH - 1) & (row > 1) & (row < HEIGHT - 1)
        np.testing.assert_array_equal(cloud.seen[clear, view], expected[clear])
    # the panel hides part of the wall from some views: some wall points are seen by few
    wall = cloud.points[:, 2] > PANEL_Z + 1e-6
    assert (cloud.seen[wall].sum(axis=1) < len(CAMERAS)).any()


def test_more_views_required_keeps_fewer_points():
    two = truth_sparse_points(CAMERAS, RANGES, per_view=150, min_views=2, seed=3)
    four = truth_sparse_points(CAMERAS, RANGES, per_view=150, min_views=4, seed=3)
    assert len(four.points) < len(two.points)
    assert (four.seen.sum(axis=1) >= 4).all()


@pytest.mark.parametrize("noise", [0.01, 0.03])
def test_noise_moves_points_in_proportion_to_their_range(noise):
    exact = truth_sparse_points(CAMERAS, RANGES, per_view=300, seed=5)
    noisy = truth_sparse_points(CAMERAS, RANGES, per_view=300, seed=5, noise=noise)
    np.testing.assert_array_equal(exact.seen, noisy.seen)
    moved = noisy.points - exact.points
    # per axis the error's spread is noise x the range from the drawing view (2.0-7.4 here)
    spread = np.std(moved / np.linalg.norm(exact.points - [0, 0, 0], axis=1)[:, None])
    assert 0.5 * noise < spread < 1.5 * noise


def test_views_without_surfaces_give_an_empty_cloud():
    open_water = [np.full((HEIGHT, WIDTH), np.inf) for _ in CAMERAS]
    cloud = truth_sparse_points(CAMERAS, open_water, per_view=50)
    assert cloud.points.shape == (0, 3) and cloud.seen.shape == (0, len(CAMERAS))
    with pytest.raises(ValueError, match="range images"):
        truth_sparse_points(CAMERAS, open_water[:2])
