"""Tests of the ingest step: RAW/JPEG/PNG decoding to linear, exposure normalisation, white
balance, clipping masks, bad-input handling, and a round trip through the simulator."""

from __future__ import annotations

import argparse
import itertools
import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage
from skimage.transform import downscale_local_mean

from seathru.radiometry import linearise, stored_encoding
from seathru.errors import PipelineError
from seathru.io import raw as rawio
from seathru.io.dataset_readers import frame_names, layout_images, read_source_mask
from seathru.io.images import read_mask
from seathru.io.stored_views import read_stored_codes, read_stored_views
from seathru.io.image_folder import (every_image_file, find_inputs, image_subfolders,
                                     resolve_input, select_files, select_paths)
from seathru.steps import ingest

rawpy = pytest.importorskip("rawpy")

DNG = "raw/canon550d_colorchart.dng"
KDC = "raw/kodak_dc50.kdc"
ONE_CODE = 1.0 / 65535.0


def run_ingest(*argv) -> dict:
    """Run ``seathru ingest`` in-process; return the manifest."""
    parser = argparse.ArgumentParser()
    ingest.add_arguments(parser)
    args = parser.parse_args([str(a) for a in argv])
    ingest.run(args)
    return json.loads((Path(args.out) / "manifest.json").read_text())


def link_files(folder: Path, files: dict[str, Path]) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for name, target in files.items():
        os.symlink(target, folder / name)
    return folder


def bad_raw_files(shared_data: Path) -> dict[str, Path]:
    """The 9 damaged files (5 stripped, 4 truncated) under names with distinct stems."""
    files = sorted((shared_data / "raw" / "bad").glob("*/*"))
    assert len(files) == 9, files
    return {f"{p.parent.name}_{p.stem}_{p.suffix[1:]}{p.suffix}": p for p in files}


def raw_reference(path: Path):
    """The raw mosaic, CFA colours and levels, read directly with rawpy."""
    with rawpy.imread(str(path)) as raw:
        return (raw.raw_image_visible.astype(np.float64), raw.raw_colors_visible.copy(),
                np.array(raw.black_level_per_channel, dtype=np.float64), float(raw.white_level))


