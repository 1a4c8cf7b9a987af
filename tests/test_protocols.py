"""The community's protocol (NerfBaselines' default for the SeaThru-NeRF dataset).

- the radiometric inverse of ingest gives the stored image back (property tests through the
  ingest's own functions);
- the split, the uint8 truncation, the 16-bit reading and SSIM match transcriptions of
  NerfBaselines / dm-pix and PIL itself;
- the render's geometry goes back onto a distorted stored image;
- ``seathru evaluate --protocol nerfbaselines`` on a tiny dataset ingested by the real ingest
  step: PSNR / SSIM equal an independent computation on the stored images (PIL to read them,
  scikit-image's metrics), and the files follow NerfBaselines' layout and results format.
"""

from __future__ import annotations

import base64
import hashlib
import json
import shutil
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings as hypothesis_settings, strategies as st
from hypothesis.extra import numpy as hnp
from PIL import Image
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from seathru.cli import main
from seathru.eval import metrics, protocols
from seathru.io.cameras import CameraSet, Frame, every_nth_split, write_cameras
from seathru.io.colmap import make_camera, undistortion
from seathru.io.images import read_image, write_float_tiff
from seathru.io.stored_views import (frame_source_camera, render_to_stored,
                                     stored_image_on_frame, stored_points_on_frame)
from seathru.radiometry.colour import srgb_to_linear
from seathru.radiometry.linearise import apply_colour, resize_area
from seathru.radiometry.stored_encoding import ingest_linear, stored_values

GAINS = st.lists(st.floats(0.2, 5.0), min_size=3, max_size=3)
FACTORS = st.floats(0.25, 4.0)


# ----------------------------------------------------------------- radiometry: ingest and back

@hypothesis_settings(max_examples=60, deadline=None)
@given(hnp.arrays(np.uint8, (4, 5, 3)), GAINS, FACTORS)
def test_ingest_then_inverse_gives_the_stored_8bit_srgb_image_back(codes, gains, factor):
    # what ingest does to an 8-bit sRGB file: seathru.io.raw.read_encoded, then apply_colour
    linear = apply_colour(srgb_to_linear(codes.astype(np.float32) / np.float32(255)),
                          np.asarray(gains) * factor)
    back = stored_values(linear, gains, factor, "srgb")
    np.testing.assert_array_equal(np.round(back * 255).astype(np.uint8), codes)


@hypothesis_settings(max_examples=60, deadline=None)
@given(hnp.arrays(np.uint16, (4, 5, 3)), GAINS, FACTORS)
def test_ingest_then_inverse_gives_the_stored_16bit_linear_image_back(codes, gains, factor):
    linear = apply_colour(codes.astype(np.float32) / np.float32(65535),
                          np.asarray(gains) * factor)
    back = stored_values(linear, gains, factor, "linear")
    np.testing.assert_array_equal(np.round(back * 65535).astype(np.uint16), codes)


@hypothesis_settings(max_examples=60, deadline=None)
@given(hnp.arrays(np.float64, (3, 3, 3), elements=st.floats(0.0, 1.0)), GAINS, FACTORS,
       st.sampled_from(["srgb", "linear", "gamma 1.8", "gamma 2.2"]))
def test_inverse_of_the_float64_forward_map_is_the_identity(stored, gains, factor, encoding):
    linear = ingest_linear(stored, gains, factor, encoding)
    np.testing.assert_allclose(stored_values(linear, gains, factor, encoding), stored,
                               atol=1e-9)


def test_inverse_rejects_bad_gains_and_encodings():
    with pytest.raises(ValueError, match="gains"):
        stored_values(np.ones((1, 1, 3)), [1.0, 0.0, 1.0], 1.0, "srgb")
    with pytest.raises(ValueError, match="encoding"):
        stored_values(np.ones((1, 1, 3)), [1.0, 1.0, 1.0], 1.0, "gamma22")


# --------------------------------------------------------- the protocol against its sources

def _nerfbaselines_llff_split(names, llffhold=8):
    """nerfbaselines/datasets/seathru_nerf.py, _select_indices_llff (transcribed)."""
    inds = np.argsort(names)
    all_indices = np.arange(len(names))
    return inds[all_indices % llffhold != 0], inds[all_indices % llffhold == 0]


