"""A novel view restored with the detail of the restored training photographs, by reprojection.

The model's restored render of a view no camera took lacks what the model has not learnt (fine
texture, sharp edges), and dividing out the water magnifies that loss. The training photographs
hold that detail, and :func:`seathru.radiometry.restore.restore_photograph` carries it into
their restored versions: ``detail = restored photograph - restored render`` in each training
view. The surface behind a pixel of the novel view (its rendered range) is found in every
training view that sees it unhidden (its own rendered range agrees), and the detail there is
averaged, weighted towards the views that look at it from nearly the same direction (the
restored colour is taken as the same from every direction; a nearby view also shares the novel
view's parallax and glints). Averaging several views also averages their noise.

Pixels no training view sees (and open water) keep the model's restored render. Measured on the
demo, with the choice of defaults: docs/water.md, "Restored novel views with the photographs'
detail".
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from seathru.geometry.poses import pixel_of_points
from seathru.nerf.rays import camera_rays_np
from seathru.radiometry.restore import DEFAULT_REPROJECT_ANGLE, DEFAULT_REPROJECT_TOLERANCE

#: A training pixel lends its detail only where its own render holds a surface.
MIN_SOURCE_OPACITY = 0.5
MAX_SOURCES = 8
#: Pixels of a view sampled to choose its ``max_sources``.
SOURCE_SAMPLE = 4096
#: Support (the sum of the lending sources' angle weights) from which a restored pixel counts
#: as backed by the photographs: one source looking along the view's own ray, or two or three
#: within the angle. On the demo the pixels below it held most of the restored view's error.
SUPPORTED = 1.0


@dataclass(frozen=True)
class SourceView:
    """A training view's restored detail, with what is needed to find it from another view.

    Attributes:
        camera: the view's camera (a ``seathru.io.cameras.Frame``: ``c2w_array``, ``fx``,
            ``fy``, ``cx``, ``cy``, ``width``, ``height``, at full resolution).
        depth: ``(h, w)`` rendered range along each pixel's ray, in the cameras' units.
        opacity: ``(h, w)`` rendered object opacity.
        detail: ``(h, w, 3)`` restored photograph minus restored render.
        downscale: the render's (``seathru.nerf.inference.render_frame``): pixel ``(i, j)``
            is centred at ``((j + 0.5) * downscale, (i + 0.5) * downscale)`` of the camera.
    """

    camera: Any
    depth: np.ndarray
    opacity: np.ndarray
    detail: np.ndarray
    downscale: int = 1

    @classmethod
    def from_render(cls, camera, images: Mapping[str, np.ndarray], restored_photo: np.ndarray,
                    downscale: int = 1) -> SourceView:
        """The source of a training view from its render (``depth``, ``opacity``,
        ``restored``: ``seathru.nerf.inference.render_frame``) and its restored photograph;
        held in half precision (10 bytes a pixel: every training view is kept at once; the
        range to 0.05%, far finer than the tolerance)."""
        return cls(camera, np.asarray(images["depth"], np.float16),
                   np.asarray(images["opacity"], np.float16),
                   (np.asarray(restored_photo, np.float32)
                    - np.asarray(images["restored"], np.float32)).astype(np.float16), downscale)


def reprojected_detail(camera, depth: np.ndarray, sources: Iterable[SourceView],
                       downscale: int = 1, tolerance: float = DEFAULT_REPROJECT_TOLERANCE,
                       angle_degrees: float = DEFAULT_REPROJECT_ANGLE,
                       max_sources: int = MAX_SOURCES) -> tuple[np.ndarray, np.ndarray]:
    """The training views' restored detail at each pixel of a view, and the weight behind it.

    Args:
        camera: the view's camera (as :class:`SourceView`'s).
        depth: ``(H, W)`` the view's rendered range along each pixel's ray, rendered at
            ``downscale`` (as :class:`SourceView`'s).
        sources: the training views.
        tolerance: a source sees a pixel's surface point when its own rendered range at the
            pixel the point falls in agrees with the point's distance within this share
            (nothing nearer hides it), and its opacity there is at least 0.5.
        angle_degrees: a source counts ``exp(-(1 - cos a) / (1 - cos angle_degrees))`` where
            its ray to the point makes the angle ``a`` with the view's ray: ``1/e`` at this
            angle.
        max_sources: only the sources that lend the most weight (on a sample of the view's
            pixels) are read: a view's time grows with the sources read, and the angle
            weight leaves little to the others.

    Returns:
        ``(detail (H, W, 3), weight (H, W))``, float64: the weighted mean of the sources'
        detail (bilinear at the point's position in each), 0 with weight 0 where none sees it.

    Example::

        sources = [SourceView.from_render(f, render_frame(model, f), photo) for f, photo in ...]
        detail, weight = reprojected_detail(view, render["depth"], sources)
        restored = render["restored"] + render["opacity"][..., None] * detail
    """
    from scipy.ndimage import map_coordinates

    if tolerance <= 0 or not 0 < angle_degrees < 180:
        raise ValueError(f"tolerance must be > 0 and angle_degrees in (0, 180), got "
                         f"{tolerance}, {angle_degrees}")
    depth = np.asarray(depth, np.float64)
    height, width = depth.shape
    origins, directions = camera_rays_np(camera.c2w_array, camera.fx, camera.fy, camera.cx,
                                         camera.cy, camera.width, camera.height, downscale)
    if len(origins) != depth.size:
        raise ValueError(f"depth {depth.shape} is not {camera.name}'s render at downscale "
                         f"{downscale}")
    with np.errstate(invalid="ignore"):
        surface = np.isfinite(depth).reshape(-1) & (depth.reshape(-1) > 0)
    points = origins + directions * np.where(surface, depth.reshape(-1), 0.0)[:, None]
    spread = 1.0 - np.cos(np.radians(angle_degrees))
    sources = list(sources)
    if len(sources) > max_sources:   # the views that lend most, judged on a sample of pixels
        sample = np.flatnonzero(surface)[::max(1, int(surface.sum()) // SOURCE_SAMPLE)]
        lent = [_lent(source, points[sample], directions[sample], tolerance, spread)[1].sum()
                for source in sources]
        sources = [sources[i] for i in np.argsort(lent)[::-1][:max_sources]]
    total = np.zeros((height * width, 3))
    weights = np.zeros(height * width)
    on_surface = np.flatnonzero(surface)
    for source in sources:
        seen, weight, at = _lent(source, points[on_surface], directions[on_surface], tolerance,
                                 spread)
        if not seen.any():
            continue
        detail = np.stack([map_coordinates(source.detail[..., c].astype(np.float32), at,
                                           order=1, mode="nearest") for c in range(3)], -1)
        where = on_surface[seen]
        total[where] += weight[:, None] * detail
        weights[where] += weight
    mean = np.divide(total, weights[:, None], out=np.zeros_like(total),
                     where=weights[:, None] > 0)
    return mean.reshape(height, width, 3), weights.reshape(height, width)


def _lent(source: SourceView, points: np.ndarray, directions: np.ndarray, tolerance: float,
          spread: float) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Which ``points`` (N, 3) on rays ``directions`` (N, 3) a source sees unhidden, ``(N,)``
    bool; the weight of each seen one; and where each lies in the source's arrays (row and
    column coordinates, for ``map_coordinates``)."""
    cam, scale = source.camera, 1.0 / source.downscale
    rows, cols = source.depth.shape
    fx, fy, cx, cy = cam.fx * scale, cam.fy * scale, cam.cx * scale, cam.cy * scale
    row, column, local, inside = pixel_of_points(cam.c2w_array, fx, fy, cx, cy, cols, rows,
                                                 points)
    distance = np.linalg.norm(local, axis=-1)
    there = source.depth[row, column].astype(np.float64)
    with np.errstate(invalid="ignore"):
        seen = (inside & (source.opacity[row, column] >= MIN_SOURCE_OPACITY)
                & (np.abs(there - distance) <= tolerance * distance))
    towards = (points[seen] - cam.c2w_array[:3, 3]) / distance[seen, None]
    weight = np.exp(-(1.0 - np.sum(towards * directions[seen], axis=-1)) / spread)
    z = local[seen, 2]
    return seen, weight, [fy * local[seen, 1] / z + cy - 0.5, fx * local[seen, 0] / z + cx - 0.5]


def restored_with_detail(camera, render: Mapping[str, np.ndarray],
                         sources: Iterable[SourceView], downscale: int = 1,
                         tolerance: float = DEFAULT_REPROJECT_TOLERANCE,
                         angle_degrees: float = DEFAULT_REPROJECT_ANGLE) -> np.ndarray:
    """A view's restored render with the training photographs' restored detail added: the
    image of :func:`restored_and_support`."""
    return restored_and_support(camera, render, sources, downscale, tolerance,
                                angle_degrees)[0]


def restored_and_support(camera, render: Mapping[str, np.ndarray],
                         sources: Iterable[SourceView], downscale: int = 1,
                         tolerance: float = DEFAULT_REPROJECT_TOLERANCE,
                         angle_degrees: float = DEFAULT_REPROJECT_ANGLE
                         ) -> tuple[np.ndarray, np.ndarray]:
    """A view's restored render with the training photographs' restored detail added, and how
    much the photographs back each pixel.

    Args:
        camera: the view's camera (as :class:`SourceView`'s).
        render: its ``seathru.nerf.inference.render_frame`` dict: ``restored`` ``(H, W, 3)``,
            ``depth`` and ``opacity`` ``(H, W)``.
        sources, downscale, tolerance, angle_degrees: as :func:`reprojected_detail`.

    Returns:
        ``(image, support)``: ``(H, W, 3)`` float32, non-negative, ``restored + opacity *
        detail`` (the opacity leaves open water as the model renders it); ``(H, W)`` float32,
        the sum of the angle weights of the training views that see each pixel's surface
        (0 where none does: the model's restored render alone; from :data:`SUPPORTED` up
        the photographs back it).

    Example::

        image, support = restored_and_support(view, render_frame(model, view), sources)
        trusted = support >= SUPPORTED
    """
    detail, support = reprojected_detail(camera, render["depth"], sources, downscale,
                                         tolerance, angle_degrees)
    result = (np.asarray(render["restored"], np.float64)
              + np.asarray(render["opacity"], np.float64)[..., None] * detail)
    image = np.clip(np.nan_to_num(result, nan=0.0, posinf=0.0), 0.0, None).astype(np.float32)
    return image, support.astype(np.float32)