def expected_native(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(raw - black) / (white - black) per CFA site (>= 0), and the output channel of each site."""
    mosaic, colours, black, white = raw_reference(path)
    expected = np.clip((mosaic - black[colours]) / (white - black[colours]), 0.0, None)
    return expected, np.where(colours == 3, 1, colours)


# --- RAW decoding on real files -------------------------------------------------------------

@pytest.mark.parametrize("demosaic", ["LINEAR", "AHD"])
def test_dng_linear_output_is_black_white_normalised_raw(shared_data, demosaic):
    decoded = rawio.decode_raw(shared_data / DNG, rawio.RawSettings(demosaic=demosaic))
    meta = decoded.metadata
    assert meta["black_level"] == [2056.0] * 4
    assert meta["white_level"] == 15000.0
    assert meta["cfa_pattern"] == "RGGB"
    assert meta["raw_size"] == [1888, 1182]
    assert meta["flip"] == 0
    expected, channel = expected_native(shared_data / DNG)
    assert decoded.image.shape == expected.shape + (3,)
    assert decoded.image.dtype == np.float32
    assert expected.max() > 0.5  # the chart's white patch: the check covers the range
    # Demosaicing keeps each CFA site's own sample; only the missing channels are interpolated.
    native = np.take_along_axis(decoded.image, channel[..., None], axis=2)[..., 0]
    np.testing.assert_allclose(native, expected, rtol=0, atol=ONE_CODE)
    # Interpolated channels: over 16x16 blocks, each channel's mean matches its native samples'.
    height, width = (s // 16 * 16 for s in expected.shape)
    for c in range(3):
        sites = (channel == c)[:height, :width].reshape(height // 16, 16, width // 16, 16)
        values = expected[:height, :width].reshape(sites.shape)
        native_mean = (values * sites).sum(axis=(1, 3)) / sites.sum(axis=(1, 3))
        output_mean = decoded.image[:height, :width, c].reshape(sites.shape).mean(axis=(1, 3))
        relative = np.abs(output_mean - native_mean) / np.maximum(native_mean, 1e-3)
        assert np.median(relative) < 0.02, (c, np.median(relative))


def test_dng_half_size_bins_each_cfa_block(shared_data):
    decoded = rawio.decode_raw(shared_data / DNG, rawio.RawSettings(half_size=True))
    expected, _ = expected_native(shared_data / DNG)  # RGGB: R (0,0), G (0,1) (1,0), B (1,1)
    assert decoded.image.shape == (578, 867, 3)
    np.testing.assert_allclose(decoded.image[..., 0], expected[0::2, 0::2], atol=ONE_CODE)
    np.testing.assert_allclose(decoded.image[..., 2], expected[1::2, 1::2], atol=ONE_CODE)
    np.testing.assert_allclose(decoded.image[..., 1],
                               (expected[0::2, 1::2] + expected[1::2, 0::2]) / 2, atol=2 * ONE_CODE)


def test_kdc_decodes_with_exposure_metadata(shared_data):
    decoded = rawio.decode_raw(shared_data / KDC, rawio.RawSettings(demosaic="LINEAR"))
    assert decoded.image.shape == (512, 768, 3)
    expected, channel = expected_native(shared_data / KDC)
    native = np.take_along_axis(decoded.image, channel[..., None], axis=2)[..., 0]
    np.testing.assert_allclose(native, expected, atol=ONE_CODE)
    exposure = decoded.exposure
    assert exposure.exposure_time == pytest.approx(87 / 20000)   # EXIF 87/20000 s
    assert exposure.f_number == pytest.approx(6.2)               # EXIF 31/5
    assert exposure.iso == pytest.approx(84)                     # not in EXIF: from LibRaw
    assert exposure.source == {"exposure_time": "exif", "f_number": "exif", "iso": "libraw"}


def test_dng_without_exposure_metadata_reads_as_missing(shared_data):
    # The 550D DNG stores ExposureTime/FNumber/ISO as 0; LibRaw reports 1 s and f/1 for them.
    decoded = rawio.decode_raw(shared_data / DNG, rawio.RawSettings(half_size=True))
    assert (decoded.exposure.exposure_time, decoded.exposure.iso, decoded.exposure.f_number) == (
        None, None, None)


def test_saturation_mask_is_computed_on_the_raw_grid(shared_data):
    threshold = 0.7  # the real file has no clipped pixels; lower the bar to get some
    decoded = rawio.decode_raw(shared_data / DNG, rawio.RawSettings(
        demosaic="LINEAR", saturation_threshold=threshold))
    mosaic, _, _, white = raw_reference(shared_data / DNG)
    expected = mosaic >= threshold * white
    assert 0 < expected.sum() < expected.size / 10
    np.testing.assert_array_equal(decoded.saturated, expected)
    assert not decoded.black_clipped.any()  # raw values stay above the ADC floor

    half = rawio.decode_raw(shared_data / DNG, rawio.RawSettings(
        half_size=True, saturation_threshold=threshold))
    np.testing.assert_array_equal(half.saturated,
                                  expected.reshape(578, 2, 867, 2).any(axis=(1, 3)))


def test_orientation_matches_libraw_flip(shared_data):
    """``orient`` of the unrotated output equals LibRaw's own output for every flip code."""
    params = dict(half_size=True, user_wb=[1, 1, 1, 1], output_color=rawpy.ColorSpace.raw,
                  gamma=(1, 1), no_auto_bright=True, output_bps=16)
    with rawpy.imread(str(shared_data / KDC)) as raw:
        base = raw.postprocess(user_flip=0, **params)
        for flip in range(1, 8):
            np.testing.assert_array_equal(linearise.orient(base, flip),
                                          raw.postprocess(user_flip=flip, **params))


def test_srgb_colour_matches_libraw_conversion(shared_data):
    """Camera WB then ``color_matrix`` on the unit-WB raw decode = LibRaw's own sRGB output."""
    decoded = rawio.decode_raw(shared_data / DNG, rawio.RawSettings(half_size=True))
    assert decoded.colour_matrix is not None and decoded.camera_wb is not None
    ours = linearise.apply_colour(decoded.image, decoded.camera_wb, decoded.colour_matrix)
    with rawpy.imread(str(shared_data / DNG)) as raw:
        libraw = raw.postprocess(
            half_size=True, user_wb=[*decoded.camera_wb, decoded.camera_wb[1]], user_flip=0,
            output_color=rawpy.ColorSpace.sRGB, gamma=(1, 1), no_auto_bright=True,
            adjust_maximum_thr=0.0, output_bps=16).astype(np.float64) / 65535.0
    inside = ((libraw > 0.001) & (libraw < 0.99)).all(axis=-1)  # LibRaw clips to [0, 1]
    assert inside.mean() > 0.5
    np.testing.assert_allclose(ours[inside], libraw[inside], atol=3e-4)


# --- bad input ------------------------------------------------------------------------------

def test_each_bad_raw_file_is_rejected_with_a_reason(shared_data):
    for path in bad_raw_files(shared_data).values():
        with pytest.raises(rawio.DecodeError) as info:
            rawio.decode_raw(path, rawio.RawSettings(half_size=True))
        reason = str(info.value)
        assert len(reason) > 20, (path.name, reason)
        assert any(word in reason for word in ("truncated", "stripped", "damaged", "corrupt",
                                               "missing")), (path.name, reason)


def test_mixed_dataset_keeps_good_files_and_names_each_reject(shared_data, tmp_path):
    bad = bad_raw_files(shared_data)
    folder = link_files(tmp_path / "dive", {
        "canon.dng": shared_data / DNG, "kodak_dc50.kdc": shared_data / KDC,
        "kodak_dc50.DNG": shared_data / DNG,  # the same file as the first: rejected as a copy
        "notes.txt": shared_data / "README.md", **bad})
    manifest = run_ingest("--input", folder, "--out", tmp_path / "out", "--half-size",
                          "--min-images", 2, "--downscale", 2, "--workers", 2)
    out = tmp_path / "out"
    assert [im["name"] for im in manifest["images"]] == ["canon", "kodak_dc50"]
    assert manifest["input"]["kind"] == "raw" and manifest["input"]["ignored"] == ["notes.txt"]
    rejected = {r["file"]: r["reason"] for r in manifest["rejected"]}
    assert set(rejected) == set(bad) | {"kodak_dc50.DNG"}
    assert "copy of canon.dng" in rejected["kodak_dc50.DNG"]   # the shorter name is kept
    assert all(len(reason) > 20 for reason in rejected.values())
    for image in manifest["images"]:
        linear = tifffile.imread(out / image["linear"])
        assert linear.shape == (image["height"], image["width"], 3)
        mask = cv2.imread(str(out / image["mask"]), cv2.IMREAD_UNCHANGED)
        assert mask.shape == linear.shape[:2] and set(np.unique(mask)) <= {0, 255}
        small = image["downscaled"]["2"]
        assert tifffile.imread(out / small["linear"]).shape == (small["height"], small["width"],
                                                                3)
        assert cv2.imread(str(out / image["matching"])).shape[:2] == linear.shape[:2]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dive", "out"]  # no temp left over


def test_only_bad_files_fail_and_leave_previous_output(shared_data, tmp_path):
    files = bad_raw_files(shared_data)
    folder = link_files(tmp_path / "dive", files)
    out = tmp_path / "out"
    out.mkdir()
    (out / "previous.txt").write_text("an earlier, complete run")
    with pytest.raises(PipelineError) as info:
        run_ingest("--input", folder, "--out", out, "--half-size", "--workers", 1)
    message = str(info.value)
    assert "only 0 usable image(s) of 9" in message and "9 rejected" in message
    assert all(name in message for name in files)
    assert (out / "previous.txt").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dive", "out"]


def test_invalid_raw_reasons():
    rng = np.random.default_rng(0)
    photo = rng.integers(500, 4000, size=(64, 96), dtype=np.uint16)
    assert linearise.invalid_raw_reason(photo, 64 * 96 * 2, 96, 64) is None
    assert "0x0" in linearise.invalid_raw_reason(photo[:0], 1000, 0, 0)
    assert "stripped or truncated" in linearise.invalid_raw_reason(photo, 100, 96, 64)
    constant = np.zeros_like(photo)
    constant[0, :5] = 7
    assert "share one value" in linearise.invalid_raw_reason(constant, 64 * 96 * 2, 96, 64)
    # A mostly saturated frame is a real (overexposed) photo: judged on its unsaturated part.
    bright = photo.copy()
    bright[:60] = 4095
    assert linearise.invalid_raw_reason(bright, 64 * 96 * 2, 96, 64, bright >= 4095) is None
    assert "constant" in linearise.invalid_image_reason(np.zeros((4, 4, 3)))


def _mosaic_dng(path: Path, scene: np.ndarray, focal_length_35mm: int | None = None) -> None:
    """``scene`` (H, W, 3) in [0, 1] sampled on an RGGB mosaic, noise-free, as a DNG."""
    from seathru.io.dng import write_dng

    height, width = scene.shape[:2]
    channel = np.full((height, width), 1)
    channel[0::2, 0::2], channel[1::2, 1::2] = 0, 2
    mosaic = np.take_along_axis(scene, channel[..., None], -1)[..., 0]
    write_dng(path, (1024 + mosaic * (16383 - 1024)).round().astype(np.uint16),
              black_level=1024, white_level=16383, exposure_time_s=0.01, iso=100, f_number=4.0,
              focal_length_35mm=focal_length_35mm)


def test_the_exif_focal_length_reaches_the_manifest_where_the_poses_step_finds_it(tmp_path):
    from seathru.geometry.intrinsics import focal_from_metadata

    rng = np.random.default_rng(1)
    for folder, focal in (("with", 28), ("without", None)):
        for i in range(3):
            _mosaic_dng(tmp_path / folder / f"im{i}.dng", rng.uniform(0.1, 0.9, (24, 32, 3)),
                        focal)
        manifest = run_ingest("--input", tmp_path / folder, "--out", tmp_path / f"{folder}_out")
        recorded = [image.get("focal_length_35mm") for image in manifest["images"]]
        width, height = manifest["images"][0]["matching_size"]
        focal_px, source = focal_from_metadata(manifest, width, height)
        if focal is None:
            assert recorded == [None] * 3 and focal_px is None
        else:
            assert recorded == [28.0] * 3 and "35 mm" in source
            # by the diagonal: a 28 mm equivalent spans 75 degrees across the diagonal
            assert focal_px == pytest.approx(28.0 / np.hypot(36.0, 24.0) * np.hypot(width,
                                                                                     height))


def test_linear_demosaic_keeps_each_channel_to_its_own_samples_and_ahd_does_not(tmp_path):
    """Underwater the colour changes with range: blue fades while green stays. Demosaics that
    interpolate the colour difference (AHD, the default, and PPG, DCB) copy green's texture into
    red and blue; LINEAR interpolates every channel from its own samples, so a flat blue stays
    flat beside textured green. docs/water.md ("The demosaic") measures what each costs the
    water; ingest.demosaic's help says which to choose."""
    rng = np.random.default_rng(0)
    green = np.kron(rng.uniform(0.1, 0.6, (12, 16)), np.ones((4, 4)))
    scene = np.stack([np.full_like(green, 0.3), green, np.full_like(green, 0.2)], -1)
    _mosaic_dng(tmp_path / "flat_blue.dng", scene)
    inner = (slice(4, -4), slice(4, -4))

    def relative_spread(demosaic: str) -> np.ndarray:
        image = rawio.decode_raw(tmp_path / "flat_blue.dng",
                                 rawio.RawSettings(demosaic=demosaic)).image[inner]
        return image.std(axis=(0, 1)) / image.mean(axis=(0, 1))

    linear = relative_spread("LINEAR")
    assert linear[0] < 1e-3 and linear[2] < 1e-3
    assert linear[1] > 0.3    # green keeps its texture
    for leaky in ("AHD", "PPG", "DCB"):
        assert relative_spread(leaky)[2] > 0.1, leaky
    assert ingest.Settings().demosaic == rawio.RawSettings().demosaic


# --- encoded inputs -------------------------------------------------------------------------

def _srgb_decode_reference(code: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 inverse transfer in float64, written out independently of the package."""
    v = code.astype(np.float64) / 255.0
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


@pytest.fixture(scope="module")
def reef(shared_data, tmp_path_factory) -> Path:
    names = sorted(p.name for p in (shared_data / "d3_reef").glob("*.jpg"))[:4]
    return link_files(tmp_path_factory.mktemp("reef") / "images",
                      {n: shared_data / "d3_reef" / n for n in names})


def test_reef_jpegs_follow_the_inverse_srgb_curve(reef, tmp_path):
    manifest = run_ingest("--input", reef, "--out", tmp_path / "out", "--wb", "none",
                          "--workers", 1)
    assert manifest["input"]["kind"] == "srgb" and manifest["colour_space"] == "as stored"
    assert len(manifest["images"]) == 4
    for image in manifest["images"]:
        assert image["exposure_factor"] == 1.0 and image["exposure_time"] is None
        codes = cv2.cvtColor(cv2.imread(str(reef / image["source"])), cv2.COLOR_BGR2RGB)
        linear = tifffile.imread(tmp_path / "out" / image["linear"])
        assert linear.shape == codes.shape == (540, 720, 3)
        # Exact values at a few pixels, dark (linear segment) and bright (power segment).
        flat = codes.reshape(-1, 3)
        for code in (5, 30, 120, 250):
            index = np.argmin(np.abs(flat[:, 0].astype(int) - code))
            pixel = np.unravel_index(index, codes.shape[:2])
            np.testing.assert_allclose(linear[pixel], _srgb_decode_reference(codes[pixel]),
                                       rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(linear, _srgb_decode_reference(codes), rtol=1e-5, atol=1e-7)
        # Saturated codes (255 in any channel) and black pixels (0 in every channel) are invalid,
        # and so are their neighbours.
        mask = cv2.imread(str(tmp_path / "out" / image["mask"]), cv2.IMREAD_UNCHANGED) > 0
        clipped = (codes == 255).any(axis=-1) | (codes == 0).all(axis=-1)  # one channel at 0: valid
        np.testing.assert_array_equal(~mask, ndimage.binary_dilation(clipped, np.ones((3, 3))))
        assert image["clipped_fraction"] == pytest.approx(1 - mask.mean())


@pytest.mark.parametrize("stats_pixels", [540 * 720, 20_000])
def test_percentile_white_balance_puts_each_channel_percentile_at_one(reef, tmp_path,
                                                                      stats_pixels):
    manifest = run_ingest("--input", reef, "--out", tmp_path / "out", "--wb", "percentile",
                          "--stats-pixels", stats_pixels, "--workers", 1)
    # Every pixel sampled: exact. A subsample (bounded memory): within the 8-bit code step
    # (~1 % near white), which is what a subsample can resolve on JPEG input.
    tolerance = 1e-4 if stats_pixels >= 540 * 720 else 0.02
    outputs = np.stack([tifffile.imread(tmp_path / "out" / im["linear"])
                        for im in manifest["images"]]).reshape(-1, 3)
    np.testing.assert_allclose(np.percentile(outputs, 99.8, axis=0), 1.0, rtol=tolerance)
    inputs = np.stack([_srgb_decode_reference(cv2.cvtColor(
        cv2.imread(str(reef / im["source"])), cv2.COLOR_BGR2RGB)) for im in manifest["images"]])
    reference_gains = 1.0 / np.percentile(inputs.reshape(-1, 3), 99.8, axis=0)
    np.testing.assert_allclose(manifest["white_balance"]["gains"], reference_gains,
                               rtol=tolerance)
    assert reference_gains[0] > 1.2 * reference_gains[2]  # the water cast: red is weakest
    matching = cv2.imread(str(tmp_path / "out" / manifest["images"][0]["matching"]))
    assert matching.dtype == np.uint8 and 60 < np.median(matching) < 180  # mid-grey-ish


def _write_tiff16(path: Path, image: np.ndarray, exposure_time: float | None, iso: int = 100,
                  f_number: float = 4.0) -> None:
    tags = []
    if exposure_time is not None:
        tags = [(33434, 5, 1, (1, round(1 / exposure_time)), True),
                (33437, 5, 1, (round(f_number * 10), 10), True), (34855, 3, 1, iso, True)]
    tifffile.imwrite(path, image, photometric="rgb", extratags=tags)


def test_exposure_normalisation_equalises_the_same_scene(tmp_path):
    rng = np.random.default_rng(1)
    scene = rng.uniform(0.02, 0.3, size=(24, 32, 3))  # radiance at 1/100 s, ISO 100, f/4
    folder = tmp_path / "linear_in"
    folder.mkdir()
    shots = {"a": (1 / 100, 100, 4.0), "b": (1 / 50, 100, 4.0), "c": (1 / 100, 400, 8.0),
             "d": (1 / 200, 100, 2.0)}
    for name, (t, iso, n) in shots.items():
        relative = (t * iso / n ** 2) / (1 / 100 * 100 / 16)
        _write_tiff16(folder / f"{name}.tif", np.round(scene * relative * 65535).astype(np.uint16),
                      t, iso, n)
    manifest = run_ingest("--input", folder, "--out", tmp_path / "out", "--wb", "none",
                          "--workers", 1)
    assert manifest["input"]["kind"] == "linear"
    factors = {im["name"]: im["exposure_factor"] for im in manifest["images"]}
    # E = t * ISO / N^2 = (1, 2, 1, 2) x 1/1600; median 1.5/1600
    assert factors == pytest.approx({"a": 1.5, "b": 0.75, "c": 1.5, "d": 0.75})
    outputs = [tifffile.imread(tmp_path / "out" / im["linear"]) for im in manifest["images"]]
    for output in outputs:
        np.testing.assert_allclose(output, outputs[0], rtol=2e-3, atol=2e-5)
    np.testing.assert_allclose(outputs[0], scene * 1.5, rtol=2e-3, atol=2e-5)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(st.floats(1e-4, 2.0), st.floats(50, 12800), st.floats(1.0, 22.0)),
                min_size=1, max_size=12),
       st.floats(1e-3, 1.0))
def test_exposure_factors_undo_exposure(shots, radiance):
    times, isos, fnumbers = zip(*shots)
    observed = np.array([radiance * t * s / n ** 2 for t, s, n in shots])
    norm = linearise.exposure_normalisation(times, isos, fnumbers)
    normalised = observed * norm.factors
    reference = radiance * np.median([t * s / n ** 2 for t, s, n in shots])
    np.testing.assert_allclose(normalised, reference, rtol=1e-9)
    assert not norm.unknown.any() and norm.fields_used == linearise.EXPOSURE_FIELDS


def test_exposure_factors_with_missing_metadata():
    norm = linearise.exposure_normalisation([0.01, 0.02, None], [None] * 3, [2.0, 2.0, 2.0])
    assert norm.fields_used == ("exposure_time", "f_number")  # no ISO anywhere: left out
    # E = t / N^2 = (0.0025, 0.005); median 0.00375
    np.testing.assert_allclose(norm.factors, [1.5, 0.75, 1.0])
    assert norm.unknown.tolist() == [False, False, True]
    assert norm.warnings[2] and "exposure_time" in norm.warnings[2][0]
    nothing = linearise.exposure_normalisation([None, 0.0], [None, None], [None, None])
    assert nothing.fields_used == () and nothing.factors.tolist() == [1.0, 1.0]
    assert all(w for w in nothing.warnings)


def test_linear_png_subfolder_downscale_and_max_size(tmp_path):
    rng = np.random.default_rng(2)
    folder = tmp_path / "release" / "Images_wb"  # SeaThru-NeRF release spelling
    folder.mkdir(parents=True)
    images = {}
    for name in ("i1", "i2", "i3"):
        codes = rng.integers(1, 65535, size=(40, 60, 3), dtype=np.uint16)
        codes[5, 7, 1] = 65535  # saturated
        images[name] = codes
        cv2.imwrite(str(folder / f"{name}.png"), cv2.cvtColor(codes, cv2.COLOR_RGB2BGR))
    manifest = run_ingest("--input", tmp_path / "release", "--subdir", "images_wb", "--out",
                          tmp_path / "out", "--wb", "none", "--downscale", 2, "--workers", 1)
    assert manifest["input"]["kind"] == "linear"
    out = tmp_path / "out"
    for image in manifest["images"]:
        expected = images[image["name"]] / 65535.0
        linear = tifffile.imread(out / image["linear"])
        np.testing.assert_allclose(linear, expected, rtol=1e-6)
        np.testing.assert_allclose(tifffile.imread(out / image["downscaled"]["2"]["linear"]),
                                   downscale_local_mean(expected, (2, 2, 1)), rtol=1e-5)
        mask = cv2.imread(str(out / image["mask"]), cv2.IMREAD_UNCHANGED) > 0
        assert not mask[4:7, 6:9].any() and mask.sum() == mask.size - 9
        small_mask = cv2.imread(str(out / image["downscaled"]["2"]["mask"]),
                                cv2.IMREAD_UNCHANGED) > 0
        assert (~small_mask).sum() == 4  # every 2x2 block touching the 3x3 hole

    capped = run_ingest("--input", folder, "--out", tmp_path / "capped", "--wb", "none",
                        "--max-size", 30, "--matching-max-size", 15, "--workers", 1)
    image = capped["images"][0]
    assert (image["width"], image["height"]) == (30, 20)
    assert image["matching_size"] == [15, 10]
    np.testing.assert_allclose(tifffile.imread(tmp_path / "capped" / image["linear"]),
                               downscale_local_mean(images["i1"] / 65535.0, (2, 2, 1)), rtol=1e-5)


def test_large_photographs_are_downscaled_by_default_and_kept_whole_on_request(tmp_path):
    folder = tmp_path / "dive"
    folder.mkdir()
    rng = np.random.default_rng(5)
    for name in ("a", "b", "c"):
        cv2.imwrite(str(folder / f"{name}.jpg"), rng.integers(0, 255, (1000, 2000, 3), np.uint8))
    default = run_ingest("--input", folder, "--out", tmp_path / "default", "--workers", 1)
    assert {(i["width"], i["height"]) for i in default["images"]} == {(1600, 800)}
    assert default["settings"]["max_size"] == 1600
    whole = run_ingest("--input", folder, "--out", tmp_path / "whole", "--max-size", 0,
                       "--workers", 1)
    assert {(i["width"], i["height"]) for i in whole["images"]} == {(2000, 1000)}


def test_file_selection_kinds_duplicates_and_hints(tmp_path):
    folder = tmp_path / "mixed"
    folder.mkdir()
    for name in ("IMG_1.dng", "IMG_2.nef"):
        (folder / name).write_bytes(name.encode())  # selection looks at names only
    cv2.imwrite(str(folder / "IMG_1.jpg"), np.zeros((4, 4, 3), np.uint8))
    (folder / "IMG_1.xmp").write_text("sidecar")
    selected, rejected, detection = select_files(folder, "auto")
    assert [(p.name, n, k) for p, n, k in selected] == [("IMG_1.dng", "IMG_1", "raw"),
                                                        ("IMG_2.nef", "IMG_2", "raw")]
    assert [r["file"] for r in rejected] == ["IMG_1.jpg"] and detection["ignored"] == ["IMG_1.xmp"]

    selected, rejected, _ = select_files(folder, "srgb")
    assert [p.name for p, _, _ in selected] == ["IMG_1.jpg"] and len(rejected) == 2

    pngs = tmp_path / "pngs"
    pngs.mkdir()
    cv2.imwrite(str(pngs / "a.png"), np.zeros((4, 4, 3), np.uint16))
    tifffile.imwrite(pngs / "a.tif", np.zeros((4, 4, 3), np.uint16))
    selected, rejected, detection = select_files(pngs, "auto")
    assert detection["kind"] == "linear" and [p.name for p, _, _ in selected] == ["a.png"]
    assert "duplicate" in rejected[0]["reason"] and rejected[0]["file"] == "a.tif"

    with pytest.raises(PipelineError, match="subfolders with images: mixed \\(3\\), pngs \\(2\\)"):
        select_files(tmp_path, "auto")
    with pytest.raises(PipelineError, match="subfolders: mixed, pngs"):
        resolve_input(tmp_path, "images_wb")


def _textured_jpeg(progressive: bool = False, size=(96, 128), seed: int = 3) -> bytes:
    rng = np.random.default_rng(seed)
    image = cv2.resize(rng.integers(0, 256, (12, 16, 3), dtype=np.uint8), size[::-1],
                       interpolation=cv2.INTER_CUBIC)
    ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 95,
                                            cv2.IMWRITE_JPEG_PROGRESSIVE, int(progressive)])
    assert ok
    return data.tobytes()


def _with_thumbnail(jpeg: bytes) -> bytes:
    """The JPEG with an EXIF-like APP1 segment holding a whole small JPEG (its own end marker)
    right after the start marker, as camera files carry their thumbnail."""
    payload = b"Exif\x00\x00" + _textured_jpeg(size=(16, 16))
    return jpeg[:2] + b"\xff\xe1" + (len(payload) + 2).to_bytes(2, "big") + payload + jpeg[2:]


@pytest.mark.parametrize("progressive", [False, True])
def test_a_jpeg_cut_short_is_refused_and_a_whole_one_decodes(tmp_path, progressive):
    whole = _with_thumbnail(_textured_jpeg(progressive))
    assert b"\xff\xd9" in whole[:len(whole) // 4]  # the thumbnail's end marker, early on
    path = tmp_path / "frame.jpg"
    for data in (whole, whole + b"\x00" * 64 + b"maker trailer"):
        path.write_bytes(data)
        assert rawio.read_encoded(path, "srgb").image.shape == (96, 128, 3)
    for cut in (len(whole) // 2, len(whole) - 200, len(whole) - 2, 40):
        path.write_bytes(whole[:cut])
        assert rawio.jpeg_cut_short(whole[:cut])
        with pytest.raises(rawio.DecodeError, match="stops before its end-of-image marker"):
            rawio.read_encoded(path, "srgb")
    (tmp_path / "folder.jpg").mkdir()
    with pytest.raises(rawio.DecodeError, match="cannot be read"):
        rawio.read_encoded(tmp_path / "folder.jpg", "srgb")


@pytest.mark.parametrize("factor, chroma", [
    (cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444, "4:4:4"),
    (cv2.IMWRITE_JPEG_SAMPLING_FACTOR_422, "4:2:2"),
    (cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420, "4:2:0")])
def test_a_jpegs_chroma_sampling_is_recorded(tmp_path, factor, chroma):
    """How the camera stored the colour goes into the manifest's decoder facts (4:2:0 with
    a camera's white balance took green and blue attenuation lower: docs/water.md); grey
    JPEGs and other files have none."""
    colour = np.random.default_rng(4).integers(0, 255, (32, 48, 3), dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "frame.jpg"), colour,
                [cv2.IMWRITE_JPEG_SAMPLING_FACTOR, factor])
    assert rawio.read_encoded(tmp_path / "frame.jpg", "srgb").metadata["chroma"] == chroma
    cv2.imwrite(str(tmp_path / "grey.jpg"), colour[..., 0])
    cv2.imwrite(str(tmp_path / "frame.png"), colour)
    assert "chroma" not in rawio.read_encoded(tmp_path / "grey.jpg", "srgb").metadata
    assert "chroma" not in rawio.read_encoded(tmp_path / "frame.png", "srgb").metadata
    assert rawio.jpeg_chroma(tmp_path / "frame.png") is None
    from seathru.io.manifest import transfer_summary

    images = [{"kind": "srgb", "decoder": {"transfer": "srgb", "chroma": chroma}}] * 2 + [
        {"kind": "srgb", "decoder": {"transfer": "srgb"}}]
    assert transfer_summary({"images": images}) == \
        f"srgb (by kind), colour {chroma}: 2 images; srgb (by kind): 1 image"


def test_a_cut_jpeg_among_whole_ones_is_rejected_by_name(tmp_path):
    folder = tmp_path / "DCIM"
    folder.mkdir()
    for index in range(3):
        (folder / f"GOPR000{index}.JPG").write_bytes(_textured_jpeg(seed=index))
    whole = _textured_jpeg(seed=9)
    (folder / "GOPR0009.JPG").write_bytes(whole[:len(whole) // 3])
    manifest = run_ingest("--input", folder, "--out", tmp_path / "out", "--min-images", 3,
                          "--workers", 1)
    assert [image["name"] for image in manifest["images"]] == ["GOPR0000", "GOPR0001",
                                                               "GOPR0002"]
    assert [r["file"] for r in manifest["rejected"]] == ["GOPR0009.JPG"]
    assert "end-of-image marker" in manifest["rejected"][0]["reason"]


def test_a_camera_card_with_one_image_folder_is_read_from_it(tmp_path):
    card = tmp_path / "card"
    folder = card / "DCIM" / "100GOPRO"
    folder.mkdir(parents=True)
    for index in range(3):
        (folder / f"GOPR000{index}.JPG").write_bytes(_textured_jpeg(seed=index))
    (folder / "GOPR0000.THM").write_bytes(b"thumbnail")
    (card / "MISC").mkdir()
    (card / "MISC" / "version.txt").write_text("camera firmware")
    found = find_inputs(card, None, None, "auto", "auto")
    assert found.folder == folder and found.subdir == "DCIM/100GOPRO"
    assert [name for _, name, _ in found.selected] == ["GOPR0000", "GOPR0001", "GOPR0002"]
    assert "DCIM/100GOPRO, the only subfolder with images" in found.reason
    manifest = run_ingest("--input", card, "--out", tmp_path / "out", "--workers", 1)
    assert manifest["input"]["subdir"] == "DCIM/100GOPRO" and len(manifest["images"]) == 3

    (card / "DCIM" / "101GOPRO").mkdir()
    (card / "DCIM" / "101GOPRO" / "GOPR0100.JPG").write_bytes(_textured_jpeg(seed=7))
    with pytest.raises(PipelineError, match="DCIM/100GOPRO \\(3\\), DCIM/101GOPRO \\(1\\)"):
        find_inputs(card, None, None, "auto", "auto")
    assert len(find_inputs(card, None, None, "all", "auto").selected) == 4


# --- pure helpers ---------------------------------------------------------------------------

def test_exif_orientation_codes():
    image = np.arange(12).reshape(3, 4)
    for orientation, expected in [(1, image), (3, np.rot90(image, 2)), (6, np.rot90(image, -1)),
                                  (8, np.rot90(image, 1)), (2, image[:, ::-1]),
                                  (4, image[::-1]), (5, image.T), (7, np.rot90(image, 2).T)]:
        flip = linearise.exif_orientation_to_flip(orientation)
        np.testing.assert_array_equal(linearise.orient(image, flip), expected)


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 9), st.integers(1, 9), st.integers(0, 2**31 - 1))
def test_block_any_and_dilation_against_reference(height, width, seed):
    mask = np.random.default_rng(seed).random((height, width)) < 0.1
    shape = ((height + 1) // 2, (width + 1) // 2)
    reference = np.zeros(shape, dtype=bool)
    for r in range(height):
        for c in range(width):
            reference[r // 2, c // 2] |= mask[r, c]
    np.testing.assert_array_equal(linearise.block_any(mask, shape), reference)
    np.testing.assert_array_equal(linearise.dilate_invalid(mask, 1),
                                  ndimage.binary_dilation(mask, np.ones((3, 3), bool)))


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(90.0, 100.0))
def test_percentile_gains_against_float64_reference(seed, percentile):
    samples = np.random.default_rng(seed).gamma(2.0, [0.05, 0.1, 0.2], size=(500, 3))
    gains, levels = linearise.percentile_gains(samples.astype(np.float32), percentile)
    reference = np.percentile(samples, percentile, axis=0)
    np.testing.assert_allclose(levels, reference, rtol=1e-5)
    np.testing.assert_allclose(gains * reference, 1.0, rtol=1e-5)


def test_camera_gains_and_stat_sampling():
    np.testing.assert_allclose(linearise.camera_wb_gains([1.0, 0.4, 0.68, 0.0]), [2.5, 1, 1.7])
    assert linearise.camera_wb_gains([0.0, 0.0, 0.0, 0.0]) is None
    gains = linearise.dataset_camera_gains([np.array([2.0, 1, 1.5]), None,
                                            np.array([2.4, 1, 1.7]), np.array([2.2, 1, 1.6])])
    np.testing.assert_allclose(gains, [2.2, 1, 1.6])
    image = np.random.default_rng(3).random((301, 402, 3)).astype(np.float32)
    samples = linearise.sample_pixels(image, 10_000)
    assert 5_000 < len(samples) <= 10_000
    np.testing.assert_array_equal(samples[0], image[0, 0])


@settings(max_examples=30, deadline=None)
@given(st.integers(1, 5000), st.integers(1, 5000), st.integers(1, 16))
def test_llff_downscaled_size_rounds_each_side(width, height, factor):
    w, h = linearise.llff_downscaled_size(width, height, factor)
    for size, full in ((w, width), (h, height)):
        assert size >= 1 and abs(size - full / factor) <= 0.5 + 1e-9 or (size == 1 and
                                                                         full < factor)


def test_matching_grey_converts_any_depth_and_equalises():
    rng = np.random.default_rng(4)
    bgr = rng.integers(0, 256, size=(64, 80, 3), dtype=np.uint8)
    # OpenCV's BT.601 weights on BGR input, float64 reference
    reference = np.round(bgr[..., 0] * 0.114 + bgr[..., 1] * 0.587 + bgr[..., 2] * 0.299)
    for image in (bgr, bgr.astype(np.uint16) * 257, bgr / 255.0):
        grey = linearise.matching_grey(image)
        assert grey.dtype == np.uint8 and grey.shape == (64, 80)
        assert np.abs(grey.astype(float) - reference).max() <= 1
    dull = (100 + bgr[..., 0] // 16).astype(np.uint8)  # values 100-115: low contrast
    equalised = linearise.matching_grey(dull, clahe_clip=2.0, clahe_tiles=4)
    assert int(np.ptp(equalised)) > 2 * int(np.ptp(dull))
    np.testing.assert_array_equal(linearise.matching_grey(dull), dull)


# --- round trip through the simulator -------------------------------------------------------

def test_simulated_dngs_round_trip_to_the_water_images(tmp_path):
    simulate = pytest.importorskip("seathru.steps.simulate",
                                   reason="seathru simulate is not built yet")
    parser = argparse.ArgumentParser()
    simulate.add_arguments(parser)
    sim = tmp_path / "sim"
    simulate.run(parser.parse_args(["--out", str(sim), "--views", "4", "--width", "96",
                                    "--height", "72", "--seed", "3"]))
    truth_dir = sim / "truth" / "water"
    if not truth_dir.is_dir() or not (sim / "raw").is_dir():
        pytest.skip("the simulator does not write raw/ and truth/water/ (layout changed?)")

    def ratios(manifest: dict, out: Path) -> np.ndarray:
        """Per image and channel, median of linear output / true water image (valid pixels)."""
        result = []
        for image in manifest["images"]:
            linear = tifffile.imread(out / image["linear"]).astype(np.float64)
            truth = tifffile.imread(truth_dir / f"{image['name']}.tiff").astype(np.float64)
            valid = cv2.imread(str(out / image["mask"]), cv2.IMREAD_UNCHANGED) > 0
            valid &= (truth > 0.02).all(axis=-1)
            result.append(np.median(linear[valid] / truth[valid], axis=0))
        return np.array(result)

    manifest = run_ingest("--input", sim, "--subdir", "raw", "--out", tmp_path / "out",
                          "--wb", "none", "--workers", 1)
    assert len(manifest["images"]) == 4 and not manifest["rejected"]
    times = [im["exposure_time"] for im in manifest["images"]]
    assert max(times) / min(times) > 1.2  # the views really differ in exposure
    normalised = ratios(manifest, tmp_path / "out")
    scale = np.median(normalised)
    # One global scale for every image and channel: same surface, same value.
    np.testing.assert_allclose(normalised, scale, rtol=0.02)

    # Pixel level: linear = scale * truth within noise and demosaic error.
    image = manifest["images"][0]
    linear = tifffile.imread(tmp_path / "out" / image["linear"])
    truth = tifffile.imread(truth_dir / f"{image['name']}.tiff")
    valid = (cv2.imread(str(tmp_path / "out" / image["mask"]), cv2.IMREAD_UNCHANGED) > 0) & (
        truth > 0.02).all(axis=-1)
    relative = np.abs(linear[valid] - scale * truth[valid]) / (scale * truth[valid])
    assert np.median(relative) < 0.05

    # Without normalisation the ratios follow the exposure times instead.
    raw = run_ingest("--input", sim / "raw", "--out", tmp_path / "raw_out", "--wb", "none",
                     "--no-exposure-normalise", "--workers", 1)
    unnormalised = ratios(raw, tmp_path / "raw_out").mean(axis=1)
    np.testing.assert_allclose(unnormalised / unnormalised[0], np.array(times) / times[0],
                               rtol=0.02)


# --- posed datasets in their own layout (--layout) ------------------------------------------

def _ramp(size=(12, 8), value=100) -> np.ndarray:
    """An 8-bit RGB image: ``value`` plus a ramp (a constant image is rejected as empty)."""
    ramp = value + np.arange(size[0] * size[1]).reshape(size[1], size[0]) % 50
    return np.repeat(ramp[..., None], 3, axis=2).astype(np.uint8)


_WRITTEN = itertools.count()


def _pngs(folder: Path, names, size=(12, 8), value=100) -> None:
    """:func:`_ramp` images, each file distinct in its last pixel (ingest rejects copies)."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        image = _ramp(size, value)
        image[-1, -1] = next(_WRITTEN) % 256
        cv2.imwrite(str(folder / name), image)


def _poses_bounds(folder: Path, rows: int) -> None:
    np.save(folder / "poses_bounds.npy", np.zeros((rows, 17)))


def test_llff_layout_prefers_images_wb_then_the_folder_with_one_image_per_row(tmp_path):
    root = tmp_path / "llff"
    _pngs(root / "images_wb", ["a.png", "b.png", "c.png"])
    _pngs(root / "images", ["IMG_1.JPG.png", "IMG_2.png", "IMG_3.png"], size=(24, 16))
    _pngs(root / "images_4", ["a.png", "b.png", "c.png"], size=(6, 4))
    _poses_bounds(root, 3)
    found = layout_images("llff", root)
    assert found.folder == "images_wb" and found.kind == "linear"
    assert "SeaThru-NeRF" in found.reason and [n for _, n in found.files] == ["a", "b", "c"]
    chosen = layout_images("llff", root, "Images_4")   # a name, matched case-insensitively
    assert chosen.folder == "images_4" and chosen.kind is None
    assert chosen.reason == "ingest.images=Images_4"
    with pytest.raises(PipelineError, match="no image folder 'images_2'.*images, images_4"):
        layout_images("llff", root, "images_2")
    # images_wb with a wrong count is passed over for the next folder that matches the rows
    (root / "images_wb" / "c.png").unlink()
    assert layout_images("llff", root).folder == "images"
    _poses_bounds(root, 5)
    with pytest.raises(PipelineError, match=r"5 rows; folders: images_wb \(2\), images \(3\)"):
        layout_images("llff", root)
    with pytest.raises(PipelineError, match="poses_bounds.npy: not found"):
        layout_images("llff", tmp_path / "llff" / "images")


def test_nerfstudio_layout_follows_file_paths_and_lists_missing_frames(tmp_path):
    root = tmp_path / "ns"
    _pngs(root / "images", ["f1.png", "f2.png"])
    _pngs(root / "images" / "cam1", ["f3.png"])
    _pngs(root / "images_2", ["f1.png", "f2.png"], size=(6, 4))
    frames = [{"file_path": p, "transform_matrix": np.eye(4).tolist()}
              for p in ("images/f1.png", "./images/f2.png", "images/cam1/f3.png", "images/f4.png",
                        "images/f5")]
    (root / "transforms.json").write_text(json.dumps({"frames": frames}))
    found = layout_images("nerfstudio", root)
    assert [(p.relative_to(root).as_posix(), n) for p, n in found.files] == [
        ("images/f1.png", "f1"), ("images/f2.png", "f2"), ("images/cam1/f3.png", "f3")]
    assert [m["name"] for m in found.missing] == ["f4", "f5"]
    half = layout_images("nerfstudio", root, "images_2")   # nerfstudio's downscale folders
    assert [p.parent.name for p, _ in half.files] == ["images_2", "images_2"]
    assert [m["name"] for m in half.missing] == ["f3", "f4", "f5"]
    (root / "transforms.json").write_text(json.dumps({"frames": [{"transform_matrix": []}]}))
    with pytest.raises(PipelineError, match="frame 0: field 'file_path' missing"):
        layout_images("nerfstudio", root)


def _ns_mask(path: Path, size=(12, 8), ignore=(slice(0, 0), slice(0, 0)), value=255) -> None:
    """A nerfstudio mask: ``value`` (kept) everywhere but 0 (ignored) in the ``ignore`` block."""
    mask = np.full((size[1], size[0]), value, np.uint8)
    mask[ignore] = 0
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), mask)


