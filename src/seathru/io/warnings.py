"""``warnings.json`` (format ``seathru-warnings/1``): what a step wants a person to look at.

Each step that finished but found something doubtful (an unconfirmed camera model, rejected
images, frames listed but missing, clipped pixels, ...) writes one ``warnings.json`` beside its
outputs, ``results/<dataset>/<step>/warnings.json``, holding a list of :class:`StepWarning`
(``step``, ``code``, ``message``, ``details``). ``code`` is a stable identifier to filter on
(:data:`CODES` lists those the pipeline writes); ``message`` is one sentence for a person, saying
what was found and what to try; ``details`` holds the figures (JSON values).

The report step reads every step's file of a dataset (:func:`read_dataset_warnings`) and shows
them in its "needs a look" column; a step with nothing to say writes an empty list.

Example::

    write_warnings(out / "warnings.json", [
        step_warning("poses", "unconfirmed_poses", "no independent model agreed ...",
                     max_centre_deviation=0.35)])
    read_warnings(out / "warnings.json")   # -> [{"step": "poses", "code": ..., ...}]
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any, Sequence, TypedDict

from seathru.io.atomic import write_json
from seathru.io.contract import check_contract
from seathru.io.jsonfile import json_safe, read_json

FORMAT = "seathru-warnings/1"
FILE_NAME = "warnings.json"
_HINT = "rerun the step that wrote it"

#: The codes the pipeline writes, by step (the report derives the train ones).
CODES = {
    "ingest": ("rejected_images", "missing_frames", "clipped_pixels", "image_warnings",
               "dataset_warning"),
    "poses": ("unconfirmed_poses", "unregistered_images", "posed_without_image",
              "images_without_pose", "few_views", "source_model_not_kept"),
    "train": ("water_model_off", "not_converged"),
}


class StepWarning(TypedDict):
    """One warning: which step, a stable code, a sentence for a person, the figures."""

    step: str
    code: str
    message: str
    details: dict[str, Any]


class WarningsFile(TypedDict):
    format: str                     # FORMAT
    warnings: list[StepWarning]


def step_warning(step: str, code: str, message: str, **details: Any) -> StepWarning:
    """A :class:`StepWarning` with JSON-safe ``details`` (numpy values become numbers)."""
    return {"step": step, "code": code, "message": message, "details": json_safe(details)}


def write_warnings(path: str | os.PathLike, warnings: Sequence[StepWarning],
                   log: logging.Logger | None = None) -> None:
    """Write ``warnings.json`` atomically (checked against the contract first); with ``log``,
    each message is also logged as a warning (it reaches the step's log file)."""
    data: WarningsFile = {"format": FORMAT, "warnings": list(warnings)}
    check_contract(data, WarningsFile, path, FORMAT)
    write_json(path, data)
    for warning in warnings if log is not None else ():
        log.warning("%s", warning["message"])


def read_warnings(path: str | os.PathLike, missing_ok: bool = False) -> list[StepWarning]:
    """The warnings of one ``warnings.json`` (``[]`` for a missing file with ``missing_ok``).

    Raises:
        PipelineError: naming the file when it is missing (unless ``missing_ok``), not JSON, not
            of format ``seathru-warnings/1`` or malformed.
    """
    data = read_json(path, missing_ok=missing_ok, hint=_HINT)
    if data is None:
        return []
    check_contract(data, WarningsFile, path, FORMAT, _HINT)
    return list(data["warnings"])


def read_dataset_warnings(dataset_dir: str | os.PathLike,
                          step_order: Sequence[str] = ()) -> list[StepWarning]:
    """Every step's warnings of one dataset (``<dataset_dir>/<step>/warnings.json``), steps in
    ``step_order`` (others after them, by name). A damaged file becomes a warning itself."""
    base = Path(dataset_dir)
    order = list(step_order)
    files = sorted(base.glob(f"*/{FILE_NAME}"), key=lambda p: (
        order.index(p.parent.name) if p.parent.name in order else len(order), p.parent.name))
    found: list[StepWarning] = []
    for path in files:
        try:
            found += read_warnings(path)
        except Exception as exc:  # noqa: BLE001 - a damaged file must not hide the others
            found.append(step_warning(path.parent.name, "unreadable_warnings",
                                      f"{path}: cannot be read ({exc})"))
    return found
