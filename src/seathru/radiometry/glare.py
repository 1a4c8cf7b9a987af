"""Photographs brighter next to the open water in the frame: the correction and its rule.

On a real dive (d3_reef) the same surface is about 20% darker each time its distance to the
open water *in the image* doubles, at any range and in every channel alike: veiling glare in
the housing's port or a camera's local tone mapping, not the water (docs/water.md). The
NeRF's object field cannot hold a brightness that depends on where a surface appears in the
frame, so it learns part of it as colour that changes with range, and the restored views keep
it. The correction divides each photograph by a grey gain that follows the distance to the
open water, fitted along COLMAP tracks beside range (``seathru.io.tracks.glare_correction``),
so that the model sees the surfaces without it.

The gain is ``(d / reference) ** coefficient`` with ``d`` the distance to the nearest open
water as a share of the image width, clipped to ``[near, far]`` (the range the fit saw); a frame
without open water takes ``d`` as ``far``. The open water itself keeps its value (it is the
veiling light the water model fits), and within ``near`` of it the gain goes to 1.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.ndimage import distance_transform_edt

#: The rule for "brighter next to the open water": the log colour falls by more than
#: ``GLARE_COEFFICIENT`` per unit of log distance, at least ``GLARE_T`` standard errors from
#: zero, in two channels or more (d3_reef: 0.28-0.33 at 23-32 standard errors; the demo, whose
#: simulator has no glare: within 0.005).
GLARE_COEFFICIENT = 0.1
GLARE_T = 5.0
GLARE_CHANNELS = 2


def brighter_near_open_water(coefficient, stderr) -> bool:
    """Whether a within-track fit's distance ``coefficient`` (C,) with its ``stderr`` (C,) meets
    the rule above.

    Example::

        >>> brighter_near_open_water([-0.33, -0.32, -0.28], [0.01, 0.01, 0.01])
        True
    """
    bright = [c is not None and e is not None and bool(np.isfinite(c) and np.isfinite(e))
              and e > 0 and c < -GLARE_COEFFICIENT and c / e < -GLARE_T
              for c, e in zip(coefficient, stderr)]
    return bool(sum(bright) >= GLARE_CHANNELS)


@dataclass(frozen=True)
class GlareCorrection:
    """A grey gain that follows the distance to the open water in each photograph.

    Attributes:
        coefficient: change of log colour per unit of log distance (negative: brighter near
            the open water); one value for every channel.
        near, reference, far: distances as shares of the image width; the gain is 1 at
            ``reference``, constant beyond ``far`` and goes to 1 on the open water below
            ``near``.
    """

    coefficient: float
    near: float
    reference: float
    far: float

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, value: dict) -> "GlareCorrection":
        return cls(**{key: float(value[key]) for key in ("coefficient", "near", "reference",
                                                         "far")})


def open_water_distance(open_water: np.ndarray) -> np.ndarray:
    """Each pixel's distance to the nearest open-water pixel, as a share of the image width.

    Args:
        open_water: (H, W) bool (``seathru.radiometry.open_water.open_water_mask``).

    Returns:
        (H, W) float64; 0 on the open water, inf everywhere in a frame without any.
    """
    water = np.asarray(open_water, dtype=bool)
    if not water.any():
        return np.full(water.shape, np.inf)
    return distance_transform_edt(~water) / water.shape[1]


def glare_gain(distance: np.ndarray, correction: GlareCorrection) -> np.ndarray:
    """The correction's gain at each pixel: what the photograph has that the scene has not.

    Args:
        distance: (...,) distance to the open water, share of the image width
            (:func:`open_water_distance`; 0 on the open water, inf without any).
        correction: the fitted correction.

    Returns:
        (...,) gain, 1 on the open water.

    Example::

        gain = glare_gain(open_water_distance(mask), correction)
        restored = image / gain[..., None]
    """
    distance = np.asarray(distance, dtype=np.float64)
    clipped = np.clip(np.where(np.isfinite(distance), distance, correction.far),
                      correction.near, correction.far)
    gain = (clipped / correction.reference) ** correction.coefficient
    # within ``near`` of the mask the gain goes to 1 (its log linearly): the mask's edge is
    # block-wise, so water just outside it would otherwise be divided as a surface, a seam
    return gain ** np.clip(distance / correction.near, 0.0, 1.0)


def photograph_gain(image: np.ndarray, correction: GlareCorrection,
                    valid: np.ndarray | None = None) -> np.ndarray:
    """:func:`glare_gain` around the open water a photograph shows
    (``seathru.radiometry.open_water.open_water_mask`` on its ``valid`` pixels).

    Args:
        image: (H, W, 3) linear photograph (non-finite values count as 0).
        correction: the fitted correction.
        valid: (H, W) bool, pixels that may be open water, or None (all).

    Returns:
        (H, W) gain; the photograph without the brightening is ``image / gain[..., None]``.
    """
    from seathru.radiometry.open_water import open_water_mask

    water = open_water_mask(np.nan_to_num(np.asarray(image, dtype=np.float64)[..., :3]),
                            valid=valid)
    return glare_gain(open_water_distance(water), correction)
