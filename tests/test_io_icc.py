"""ICC profiles' tone curves (seathru.io.icc), the encodings they are named as
(seathru.radiometry.stored_encoding), and ingest decoding an exported file by its own curve."""

from __future__ import annotations

import argparse
import json
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile
from PIL import Image, ImageCms

from seathru.io import icc
from seathru.io import raw as rawio
from seathru.io.stored_views import read_stored_views
from seathru.radiometry import stored_encoding
from seathru.radiometry.colour import srgb_to_linear
from seathru.steps import ingest

X = np.linspace(0.0, 1.0, icc.CURVE_SAMPLES)


# ----------------------------------------------------------------------- profiles, built here

def _desc_v2(name: str) -> bytes:
    text = name.encode("latin-1") + b"\x00"
    return b"desc" + bytes(4) + struct.pack(">I", len(text)) + text + bytes(79)


def _curv_gamma(gamma: float) -> bytes:
    return b"curv" + bytes(4) + struct.pack(">IH", 1, round(gamma * 256)) + bytes(2)


def _curv_table(values: np.ndarray) -> bytes:
    codes = np.round(np.clip(values, 0.0, 1.0) * 65535).astype(">u2")
    return b"curv" + bytes(4) + struct.pack(">I", len(codes)) + codes.tobytes()


def _para(function: int, parameters: list[float]) -> bytes:
    fixed = struct.pack(f">{len(parameters)}i", *(round(p * 65536) for p in parameters))
    return b"para" + bytes(4) + struct.pack(">H", function) + bytes(2) + fixed


def _profile(curves: dict[bytes, bytes], name: str | None = "ProPhoto RGB") -> bytes:
    """A matrix/TRC profile holding only what ingest reads: the name and the tone curves."""
    tags = ({b"desc": _desc_v2(name)} if name else {}) | curves
    offset = 128 + 4 + 12 * len(tags)
    table, data = b"", b""
    for signature, tag in tags.items():
        tag += bytes(-len(tag) % 4)
        table += struct.pack(">4sII", signature, offset + len(data), len(tag))
        data += tag
    size = offset + len(data)
    header = (struct.pack(">I", size) + b"none" + bytes.fromhex("02100000") + b"mntrRGB XYZ "
              + bytes(12) + b"acsp")
    header += bytes(128 - len(header))
    return header + struct.pack(">I", len(tags)) + table + data


def _rgb(tag: bytes) -> dict[bytes, bytes]:
    return {b"rTRC": tag, b"gTRC": tag, b"bTRC": tag}


PROPHOTO = _profile(_rgb(_curv_gamma(1.8)))
LINEAR_PROFILE = _profile(_rgb(b"curv" + bytes(8)), name="Linear ProPhoto")
REC709 = _profile(_rgb(_para(3, [1 / 0.45, 1 / 1.099, 0.099 / 1.099, 1 / 4.5, 0.081])),
                  name="Rec. 709")
SRGB_BUILT_IN = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()


# ------------------------------------------------------------------------- the curves themselves

@pytest.mark.parametrize("profile, expected", [
    (PROPHOTO, X ** (461 / 256)),                          # u8Fixed8: 1.8 stored as 461/256
    (LINEAR_PROFILE, X),
    (_profile(_rgb(_curv_table(srgb_to_linear(np.linspace(0, 1, 256))))),
     srgb_to_linear(X)),
    (_profile(_rgb(_para(0, [2.2]))), X ** 2.2),
    (SRGB_BUILT_IN, srgb_to_linear(X)),                     # littlecms's own: para type 3
])
def test_each_form_of_tone_curve_reads_against_its_float64_formula(profile, expected):
    curves = icc.channel_curves(profile)
    assert curves.shape == (3, icc.CURVE_SAMPLES)
    np.testing.assert_allclose(curves, np.stack([expected] * 3), atol=2e-4)


def test_the_parametric_curves_with_offsets_follow_the_specification():
    g, a, b, c, d, e, f = 2.4, 0.9, 0.1, 0.05, 0.2, 0.02, 0.01
    reference = np.where(X >= d, (a * X + b) ** g + e, c * X + f)   # ICC.1:2010 table 68
    curves = icc.channel_curves(_profile(_rgb(_para(4, [g, a, b, c, d, e, f]))))
    np.testing.assert_allclose(curves[0], reference, atol=1e-4)
    reference = np.where(X >= -0.05 / 0.95, (0.95 * X + 0.05) ** 2.0 + 0.03, 0.03)
    curves = icc.channel_curves(_profile(_rgb(_para(2, [2.0, 0.95, 0.05, 0.03]))))
    np.testing.assert_allclose(curves[1], reference, atol=1e-4)


def test_a_grey_profile_gives_its_one_curve_to_every_channel():
    curves = icc.channel_curves(_profile({b"kTRC": _curv_gamma(2.2)}))
    np.testing.assert_allclose(curves, np.stack([X ** (563 / 256)] * 3), atol=1e-9)