def test_nerfstudio_layout_keeps_each_frames_mask_path(tmp_path):
    root = tmp_path / "ns"
    _pngs(root / "images", ["f1.png", "f2.png", "f3.png"])
    _pngs(root / "images_2", ["f1.png", "f2.png", "f3.png"], size=(6, 4))
    _ns_mask(root / "masks" / "f1.png")
    _ns_mask(root / "masks_2" / "f1.png", size=(6, 4))
    frames = [{"file_path": "images/f1.png", "mask_path": "masks/f1.png"},
              {"file_path": "images/f2.png", "mask_path": "masks/f2.png"},   # mask not there
              {"file_path": "images/f3.png"},
              {"file_path": "images/f4.png", "mask_path": "masks/f4.png"}]   # frame not there
    (root / "transforms.json").write_text(json.dumps({"frames": frames}))
    found = layout_images("nerfstudio", root)
    assert {n: p.relative_to(root).as_posix() for n, p in found.masks.items()} == {
        "f1": "masks/f1.png", "f2": "masks/f2.png"}
    assert [m["name"] for m in found.missing] == ["f4"] and found.record()["masks"] == 2
    half = layout_images("nerfstudio", root, "images_2")   # nerfstudio's masks_<N>, else full
    assert {n: p.relative_to(root).as_posix() for n, p in half.masks.items()} == {
        "f1": "masks_2/f1.png", "f2": "masks/f2.png"}