@hypothesis_settings(max_examples=40, deadline=None)
@given(st.lists(st.from_regex(r"[a-z0-9_]{1,8}\.(png|jpg)", fullmatch=True), min_size=1,
                max_size=40, unique=True))
def test_held_out_names_are_nerfbaselines_llffhold_8(names):
    _, test = _nerfbaselines_llff_split(names)
    assert protocols.held_out_names(names) == sorted(names[i] for i in test)


def test_quantisation_truncates_as_convert_image_dtype():
    values = np.array([0.0, 0.999 / 255, 1.5 / 255, 0.5, 254.9 / 255, 1.0, 1.2, -0.1, np.nan])
    reference = np.clip(np.nan_to_num(values) * 255.0, 0, 255).astype(np.uint8)
    np.testing.assert_array_equal(protocols.quantise_truncate(values), reference)
    assert protocols.quantise_truncate(np.array([1.5 / 255]))[0] == 1  # rounding would give 2


def test_16bit_ground_truth_is_what_pil_reads(tmp_path):
    codes = np.random.default_rng(0).integers(0, 65536, (6, 7, 3)).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "a.png"), codes[..., ::-1])
    pil = np.array(Image.open(tmp_path / "a.png"), dtype=np.uint8)
    np.testing.assert_array_equal(protocols.stored_codes_as_uint8(codes), pil)


def _dmpix_ssim(a, b, max_val=1.0, kernel_size=11, sigma=1.5, k1=0.01, k2=0.03):
    """dm-pix's ssim as nerfbaselines/metrics.py transcribes it (float32, 'valid' filtering,
    clipped variances), for one (H, W, C) pair."""
    a, b = a.astype(np.float32), b.astype(np.float32)
    hw = kernel_size // 2
    filt = np.exp(-0.5 * ((np.arange(kernel_size) - hw) / sigma) ** 2)
    filt = (filt / filt.sum()).astype(np.float32)

    def blur(z):
        z = np.apply_along_axis(lambda r: np.convolve(r, filt, mode="valid"), 1, z)
        return np.apply_along_axis(lambda c: np.convolve(c, filt, mode="valid"), 0, z)

    mu0, mu1 = blur(a), blur(b)
    s00 = np.maximum(np.finfo(np.float32).eps ** 2, blur(a * a) - mu0 * mu0)
    s11 = np.maximum(np.finfo(np.float32).eps ** 2, blur(b * b) - mu1 * mu1)
    s01 = blur(a * b) - mu0 * mu1
    s01 = np.sign(s01) * np.minimum(np.sqrt(s00 * s11), np.abs(s01))
    c1, c2 = (k1 * max_val) ** 2, (k2 * max_val) ** 2
    ssim_map = ((2 * mu0 * mu1 + c1) * (2 * s01 + c2)) / ((mu0 ** 2 + mu1 ** 2 + c1)
                                                           * (s00 + s11 + c2))
    return float(ssim_map.mean())


@pytest.mark.parametrize("seed", [0, 1])
def test_our_ssim_is_dmpix_ssim(seed):
    rng = np.random.default_rng(seed)
    truth = rng.integers(0, 256, (23, 31, 3)).astype(np.uint8)
    noisy = np.clip(truth + rng.normal(0, 25, truth.shape), 0, 255).astype(np.uint8)
    a, b = noisy / 255.0, truth / 255.0
    assert metrics.ssim(a, b) == pytest.approx(_dmpix_ssim(a, b), abs=2e-6)
    values = protocols.view_protocol_metrics(noisy, truth)
    assert values["ssim"] == pytest.approx(_dmpix_ssim(a, b), abs=2e-6)
    assert values["psnr"] == pytest.approx(-10 * np.log10(np.mean((a - b) ** 2)), abs=1e-9)


# ------------------------------------------------------------------------------ geometry back

WIDTH, HEIGHT = 96, 72


