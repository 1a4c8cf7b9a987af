"""Camera geometry: similarity alignment, pose comparison, axis conventions, bounds, normalisation.

Pure numpy, float64, no file I/O. Shapes:
- points ``(N, 3)``; camera-to-world matrices ``c2w`` ``(N, 4, 4)`` or ``(4, 4)``;
- rotations ``(..., 3, 3)``; intrinsics ``K`` ``(3, 3)`` in pixels, pixel (u, v) centre at
  (u + 0.5, v + 0.5) as in COLMAP.

Camera axis conventions used in this module (columns of the c2w rotation):
- OpenCV / COLMAP (the project's convention): x right, y down, z forward;
- OpenGL / NeRF / nerfstudio: x right, y up, z backwards;
- LLFF ``poses_bounds.npy`` ("DRB"): x down, y right, z backwards.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

# LLFF-style per-image bounds: percentiles of the depths of the points an image sees, then a
# margin so that surfaces at the extremes are not clipped by the ray interval.
NEAR_PERCENTILE = 0.1
FAR_PERCENTILE = 99.9
NEAR_MARGIN = 0.9   # near is shrunk: near = 0.9 * percentile
FAR_MARGIN = 1.1    # far is expanded: far = 1.1 * percentile

# Column permutations/sign flips between camera axis conventions (c2w[:, :3] @ M).
_OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0])
# LLFF columns are [down, right, back]; OpenCV columns are [right, down, forward].
_OPENCV_FROM_LLFF = np.array([[0.0, 1.0, 0.0],
                              [1.0, 0.0, 0.0],
                              [0.0, 0.0, -1.0]])


@dataclass(frozen=True)
class Similarity:
    """``y = scale * rotation @ x + translation``."""

    scale: float
    rotation: np.ndarray     # (3, 3)
    translation: np.ndarray  # (3,)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform points ``(..., 3)``."""
        return self.scale * np.asarray(points, np.float64) @ self.rotation.T + self.translation

    def apply_c2w(self, c2w: np.ndarray) -> np.ndarray:
        """Transform camera-to-world poses ``(..., 4, 4)``; the rotation part stays orthonormal."""
        c2w = np.array(c2w, dtype=np.float64)
        out = c2w.copy()
        out[..., :3, :3] = self.rotation @ c2w[..., :3, :3]
        out[..., :3, 3] = self.apply(c2w[..., :3, 3])
        return out


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool = True) -> Similarity:
    """Least-squares similarity mapping ``source`` onto ``target`` (Umeyama, PAMI 1991).

    source, target: ``(N, 3)`` corresponding points, N >= 3 not all collinear.
    Minimises ``sum ||target_i - (s R source_i + t)||^2`` with R a proper rotation.
    """
    src = np.asarray(source, np.float64)
    dst = np.asarray(target, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"need two (N>=3, 3) arrays, got {src.shape} and {dst.shape}")
    mu_src, mu_dst = src.mean(0), dst.mean(0)
    src_c, dst_c = src - mu_src, dst - mu_dst
    covariance = dst_c.T @ src_c / len(src)
    u, d, vt = np.linalg.svd(covariance)
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1.0
    rotation = u @ sign @ vt
    var_src = (src_c ** 2).sum() / len(src)
    scale = float(np.trace(np.diag(d) @ sign) / var_src) if with_scale else 1.0
    translation = mu_dst - scale * rotation @ mu_src
    return Similarity(scale, rotation, translation)


