"""The blur this pipeline's own processing puts into the training images, and a copy of the
images with it taken out, for the water fit.

Each pixel of a training image is a weighted mean of its neighbours: the demosaic interpolates
each channel from its own photosites (LINEAR: red and blue from a quarter of them, green from
half), and the undistortion resamples the image. The water fit compares one surface seen from
different ranges (``seathru.nerf.water_fit``); blur mixes each pixel with its neighbours'
surfaces, over a larger patch of them the farther the view, and the image formation is not
linear in that mix. On the demo's water the refit's red backscatter came out 21% high on the
training images and 10% after deconvolving this known blur (docs/water.md, "The demosaic").

Only the blur the pipeline adds and knows is modelled: a camera's own optics, its in-camera
demosaic and sharpening (JPEG, PNG, linear TIFF inputs) are not, and neither is the pixel's own
area, which every camera has. Each part is described by the spread of its weights (the second
moment, pixels squared per axis): independent parts add, and a Gaussian of the same spread
stands in for their sum.
"""

from __future__ import annotations

import math
from typing import Sequence

import cv2
import numpy as np

#: Gaussian sigma (pixels of the decoded image, R G B) that best matches LibRaw's demosaic of a
#: Bayer mosaic, measured by decoding a mosaic of a known texture
#: (``tests/test_deblur.py::test_libraw_linear_demosaic_blur_matches_the_table``). Demosaics
#: that borrow detail across channels (AHD, PPG, DCB, ...) are left out: their red and blue
#: follow green's texture rather than a fixed kernel.
DEMOSAIC_BLUR_PX: dict[str, tuple[float, float, float]] = {"LINEAR": (0.8, 0.5, 0.8)}

#: Second moment per axis (pixels squared) of an image resampled at uniformly spread subpixel
#: offsets: bilinear ``t (1 - t)`` on average 1/6; OpenCV's cubic (a = -0.75) sharpens, -1/15.
RESAMPLE_VARIANCE: dict[str, float] = {"linear": 1.0 / 6.0, "cubic": -1.0 / 15.0}

#: Wiener regularisation (noise-to-signal power). 0.01 recovered the water of the demo's
#: noise-free and noisy training images alike (docs/water.md).
WIENER_BALANCE = 0.01


def processing_blur(demosaic: str | None, scale: float = 1.0,
                    resampled: str | None = None) -> list[float]:
    """The Gaussian sigma per channel (R, G, B; pixels of the training image) of the blur
    the pipeline's processing adds.

    Args:
        demosaic: the LibRaw demosaic of a RAW input (``ingest.demosaic``), or None (no
            demosaic by this pipeline: binned, a linear or sRGB input, a video frame).
        scale: the training image's size over the decoded image's (a resize shrinks the
            demosaic's blur in pixels).
        resampled: the undistortion's interpolation (``linear`` or ``cubic``), None when the
            image was not resampled.

    Returns:
        three sigmas, 0 where nothing is known to blur that channel.

    Example::

        processing_blur("LINEAR", 1.0, "linear")   # about [0.9, 0.65, 0.9]
    """
    base = DEMOSAIC_BLUR_PX.get(demosaic or "", (0.0, 0.0, 0.0))
    extra = RESAMPLE_VARIANCE.get(resampled or "", 0.0)
    return [round(math.sqrt(max((sigma * scale) ** 2 + extra, 0.0)), 4) for sigma in base]


def _gaussian_psf(sigma: float) -> np.ndarray:
    kernel = cv2.getGaussianKernel(2 * max(1, int(math.ceil(3.0 * sigma))) + 1, sigma)
    return kernel @ kernel.T


def deblurred(image: np.ndarray, sigma_px: Sequence[float],
              balance: float = WIENER_BALANCE) -> np.ndarray:
    """``image`` with a Gaussian blur of ``sigma_px`` per channel deconvolved (Wiener).

    Non-finite pixels stay non-finite; for the deconvolution they are filled with the mean of
    their finite neighbours, and the image is padded by reflection, so neither a hole nor the
    border rings into the pixels around it.

    Args:
        image: (H, W, C) float, C >= len(sigma_px); channels beyond ``sigma_px`` are copied.
        sigma_px: the blur of each channel (pixels); a channel with sigma below 0.05 is copied.
        balance: Wiener regularisation (noise-to-signal power ratio).

    Returns:
        (H, W, C) float32.

    Example::

        sharp = deblurred(image, processing_blur("LINEAR", 1.0, "linear"))
    """
    # scipy.signal, which skimage.restoration loads, takes 1.5 s to import: only where it is used
    from skimage.restoration import wiener

    image = np.asarray(image, dtype=np.float32)
    out = image.copy()
    finite = np.isfinite(image)
    for channel, sigma in enumerate(sigma_px):
        if sigma < 0.05:
            continue
        plane, valid = image[..., channel], finite[..., channel]
        filled = np.where(valid, plane, 0.0).astype(np.float64)
        if not valid.all():
            filled = _filled(filled, valid)
        psf = _gaussian_psf(float(sigma))
        pad = psf.shape[0]
        padded = np.pad(filled, pad, mode="reflect")
        sharp = wiener(padded, psf, balance, clip=False)[pad:-pad, pad:-pad]
        out[..., channel] = np.where(valid, sharp, plane)
    return out


def _filled(plane: np.ndarray, valid: np.ndarray, passes: int = 8) -> np.ndarray:
    """``plane`` with its invalid pixels set to the mean of the valid ones nearby (grown over
    ``passes`` 3x3 steps; the rest to the mean of all valid pixels). Smoother than OpenCV's
    inpainting (Telea), whose fill of a textured surround rang into the deconvolution beside
    a hole three times as much (``tests/test_deblur.py``)."""
    values, weight = plane * valid, valid.astype(np.float64)
    known = valid.copy()
    for _ in range(passes):
        if known.all():
            break
        total = cv2.blur(values, (3, 3), borderType=cv2.BORDER_REFLECT)
        count = cv2.blur(weight, (3, 3), borderType=cv2.BORDER_REFLECT)
        grow = ~known & (count > 0)
        values = np.where(grow, total / np.maximum(count, 1e-12), values)
        weight = np.where(grow, 1.0, weight)
        known |= grow
    mean = float(plane[valid].mean()) if valid.any() else 0.0
    return np.where(known, values, mean)
