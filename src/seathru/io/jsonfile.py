"""JSON files: reading with errors that name the file, and values made JSON-safe for writing.

Writing goes through :func:`seathru.io.atomic.write_json`.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from seathru.errors import PipelineError


def read_json(path: str | os.PathLike, *, missing_ok: bool = False, hint: str = "") -> Any:
    """The parsed content of a JSON file.

    Args:
        path: the file.
        missing_ok: return None when the file does not exist (else a PipelineError).
        hint: what to do when it is missing, appended to the error ("run the 'train' step").

    Raises:
        PipelineError: naming the file when it is missing (unless ``missing_ok``) or not JSON.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        if missing_ok:
            return None
        raise PipelineError(f"{path}: file not found" + (f"; {hint}" if hint else "")) from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise PipelineError(f"{path}: not valid JSON ({exc})") from None


def json_safe(value: Any) -> Any:
    """``value`` with NaN and infinities as None (JSON has no such numbers), numpy scalars and
    arrays as Python numbers and lists, tuples as lists."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value