def _distorted_source_and_frame():
    """A distorted source camera of WIDTH x HEIGHT, its undistortion, and the pinhole frame the
    poses step makes of it."""
    camera = make_camera("SIMPLE_RADIAL", WIDTH, HEIGHT, [80.0, 48.0, 36.0, 0.08])
    warp = undistortion(camera)
    frame = Frame(name="v", image="", width=warp.width, height=warp.height, fx=warp.fx,
                  fy=warp.fy, cx=warp.cx, cy=warp.cy, c2w=np.eye(4).tolist(), near=0.1, far=1)
    return camera, warp, frame


def test_render_goes_back_onto_the_distorted_stored_camera():
    camera, warp, frame = _distorted_source_and_frame()
    width, height = WIDTH, HEIGHT
    found = frame_source_camera(frame, (width, height), [camera])
    assert found is not None and found.params.tolist() == camera.params.tolist()
    v, u = np.mgrid[0:height, 0:width] + 0.5
    stored = np.stack([np.sin(u / 9.0), np.cos(v / 7.0), np.sin((u + v) / 11.0)], -1) * 0.4 + 0.5
    render = warp.warp_image(stored.astype(np.float32))      # what the poses step trains on
    back = render_to_stored(render, frame, found)
    inner = (slice(8, height - 8), slice(8, width - 8))
    assert np.abs(back[inner] - stored[inner]).max() < 0.02
    points = np.array([[20.5, 15.5], [70.0, 50.0]])
    on_render = stored_points_on_frame(points, (width, height), frame, [camera])
    sampled = cv2.remap(render, on_render[:, :1].astype(np.float32) - 0.5,
                        on_render[:, 1:].astype(np.float32) - 0.5, cv2.INTER_LINEAR)[:, 0]
    expected = cv2.remap(stored.astype(np.float32), points[:, :1].astype(np.float32) - 0.5,
                         points[:, 1:].astype(np.float32) - 0.5, cv2.INTER_LINEAR)[:, 0]
    np.testing.assert_allclose(sampled, expected, atol=0.02)


def _ray_texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth colour as a function of the ray direction (x/z, y/z): the same scene point has
    the same colour on the distorted and on the undistorted camera."""
    return np.stack([0.5 + 0.4 * np.sin(9 * x), 0.5 + 0.4 * np.cos(7 * y),
                     0.5 + 0.3 * np.sin(6 * (x + y))], -1).astype(np.float32)


def test_truth_goes_onto_the_undistorted_frame_and_open_water_stays_undefined():
    camera, warp, frame = _distorted_source_and_frame()
    width, height = WIDTH, HEIGHT
    v, u = np.mgrid[0:height, 0:width] + 0.5
    rays = camera.cam_from_img(np.stack([u.ravel(), v.ravel()], 1))
    stored = _ray_texture(rays[:, 0], rays[:, 1]).reshape(height, width, 3)
    fv, fu = np.mgrid[0:warp.height, 0:warp.width] + 0.5
    expected = _ray_texture((fu - warp.cx) / warp.fx, (fv - warp.cy) / warp.fy)

    on_frame = stored_image_on_frame(stored, frame, [camera])
    assert on_frame.shape == expected.shape
    assert np.abs(on_frame - expected).max() < 0.002
    resized = resize_area(stored, (warp.width, warp.height))
    assert np.abs(resized - expected).max() > 0.04       # what a resize alone gives

    # an infinite range (open water) in the left 10 columns of the stored image
    depth = np.where(u < 10, np.inf, 2.0).astype(np.float32)
    depth_on_frame = stored_image_on_frame(depth, frame, [camera])
    source_u = warp.map_x + 0.5
    assert np.isnan(depth_on_frame[source_u < 9.5]).all()
    assert np.isfinite(depth_on_frame[source_u > 11]).all()
    np.testing.assert_allclose(depth_on_frame[source_u > 11], 2.0)

    half = Frame(name="v", image="", width=warp.width // 2, height=warp.height // 2,
                 fx=warp.fx / 2, fy=warp.fy / 2, cx=warp.cx / 2, cy=warp.cy / 2,
                 c2w=np.eye(4).tolist(), near=0.1, far=1)
    assert stored_image_on_frame(stored, half, [camera]).shape == (warp.height // 2,
                                                                    warp.width // 2, 3)
    # without source cameras (a pinhole dataset) the image is only resized
    np.testing.assert_allclose(stored_image_on_frame(stored, frame, []), resized)


def test_truth_is_resampled_as_the_training_images_were():
    camera, warp, frame = _distorted_source_and_frame()
    rng = np.random.default_rng(4)
    stored = rng.random((HEIGHT, WIDTH, 3)).astype(np.float32)   # detail a kernel changes
    for how in ("linear", "cubic"):
        on_frame = stored_image_on_frame(stored, frame, [camera], how)
        np.testing.assert_allclose(on_frame, warp.warp_image(stored, how), atol=1e-5)
    # an undefined pixel leaves undefined every output pixel its kernel reaches
    stored[36, 48] = np.nan
    bump = np.ones((HEIGHT, WIDTH, 3), np.float32)
    bump[36, 48] = 2.0
    for how in ("linear", "cubic"):
        reached = (np.abs(warp.warp_image(bump, how) - 1.0) > 1e-4).any(-1)
        undefined = np.isnan(stored_image_on_frame(stored, frame, [camera], how)).any(-1)
        assert 2 <= reached.sum() and (undefined == reached).all(), how


# ------------------------------------------------------------ the step on an ingested dataset

def _srgb_encode(linear):
    """IEC 61966-2-1, written out here so the check does not use the pipeline's own code."""
    linear = np.clip(linear, 0, 1)
    return np.where(linear <= 0.0031308, 12.92 * linear,
                    1.055 * np.power(linear, 1 / 2.4) - 0.055)