def test_source_masks_keep_nonzero_pixels_and_follow_the_image_size(tmp_path):
    _ns_mask(tmp_path / "m.png", size=(12, 8), ignore=(slice(0, 4), slice(0, 6)), value=1)
    mask = read_source_mask(tmp_path / "m.png", 12, 8)
    assert mask.dtype == bool and mask.sum() == 96 - 24 and not mask[:4, :6].any()
    doubled = read_source_mask(tmp_path / "m.png", 24, 16)   # nearest, like nerfstudio
    assert doubled.shape == (16, 24) and not doubled[:8, :12].any() and doubled[8:, :].all()
    rgb = np.zeros((8, 12, 3), np.uint8)
    rgb[2, 3, 2] = 9                                          # one channel is enough
    cv2.imwrite(str(tmp_path / "rgb.png"), rgb)
    assert np.argwhere(read_source_mask(tmp_path / "rgb.png", 12, 8)).tolist() == [[2, 3]]
    with pytest.raises(PipelineError, match=r"m.png: mask of 12x8 pixels does not fit its "
                                            r"image of 8x12"):
        read_source_mask(tmp_path / "m.png", 8, 12)
    with pytest.raises(PipelineError, match="gone.png: the frame's mask_path file is not there"):
        read_source_mask(tmp_path / "gone.png", 12, 8)


