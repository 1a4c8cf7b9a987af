"""seathru.io.manifest: the ingest output contract (manifest.json and the folder layout)."""

from __future__ import annotations

import argparse
import copy
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from seathru.errors import PipelineError
from seathru.io.contract import check_contract
from seathru.io.manifest import (FORMAT, IngestFolder, IngestManifest, read_manifest,
                                 write_manifest)
from seathru.steps import ingest


@pytest.fixture(scope="module")
def ingested(tmp_path_factory) -> Path:
    """A real ingest output of three small 16-bit PNGs, with linear_2/ and masks_2/."""
    root = tmp_path_factory.mktemp("manifest")
    folder = root / "pngs"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for name in ("a", "b", "c"):
        cv2.imwrite(str(folder / f"{name}.png"),
                    rng.integers(1, 65535, size=(24, 32, 3), dtype=np.uint16))
    parser = argparse.ArgumentParser()
    ingest.add_arguments(parser)
    out = root / "ingest"
    ingest.run(parser.parse_args(["--input", str(folder), "--out", str(out), "--downscale", "2",
                                  "--workers", "1"]))
    return out


def test_the_ingest_step_writes_a_manifest_that_reads_back_unchanged(ingested, tmp_path):
    path = ingested / "manifest.json"
    manifest = read_manifest(path)
    assert manifest == json.loads(path.read_text())
    assert manifest["format"] == FORMAT and [im["name"] for im in manifest["images"]] == [
        "a", "b", "c"]
    assert manifest["images"][0]["downscaled"]["2"]["linear"] == "linear_2/a.tiff"
    assert manifest["settings"]["downscale"] == [2] and manifest["exposure"]["normalised"]
    again = tmp_path / "manifest.json"
    write_manifest(again, manifest)
    assert again.read_text() == path.read_text()


def _broken(manifest: dict, tmp_path: Path, edit) -> Path:
    data = copy.deepcopy(manifest)
    edit(data)
    path = tmp_path / "manifest.json"
    path.write_text(json.dumps(data))
    return path


@pytest.mark.parametrize("edit, key", [
    (lambda m: m["images"][1].pop("mask"), "images[1].mask"),
    (lambda m: m.pop("white_balance"), "white_balance"),
    (lambda m: m["images"][0]["downscaled"]["2"].pop("width"), "images[0].downscaled.2.width"),
    (lambda m: m["input"].pop("kind"), "input.kind"),
    (lambda m: m["rejected"].append({"file": "x.jpg"}), "rejected[0].reason"),
    (lambda m: m.__setitem__("images", {"a": 1}), "images"),
])
def test_a_malformed_manifest_names_the_file_and_the_key(ingested, tmp_path, edit, key):
    path = _broken(read_manifest(ingested / "manifest.json"), tmp_path, edit)
    with pytest.raises(PipelineError) as info:
        read_manifest(path)
    message = str(info.value)
    assert str(path) in message and key in message and "run the 'ingest' step" in message


def test_wrong_format_bad_json_and_absence_are_errors_naming_the_file(ingested, tmp_path):
    manifest = read_manifest(ingested / "manifest.json")
    path = _broken(manifest, tmp_path, lambda m: m.__setitem__("format", "seathru-ingest/0"))
    with pytest.raises(PipelineError, match="expected format 'seathru-ingest/1'"):
        read_manifest(path)
    path.write_text("{not json")
    with pytest.raises(PipelineError, match=f"{path}: not valid JSON"):
        read_manifest(path)
    with pytest.raises(PipelineError, match="not found; run the 'ingest' step"):
        read_manifest(tmp_path / "nowhere.json")
    # not strict: any JSON, e.g. a hand-written file of EXIF focal lengths
    path.write_text(json.dumps({"images": [{"exif": {"FocalLengthIn35mmFilm": 28}}]}))
    assert read_manifest(path, strict=False)["images"][0]["exif"]["FocalLengthIn35mmFilm"] == 28


def test_write_refuses_a_manifest_that_breaks_the_contract(ingested, tmp_path):
    manifest = read_manifest(ingested / "manifest.json")
    del manifest["images"][2]["exposure_factor"]
    with pytest.raises(PipelineError, match=r"images\[2\]\.exposure_factor: missing"):
        write_manifest(tmp_path / "manifest.json", manifest)
    assert not (tmp_path / "manifest.json").exists()


def test_contract_check_allows_keys_it_does_not_know(ingested):
    manifest = read_manifest(ingested / "manifest.json")
    manifest["images"][0]["added_by_a_newer_writer"] = 1
    check_contract(manifest, IngestManifest, "manifest.json", FORMAT)


def test_ingest_folder_pairs_downscaled_linear_images_with_their_masks(ingested, tmp_path):
    folder = IngestFolder(ingested, "linear_2")
    assert sorted(folder.linear) == ["a", "b", "c"] and folder.masks_dir.name == "masks_2"
    assert folder.matching_masks["a"].parent.name == "masks"
    assert folder.manifest["format"] == FORMAT
    with pytest.raises(PipelineError, match="no linear images"):
        IngestFolder(ingested, "linear_8")
    with pytest.raises(PipelineError, match="ingest folder not found"):
        IngestFolder(tmp_path / "missing")
    twins = tmp_path / "twins"
    (twins / "linear").mkdir(parents=True)
    for name in ("x.png", "x.tiff"):
        cv2.imwrite(str(twins / "linear" / name), np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(PipelineError, match="two images share the name 'x'"):
        IngestFolder(twins)
