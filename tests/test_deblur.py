"""The pipeline's processing blur and its deconvolution (``seathru.radiometry.deblur``)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from seathru.io.dng import write_dng
from seathru.io.raw import RawSettings, decode_raw
from seathru.radiometry.deblur import (DEMOSAIC_BLUR_PX, RESAMPLE_VARIANCE, deblurred,
                                       processing_blur)
from seathru.sim.sensor import mosaic_rggb


def _texture(height: int, width: int, seed: int = 0) -> np.ndarray:
    """(H, W, 3) float64 in about [0.1, 0.7]: white noise softened by a 1-pixel Gaussian (the
    spectrum of a photograph's fine detail rather than of pure noise)."""
    rng = np.random.default_rng(seed)
    # the channels share most of their detail, as a photograph's do (a demosaic such as AHD
    # relies on it)
    shared = rng.normal(size=(height, width, 1))
    noise = cv2.GaussianBlur(0.8 * shared + 0.2 * rng.normal(size=(height, width, 3)),
                             (0, 0), 1.0)
    return 0.4 + 0.3 * noise / np.abs(noise).max()


def _best_sigma(reference: np.ndarray, observed: np.ndarray, margin: int = 6) -> float:
    """The Gaussian sigma (0 to 1.5 px, steps of 0.05) that, with a gain and an offset, best
    maps ``reference`` (H, W) onto ``observed`` on the interior."""
    inner = (slice(margin, -margin), slice(margin, -margin))
    target = observed[inner].ravel()
    errors = []
    for sigma in np.arange(0.0, 1.51, 0.05):
        blurred = cv2.GaussianBlur(reference, (0, 0), sigma) if sigma > 0 else reference
        design = np.stack([blurred[inner].ravel(), np.ones(target.size)], 1)
        residual = np.linalg.lstsq(design, target, rcond=None)[1]
        errors.append((float(residual[0]), float(sigma)))
    return min(errors)[1]


def test_processing_blur_adds_the_demosaic_and_the_resampling_as_spreads():
    linear = DEMOSAIC_BLUR_PX["LINEAR"]
    both = processing_blur("LINEAR", 1.0, "linear")
    assert both == pytest.approx([math.sqrt(s * s + 1 / 6) for s in linear], abs=1e-4)
    # a resize to half the decoded size halves the demosaic's blur in pixels
    half = processing_blur("LINEAR", 0.5, None)
    assert half == pytest.approx([0.5 * s for s in linear], abs=1e-4)
    # a demosaic that borrows detail across channels, binning, or a camera's own JPEG: only
    # the undistortion is known
    for demosaic in ("AHD", "half_size", None):
        assert processing_blur(demosaic, 1.0, "linear") == pytest.approx(
            [math.sqrt(RESAMPLE_VARIANCE["linear"])] * 3, abs=1e-4)
        assert processing_blur(demosaic, 1.0, None) == [0.0, 0.0, 0.0]
    # the cubic kernel sharpens: it takes a little off the demosaic's blur, never below zero
    cubic = processing_blur("LINEAR", 1.0, "cubic")
    assert all(c < s for c, s in zip(cubic, linear))
    assert processing_blur(None, 1.0, "cubic") == [0.0, 0.0, 0.0]


def test_libraw_linear_demosaic_blur_matches_the_table(tmp_path):
    """The table's LINEAR entry is what LibRaw does to a mosaic of a known texture; AHD's
    red is not blurred like that (it follows green's detail), which is why it has no entry."""
    texture = _texture(96, 128)
    white = 4000
    raw = np.round(mosaic_rggb(texture) * white).astype(np.uint16)
    path = tmp_path / "texture.dng"
    write_dng(path, raw, black_level=0, white_level=white, exposure_time_s=0.01, iso=100,
              f_number=4.0)
    found = {}
    for demosaic in ("LINEAR", "AHD"):
        image = decode_raw(path, RawSettings(demosaic=demosaic)).image.astype(np.float64)
        assert image.shape[:2] == texture.shape[:2]
        found[demosaic] = [_best_sigma(texture[..., c], image[..., c]) for c in range(3)]
    assert found["LINEAR"] == pytest.approx(DEMOSAIC_BLUR_PX["LINEAR"], abs=0.15)
    assert "AHD" not in DEMOSAIC_BLUR_PX
    assert found["AHD"][0] < DEMOSAIC_BLUR_PX["LINEAR"][0] - 0.3


@pytest.mark.parametrize("sigma", [0.5, 0.9])
def test_deblurred_undoes_a_known_gaussian_blur(sigma):
    sharp = _texture(80, 100, seed=1).astype(np.float32)
    blurred = cv2.GaussianBlur(sharp, (0, 0), sigma)
    restored = deblurred(blurred, [sigma, sigma, 0.0])
    inner = (slice(8, -8), slice(8, -8))
    before = np.abs(blurred - sharp)[inner].mean(axis=(0, 1))
    after = np.abs(restored - sharp)[inner].mean(axis=(0, 1))
    # Wiener's regularisation (balance 0.01) leaves the finest detail damped: about half of
    # the blur's error is taken out at these widths
    assert np.all(after[:2] < 0.6 * before[:2])
    # a channel with no blur is copied as it is
    np.testing.assert_array_equal(restored[..., 2], blurred[..., 2])
    assert restored.dtype == np.float32


def test_deblurred_keeps_holes_and_does_not_ring_around_them():
    sharp = _texture(64, 64, seed=2).astype(np.float32)
    blurred = cv2.GaussianBlur(sharp, (0, 0), 0.8)
    holed = blurred.copy()
    holed[20:30, 20:30] = np.nan
    restored = deblurred(holed, [0.8, 0.8, 0.8])
    assert np.isnan(restored[20:30, 20:30]).all()
    assert np.isfinite(restored[:20]).all() and np.isfinite(restored[30:]).all()
    # beside the hole the deconvolution is no worse than the blurred image itself
    ring = np.zeros((64, 64), bool)
    ring[17:33, 17:33] = True
    ring[20:30, 20:30] = False
    assert np.abs(restored - sharp)[ring].mean() < np.abs(blurred - sharp)[ring].mean()