@pytest.mark.parametrize("profile", [
    b"", b"not a profile" * 20,
    _profile({b"rTRC": _curv_gamma(1.8)}),                  # green and blue missing
    _profile(_rgb(_curv_table(X)[:20])),                     # a table cut short
    _profile(_rgb(_para(7, [1.0]))),                         # no such function
    _profile(_rgb(b"mAB " + bytes(28))),                     # a lookup table, not a curve
])
def test_what_holds_no_readable_curve_gives_none(profile):
    assert icc.channel_curves(profile) is None


def test_the_profile_name_reads_from_v2_and_v4_descriptions():
    assert icc.description(PROPHOTO) == "ProPhoto RGB"
    assert icc.description(SRGB_BUILT_IN) == "sRGB built-in"      # v4 multi-localised text
    assert icc.description(_profile(_rgb(_curv_gamma(1.8)), name=None)) is None


@pytest.mark.parametrize("curve, expected", [
    (X, "linear"), (srgb_to_linear(X), "srgb"), (X ** 1.8, "gamma 1.8"),
    (X ** (563 / 256), "gamma 2.2"),            # Adobe RGB (1998): 2.19921875
    (X ** 1.0004, "linear"),
    (np.where(X < 0.081, X / 4.5, ((X + 0.099) / 1.099) ** (1 / 0.45)), None),   # Rec. 709
    (np.log1p(20 * X) / np.log(21), None),   # a log curve
])
def test_curves_are_named_as_the_encoding_they_follow(curve, expected):
    assert stored_encoding.encoding_of_curves(np.stack([curve] * 3)) == expected


def test_channels_with_different_curves_are_not_named():
    assert stored_encoding.encoding_of_curves(np.stack([X ** 1.8, X ** 1.8, X ** 2.2])) is None


@pytest.mark.parametrize("encoding", ["gamma", "gamma x", "gamma 0", "gamma 40", "power 2"])
def test_malformed_gamma_encodings_are_refused(encoding):
    with pytest.raises(ValueError, match="encoding"):
        stored_encoding.gamma_of(encoding)


# --------------------------------------------------------------------------- files and ingest

CODES = (np.arange(24 * 32 * 3).reshape(24, 32, 3) * 83 % 60000 + 2000).astype(np.uint16)


def _tiff(path: Path, codes: np.ndarray = CODES, profile: bytes | None = PROPHOTO) -> Path:
    extratags = [] if profile is None else [(rawio.TIFF_ICC_TAG, 7, len(profile), profile, True)]
    tifffile.imwrite(path, codes, photometric="rgb", extratags=extratags)
    return path


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(
        ">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def _png(path: Path, codes: np.ndarray, chunk: bytes) -> Path:
    """A PNG (16-bit where the codes are) with one more chunk after its header."""
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(codes, cv2.COLOR_RGB2BGR))
    data = encoded.tobytes()
    path.write_bytes(data[:33] + chunk + data[33:])          # after the signature and IHDR
    return path


def test_a_16bit_tiff_with_a_gamma_profile_is_decoded_by_its_curve(tmp_path):
    path = _tiff(tmp_path / "prophoto.tif")
    assert rawio.recorded_curve(path) == rawio.RecordedCurve("gamma 1.8",
                                                             "ICC profile 'ProPhoto RGB'")
    assert rawio.detect_kind(path) == "srgb"
    decoded = rawio.read_encoded(path, "srgb")
    reference = (CODES.astype(np.float64) / 65535) ** 1.8
    np.testing.assert_allclose(decoded.image, reference, rtol=1e-5, atol=1e-7)
    assert decoded.metadata["transfer"] == "gamma 1.8" and not decoded.warnings
    as_linear = rawio.read_encoded(path, "linear")               # ingest.kind=linear asked
    np.testing.assert_allclose(as_linear.image, CODES / 65535, rtol=1e-6)
    assert as_linear.metadata["transfer"] == "linear" and "gamma 1.8" in as_linear.warnings[0]