def rotation_angle_deg(rot_a: np.ndarray, rot_b: np.ndarray) -> np.ndarray:
    """Geodesic angle between rotations ``(..., 3, 3)``, in degrees."""
    relative = np.swapaxes(np.asarray(rot_a, np.float64), -1, -2) @ np.asarray(rot_b, np.float64)
    cos = (np.trace(relative, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


@dataclass(frozen=True)
class TrajectoryComparison:
    alignment: Similarity            # maps the estimate into the reference frame
    position_errors: np.ndarray      # (N,) reference units
    rotation_errors_deg: np.ndarray  # (N,)
    extent: float                    # largest distance between two reference camera centres

    @property
    def max_relative_position_error(self) -> float:
        return float(self.position_errors.max() / self.extent)


def compare_trajectories(c2w_estimate: np.ndarray, c2w_reference: np.ndarray
                         ) -> TrajectoryComparison:
    """Align estimated camera centres to the reference ones and measure pose errors.

    Both inputs ``(N, 4, 4)`` OpenCV c2w in corresponding order. Rotation errors compare the
    aligned estimate's camera axes with the reference's.
    """
    est = np.asarray(c2w_estimate, np.float64)
    ref = np.asarray(c2w_reference, np.float64)
    alignment = umeyama(est[:, :3, 3], ref[:, :3, 3])
    aligned = alignment.apply_c2w(est)
    position_errors = np.linalg.norm(aligned[:, :3, 3] - ref[:, :3, 3], axis=1)
    rotation_errors = rotation_angle_deg(aligned[:, :3, :3], ref[:, :3, :3])
    centres = ref[:, :3, 3]
    extent = float(np.max(np.linalg.norm(centres[:, None] - centres[None], axis=-1)))
    return TrajectoryComparison(alignment, position_errors, rotation_errors, extent)


def c2w_from_cam_from_world(cam_from_world: np.ndarray) -> np.ndarray:
    """Invert a world-to-camera ``(3, 4)`` or ``(4, 4)`` rigid transform into a ``(4, 4)`` c2w."""
    m = np.asarray(cam_from_world, np.float64)
    rotation, translation = m[:3, :3], m[:3, 3]
    c2w = np.eye(4)
    c2w[:3, :3] = rotation.T
    c2w[:3, 3] = -rotation.T @ translation
    return c2w


def opengl_to_opencv(c2w: np.ndarray) -> np.ndarray:
    """OpenGL/nerfstudio c2w (x right, y up, z back) to OpenCV (x right, y down, z forward).

    The flip is its own inverse, so this also converts OpenCV to OpenGL.
    """
    out = np.array(c2w, dtype=np.float64)
    out[..., :3, :3] = out[..., :3, :3] @ _OPENGL_FROM_OPENCV
    return out


opencv_to_opengl = opengl_to_opencv


def llff_to_opencv(poses: np.ndarray) -> np.ndarray:
    """LLFF ``(N, 3, 4)`` [R|t] with DRB camera axes to OpenCV ``(N, 4, 4)`` c2w.

    LLFF's rotation columns are (down, right, back); OpenCV's are (right, down, forward), so the
    first two columns swap and the third changes sign. The camera centre is unchanged.
    """
    poses = np.asarray(poses, np.float64)
    c2w = np.tile(np.eye(4), poses.shape[:-2] + (1, 1))
    c2w[..., :3, :3] = poses[..., :3, :3] @ _OPENCV_FROM_LLFF
    c2w[..., :3, 3] = poses[..., :3, 3]
    return c2w


def opencv_to_llff(c2w: np.ndarray) -> np.ndarray:
    """Inverse of :func:`llff_to_opencv`: OpenCV ``(N, 4, 4)`` to LLFF DRB ``(N, 3, 4)``."""
    c2w = np.asarray(c2w, np.float64)
    poses = np.array(c2w[..., :3, :4])
    poses[..., :3, :3] = c2w[..., :3, :3] @ _OPENCV_FROM_LLFF.T
    return poses


def depth_bounds(depths: np.ndarray) -> tuple[float, float]:
    """LLFF-style (near, far) from the depths (camera z) of the points one image sees.

    The 0.1 / 99.9 percentiles ignore stray points; near is then shrunk by NEAR_MARGIN and far
    expanded by FAR_MARGIN. Points behind the camera are ignored. Raises ValueError when no point
    is in front of the camera.
    """
    depths = np.asarray(depths, np.float64)
    depths = depths[np.isfinite(depths) & (depths > 0)]
    if depths.size == 0:
        raise ValueError("no point in front of the camera")
    near = float(np.percentile(depths, NEAR_PERCENTILE)) * NEAR_MARGIN
    far = float(np.percentile(depths, FAR_PERCENTILE)) * FAR_MARGIN
    return near, far


def range_bounds(near: float, far: float, intrinsics: np.ndarray, width: int,
                 height: int) -> tuple[float, float]:
    """Camera-depth bounds (LLFF style: z along the optical axis) as bounds on the range, the
    distance from the camera centre along each pixel's ray, which is what the renderer
    integrates over.

    A point at depth z lies at range z / cos(angle to the axis): at least z, and at most z times
    the longest corner ray of unit depth. Without this, rays towards the image corners would
    stop short of the far bound by that factor (1.2-1.3 for common fields of view).
    """
    corners = np.array([[0.0, 0.0, 1.0], [width, 0.0, 1.0], [0.0, height, 1.0],
                        [width, height, 1.0]])
    rays = corners @ np.linalg.inv(np.asarray(intrinsics, np.float64)).T   # z = 1
    return float(near), float(far) * float(np.linalg.norm(rays, axis=1).max())


def point_depths(c2w: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Depths (camera z) of world points ``(M, 3)`` in one camera with c2w ``(4, 4)``."""
    c2w = np.asarray(c2w, np.float64)
    return (np.asarray(points, np.float64) - c2w[:3, 3]) @ c2w[:3, 2]


def pixel_of_points(c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float, width: int,
                    height: int, points: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where world points ``(..., 3)`` fall in a pinhole camera (OpenCV axes, c2w ``(4, 4)``).

    Returns:
        ``(row, column, camera_points, inside)``: the integer pixel each point falls in (the
        centre of pixel (u, v) is at (u + 0.5, v + 0.5)), 0 where it falls outside; the points
        in camera coordinates ``(..., 3)``; and whether the point is in front of the camera and
        inside the image.

    Example::

        row, column, local, inside = pixel_of_points(c2w, 500, 500, 320, 240, 640, 480, points)
    """
    c2w = np.asarray(c2w, np.float64)
    local = (np.asarray(points, np.float64) - c2w[:3, 3]) @ c2w[:3, :3]   # R^T (p - t)
    depth = local[..., 2]
    in_front = depth > 1e-9
    safe = np.where(in_front, depth, 1.0)
    column = np.floor(fx * local[..., 0] / safe + cx)
    row = np.floor(fy * local[..., 1] / safe + cy)
    inside = in_front & (column >= 0) & (column < width) & (row >= 0) & (row < height)
    return (np.where(inside, row, 0).astype(np.int64), np.where(inside, column, 0).astype(np.int64),
            local, inside)


def sees_unhidden(camera, camera_range: np.ndarray, points: np.ndarray,
                  tolerance: float) -> np.ndarray:
    """Whether a camera sees world points ``(N, 3)`` with nothing nearer in front of them.

    A point is seen when it lies in front of the camera, inside its image, and the camera's own
    range at the pixel it falls in (``camera_range`` ``(H, W)``, along the pixel's ray) agrees
    with the point's distance within ``tolerance`` (relative). ``camera`` has ``c2w_array``,
    ``fx``, ``fy``, ``cx``, ``cy``, ``width``, ``height`` (a ``seathru.io.cameras.Frame``).

    Returns:
        ``(N,)`` bool.
    """
    row, column, local, inside = pixel_of_points(camera.c2w_array, camera.fx, camera.fy,
                                                 camera.cx, camera.cy, camera.width,
                                                 camera.height, points)
    there = np.asarray(camera_range, np.float64)[row, column]
    distance = np.linalg.norm(local, axis=-1)
    with np.errstate(invalid="ignore"):
        return inside & (np.abs(there - distance) <= tolerance * distance)


def frustum_corners(c2w: np.ndarray, intrinsics: np.ndarray, width: int, height: int,
                    depth: float) -> np.ndarray:
    """World positions ``(4, 3)`` of the image corners at camera depth ``depth``."""
    pixels = np.array([[0.0, 0.0, 1.0], [width, 0.0, 1.0], [0.0, height, 1.0],
                       [width, height, 1.0]])
    rays = pixels @ np.linalg.inv(np.asarray(intrinsics, np.float64)).T   # z = 1 in camera
    c2w = np.asarray(c2w, np.float64)
    return depth * rays @ c2w[:3, :3].T + c2w[:3, 3]


def unit_ball_normalisation(c2w: np.ndarray, intrinsics: np.ndarray, sizes: np.ndarray,
                            fars: np.ndarray) -> tuple[np.ndarray, float]:
    """The project's scene normalisation: (centre, scale) with normalised = (x - centre) * scale.

    Every camera's viewing frustum, cut at its far bound, is the convex hull of the camera
    centre and the four image corners at depth ``far``. ``centre`` is the middle of the
    axis-aligned bounding box of all these vertices and ``scale`` makes the vertex furthest from
    the centre lie on the unit sphere; as the norm is convex, every ray segment any camera
    samples (between its near and far bounds) then lies inside the unit ball, whatever the
    trajectory (orbit, forward transect).

    c2w ``(N, 4, 4)``; intrinsics ``(N, 3, 3)``; sizes ``(N, 2)`` (width, height); fars ``(N,)``
    in source units.
    """
    c2w = np.asarray(c2w, np.float64)
    vertices = [c2w[:, :3, 3]]
    for pose, k, (width, height), far in zip(c2w, intrinsics, sizes, fars):
        vertices.append(frustum_corners(pose, k, width, height, far))
    vertices = np.concatenate(vertices, axis=0)
    centre = 0.5 * (vertices.min(0) + vertices.max(0))
    radius = float(np.linalg.norm(vertices - centre, axis=1).max())
    if not np.isfinite(radius) or radius <= 0:
        raise ValueError("degenerate scene: all cameras and bounds coincide")
    return centre, 1.0 / radius


def normalise_c2w(c2w: np.ndarray, centre: np.ndarray, scale: float) -> np.ndarray:
    """Apply normalised = (x - centre) * scale to camera-to-world poses ``(..., 4, 4)``."""
    out = np.array(c2w, dtype=np.float64)
    out[..., :3, 3] = (out[..., :3, 3] - np.asarray(centre, np.float64)) * scale
    return out


def denormalise_c2w(c2w: np.ndarray, centre: np.ndarray, scale: float) -> np.ndarray:
    """Inverse of :func:`normalise_c2w`: back to source units."""
    out = np.array(c2w, dtype=np.float64)
    out[..., :3, 3] = out[..., :3, 3] / scale + np.asarray(centre, np.float64)
    return out


def complete_bounds(near: Sequence[float | None], far: Sequence[float | None],
                    near_override: float | None = None, far_override: float | None = None
                    ) -> tuple[list[float], list[float], list[bool]]:
    """Per-frame depth bounds with overrides applied and gaps filled with the scene's.

    Args:
        near, far: ``N`` per-frame bounds (None where the source has none).
        near_override, far_override: replace every frame's bound when given.

    Returns:
        ``(near, far, filled)``: the bounds, and per frame whether a missing bound was taken
        from the scene (smallest near, largest far over the frames that have both).

    Raises:
        ValueError: no frame has both bounds.

    Example::

        >>> complete_bounds([1.0, None], [5.0, None])
        ([1.0, 1.0], [5.0, 5.0], [False, True])
    """
    near = [near_override if near_override is not None else n for n in near]
    far = [far_override if far_override is not None else f for f in far]
    known = [(n, f) for n, f in zip(near, far) if n is not None and f is not None]
    if not known:
        raise ValueError("no near/far bounds")
    scene_near, scene_far = min(n for n, _ in known), max(f for _, f in known)
    filled = [n is None or f is None for n, f in zip(near, far)]
    return ([scene_near if n is None else n for n in near],
            [scene_far if f is None else f for f in far], filled)