def _make_dataset(root: Path, kind: str, views: int = 9, test_every: int = 8) -> dict:
    """Stored images -> the real ingest step -> a hand-written camera file and renders (the
    ingest's linear image times a per-view colour error, so the metrics are not trivial)."""
    rng = np.random.default_rng(3)
    source = root / "source"
    source.mkdir(parents=True)
    height, width = 30, 40
    yy, xx = np.mgrid[0:height, 0:width]
    for i in range(views):
        base = 0.5 + 0.35 * np.stack([np.sin(xx / 5 + i), np.cos(yy / 4 - i),
                                      np.sin((xx + yy) / 6)], -1)
        base *= np.array([0.9, 0.7, 0.5])            # a colour cast: unequal white balance
        image = np.clip(base + rng.normal(0, 0.03, base.shape), 0, 1)
        codes = (image * 255).astype(np.uint8) if kind == "srgb" else \
            (image * 65535).astype(np.uint16)
        cv2.imwrite(str(source / f"view_{i:02d}.png"), codes[..., ::-1])
    assert main(["ingest", "--input", str(source), "--out", str(root / "ingest"),
                 "--workers", "1"]) == 0
    manifest = json.loads((root / "ingest" / "manifest.json").read_text())
    split = every_nth_split([f"view_{i:02d}" for i in range(views)], test_every)
    frames = []
    for i in range(views):
        name = f"view_{i:02d}"
        (root / "poses" / "images").mkdir(parents=True, exist_ok=True)
        shutil.copy(root / "ingest" / "linear" / f"{name}.tiff",
                    root / "poses" / "images" / f"{name}.tiff")
        pose = np.eye(4)
        pose[0, 3] = 0.1 * i
        frames.append(Frame(name=name, image=f"images/{name}.tiff", width=width, height=height,
                            fx=30.0, fy=30.0, cx=width / 2, cy=height / 2, c2w=pose.tolist(),
                            near=0.1, far=2.0, split=split[name]))
        if split[name] == "test":
            linear = read_image(root / "ingest" / "linear" / f"{name}.tiff")
            full = linear * np.array([1.04, 0.97, 1.01]) + rng.normal(0, 0.01, linear.shape)
            write_float_tiff(root / "render" / "test" / name / "full.tiff", full)
            write_float_tiff(root / "render" / "test" / name / "restored.tiff", full)
    write_cameras(root / "poses" / "cameras.json",
                  CameraSet(frames=frames, near=0.1, far=2.0, source="llff"))
    (root / "train").mkdir()
    return {"root": root, "manifest": manifest, "test": sorted(n for n, s in split.items()
                                                                if s == "test")}


