"""seathru.geometry.intrinsics: focal lengths known before SfM and the initial COLMAP camera."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from seathru.geometry.intrinsics import (CAMERA_MODELS, FocalPrior, focal_from_metadata,
                                         initial_camera_params)


@settings(max_examples=40, deadline=None)
@given(st.floats(8.0, 200.0), st.integers(16, 8000), st.integers(16, 6000))
def test_35mm_equivalent_focal_scales_with_the_image_diagonal(focal_35, width, height):
    found, how = focal_from_metadata({"images": [{"exif": {"EXIF FocalLengthIn35mmFilm":
                                                           f"{focal_35}"}}]}, width, height)
    # a 35 mm frame is 36 x 24 mm; the angle of view along the diagonal is kept
    reference = focal_35 * math.sqrt(width ** 2 + height ** 2) / math.sqrt(36.0 ** 2 + 24.0 ** 2)
    assert found == pytest.approx(reference, rel=1e-12) and "35 mm" in how


def test_metadata_precedence_and_disagreement():
    both = {"focal_length_px": 700, "focal_length_mm": 10, "sensor_width_mm": 20,
            "focal_length_35mm": 28}
    assert focal_from_metadata(both, 800, 600) == (700.0, "manifest focal_length_px")
    del both["focal_length_px"]
    assert focal_from_metadata(both, 800, 600)[0] == pytest.approx(400.0)
    # within 1 %: the median; beyond: unknown
    assert focal_from_metadata([{"focal_px": 500}, {"focal_px": 504}, {"focal_px": 502}],
                               80, 60)[0] == 502.0
    assert focal_from_metadata([{"focal_px": 500}, {"focal_px": 520}], 80, 60)[0] is None
    assert focal_from_metadata({"focal_mm": 12}, 80, 60) == (
        None, "manifest focal lengths missing a sensor width or not the same for all")
    assert focal_from_metadata(None, 80, 60) == (None, "no manifest")
    assert focal_from_metadata({"focal_px": "n/a", "other": [1, 2]}, 80, 60)[0] is None


def test_focal_prior_order_and_units():
    metadata = {"focal_length_35mm": 28}
    assert FocalPrior(focal_px=321.0, focal_mm=5.0, metadata=metadata).at_size(640, 480) == (
        321.0, "--focal-px")
    focal, how = FocalPrior(focal_mm=6.0, sensor_width_mm=12.0, metadata=metadata).at_size(640,
                                                                                           480)
    assert focal == pytest.approx(320.0) and how == "--focal-mm / --sensor-width-mm"
    assert FocalPrior(metadata=metadata).at_size(640, 480)[0] == pytest.approx(
        28 / math.hypot(36, 24) * 800.0)
    assert FocalPrior().at_size(640, 480)[0] is None
    with pytest.raises(ValueError, match="--sensor-width-mm"):
        FocalPrior(focal_mm=6.0).at_size(640, 480)


@pytest.mark.parametrize("model", CAMERA_MODELS)
def test_initial_camera_params_put_the_principal_point_at_the_centre(model):
    pycolmap = pytest.importorskip("pycolmap")
    params = [float(v) for v in initial_camera_params(model, 412.5, 640, 481).split(",")]
    camera = pycolmap.Camera(model=model, width=640, height=481, params=params)
    k = camera.calibration_matrix()
    assert (k[0, 0], k[1, 1], k[0, 2], k[1, 2]) == (412.5, 412.5, 320.0, 240.5)
    assert all(p == 0.0 for p in params[len(params) - len(camera.extra_params_idxs()):])


@pytest.mark.parametrize("width, height", [(320, 240), (240, 320), (6000, 4000)])
def test_35mm_equivalents_go_by_the_diagonal_both_ways(width, height):
    from seathru.geometry.intrinsics import focal_35mm_from_px, focal_px_from_35mm

    # a 43.27 mm equivalent (the frame's diagonal) sees 53.1 degrees across the diagonal
    assert focal_px_from_35mm(math.hypot(36.0, 24.0), width, height) == pytest.approx(
        math.hypot(width, height))
    assert focal_35mm_from_px(focal_px_from_35mm(27.0, width, height), width, height) == \
        pytest.approx(27.0)
