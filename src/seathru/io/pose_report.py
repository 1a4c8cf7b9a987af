"""The poses step's ``report.json`` (format ``seathru-poses-report/1``): what was tried and
measured while recovering the cameras.

Every report is a :class:`PoseReport` (source, settings, the output summary, timing). A COLMAP run
(``--source colmap``) adds :class:`ColmapDetails` (the quality gate, every attempt, unregistered
images): :class:`ColmapPoseReport`; reading existing poses adds the reader's notes:
:class:`ReaderPoseReport`. Written by :func:`write_pose_report`, read by :func:`read_pose_report`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, TypedDict, Union

from seathru.io.atomic import write_json
from seathru.io.contract import check_contract
from seathru.io.jsonfile import read_json
from seathru.io.warnings import StepWarning, step_warning

FORMAT = "seathru-poses-report/1"
_HINT = "run the 'poses' step"


class ClaheRecord(TypedDict):
    enabled: bool
    clip: float
    tiles: int


class _GateOptional(TypedDict, total=False):
    rival_error_ratio: float     # absent in reports written before it existed


class GateRecord(_GateOptional):
    """``seathru.geometry.quality.QualityGate`` as used."""

    min_registered_fraction: float
    max_reprojection_px: float
    reprojection_scale: float
    max_disagreement: float
    max_rotation_disagreement_deg: float


class AttemptRecord(TypedDict):
    """``seathru.geometry.quality.SfmAttempt.to_dict()``."""

    settings: dict[str, Any]     # SfmSettings: matcher, mapper, seed, focal_px, ...
    role: str                    # first | cross-check | retry
    registered: int
    total: int
    registered_fraction: float
    mean_reprojection_px: float | None
    num_points: int
    mean_track_length: float | None
    seconds: float
    passed: bool
    unregistered: list[str]
    error: str | None
    agreement: dict[str, Any] | None
    comparisons: list[dict[str, Any]]
    note: str | None


class _ColmapDetailsOptional(TypedDict, total=False):
    """Keys reports written before ``poses.on_unconfirmed`` existed do not have."""

    gate_message: str | None     # why the model kept is doubtful (None: confirmed)
    on_unconfirmed: str          # fail | warn, as used


class ColmapDetails(_ColmapDetailsOptional):
    clahe: ClaheRecord
    initial_focal_px: float | None
    initial_focal_source: str
    extraction_masks: bool
    global_mapping_available: bool
    gate: GateRecord
    gate_passed: bool
    attempts: list[AttemptRecord]
    chosen_attempt: int          # index into attempts, from 1
    registered: int
    total: int
    mean_reprojection_px: float | None
    unregistered: list[str]      # image stems
    left_out_not_in_both_folders: list[str]


class ReaderDetails(TypedDict):
    reader_notes: dict[str, Any]


class NormalisationRecord(TypedDict):
    centre: list[float]
    scale: float
    method: str


class SourceModelRecord(TypedDict):
    """The poses report's ``source_model``: a source's COLMAP model and whether it was kept."""

    model: str                        # the model folder read
    points: int                       # 3D points in the model
    kept: bool                        # written to poses/sparse
    reason: str                       # why (not) kept, for a person
    shared_images: int                # registered model images named like a posed view
    max_position_error_share: float | None  # after the similarity; of the poses' spread
    max_rotation_error_deg: float | None
    scale: float | None               # source units per model unit (the similarity's)



class _OutputSummaryOptional(TypedDict, total=False):
    # linear | cubic (seathru.io.colmap.Interpolation); reports written before it: linear
    undistort_interpolation: str
    # points of a source's COLMAP model kept in sparse/ (seathru.io.source_model)
    source_points_kept: int
    # the source's COLMAP model, kept or not (a colmap dataset, an LLFF one with sparse/0)
    source_model: SourceModelRecord


class OutputSummary(_OutputSummaryOptional):
    """What was written next to the report (cameras.json, images/, masks/)."""

    frames: int
    test_frames: int
    normalisation: NormalisationRecord
    near: float
    far: float
    source_cameras: list[dict[str, Any]]  # distinct source cameras: model, width, height, params
    undistorted: bool
    posed_without_linear_image: list[str]
    linear_images_without_pose: list[str]


class PoseReport(OutputSummary):
    format: str                  # FORMAT
    source: str                  # colmap | llff | nerfstudio (cameras.json's source)
    ingest: str                  # the ingest folder
    arguments: dict[str, Any]    # every flag and setting, as used
    seconds: float


class ColmapPoseReport(PoseReport, ColmapDetails):
    """The report of ``--source colmap``."""


class ReaderPoseReport(PoseReport, ReaderDetails):
    """The report of ``--source llff | colmap-model | nerfstudio``."""


AnyPoseReport = Union[ColmapPoseReport, ReaderPoseReport]


def _contract(data: Any) -> type:
    return ReaderPoseReport if isinstance(data, dict) and "reader_notes" in data \
        else ColmapPoseReport


def write_pose_report(path: str | Path, report: AnyPoseReport) -> None:
    """Write ``report.json`` atomically (checked against the contract first)."""
    check_contract(report, _contract(report), path, FORMAT)
    write_json(path, report)


def read_pose_report(path: str | Path) -> AnyPoseReport:
    """The report at ``path``.

    Raises:
        PipelineError: naming the file, when it is absent, not JSON, not of format
            ``seathru-poses-report/1`` or missing a key.
    """
    data = read_json(path, hint=_HINT)
    check_contract(data, _contract(data), path, FORMAT, _HINT)
    return data


#: Fewer training views than this: the model fits them and shows little else (a NeRF needs
#: tens of overlapping photographs).
FEW_TRAINING_VIEWS = 10


def pose_warnings(report: AnyPoseReport, layout: dict | None = None) -> list[StepWarning]:
    """What the poses step's user should look at, from its report: an unconfirmed camera model
    (kept with ``poses.on_unconfirmed=warn``), images COLMAP did not register, posed frames
    without an image (except those the ingest step already named missing in its ``layout``
    record), images without a pose, a source's COLMAP model that does not match its poses, and
    fewer than ``FEW_TRAINING_VIEWS`` training views."""
    found: list[StepWarning] = []
    if report.get("gate_passed") is False:
        found.append(step_warning(
            "poses", "unconfirmed_poses", report.get("gate_message") or
            "the camera model did not pass the quality gate; kept: the model is trained on "
            "cameras that may be wrong",
            attempt=report.get("chosen_attempt"), registered=report.get("registered"),
            mean_reprojection_px=report.get("mean_reprojection_px"),
            comparisons=[c for a in report.get("attempts", []) for c in a.get("comparisons", [])]))
    unregistered = report.get("unregistered") or []
    if unregistered:
        found.append(step_warning(
            "poses", "unregistered_images", f"{len(unregistered)} of {report.get('total')} "
            f"images were not registered by COLMAP and are left out: "
            + ", ".join(unregistered[:10]) + (" ..." if len(unregistered) > 10 else ""),
            images=unregistered))
    named = {m["name"] for m in ((layout or {}).get("missing") or [])}
    without_image = [n for n in report["posed_without_linear_image"] if n not in named]
    if without_image:
        found.append(step_warning(
            "poses", "posed_without_image", f"{len(without_image)} posed frame(s) have no "
            f"ingested image and are left out: " + ", ".join(without_image[:10])
            + (" ..." if len(without_image) > 10 else ""), frames=without_image))
    # COLMAP's unregistered images have no pose either: said once, above
    without_pose = [n for n in report["linear_images_without_pose"] if n not in unregistered]
    if without_pose:
        found.append(step_warning(
            "poses", "images_without_pose", f"{len(without_pose)} image(s) have no pose in "
            f"the source and are left out: " + ", ".join(without_pose[:10])
            + (" ..." if len(without_pose) > 10 else ""), images=without_pose))
    source_model = report.get("source_model")
    if source_model and not source_model["kept"]:
        found.append(step_warning(
            "poses", "source_model_not_kept", f"the dataset's COLMAP model "
            f"({source_model['model']}) is not used: {source_model['reason']}; training goes "
            f"without depth from its points and the medium decision without its tracks. Put "
            f"the model the poses came from beside them, or leave it out",
            **{k: v for k, v in source_model.items() if k not in ("model", "reason")}))
    frames, held_out = report.get("frames"), report.get("test_frames")
    if isinstance(frames, int) and isinstance(held_out, int) \
            and frames - held_out < FEW_TRAINING_VIEWS:
        found.append(step_warning(
            "poses", "few_views", f"only {frames - held_out} training views ({held_out} held "
            f"out): a NeRF needs tens of overlapping photographs, each part of the scene seen "
            f"from three or more positions; the model will fit these views and show little "
            f"else, and the held-out figures rest on {held_out} view(s)",
            training_views=frames - held_out, held_out_views=held_out))
    return found