def test_ingest_ands_nerfstudio_masks_into_the_clipping_masks(tmp_path):
    root = tmp_path / "ns"
    _pngs(root / "images", ["f1.png", "f2.png", "f3.png", "f4.png"])
    clipped = _ramp()
    clipped[6:, 9:] = 255                     # clipped in every channel, bottom right
    cv2.imwrite(str(root / "images" / "f1.png"), clipped)
    _ns_mask(root / "masks" / "f1.png", ignore=(slice(0, 3), slice(0, 4)))
    _ns_mask(root / "masks" / "f2.png", size=(6, 4), ignore=(slice(0, 2), slice(4, 6)))
    _ns_mask(root / "masks" / "f3.png", size=(8, 12))          # transposed: does not fit
    frames = [{"file_path": "images/f1.png", "mask_path": "masks/f1.png"},
              {"file_path": "images/f2.png", "mask_path": "masks/f2.png"},
              {"file_path": "images/f3.png", "mask_path": "masks/f3.png"},
              {"file_path": "images/f4.png"},
              {"file_path": "images/f5.png", "mask_path": "masks/f5.png"}]
    (root / "transforms.json").write_text(json.dumps({"frames": frames}))
    out = tmp_path / "out"
    manifest = run_ingest("--input", root, "--layout", "nerfstudio", "--out", out,
                          "--workers", 1, "--wb", "none", "--mask-dilation", 0,
                          "--min-images", 2, "--downscale", 2)
    assert [image["name"] for image in manifest["images"]] == ["f1", "f2", "f4"]
    assert [r["file"] for r in manifest["rejected"]] == ["f3.png"]
    assert "does not fit its image of 12x8" in manifest["rejected"][0]["reason"]
    assert [m["name"] for m in manifest["input"]["layout"]["missing"]] == ["f5"]
    assert manifest["input"]["layout"]["masks"] == 3
    expected = np.ones((8, 12), bool)
    expected[6:, 9:] = False                  # clipped
    expected[:3, :4] = False                  # the dataset's mask
    assert np.array_equal(read_mask(out / "masks" / "f1.png"), expected)
    half = np.ones((8, 12), bool)
    half[:4, 8:] = False                      # the half-size mask, scaled up
    assert np.array_equal(read_mask(out / "masks" / "f2.png"), half)
    assert read_mask(out / "masks" / "f4.png").all()
    assert np.array_equal(read_mask(out / "masks_2" / "f1.png"),
                          linearise.resize_mask(expected, (6, 4)))
    clipped_share = {image["name"]: image["clipped_fraction"] for image in manifest["images"]}
    assert clipped_share == {"f1": pytest.approx(6 / 96), "f2": 0.0, "f4": 0.0}  # clipping only
    warnings = json.loads((out / "warnings.json").read_text())["warnings"]
    assert {w["code"] for w in warnings} >= {"rejected_images", "missing_frames"}