def _evaluate(data: dict, *extra: str) -> int:
    root = data["root"]
    return main(["evaluate", "--renders", str(root / "render"), "--cameras",
                 str(root / "poses" / "cameras.json"), "--train-dir", str(root / "train"),
                 "--out", str(root / "evaluate"), "--protocol", "nerfbaselines",
                 "--no-chart-detect", *extra])


@pytest.mark.parametrize("kind", ["srgb", "linear"])
def test_nerfbaselines_protocol_equals_an_independent_computation(tmp_path, kind):
    data = _make_dataset(tmp_path / kind, kind)
    assert _evaluate(data) == 0
    out = data["root"] / "evaluate" / "nerfbaselines"
    results = json.loads((out / "results.json").read_text())
    info = json.loads((out / "info.json").read_text())
    assert data["test"] == ["view_00", "view_08"]
    gains = np.asarray(data["manifest"]["white_balance"]["gains"])
    assert np.ptp(gains) > 0.1, "the test needs a white balance that is not neutral"
    psnrs, ssims = [], []
    for name in data["test"]:
        image = next(i for i in data["manifest"]["images"] if i["name"] == name)
        # the ground truth: the stored file as NerfBaselines reads it (PIL, uint8)
        truth = np.array(Image.open(data["root"] / "source" / f"{name}.png"), dtype=np.uint8)
        full = read_image(data["root"] / "render" / "test" / name / "full.tiff")
        stored = np.clip(full / (gains * image["exposure_factor"]), 0, 1)
        if kind == "srgb":
            stored = _srgb_encode(stored)
        prediction = np.clip(stored * 255.0, 0, 255).astype(np.uint8)
        written = np.array(Image.open(out / "color" / f"{name}.png"))
        assert np.mean(written != prediction) < 0.01   # float32 vs float64 at code boundaries
        np.testing.assert_array_equal(np.array(Image.open(out / "gt-color" / f"{name}.png")),
                                      truth)
        psnrs.append(peak_signal_noise_ratio(truth, prediction, data_range=255))
        ssims.append(structural_similarity(
            truth, prediction, channel_axis=-1, gaussian_weights=True, sigma=1.5,
            use_sample_covariance=False, data_range=255))
        mine = results["seathru"]["per_image"][name]
        assert mine["psnr"] == pytest.approx(psnrs[-1], abs=0.02)
        assert mine["ssim"] == pytest.approx(ssims[-1], abs=5e-4)
        assert 15 < mine["psnr"] < 45
    per_image = [results["seathru"]["per_image"][name]["psnr"] for name in data["test"]]
    assert results["metrics"]["psnr"] == pytest.approx(np.mean(psnrs), abs=0.02)
    assert results["metrics"]["ssim"] == pytest.approx(np.mean(ssims), abs=5e-4)
    assert results["metrics"]["psnr"] == pytest.approx(np.mean(per_image), abs=1e-5)
    raw = base64.b64decode(results["metrics_raw"]["psnr"])
    np.testing.assert_allclose(struct.unpack(f"{len(psnrs)}f", raw), per_image, rtol=1e-6)
    sha = hashlib.sha256()
    for name in data["test"]:
        sha.update((out / "color" / f"{name}.png").read_bytes())
    assert results["predictions_sha256"] == sha.hexdigest()
    assert results["evaluation_protocol"] == "default" == info["evaluation_protocol"]
    assert "seathru" in info["method"] and {"nb_info", "metrics_sha256", "ground_truth_sha256",
                                            "evaluate_datetime"} <= set(results)
    summary = json.loads((data["root"] / "evaluate" / "summary.json").read_text())
    assert summary["protocol"]["means"]["psnr"] == pytest.approx(np.mean(per_image), abs=1e-9)
    assert summary["means"]["psnr_linear"] > 0          # today's metrics stay


def test_protocol_refuses_a_split_that_is_not_every_8th(tmp_path, capsys):
    data = _make_dataset(tmp_path, "srgb", views=9, test_every=4)
    assert _evaluate(data) == 2
    assert "poses.test_every=8" in capsys.readouterr().err
