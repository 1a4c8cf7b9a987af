"""seathru.io.pose_report: the poses step's report.json contract."""

from __future__ import annotations

import copy
import json
from dataclasses import asdict
from pathlib import Path

import pytest

from seathru.errors import PipelineError
from seathru.geometry.quality import QualityGate, SfmAttempt, SfmSettings
from seathru.io.pose_report import FORMAT, read_pose_report, write_pose_report
from tests.test_poses import nerfstudio_poses


def summary() -> dict:
    return {"frames": 3, "test_frames": 1,
            "normalisation": {"centre": [0.0, 0.0, 0.0], "scale": 0.5, "method": "unit ball"},
            "near": 0.1, "far": 1.9,
            "source_cameras": [{"model": "PINHOLE", "width": 8, "height": 6,
                                "params": [5.0, 5.0, 4.0, 3.0]}],
            "undistorted": False, "posed_without_linear_image": [],
            "linear_images_without_pose": []}


def colmap_report() -> dict:
    attempt = SfmAttempt(settings=asdict(SfmSettings()), registered=3, total=3,
                         mean_reprojection_px=0.4, passed=True)
    return {"format": FORMAT, "source": "colmap", "ingest": "results/d/ingest",
            "arguments": {"matcher": "sequential"},
            "clahe": {"enabled": True, "clip": 2.0, "tiles": 8}, "initial_focal_px": None,
            "initial_focal_source": "no manifest", "extraction_masks": True,
            "global_mapping_available": True, "gate": asdict(QualityGate()), "gate_passed": True,
            "attempts": [attempt.to_dict()], "chosen_attempt": 1, "registered": 3, "total": 3,
            "mean_reprojection_px": 0.4, "unregistered": [], "left_out_not_in_both_folders": [],
            **summary(), "seconds": 1.5}


def test_colmap_report_round_trip(tmp_path):
    path = tmp_path / "report.json"
    report = colmap_report()
    write_pose_report(path, report)
    assert read_pose_report(path) == json.loads(json.dumps(report))


@pytest.mark.parametrize("edit, key", [
    (lambda r: r["attempts"][0].pop("registered"), "attempts[0].registered"),
    (lambda r: r.pop("gate_passed"), "gate_passed"),
    (lambda r: r["gate"].pop("max_disagreement"), "gate.max_disagreement"),
    (lambda r: r["normalisation"].pop("scale"), "normalisation.scale"),
    (lambda r: r.pop("seconds"), "seconds"),
])
def test_a_malformed_report_names_the_file_and_the_key(tmp_path, edit, key):
    report = copy.deepcopy(colmap_report())
    edit(report)
    path = tmp_path / "report.json"
    path.write_text(json.dumps(report))
    with pytest.raises(PipelineError) as info:
        read_pose_report(path)
    assert str(path) in str(info.value) and key in str(info.value)
    with pytest.raises(PipelineError, match="missing"):
        write_pose_report(tmp_path / "again.json", report)
    assert not (tmp_path / "again.json").exists()


def test_format_and_json_errors(tmp_path):
    path = tmp_path / "report.json"
    path.write_text(json.dumps({k: v for k, v in colmap_report().items() if k != "format"}))
    with pytest.raises(PipelineError, match="expected format 'seathru-poses-report/1', found None"):
        read_pose_report(path)
    path.write_text("[1, 2")
    with pytest.raises(PipelineError, match="not valid JSON"):
        read_pose_report(path)
    with pytest.raises(PipelineError, match="run the 'poses' step"):
        read_pose_report(tmp_path / "absent.json")


def test_the_poses_step_writes_a_reader_report_that_reads_back(tmp_path):
    """Existing poses (nerfstudio): the report carries the reader's notes, no COLMAP fields."""
    out = nerfstudio_poses(tmp_path, "poses", "--test-every", "2")
    report = read_pose_report(out / "report.json")
    assert report["format"] == FORMAT and report["frames"] == 3 and report["test_frames"] == 2
    assert report["reader_notes"]["transforms"] == str(tmp_path / "transforms.json")
    assert "attempts" not in report
    # every setting is recorded, with its default when not given
    assert report["arguments"]["matcher"] == "sequential" and report["arguments"]["far"] == 5.0
    assert report["arguments"]["source_dir"] == str(tmp_path)
    broken = {k: v for k, v in report.items() if k != "reader_notes"}
    Path(out / "report.json").write_text(json.dumps(broken))
    with pytest.raises(PipelineError, match="attempts: missing"):
        read_pose_report(out / "report.json")  # neither reader notes nor a COLMAP run