def test_frame_names_stay_unique_across_subfolders():
    assert frame_names(["images/a.jpg", "images/b.JPG"]) == ["a", "b"]
    assert frame_names(["cam0/0001.jpg", "cam1/0001.jpg", "./x.png"]) == [
        "cam0__0001", "cam1__0001", "x"]


def test_select_paths_names_and_duplicates(tmp_path):
    _pngs(tmp_path / "a", ["1.png"])
    _pngs(tmp_path / "b", ["1.png"])
    (tmp_path / "notes.txt").write_text("x")
    selected, rejected, detection = select_paths(
        [(tmp_path / "a" / "1.png", "a__1"), (tmp_path / "b" / "1.png", "a__1"),
         (tmp_path / "notes.txt", "notes")], "auto")
    assert [(n, k) for _, n, k in selected] == [("a__1", "srgb")]
    assert "duplicate image name 'a__1'" in rejected[0]["reason"]
    assert detection["ignored"] == ["notes.txt"]
    with pytest.raises(PipelineError, match="no image files"):
        select_paths([(tmp_path / "notes.txt", "notes")], "auto")


def test_ingest_of_a_colmap_layout_decodes_the_model_images(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    root = tmp_path / "colmap"
    _pngs(root / "images" / "sub", ["a.png", "b.png", "c.png"], value=200)
    model = root / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text("1 PINHOLE 12 8 10 10 6 4\n")
    (model / "images.txt").write_text("".join(
        f"{i} 1 0 0 0 {i} 0 0 1 {name}\n\n" for i, name in
        enumerate(["sub/a.png", "sub/b.png", "sub/c.png", "sub/gone.png"], start=1)))
    (model / "points3D.txt").write_text("")
    assert pycolmap.Reconstruction(model).num_images() == 4
    manifest = run_ingest("--input", root, "--layout", "colmap", "--out", tmp_path / "out",
                          "--workers", 1, "--wb", "none")
    assert [image["name"] for image in manifest["images"]] == ["a", "b", "c"]
    layout = manifest["input"]["layout"]
    assert layout["layout"] == "colmap" and layout["images"] == "images"
    assert [m["name"] for m in layout["missing"]] == ["gone"]
    warnings = json.loads((tmp_path / "out" / "warnings.json").read_text())["warnings"]
    # (the test's ramps are grey and record no exposure)
    assert [w["code"] for w in warnings if w["code"] not in (
        "grey_images", "no_exposure_metadata")] == ["missing_frames"]
    with pytest.raises(PipelineError, match="no COLMAP model found"):
        run_ingest("--input", root / "images", "--layout", "colmap", "--out", tmp_path / "o2")


def test_colmap_layout_of_the_release_finds_images_wb_under_other_extensions(tmp_path):
    """The SeaThru-NeRF release as a colmap source: sparse/0 beside images_wb/ (no images/),
    the model naming the camera's JPEGs, the folder holding PNGs."""
    root = tmp_path / "release"
    _pngs(root / "images_wb", ["IMG_1.png", "IMG_2.png"])
    model = root / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text("1 PINHOLE 12 8 10 10 6 4\n")
    (model / "images.txt").write_text("1 1 0 0 0 0 0 0 1 IMG_1.JPG\n\n"
                                      "2 1 0 0 0 1 0 0 1 IMG_2.JPG\n\n")
    (model / "points3D.txt").write_text("")
    found = layout_images("colmap", root)
    assert found.folder == "images_wb" and found.kind == "linear" and found.missing == []
    assert [(p.name, n) for p, n in found.files] == [("IMG_1.png", "IMG_1"),
                                                     ("IMG_2.png", "IMG_2")]


def test_a_byte_for_byte_copy_of_a_photograph_is_rejected_naming_the_one_kept(tmp_path):
    """The same photograph under a second name (copied twice off the card) is left out with a
    reason; identical pixels in another file format are not a copy of the file."""
    import shutil

    folder = tmp_path / "dive"
    _pngs(folder, ["IMG_1.png", "IMG_2.png", "IMG_3.png"])
    shutil.copy(folder / "IMG_2.png", folder / "IMG_2 (1).png")
    shutil.copy(folder / "IMG_3.png", folder / "zz_copy.png")
    manifest = run_ingest("--input", folder, "--out", tmp_path / "out", "--workers", 1)
    assert [image["name"] for image in manifest["images"]] == ["IMG_1", "IMG_2", "IMG_3"]
    rejected = {r["file"]: r["reason"] for r in manifest["rejected"]}
    assert set(rejected) == {"IMG_2 (1).png", "zz_copy.png"}
    assert "byte-for-byte copy of IMG_2.png" in rejected["IMG_2 (1).png"]
    assert "byte-for-byte copy of IMG_3.png" in rejected["zz_copy.png"]
    warnings = json.loads((tmp_path / "out" / "warnings.json").read_text())["warnings"]
    assert any("zz_copy.png" in w["message"] for w in warnings)
    cv2.imwrite(str(folder / "IMG_1.tif"), cv2.imread(str(folder / "IMG_1.png")))
    selected, rejected, _ = select_paths([(folder / "IMG_1.png", "a"),
                                          (folder / "IMG_1.tif", "b")], "auto")
    assert len(selected) == 2 and not rejected


def test_ingest_of_the_release_layout_reads_images_wb_as_linear(tmp_path):
    root = tmp_path / "release"
    _pngs(root / "images_wb", ["a.png", "b.png", "c.png"], value=128)
    _poses_bounds(root, 3)
    manifest = run_ingest("--input", root, "--layout", "llff", "--out", tmp_path / "out",
                          "--workers", 1, "--wb", "none", "--no-exposure-normalise")
    assert manifest["input"]["kind"] == "linear" and manifest["settings"]["kind"] == "auto"
    assert manifest["input"]["layout"]["images"] == "images_wb"
    linear = tifffile.imread(tmp_path / "out" / manifest["images"][0]["linear"])
    np.testing.assert_allclose(linear[:-1], _ramp(value=128)[:-1] / 255, rtol=1e-6)  # no sRGB
    srgb = run_ingest("--input", root, "--layout", "llff", "--out", tmp_path / "srgb",
                      "--workers", 1, "--wb", "none", "--no-exposure-normalise", "--kind", "srgb")
    assert srgb["input"]["kind"] == "srgb"   # an explicit kind wins


def test_images_setting_names_the_subfolder_of_a_plain_source(tmp_path):
    _pngs(tmp_path / "dive" / "images", ["a.png", "b.png", "c.png"])
    assert find_inputs(tmp_path / "dive", None, None, "auto", "auto").subdir == "images"
    (tmp_path / "dive" / "sparse" / "0").mkdir(parents=True)  # a COLMAP layout: ask
    with pytest.raises(PipelineError, match="subfolders with images: images.*source llff, "
                                            "colmap or nerfstudio"):
        run_ingest("--input", tmp_path / "dive", "--out", tmp_path / "out")
    manifest = run_ingest("--input", tmp_path / "dive", "--images", "images", "--out",
                          tmp_path / "out", "--workers", 1)
    assert len(manifest["images"]) == 3 and manifest["input"]["subdir"] == "images"
    assert manifest["input"]["layout"] is None


def test_a_camera_cards_folders_are_named_and_read_with_images_all(tmp_path):
    """A card dump (DCIM/100GOPRO, DCIM/101GOPRO, sidecar files, hidden files): without a
    choice ingest names the folders that hold images; ``images=all`` reads them all in path
    order, and names repeated across folders are made unique by their path."""
    card = tmp_path / "card"
    _pngs(card / "DCIM" / "100GOPRO", ["G0001.png", "G0002.png"])
    _pngs(card / "DCIM" / "101GOPRO", ["G0003.png", "G0004.png"])
    _pngs(card / "DCIM" / ".thumbnails", ["G0001.png"])
    (card / "DCIM" / "100GOPRO" / "G0001.THM").write_bytes(b"thumb")
    (card / "DCIM" / "100GOPRO" / "._G0002.png").write_bytes(b"apple double")
    with pytest.raises(PipelineError, match=r"subfolders with images: DCIM/100GOPRO \(2\), "
                                            r"DCIM/101GOPRO \(2\).*ingest.images=all"):
        run_ingest("--input", card, "--out", tmp_path / "out")
    manifest = run_ingest("--input", card, "--images", "all", "--out", tmp_path / "out",
                          "--workers", 1)
    assert [image["name"] for image in manifest["images"]] == ["G0001", "G0002", "G0003",
                                                               "G0004"]
    one = run_ingest("--input", card, "--images", "DCIM/101GOPRO", "--out", tmp_path / "one",
                     "--workers", 1, "--min-images", 2)
    assert [image["name"] for image in one["images"]] == ["G0003", "G0004"]
    # a camera that restarts its numbering in the next folder
    _pngs(card / "DCIM" / "101GOPRO", ["G0001.png"])
    files = every_image_file(card)
    assert [name for path, name in files if path.suffix == ".png"] == [
        "DCIM__100GOPRO__G0001", "DCIM__100GOPRO__G0002", "DCIM__101GOPRO__G0001",
        "DCIM__101GOPRO__G0003", "DCIM__101GOPRO__G0004"]
    assert image_subfolders(card) == [("DCIM/100GOPRO", 2), ("DCIM/101GOPRO", 3)]
    assert image_subfolders(card, depth=1) == []


@pytest.mark.parametrize(("name", "expected"), [
    ("dive.zip", "an archive, not a folder: unpack it"),
    ("notes.txt", "a file, not a folder"),
    ("absent", "folder not found"),
])
def test_an_input_that_is_no_folder_says_what_it_is(tmp_path, name, expected):
    given = tmp_path / name
    if name != "absent":
        given.write_bytes(b"PK\x03\x04" if name.endswith(".zip") else b"x")
    for layout in (None, "llff"):
        argv = ["--input", given, "--out", tmp_path / "out"]
        with pytest.raises(PipelineError, match=expected):
            run_ingest(*argv, *(["--layout", layout] if layout else []))


# ------------------------------------------------------------------- HEIC, WebP, what is not read

HEIF_FIXTURES = Path(__file__).parent / "fixtures" / "heif"


def _srgb_reference(values: np.ndarray) -> np.ndarray:
    """:func:`_srgb_decode_reference` of values in [0, 1]."""
    return _srgb_decode_reference(np.asarray(values, np.float64) * 255.0)


def _fixture_pattern(width: int, height: int, top: int) -> np.ndarray:
    """tests/fixtures/heif/make_fixtures.py's pattern: a grey ramp, a red block top-left."""
    image = np.round(np.linspace(0.2, 0.8, width)[None, :, None] * np.ones((height, 1, 3)) * top)
    image[:8, :8] = (0.9 * top, 0.1 * top, 0.1 * top)
    return image


def test_a_heic_photograph_decodes_turned_by_its_container_with_its_exposure():
    decoded = rawio.read_encoded(HEIF_FIXTURES / "rotated.heic", "srgb")
    # stored 48 wide, 32 high with EXIF orientation 6: libheif turns it 90 degrees clockwise,
    # once (the EXIF orientation is not applied on top)
    assert decoded.image.shape == (48, 32, 3) and decoded.metadata["flip"] == 0
    turned = np.rot90(_fixture_pattern(48, 32, 255), k=-1) / 255
    np.testing.assert_allclose(decoded.image, _srgb_reference(turned), atol=0.012)
    assert decoded.image[2, -2, 0] > 5 * decoded.image[2, -2, 1]     # the red block, top-right
    assert decoded.exposure.orientation == 6
    assert (decoded.exposure.exposure_time, decoded.exposure.iso,
            decoded.exposure.f_number) == pytest.approx((1 / 125, 400, 5.6))
    assert decoded.metadata["transfer"] == "srgb"


def test_a_ten_bit_heic_keeps_its_depth():
    decoded = rawio.read_encoded(HEIF_FIXTURES / "ten_bit.heic", "srgb")
    assert decoded.metadata["bit_depth"] == 16 and decoded.image.shape == (24, 32, 3)
    expected = _srgb_reference(_fixture_pattern(32, 24, 1023) / 1023)
    np.testing.assert_allclose(decoded.image, expected, atol=2e-3)
    stored = stored_encoding.encode(decoded.image.astype(np.float64), "srgb")
    assert np.abs(stored * 1023 - np.round(stored * 1023)).max() < 0.02   # on the 10-bit grid
    assert np.abs(stored * 255 - np.round(stored * 255)).max() > 0.25      # not on an 8-bit one


def test_a_folder_of_heic_and_webp_photographs_is_ingested(tmp_path):
    folder = tmp_path / "phone"
    folder.mkdir()
    for index in range(3):
        (folder / f"IMG_{index:04d}.HEIC").write_bytes(
            (HEIF_FIXTURES / ("rotated.heic" if index else "ten_bit.heic")).read_bytes()
            + bytes(index))   # distinct files: a byte-for-byte copy is left out
        cv2.imwrite(str(folder / f"IMG_{index:04d}_edit.webp"), _ramp(value=40 + index),
                    [cv2.IMWRITE_WEBP_QUALITY, 101])
    manifest = run_ingest("--input", folder, "--out", tmp_path / "out", "--workers", 1,
                          "--wb", "none")
    by_name = {image["name"]: image for image in manifest["images"]}
    assert len(by_name) == 6 and manifest["input"]["kind"] == "srgb"
    assert by_name["IMG_0001"]["exposure_time"] == pytest.approx(1 / 125)
    assert (by_name["IMG_0001"]["width"], by_name["IMG_0001"]["height"]) == (32, 48)
    # the evaluation reads the stored photographs as ingest did: turned, at full depth
    views = read_stored_views(tmp_path / "out")
    assert read_stored_codes(views["IMG_0001"]).shape == (48, 32, 3)
    assert read_stored_codes(views["IMG_0000"]).dtype == np.uint16
    webp = tifffile.imread(tmp_path / "out" / by_name["IMG_0002_edit"]["linear"])
    np.testing.assert_allclose(webp, _srgb_reference(_ramp(value=42) / 255.0)
                               * by_name["IMG_0002_edit"]["exposure_factor"], rtol=1e-5)


def test_a_damaged_heic_is_refused_with_a_reason(tmp_path):
    path = tmp_path / "IMG_0001.HEIC"
    path.write_bytes(_textured_jpeg())           # a JPEG under a HEIC name
    with pytest.raises(rawio.DecodeError, match="cannot be read as a HEIF image"):
        rawio.read_encoded(path, "srgb")
    data = (HEIF_FIXTURES / "rotated.heic").read_bytes()
    path.write_bytes(data[:len(data) * 2 // 3])  # cut short
    with pytest.raises(rawio.DecodeError, match="HEIF"):
        rawio.read_encoded(path, "srgb")


def test_a_folder_of_formats_ingest_does_not_read_says_what_to_do(tmp_path):
    folder = tmp_path / "export"
    folder.mkdir()
    for name in ("a.avif", "b.AVIF", "c.jxl", "notes.txt"):
        (folder / name).write_bytes(b"\x00" * 16)
    with pytest.raises(PipelineError, match=r"2 AVIF \(\.avif\), 1 JPEG XL \(\.jxl\) files, a "
                       r"format ingest does not read: convert them to JPEG"):
        select_files(folder, "auto")
