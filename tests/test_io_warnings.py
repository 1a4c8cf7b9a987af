"""The warnings contract (seathru.io.warnings) and the warnings the ingest and poses steps derive
from their outputs (seathru.io.manifest.ingest_warnings, seathru.io.pose_report.pose_warnings)."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from seathru.errors import PipelineError
from seathru.io.manifest import ingest_warnings
from seathru.io.pose_report import pose_warnings
from seathru.io.warnings import (FORMAT, read_dataset_warnings, read_warnings, step_warning,
                                 write_warnings)


def test_round_trip_with_numpy_details(tmp_path):
    warning = step_warning("poses", "unconfirmed_poses", "doubtful", deviation=np.float32(0.25),
                           images=np.array([1, 2]), worst=float("nan"))
    path = tmp_path / "warnings.json"
    write_warnings(path, [warning])
    data = json.loads(path.read_text())
    assert data["format"] == FORMAT
    assert read_warnings(path) == [{"step": "poses", "code": "unconfirmed_poses",
                                    "message": "doubtful",
                                    "details": {"deviation": 0.25, "images": [1, 2],
                                                "worst": None}}]


def test_writing_logs_each_message(tmp_path, caplog):
    with caplog.at_level(logging.WARNING):
        write_warnings(tmp_path / "w.json", [step_warning("ingest", "x", "look at me")],
                       logging.getLogger("test"))
    assert "look at me" in caplog.text


def test_bad_files_are_refused_naming_the_file(tmp_path):
    path = tmp_path / "warnings.json"
    assert read_warnings(path, missing_ok=True) == []
    with pytest.raises(PipelineError, match="warnings.json: file not found"):
        read_warnings(path)
    path.write_text(json.dumps({"format": FORMAT, "warnings": [{"step": "x", "code": "y"}]}))
    with pytest.raises(PipelineError, match=r"warnings\[0\]\.details: missing"):
        read_warnings(path)
    path.write_text(json.dumps({"format": "other/1", "warnings": []}))
    with pytest.raises(PipelineError, match="expected format 'seathru-warnings/1'"):
        read_warnings(path)


def test_dataset_warnings_in_step_order_and_damage_reported(tmp_path):
    for step in ("poses", "ingest", "zzz"):
        write_warnings(tmp_path / step / "warnings.json", [step_warning(step, f"{step}_code", "m")])
    (tmp_path / "evaluate").mkdir()
    (tmp_path / "evaluate" / "warnings.json").write_text("{not json")
    found = read_dataset_warnings(tmp_path, ("ingest", "poses", "evaluate"))
    assert [w["code"] for w in found] == ["ingest_code", "poses_code", "unreadable_warnings",
                                          "zzz_code"]
    assert "not valid JSON" in found[2]["message"]


def _manifest(clipped=(0.01, 0.2), image_warnings=(["shared"], ["shared", "own"]),
              rejected=(), missing=()):
    images = [{"name": f"im{i}", "clipped_fraction": c, "warnings": list(w)}
              for i, (c, w) in enumerate(zip(clipped, image_warnings))]
    return {"images": images, "rejected": list(rejected), "warnings": ["no as-shot gains"],
            "input": {"layout": {"layout": "nerfstudio", "missing": list(missing)}}}


def test_ingest_warnings_from_the_manifest():
    manifest = _manifest(rejected=[{"file": "a.NEF", "reason": "truncated"}],
                         missing=[{"name": "f9", "file": "/d/images/f9.png"}])
    found = {w["code"]: w for w in ingest_warnings(manifest, clipped_share=0.1)}
    assert set(found) == {"rejected_images", "missing_frames", "clipped_pixels", "image_warnings",
                          "dataset_warning"}
    assert "a.NEF (truncated)" in found["rejected_images"]["message"]
    assert "f9" in found["missing_frames"]["message"]
    assert found["clipped_pixels"]["details"]["images"] == {"im1": 0.2}
    # a warning every image has describes the dataset: only im1's own one is listed
    assert found["image_warnings"]["details"]["images"] == {"im1": ["own"]}
    quiet = ingest_warnings(_manifest(clipped=(0.01, 0.02), image_warnings=(["s"], ["s"])), 0.1)
    assert [w["code"] for w in quiet] == ["dataset_warning"]


@pytest.mark.parametrize("kind, fields, warned", [
    ("srgb", [], True), ("raw", [], True), ("srgb", ["exposure_time"], False),
    ("linear", [], False)])   # linear images (the release's images_wb) come processed
def test_camera_images_none_of_which_records_its_exposure_are_named(kind, fields, warned):
    manifest = _manifest(clipped=(0.01, 0.02), image_warnings=([], []))
    manifest["input"]["kind"] = kind
    manifest["exposure"] = {"normalised": True, "fields_used": fields}
    codes = [w["code"] for w in ingest_warnings(manifest, 0.1)]
    assert ("no_exposure_metadata" in codes) == warned


def _report(**changes):
    report = {"gate_passed": True, "posed_without_linear_image": [],
              "linear_images_without_pose": [], "unregistered": [], "total": 10}
    report.update(changes)
    return report


def test_pose_warnings_from_the_report():
    assert pose_warnings(_report()) == []
    assert pose_warnings({"posed_without_linear_image": [], "linear_images_without_pose": [],
                          "reader_notes": {}}) == []   # a reader's report has no gate
    found = pose_warnings(_report(
        gate_passed=False, gate_message="the camera model was not confirmed: x",
        attempts=[{"comparisons": [{"with_attempt": 1, "max_centre_deviation": 0.4}]}],
        unregistered=["b"], posed_without_linear_image=["gone", "named"],
        linear_images_without_pose=["c"]), {"missing": [{"name": "named", "file": "f"}]})
    by_code = {w["code"]: w for w in found}
    assert list(by_code) == ["unconfirmed_poses", "unregistered_images", "posed_without_image",
                             "images_without_pose"]
    assert by_code["unconfirmed_poses"]["message"].startswith("the camera model was not")
    assert by_code["unconfirmed_poses"]["details"]["comparisons"][0]["max_centre_deviation"] \
        == 0.4
    # ingest named the other one missing already
    assert by_code["posed_without_image"]["details"]["frames"] == ["gone"]
    # an image COLMAP did not register has no pose: one warning, not two
    once = pose_warnings(_report(unregistered=["b", "c"], linear_images_without_pose=["b", "c"]))
    assert [w["code"] for w in once] == ["unregistered_images"]


@pytest.mark.parametrize("frames, held_out, warned", [(4, 1, True), (11, 2, True),
                                                      (12, 2, False), (40, 5, False)])
def test_a_handful_of_training_views_is_warned_about(frames, held_out, warned):
    found = pose_warnings(_report(frames=frames, test_frames=held_out))
    assert [w["code"] for w in found] == (["few_views"] if warned else [])
    if warned:
        assert found[0]["message"].startswith(f"only {frames - held_out} training views")
        assert found[0]["details"] == {"training_views": frames - held_out,
                                       "held_out_views": held_out}