def test_the_bit_depth_decides_only_where_no_curve_is_recorded(tmp_path):
    assert rawio.detect_kind(_tiff(tmp_path / "plain.tif", profile=None)) == "linear"
    assert rawio.detect_kind(_tiff(tmp_path / "lin16.tif", profile=LINEAR_PROFILE)) == "linear"
    eight = (CODES // 257).astype(np.uint8)
    assert rawio.detect_kind(_tiff(tmp_path / "lin8.tif", eight, LINEAR_PROFILE)) == "linear"
    assert rawio.detect_kind(_tiff(tmp_path / "srgb16.tif", profile=SRGB_BUILT_IN)) == "srgb"
    decoded = rawio.read_encoded(tmp_path / "plain.tif", "linear")
    assert decoded.metadata["transfer_source"] == "no curve recorded"


def test_pngs_record_their_curve_by_profile_or_gamma_chunk(tmp_path):
    icc_chunk = _png_chunk(b"iCCP", b"ProPhoto\x00\x00" + zlib.compress(PROPHOTO))
    path = _png(tmp_path / "prophoto.png", CODES, icc_chunk)
    assert rawio.detect_kind(path) == "srgb"
    np.testing.assert_allclose(rawio.read_encoded(path, "srgb").image,
                               (CODES / 65535) ** 1.8, rtol=1e-5, atol=1e-7)
    gamma_one = _png(tmp_path / "g10.png", (CODES // 257).astype(np.uint8),
                     _png_chunk(b"gAMA", struct.pack(">I", 100000)))
    assert rawio.recorded_curve(gamma_one) == rawio.RecordedCurve("linear", "PNG gAMA 1")
    assert rawio.detect_kind(gamma_one) == "linear"
    srgb_chunk = _png(tmp_path / "s.png", CODES, _png_chunk(b"sRGB", b"\x00"))
    assert rawio.detect_kind(srgb_chunk) == "srgb"
    assert rawio.read_encoded(srgb_chunk, "srgb").metadata["transfer"] == "srgb"


def test_a_jpeg_is_decoded_by_its_profiles_curve(tmp_path):
    codes = (CODES // 257).astype(np.uint8)
    Image.fromarray(codes).save(tmp_path / "adobe.jpg", quality=100,
                                icc_profile=_profile(_rgb(_curv_gamma(2.2)), "Adobe RGB (1998)"))
    decoded = rawio.read_encoded(tmp_path / "adobe.jpg", "srgb")
    assert decoded.metadata["transfer"] == "gamma 2.2"
    stored = cv2.cvtColor(cv2.imread(str(tmp_path / "adobe.jpg")), cv2.COLOR_BGR2RGB)
    np.testing.assert_allclose(decoded.image, (stored / 255.0) ** 2.2, rtol=1e-5, atol=1e-7)


def test_a_curve_of_no_known_kind_falls_back_to_srgb_with_a_warning(tmp_path):
    path = _tiff(tmp_path / "rec709.tif", profile=REC709)
    assert rawio.recorded_curve(path).encoding is None
    assert rawio.detect_kind(path) == "srgb"        # display-encoded, whatever the bit depth
    decoded = rawio.read_encoded(path, "srgb")
    assert decoded.metadata["transfer"] == "srgb"
    assert decoded.metadata["transfer_source"] == "in place of the ICC profile 'Rec. 709''s curve"
    folder = tmp_path / "exports"
    folder.mkdir()
    for index in range(3):
        _tiff(folder / f"F{index}.tif", CODES + index, REC709 if index else PROPHOTO)
    manifest, warnings = _ingest(folder, tmp_path / "out")
    warning, = [w for w in warnings if w["code"] == "unknown_curve"]
    assert warning["details"]["images"] == ["F1", "F2"] and "2 of 3 image(s)" in warning["message"]
    assert "ingest.kind=linear" in warning["message"]
    assert [image["decoder"]["transfer"] for image in manifest["images"]] == [
        "gamma 1.8", "srgb", "srgb"]


def _ingest(folder: Path, out: Path) -> tuple[dict, list[dict]]:
    """Run the ingest step in-process: its manifest and its warnings."""
    parser = argparse.ArgumentParser()
    ingest.add_arguments(parser)
    ingest.run(parser.parse_args(["--input", str(folder), "--out", str(out), "--workers", "1",
                                  "--wb", "none", "--no-exposure-normalise"]))
    return (json.loads((out / "manifest.json").read_text()),
            json.loads((out / "warnings.json").read_text())["warnings"])


def test_ingest_of_prophoto_exports_decodes_them_and_the_evaluation_inverts_it(tmp_path):
    folder = tmp_path / "exports"
    folder.mkdir()
    for index in range(3):
        _tiff(folder / f"DSC_{index:04d}.tif", CODES + index)
    manifest, warnings = _ingest(folder, tmp_path / "out")
    assert manifest["input"]["kind"] == "srgb" and not warnings
    for image in manifest["images"]:
        assert image["decoder"]["transfer"] == "gamma 1.8"
        assert image["decoder"]["transfer_source"] == "ICC profile 'ProPhoto RGB'"
    first = manifest["images"][0]
    linear = tifffile.imread(tmp_path / "out" / first["linear"])
    np.testing.assert_allclose(linear, (CODES / 65535) ** 1.8, rtol=1e-5, atol=1e-7)
    view = read_stored_views(tmp_path / "out")[first["name"]]
    assert view.encoding == "gamma 1.8"
    back = stored_encoding.stored_values(linear, view.gains, view.exposure_factor, view.encoding)
    np.testing.assert_allclose(back * 65535, CODES, atol=0.05)


def test_grey_photographs_are_ingested_with_a_warning_that_names_the_water_they_cannot_show(
        tmp_path):
    folder = tmp_path / "mono"
    folder.mkdir()
    for index in range(3):
        grey = (CODES[..., 1] // 257 + index).astype(np.uint8)
        cv2.imwrite(str(folder / f"mono_{index}.png"), grey)             # one channel
    cv2.imwrite(str(folder / "colour.png"), (CODES // 257).astype(np.uint8))
    manifest, warnings = _ingest(folder, tmp_path / "out")
    warning, = [w for w in warnings if w["code"] == "grey_images"]
    assert warning["details"]["images"] == ["mono_0", "mono_1", "mono_2"]
    assert "3 of 4 image(s) hold one channel" in warning["message"]
    assert [image["decoder"]["grey"] for image in manifest["images"]] == [False, True, True, True]
