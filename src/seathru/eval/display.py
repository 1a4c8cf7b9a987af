"""Linear radiance to display images: one exposure per dataset, sRGB gamma, depth colour maps.

Linear underwater images straight from the camera (and the official SeaThru-NeRF release's
linear PNGs) use a small part of the [0, 1] range and look grey and dark when shown as they are.
A display copy multiplies by one exposure scale per dataset, chosen so that a high percentile of
the dataset's reference linear images lands near white, then applies the sRGB transfer curve.
The same scale is used for every output of a dataset (full render, restored, direct,
backscatter, ground truth) so they can be compared by eye.

Pure numpy (matplotlib only for colour maps), no file I/O.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from seathru.radiometry.colour import linear_to_srgb

DEFAULT_PERCENTILE = 99.0
DEFAULT_TARGET = 0.9
DEFAULT_DEPTH_CMAP = "turbo"


def sample_values(image: np.ndarray, max_samples: int = 100_000) -> np.ndarray:
    """A deterministic, evenly strided sample of an image's finite values (all channels)."""
    values = np.asarray(image, dtype=np.float32).reshape(-1)
    step = max(1, values.size // max_samples)
    values = values[::step]
    return values[np.isfinite(values)]


def exposure_scale(linear_images: Iterable[np.ndarray], percentile: float = DEFAULT_PERCENTILE,
                   target: float = DEFAULT_TARGET, max_samples_per_image: int = 100_000) -> float:
    """The factor that maps the ``percentile`` of all channel values of the images to ``target``.

    Images are sampled with a stride, so memory stays bounded for any number and size of images.
    Returns 1 when there are no images or the percentile is not positive.
    """
    samples = [sample_values(image, max_samples_per_image) for image in linear_images]
    samples = [s for s in samples if s.size]
    if not samples:
        return 1.0
    level = float(np.percentile(np.concatenate(samples), percentile))
    return target / level if level > 0 else 1.0


def to_display(linear: np.ndarray, scale: float) -> np.ndarray:
    """Linear ``(H, W, 3)`` radiance to an sRGB-encoded float32 image in [0, 1]."""
    return np.asarray(linear_to_srgb(np.asarray(linear, dtype=np.float32) * np.float32(scale)),
                      dtype=np.float32)


def depth_range(depths: Iterable[np.ndarray], low: float = 1.0, high: float = 99.0,
                max_samples_per_image: int = 100_000) -> tuple[float, float]:
    """Robust colour-map limits (percentiles ``low`` and ``high``) pooled over depth maps.

    Non-finite and non-positive depths are ignored; returns (0, 1) when nothing is valid.
    """
    samples = [sample_values(d, max_samples_per_image) for d in depths]
    values = np.concatenate([s[s > 0] for s in samples]) if samples else np.zeros(0)
    if values.size == 0:
        return 0.0, 1.0
    lo, hi = (float(v) for v in np.percentile(values, [low, high]))
    if not hi > lo:
        hi = lo + max(abs(lo) * 1e-3, 1e-6)
    return lo, hi


def colourise_depth(depth: np.ndarray, lo: float, hi: float, cmap: str = DEFAULT_DEPTH_CMAP,
                    valid: np.ndarray | None = None) -> np.ndarray:
    """Map an ``(H, W)`` depth to an ``(H, W, 3)`` float32 RGB image in [0, 1].

    Near is drawn with the warm end of the colour map and far with the cool end (the NeRF
    habit of showing inverse depth); depths outside [lo, hi] are clipped; invalid pixels
    (``valid`` false, or non-finite depth) are black.
    """
    import matplotlib

    depth = np.asarray(depth, dtype=np.float64)
    finite = np.isfinite(depth)
    normalised = np.clip((hi - np.where(finite, depth, hi)) / (hi - lo), 0.0, 1.0)
    rgb = matplotlib.colormaps[cmap](normalised)[..., :3].astype(np.float32)
    invalid = ~finite if valid is None else ~(finite & np.asarray(valid, dtype=bool))
    rgb[invalid] = 0.0
    return rgb
