"""Restored detail reprojected from training views into a novel view (seathru.nerf.reproject)."""

from __future__ import annotations

import numpy as np
import pytest

from seathru.io.cameras import Frame
from seathru.nerf.rays import camera_rays_np
from seathru.nerf.reproject import (SUPPORTED, SourceView, reprojected_detail,
                                    restored_and_support, restored_with_detail)

PLANE_Z = 5.0


def camera(x: float = 0.0, width: int = 64, height: int = 48, name: str = "view") -> Frame:
    c2w = np.eye(4)
    c2w[0, 3] = x
    return Frame(name=name, image=f"{name}.png", width=width, height=height, fx=60.0, fy=60.0,
                 cx=width / 2, cy=height / 2, c2w=c2w.tolist(), near=0.1, far=50.0)


def pixel_rays(cam: Frame, downscale: int = 1) -> tuple[np.ndarray, np.ndarray]:
    return camera_rays_np(cam.c2w_array, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height,
                          downscale)


def plane_range(cam: Frame, downscale: int = 1) -> np.ndarray:
    """Range along each pixel's ray to the plane z = PLANE_Z (cameras look along +z)."""
    _, directions = pixel_rays(cam, downscale)
    return (PLANE_Z / directions[:, 2]).reshape(cam.height // downscale, cam.width // downscale)


def texture(points: np.ndarray) -> np.ndarray:
    """A smooth colour pattern on the plane, (N, 3)."""
    x, y = points[:, 0], points[:, 1]
    return np.stack([np.sin(1.3 * x), np.cos(0.9 * y), 0.5 * np.sin(x + y)], -1)


def source_of(cam: Frame, downscale: int = 1, detail=None) -> SourceView:
    depth = plane_range(cam, downscale)
    height, width = depth.shape
    if detail is None:
        origins, directions = pixel_rays(cam, downscale)
        detail = texture(origins + directions * depth.reshape(-1, 1)).reshape(height, width, 3)
    detail = np.broadcast_to(np.asarray(detail, np.float64), (height, width, 3))
    return SourceView(cam, depth.astype(np.float32), np.ones((height, width), np.float32),
                      np.asarray(detail, np.float32), downscale)


def test_the_detail_on_a_surface_is_found_again_from_another_view():
    view = camera(0.3)
    depth = plane_range(view)
    detail, weight = reprojected_detail(view, depth, [source_of(camera(0.0)),
                                                      source_of(camera(0.6))])
    origins, directions = pixel_rays(view)
    expected = texture(origins + directions * depth.reshape(-1, 1)).reshape(48, 64, 3)
    seen = weight > 0
    assert seen.mean() > 0.9
    np.testing.assert_allclose(detail[seen], expected[seen], atol=5e-3)


def test_a_source_rendered_at_half_size_is_read_at_the_right_pixels():
    view = camera(0.2)
    depth = plane_range(view)
    full, _ = reprojected_detail(view, depth, [source_of(camera(0.0))])
    half, weight = reprojected_detail(view, depth, [source_of(camera(0.0), downscale=2)])
    # away from the source's border, where the half-size image has no pixel centre to lean on
    columns = np.flatnonzero((weight > 0).any(axis=0))
    inner = weight > 0
    inner[:2], inner[-2:] = False, False
    inner[:, :columns[0] + 2], inner[:, columns[-1] - 1:] = False, False
    np.testing.assert_allclose(half[inner], full[inner], atol=0.03)


def test_a_source_with_something_nearer_in_the_way_lends_nothing():
    view = camera(0.0)
    blocked = source_of(camera(0.5), detail=[1.0, 1.0, 1.0])
    blocked.depth[:] *= 0.5   # its render holds a surface at half the range
    detail, weight = reprojected_detail(view, plane_range(view), [blocked])
    assert not weight.any()
    assert not detail.any()


def test_a_source_whose_render_holds_no_surface_there_lends_nothing():
    view = camera(0.0)
    empty = source_of(camera(0.5), detail=[1.0, 1.0, 1.0])
    empty.opacity[:] = 0.2
    _, weight = reprojected_detail(view, plane_range(view), [empty])
    assert not weight.any()


def test_views_looking_from_nearly_the_same_direction_count_more():
    view = camera(0.0)
    near_source = source_of(camera(0.1, name="near"), detail=[1.0, 1.0, 1.0])
    far_source = source_of(camera(2.0, name="far"), detail=[0.0, 0.0, 0.0])
    depth = plane_range(view)
    detail, weight = reprojected_detail(view, depth, [near_source, far_source],
                                        angle_degrees=8.0)
    pixel = (24, 32)
    _, directions = pixel_rays(view)
    ray = directions[pixel[0] * 64 + pixel[1]]
    point = ray * depth[pixel]
    spread = 1 - np.cos(np.radians(8.0))

    def weight_of(x: float) -> float:
        towards = (point - [x, 0, 0]) / np.linalg.norm(point - [x, 0, 0])
        return float(np.exp(-(1 - towards @ ray) / spread))

    near, far = weight_of(0.1), weight_of(2.0)
    assert weight[pixel] == pytest.approx(near + far, rel=1e-6)
    assert detail[pixel][0] == pytest.approx(near / (near + far), rel=1e-6)
    assert detail[pixel][0] > 0.9


def test_pixels_no_source_sees_and_open_water_keep_the_restored_render():
    view = camera(0.0)
    depth = plane_range(view)
    depth[:, :10] = np.inf     # open water on the left
    restored = np.full((48, 64, 3), 0.4, np.float32)
    render = {"restored": restored, "depth": depth, "opacity": np.ones((48, 64))}
    source = source_of(camera(1.5), detail=[0.1, 0.2, 0.3])   # sees the right part only
    result = restored_with_detail(view, render, [source])
    _, weight = reprojected_detail(view, depth, [source])
    unseen = weight == 0
    assert unseen[:, :10].all() and 0 < unseen.mean() < 1
    np.testing.assert_array_equal(result[unseen], restored[unseen])
    np.testing.assert_allclose(result[~unseen], restored[~unseen] + [0.1, 0.2, 0.3], atol=1e-6)


def test_the_support_says_how_many_views_back_a_pixel_and_from_how_near():
    """One view along the same rays backs every pixel it sees (support 1 = SUPPORTED), one
    30 degrees off barely counts, a second one alongside doubles it; open water and pixels
    no view sees have none."""
    view = camera(0.0)
    depth = plane_range(view)
    depth[:, :6] = np.inf
    render = {"restored": np.full((48, 64, 3), 0.4, np.float32), "depth": depth,
              "opacity": np.ones((48, 64))}
    same = source_of(camera(0.0, name="same"))
    aside = source_of(camera(PLANE_Z * np.tan(np.radians(30)), name="aside"))
    image, support = restored_and_support(view, render, [same])
    np.testing.assert_array_equal(image, restored_with_detail(view, render, [same]))
    assert support.dtype == np.float32 and support.shape == depth.shape
    np.testing.assert_allclose(support[:, 6:], 1.0, atol=1e-4)
    assert (support[:, :6] == 0).all() and SUPPORTED == 1.0
    _, off = restored_and_support(view, render, [aside])
    assert 0 < off.max() < 0.01
    _, both = restored_and_support(view, render, [same, source_of(camera(0.0, name="twin"))])
    np.testing.assert_allclose(both[:, 6:], 2.0, atol=2e-4)


def test_the_detail_is_blended_in_by_the_views_opacity_and_never_goes_negative():
    view = camera(0.0)
    depth = plane_range(view)
    render = {"restored": np.full((48, 64, 3), 0.1), "depth": depth,
              "opacity": np.full((48, 64), 0.5)}
    result = restored_with_detail(view, render, [source_of(camera(0.1), detail=[-1.0, 0.2, 0])])
    _, weight = reprojected_detail(view, depth, [source_of(camera(0.1))])
    seen = weight > 0
    assert seen.mean() > 0.5
    np.testing.assert_allclose(result[seen], [[0.0, 0.2, 0.1]] * int(seen.sum()), atol=1e-6)
    assert result.dtype == np.float32


def test_the_training_views_detail_is_their_restored_photograph_less_their_render():
    cam = camera()
    images = {"depth": np.full((2, 2), 3.0), "opacity": np.ones((2, 2)),
              "restored": np.full((2, 2, 3), 0.25)}
    source = SourceView.from_render(cam, images, np.full((2, 2, 3), 0.5), downscale=32)
    np.testing.assert_allclose(source.detail, 0.25)
    assert source.detail.dtype == np.float16 and source.downscale == 32


def test_a_depth_not_rendered_at_the_given_downscale_is_refused():
    view = camera()
    with pytest.raises(ValueError, match="downscale 2"):
        reprojected_detail(view, plane_range(view), [], downscale=2)


@pytest.mark.parametrize("tolerance, angle", [(0.0, 8.0), (0.05, 0.0), (0.05, 180.0)])
def test_settings_out_of_range_are_refused(tolerance, angle):
    view = camera()
    with pytest.raises(ValueError, match="tolerance"):
        reprojected_detail(view, plane_range(view), [], 1, tolerance, angle)


def test_only_the_sources_that_lend_most_are_read():
    view = camera(0.0)
    depth = plane_range(view)
    near = [source_of(camera(x, name=f"near{x}"), detail=[1.0, 1.0, 1.0]) for x in (-0.05, 0.05)]
    far = [source_of(camera(x, name=f"far{x}"), detail=[0.0, 0.0, 0.0])
           for x in (-2.0, -1.5, 1.5, 2.0)]
    detail, weight = reprojected_detail(view, depth, far + near, max_sources=2)
    seen = weight > 0
    assert seen.mean() > 0.9
    np.testing.assert_allclose(detail[seen], 1.0, atol=1e-3)
    everything, _ = reprojected_detail(view, depth, far + near, max_sources=6)
    assert everything[seen].min() < 0.999
