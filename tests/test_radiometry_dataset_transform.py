"""seathru.radiometry.dataset_transform: the dataset-level exposure and white-balance map,
checked against float64 references written out here."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from seathru.radiometry.dataset_transform import ImageStatistics, dataset_transform
from seathru.radiometry.linearise import MATCHING_TARGET_MEDIAN, apply_colour


def _views(seed: int, count: int, with_exif: bool = True) -> list[ImageStatistics]:
    rng = np.random.default_rng(seed)
    views = []
    for _ in range(count):
        samples = rng.gamma(2.0, [0.05, 0.1, 0.2], size=(400, 3)).astype(np.float32)
        exif = dict(exposure_time=float(rng.uniform(1e-3, 0.1)), iso=float(rng.choice([100, 400])),
                    f_number=float(rng.uniform(2.0, 8.0))) if with_exif else {}
        gains = np.array([rng.uniform(1.5, 2.5), 1.0, rng.uniform(1.2, 2.0)])
        views.append(ImageStatistics(samples=samples, camera_wb=gains, **exif))
    return views


def _applied(transform, views) -> np.ndarray:
    """Every sample through the per-image map, as ingest applies it to the images."""
    return np.concatenate([apply_colour(v.samples, transform.image_gains(i),
                                        transform.matrices[i], transform.post_gains)
                           for i, v in enumerate(views)]).astype(np.float64)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 6), st.floats(90.0, 100.0))
def test_percentile_white_balance_after_exposure_against_float64(seed, count, percentile):
    views = _views(seed, count)
    transform = dataset_transform(views, kind="linear", wb="percentile", wb_percentile=percentile)
    exposure = np.array([v.exposure_time * v.iso / v.f_number ** 2 for v in views])
    np.testing.assert_allclose(transform.factors, np.median(exposure) / exposure, rtol=1e-12)
    np.testing.assert_allclose(transform.exposure_values, exposure, rtol=1e-12)
    scaled = np.concatenate([v.samples.astype(np.float64) * k
                             for v, k in zip(views, transform.factors)])
    levels = np.percentile(scaled, percentile, axis=0)
    np.testing.assert_allclose(transform.percentile_levels, levels, rtol=1e-5)
    np.testing.assert_allclose(transform.wb_gains, 1.0 / levels, rtol=1e-5)
    np.testing.assert_allclose(np.percentile(_applied(transform, views), percentile, axis=0),
                               1.0, rtol=1e-4)
    assert transform.colour_space == "as stored" and transform.post_gains is None
    assert transform.sampled_pixels == 400 * count
    # the matching copies put the median channel mean at 18 % grey
    level = np.median(_applied(transform, views).mean(axis=1))
    assert transform.matching_scale * level == pytest.approx(MATCHING_TARGET_MEDIAN, rel=1e-5)


def test_camera_white_balance_is_the_dataset_median_and_exposure_can_be_off():
    views = _views(1, 3)
    transform = dataset_transform(views, kind="raw", wb="camera", exposure_normalise=False)
    expected = np.median(np.stack([v.camera_wb for v in views]), axis=0)
    np.testing.assert_allclose(transform.wb_gains, expected / expected[1])
    np.testing.assert_allclose(transform.camera_gains, transform.wb_gains)
    assert transform.factors.tolist() == [1.0] * 3 and transform.exposure is None
    assert np.isnan(transform.exposure_values).all()
    assert transform.colour_space == "camera raw" and transform.percentile_levels is None
    none = dataset_transform(views, kind="raw", wb="none")
    assert none.wb_gains.tolist() == [1.0, 1.0, 1.0] and none.camera_gains is None


def test_srgb_matrix_then_percentile_post_gains():
    views = _views(2, 3)
    matrix = np.array([[1.6, -0.4, -0.2], [-0.2, 1.5, -0.3], [0.0, -0.5, 1.5]])
    views = [ImageStatistics(samples=v.samples, exposure_time=v.exposure_time, iso=v.iso,
                             f_number=v.f_number, camera_wb=v.camera_wb,
                             colour_matrix=None if i == 2 else matrix)
             for i, v in enumerate(views)]
    transform = dataset_transform(views, kind="raw", wb="percentile", colour="srgb")
    camera = np.median(np.stack([v.camera_wb for v in views]), axis=0)
    np.testing.assert_allclose(transform.wb_gains, camera / camera[1])   # before the matrix
    assert transform.matrices[0] is matrix and transform.matrices[2] is None
    assert transform.colour_space == "srgb-linear"
    np.testing.assert_allclose(np.percentile(_applied(transform, views), 99.8, axis=0), 1.0,
                               rtol=1e-4)
    assert transform.image_warnings[2] and "matrix" in transform.image_warnings[2][-1]
    assert not transform.image_warnings[0]
    # encoded files have no matrix: colour srgb leaves them as stored
    assert dataset_transform(views, kind="linear", colour="srgb").matrices == [None] * 3


def test_missing_metadata_gives_warnings_not_errors():
    views = _views(3, 2, with_exif=False)
    views = [ImageStatistics(samples=v.samples) for v in views]
    transform = dataset_transform(views, kind="srgb", wb="camera")
    assert transform.factors.tolist() == [1.0, 1.0]
    assert all(w for w in transform.image_warnings)  # no exposure metadata
    assert transform.warnings and "white balance" in transform.warnings[0]
    assert transform.wb_gains.tolist() == [1.0, 1.0, 1.0]


def test_a_black_channel_cannot_be_percentile_balanced():
    samples = np.zeros((100, 3), np.float32)
    samples[:, 1] = 0.5
    with pytest.raises(ValueError, match="not positive in every channel"):
        dataset_transform([ImageStatistics(samples=samples)], kind="linear", wb="percentile")
