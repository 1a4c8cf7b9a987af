"""A photograph with the water taken out, by a fitted model's render of the same view.

The model's restored render is its own picture of the scene: whatever detail it has not learnt
(fine texture, a surface only one photograph shows) is missing from it, and dividing by the water's
transmission magnifies that error in the far, dim parts of a view. The photograph holds that
detail. :func:`restore_photograph` keeps the model's restored render and adds back what the model
does not explain in the photograph (``photograph - full render``), carried through the water as
the model's own object term carries it: for an object colour ``c`` along a ray the model renders
``direct = direct_share * c`` and ``restored = opacity * c``, so a change in the photograph of
``r`` is a change in the restored colour of ``r * opacity / direct_share`` (one over the water's
effective transmission at the surface). This is Sea-thru's ``(I - B) / T`` with the NeRF's
range, backscatter and transmission, and with the NeRF's render as the answer where the
photograph cannot be divided out.

Only the residual's detail is carried over: its variations over more than ``detail_scale`` of
the image width are left to the model. A residual that changes slowly across the frame is
often a colour the model's water does not reproduce; dividing it by the transmission would add it
to the restored colour, magnified most where the water is thickest (measured, with the choice of
the defaults: docs/water.md, "Restoring the photographs themselves").
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

import numpy as np

from seathru.settings import setting

DEFAULT_MAX_GAIN = 3.0
DEFAULT_DETAIL_SCALE = 0.05
DEFAULT_REPROJECT_TOLERANCE = 0.05   # seathru.nerf.reproject
DEFAULT_REPROJECT_ANGLE = 8.0


@dataclass
class PhotoRestoration:
    """The photographs with the water removed through the model's render."""

    restore: Literal["none", "test", "all"] = setting("test", help="test: the held-out views' "
        "(test/<view>/restored_photo.*); all: also every training view's (photos/<view>.*; "
        "one render per view), and their detail reprojected into the held-out views' restored "
        "renders (test/<view>/restored_reprojected.*) and the restored path video")
    max_gain: float = setting(DEFAULT_MAX_GAIN, help="the most the photograph minus the full "
                              "render is magnified (one over the least transmission divided out)")
    detail_scale: float = setting(DEFAULT_DETAIL_SCALE, help="only the residual's variations "
                                  "within this share of the image width are carried over (0: all)")
    reproject_tolerance: float = setting(DEFAULT_REPROJECT_TOLERANCE, help="a training view lends its "
                                         "detail to a pixel where its rendered range agrees "
                                         "with the pixel's surface within this share")
    reproject_angle: float = setting(DEFAULT_REPROJECT_ANGLE, help="degrees between a training "
                                     "view's ray and the pixel's at which its detail counts "
                                     "1/e as much as along the ray")

    def validate(self) -> None:
        _check_limits(self.max_gain, self.detail_scale)
        if self.reproject_tolerance <= 0 or not 0 < self.reproject_angle < 180:
            raise ValueError("reproject_tolerance must be > 0 and reproject_angle in (0, 180), "
                             f"got {self.reproject_tolerance}, {self.reproject_angle}")


def _check_limits(max_gain: float, detail_scale: float) -> None:
    if max_gain < 1:
        raise ValueError(f"max_gain must be >= 1, got {max_gain}")
    if detail_scale < 0:
        raise ValueError(f"detail_scale must be >= 0, got {detail_scale}")


def restore_photograph(photograph: np.ndarray, render: Mapping[str, np.ndarray],
                       max_gain: float = DEFAULT_MAX_GAIN,
                       detail_scale: float = DEFAULT_DETAIL_SCALE) -> np.ndarray:
    """The photograph of a view with the water removed, using the model's render of that view.

    Args:
        photograph: the view's linear image ``(H, W, 3)``, in the render's colour scale and size.
        render: ``seathru.nerf.inference.render_frame``'s dict for the view: ``rgb`` (full),
            ``restored``, ``direct_share`` ``(H, W, 3)`` and ``opacity`` ``(H, W)``.
        max_gain: the most the residual is magnified (one over the least effective
            transmission used): beyond it, far in dense water, noise would dominate, so the
            correction is limited and the result leans on the model's restored render.
        detail_scale: the residual ``photograph - rgb`` less its Gaussian blur (standard
            deviation this share of the image width; weighted by the opacity, so open water
            does not bleed into it) is what is carried over; 0: the whole residual.

    Returns:
        ``(H, W, 3)`` float32, non-negative: ``restored + opacity * min(opacity / direct_share,
        max_gain) * residual``. The opacity weight leaves open water (no surface) as the model
        renders it, and blends the correction in at a surface's soft edge.

    Example::

        images = render_frame(model, frame)
        clean_photo = restore_photograph(read_image(cameras.image_path(frame)), images)
    """
    _check_limits(max_gain, detail_scale)
    photograph = np.asarray(photograph, dtype=np.float64)
    full = np.asarray(render["rgb"], dtype=np.float64)
    if photograph.shape != full.shape:
        raise ValueError(f"photograph {photograph.shape} and render {full.shape} differ in size")
    restored = np.asarray(render["restored"], dtype=np.float64)
    opacity = np.asarray(render["opacity"], dtype=np.float64)[..., None]
    share = np.asarray(render["direct_share"], dtype=np.float64)
    # opacity / direct_share >= 1 (the water only dims); where both vanish the opacity weight
    # takes the correction to 0
    gain = np.clip(opacity / np.maximum(share, 1e-12), 1.0, max_gain) * opacity
    residual = photograph - full
    if detail_scale > 0:
        residual = residual - _smooth_part(residual, opacity[..., 0],
                                           detail_scale * residual.shape[1])
    result = restored + gain * residual
    return np.clip(np.nan_to_num(result, nan=0.0, posinf=0.0), 0.0, None).astype(np.float32)


def _smooth_part(residual: np.ndarray, weight: np.ndarray, sigma: float) -> np.ndarray:
    """The weighted Gaussian blur of ``residual`` (H, W, 3): ``G * (w r) / G * w``."""
    from scipy.ndimage import gaussian_filter

    total = gaussian_filter(weight, sigma, mode="nearest")
    blurred = np.stack([gaussian_filter(weight * residual[..., c], sigma, mode="nearest")
                        for c in range(residual.shape[-1])], -1)
    return blurred / np.maximum(total, 1e-9)[..., None]
