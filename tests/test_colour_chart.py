"""Colour accuracy on colour charts: CIEDE2000 against the published values and the grey
angular error, on synthetic charts (exact, perturbed by a known amount, under a colour cast),
through OpenCV's mcc detector and the evaluate step, and on the d3_reef photo's chart."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from skimage.color import deltaE_ciede2000

from seathru.cli import main
from seathru.eval import colour_chart as cc
from seathru.io.cameras import CameraSet, Frame, every_nth_split, write_cameras
from seathru.io.chart import read_chart_annotation
from seathru.io.images import read_image, write_float_tiff
from seathru.radiometry.colour import linear_to_srgb, srgb_to_linear

MACBETH = cc.CHARTS["macbeth-classic-24"]
FIXTURE = Path(__file__).parent / "fixtures" / "d3_reef_colour_chart.json"
CORNERS = np.array([[52.3, 40.1], [262.8, 55.6], [250.2, 190.4], [40.7, 170.9]])


def chart_image(colours: np.ndarray, corners: np.ndarray, size=(320, 240), rows=4, cols=6,
                background=0.18, border=0.02) -> np.ndarray:
    """A linear image of a chart whose patch area has ``corners`` (module convention of
    seathru.eval.colour_chart): patches fill 80 % of their cells, dark gaps and border."""
    cell = 40
    flat = np.full((rows * cell, cols * cell, 3), border, np.float32)
    for k, colour in enumerate(np.asarray(colours, np.float32)):
        r, c = divmod(k, cols)
        flat[r * cell + 4:(r + 1) * cell - 4, c * cell + 4:(c + 1) * cell - 4] = colour
    source = np.float32([[-0.5, -0.5], [cols * cell - 0.5, -0.5],
                         [cols * cell - 0.5, rows * cell - 0.5], [-0.5, rows * cell - 0.5]])
    homography = cv2.getPerspectiveTransform(source, np.float32(corners) - 0.5)
    canvas = np.full((size[1], size[0], 3), background, np.float32)
    margin = cv2.warpPerspective(np.ones_like(flat), homography, size, flags=cv2.INTER_LINEAR)
    warped = cv2.warpPerspective(flat, homography, size, flags=cv2.INTER_LINEAR)
    return np.where(margin > 0.5, warped, canvas)


def _measure(image, corners, spec=MACBETH):
    return cc.patch_means(image, corners, spec.rows, spec.cols)


# --------------------------------------------------------------------------- synthetic charts

def test_exact_reference_colours_give_zero_delta_e():
    reference = cc.lab_to_linear_srgb(MACBETH.reference_lab)
    errors = cc.chart_errors(_measure(chart_image(reference, CORNERS), CORNERS), MACBETH)
    assert errors["mean_delta_e00"] < 0.05 and errors["max_delta_e00"] < 0.2
    assert errors["patches_used"] == 24
    assert errors["exposure_scale"] == pytest.approx(1.0, abs=1e-3)
    # the reference neutrals are nearly neutral in linear sRGB: the white's b* = 2.93 is ~1.5 deg
    assert errors["mean_grey_angular_error_deg"] < 2.0


def test_exposure_does_not_change_delta_e_or_angles():
    reference = cc.lab_to_linear_srgb(MACBETH.reference_lab)
    dim = cc.chart_errors(_measure(chart_image(0.3 * reference, CORNERS), CORNERS), MACBETH)
    assert dim["mean_delta_e00"] < 0.05
    assert dim["exposure_scale"] == pytest.approx(1 / 0.3, rel=1e-3)


def _ciede2000_lightness_only(l1: float, l2: float) -> float:
    """CIEDE2000 of two colours with the same a*, b*: |dL| / S_L (Sharma et al. 2005, eq. 8-18:
    dC' = dH' = 0 removes the chroma, hue and rotation terms)."""
    mean = (l1 + l2) / 2
    s_l = 1 + 0.015 * (mean - 50) ** 2 / math.sqrt(20 + (mean - 50) ** 2)
    return abs(l2 - l1) / s_l


def test_perturbed_patches_give_the_known_delta_e():
    lab = MACBETH.reference_lab.copy()
    shifted = lab.copy()
    shifted[:18, 0] += 4.0                       # chromatic patches 4 L* lighter; greys kept
    image = chart_image(cc.lab_to_linear_srgb(shifted), CORNERS)
    errors = cc.chart_errors(_measure(image, CORNERS), MACBETH)
    expected = [_ciede2000_lightness_only(l, l + 4.0) for l in lab[:18, 0]]
    np.testing.assert_allclose(errors["delta_e00"][:18], expected, atol=0.05)
    assert max(errors["delta_e00"][18:]) < 0.1
    np.testing.assert_allclose(expected, deltaE_ciede2000(lab[:18], shifted[:18]), atol=1e-9)


def test_a_colour_cast_shows_in_the_grey_angle_and_delta_e():
    reference = cc.lab_to_linear_srgb(MACBETH.reference_lab)
    cast = np.array([0.55, 1.0, 1.15])                        # blue-green water
    image = chart_image(reference * cast, CORNERS)
    errors = cc.chart_errors(_measure(image, CORNERS), MACBETH)
    greys = reference[18:] * cast
    cosine = greys.sum(1) / (np.linalg.norm(greys, axis=1) * np.sqrt(3))
    expected = np.degrees(np.arccos(cosine))
    np.testing.assert_allclose(errors["grey_angular_error_deg"], expected, atol=0.05)
    assert errors["mean_delta_e00"] > 5


def test_excluded_patches_are_left_out():
    reference = cc.lab_to_linear_srgb(MACBETH.reference_lab)
    measured = _measure(chart_image(reference, CORNERS), CORNERS)
    measured[3] = [1.0, 0.0, 0.0]
    use = np.ones(24, bool)
    use[[3, 19]] = False
    errors = cc.chart_errors(measured, MACBETH, use)
    assert errors["delta_e00"][3] is None and errors["grey_angular_error_deg"][1] is None
    assert errors["patches_used"] == 22 and errors["mean_delta_e00"] < 0.05


def test_lab_conversion_round_trips_and_takes_the_d65_white_to_d50_white():
    rng = np.random.default_rng(0)
    rgb = rng.random((50, 3))
    np.testing.assert_allclose(cc.lab_to_linear_srgb(cc.linear_srgb_to_lab(rgb)), rgb,
                               atol=1e-9)
    # the D65 white adapts to the D50 white: L* 100, a* = b* = 0
    np.testing.assert_allclose(cc.linear_srgb_to_lab(np.ones(3)), [100, 0, 0], atol=1e-3)


def test_mcc_finds_a_clear_chart_and_its_corners_measure_it():
    reference = cc.lab_to_linear_srgb(MACBETH.reference_lab)
    corners = np.array([[60.0, 50.0], [600.0, 70.0], [590.0, 420.0], [70.0, 400.0]])
    image = chart_image(reference, corners, size=(680, 480))
    found = cc.detect_macbeth(linear_to_srgb(np.clip(image, 0, 1)))
    assert found is not None
    errors = cc.chart_errors(_measure(image, found), MACBETH)
    assert errors["mean_delta_e00"] < 1.0, found


def test_implausible_charts_are_refused():
    reference = cc.lab_to_linear_srgb(MACBETH.reference_lab)
    image = chart_image(reference, CORNERS)
    assert cc.implausible_chart(image, CORNERS, MACBETH) is None
    crossed = CORNERS[[0, 2, 1, 3]]
    assert "convex" in cc.implausible_chart(image, crossed, MACBETH)
    assert "outside" in cc.implausible_chart(image, CORNERS + [300, 0], MACBETH)
    flipped = CORNERS[[2, 3, 0, 1]]            # rotated by 180 degrees: black before white
    assert "light to dark" in cc.implausible_chart(image, flipped, MACBETH)


def test_mcc_false_positive_on_fern_is_refused(shared_data):
    # mcc proposes a self-intersecting "chart" reaching outside this image of ferns
    image = read_image(shared_data / "fern_llff" / "images_8" / "image012.png")
    assert cc.detect_macbeth(image) is None


# ------------------------------------------------------------------------ through the step

def _dataset(root: Path, chart_view: int, views: int = 9) -> dict:
    """Stored 8-bit images (one with a chart), the real ingest, a camera file and renders whose
    restored image is the ingest's image with its white balance undone (the photo's colours)."""
    source = root / "source"
    source.mkdir(parents=True)
    reference = cc.lab_to_linear_srgb(MACBETH.reference_lab)
    rng = np.random.default_rng(5)
    corners = np.array([[40.0, 40.0], [280.0, 50.0], [275.0, 200.0], [45.0, 190.0]])
    for i in range(views):
        linear = np.clip(0.2 + 0.1 * rng.random((240, 320, 3)), 0, 1) * [0.7, 1.0, 1.1]
        if i == chart_view:
            linear = chart_image(reference, corners, background=0.2)
        codes = np.round(linear_to_srgb(np.clip(linear, 0, 1)) * 255).astype(np.uint8)
        cv2.imwrite(str(source / f"view_{i:02d}.png"), codes[..., ::-1])
    assert main(["ingest", "--input", str(source), "--out", str(root / "ingest"),
                 "--workers", "1"]) == 0
    manifest = json.loads((root / "ingest" / "manifest.json").read_text())
    gains = np.asarray(manifest["white_balance"]["gains"])
    split = every_nth_split([f"view_{i:02d}" for i in range(views)], 8)
    frames = []
    for i in range(views):
        name = f"view_{i:02d}"
        (root / "poses" / "images").mkdir(parents=True, exist_ok=True)
        shutil.copy(root / "ingest" / "linear" / f"{name}.tiff",
                    root / "poses" / "images" / f"{name}.tiff")
        frames.append(Frame(name=name, image=f"images/{name}.tiff", width=320, height=240,
                            fx=250.0, fy=250.0, cx=160.0, cy=120.0, c2w=np.eye(4).tolist(),
                            near=0.1, far=2.0, split=split[name]))
        if split[name] == "test":
            linear = read_image(root / "ingest" / "linear" / f"{name}.tiff")
            for kind, image in (("full", linear), ("restored", linear / gains)):
                write_float_tiff(root / "render" / "test" / name / f"{kind}.tiff", image)
    write_cameras(root / "poses" / "cameras.json",
                  CameraSet(frames=frames, near=0.1, far=2.0, source="llff"))
    (root / "train").mkdir()
    return {"root": root, "corners": corners, "source": source}


def _evaluate(root: Path, *extra: str) -> dict:
    assert main(["evaluate", "--renders", str(root / "render"), "--cameras",
                 str(root / "poses" / "cameras.json"), "--train-dir", str(root / "train"),
                 "--out", str(root / "evaluate"), *extra]) == 0
    return json.loads((root / "evaluate" / "summary.json").read_text())["colour_chart"]


def test_evaluate_measures_an_annotated_chart_in_the_dataset_folder(tmp_path):
    data = _dataset(tmp_path, chart_view=0)
    annotation = {"format": "seathru-colour-chart/1", "chart": "macbeth-classic-24",
                  "image": "view_00.png", "corners": data["corners"].tolist(),
                  "occluded": [5]}
    (data["source"] / "colour_chart.json").write_text(json.dumps(annotation))
    chart = _evaluate(data["root"], "--no-chart-detect")
    assert chart["source"].endswith("colour_chart.json") and chart["image"] == "view_00"
    assert chart["occluded"] == [5] and chart["stored"]["delta_e00"][5] is None
    # the photo holds the reference colours (8-bit sRGB): small errors; the restored render is
    # the photo's colours too (white balance undone), the ingest image is white-balanced
    assert chart["stored"]["mean_delta_e00"] < 1.0
    assert chart["restored"]["mean_delta_e00"] < 1.0
    assert chart["ingest"]["mean_delta_e00"] > chart["stored"]["mean_delta_e00"]
    written = json.loads((data["root"] / "evaluate" / "colour_chart.json").read_text())
    assert written["stored"]["mean_delta_e00"] == pytest.approx(chart["stored"]
                                                                ["mean_delta_e00"])
    assert "restored no photograph of view_00" in chart["restored_photo"]["reason"]
    # the render step's restored photograph of the view (photos/, a training view's) is
    # measured too: here the ingest image, so its error is the ingest's
    write_float_tiff(data["root"] / "render" / "photos" / "view_00.tiff",
                     read_image(data["root"] / "ingest" / "linear" / "view_00.tiff"))
    chart = _evaluate(data["root"], "--no-chart-detect")
    assert chart["restored_photo"]["mean_delta_e00"] == pytest.approx(
        chart["ingest"]["mean_delta_e00"], rel=1e-3)


def test_evaluate_finds_a_chart_with_mcc_or_records_that_it_found_none(tmp_path):
    data = _dataset(tmp_path / "with", chart_view=8)
    chart = _evaluate(data["root"])
    assert chart["source"] == "mcc" and chart["image"] == "view_08"
    assert chart["stored"]["mean_delta_e00"] < 1.5
    empty = _dataset(tmp_path / "without", chart_view=-1)
    chart = _evaluate(empty["root"])
    assert chart["source"] == "none" and "mcc found no ColorChecker" in chart["reason"]


# ------------------------------------------------------------------------------- d3_reef

def test_d3_reef_chart_on_the_input_jpeg(shared_data):
    annotation = read_chart_annotation(FIXTURE)
    spec = cc.CHARTS[annotation["chart"]]
    codes = read_image(shared_data / "d3_reef" / annotation["image"]).astype(np.float64)
    assert (codes.shape[1], codes.shape[0]) == annotation["image_size"]
    samples = cc.patch_samples(codes, annotation["corners"], spec.rows, spec.cols)
    use = np.ones(spec.patches, bool)
    use[annotation["occluded"]] = False
    use[np.nanmax(samples, axis=(1, 2)) >= 0.98] = False          # clipped in the JPEG
    linear = np.nanmean(cc.patch_samples(srgb_to_linear(codes), annotation["corners"],
                                         spec.rows, spec.cols), axis=1)
    # the corners sit on the neutral row: white to black, every usable patch darker than the
    # one before it, and green/blue far above red (the water's cast) on every patch
    luminance = linear @ [0.2126, 0.7152, 0.0722]
    usable = np.flatnonzero(use)
    assert len(usable) >= 3 and np.all(np.diff(luminance[usable]) < 0)
    assert np.all(linear[:, 1] > 3 * linear[:, 0])
    errors = cc.chart_errors(linear, spec, use)
    assert 20 < errors["mean_grey_angular_error_deg"] < 45
    assert 10 < errors["mean_delta_e00"] < 30
    # OpenCV's mcc detector is no help here: the chart is small and seen at a grazing angle
    found = cc.detect_macbeth(np.clip(codes, 0, 1))
    assert found is None or np.abs(found - annotation["corners"]).max() < 10
