"""The photos of a dataset folder: which files ingest decodes, which it rejects and why.

Kinds (``seathru.io.raw.detect_kind``): ``raw``, ``linear`` (16-bit/float PNG or TIFF), ``srgb``
(JPEG, 8-bit PNG/TIFF). With ``kind='auto'`` a folder that mixes kinds (RAW+JPEG pairs) uses
the preferred one (raw, then linear, then srgb) and rejects the other files; an explicit
``linear`` or ``srgb`` decides the transfer of every encoded file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, TypedDict

from seathru.errors import PipelineError
from seathru.io.raw import KINDS, detect_kind


class RejectedFile(TypedDict):
    """A file left out, with the reason (a manifest ``rejected`` entry)."""

    file: str
    reason: str


def resolve_input(folder: Path, subdir: str | None) -> Path:
    """The image folder: ``folder/subdir`` (case-insensitive match of ``subdir``) or ``folder``."""
    if not folder.is_dir():
        raise PipelineError(f"--input {folder}: folder not found")
    if not subdir:
        return folder
    exact = folder / subdir
    if exact.is_dir():
        return exact
    matches = [p for p in folder.iterdir() if p.is_dir() and p.name.lower() == subdir.lower()]
    if len(matches) == 1:
        return matches[0]
    available = sorted(p.name for p in folder.iterdir() if p.is_dir())
    raise PipelineError(f"--subdir {subdir}: no such folder in {folder} "
                        f"(subfolders: {', '.join(available) or 'none'})")


def select_files(folder: Path, kind: str) -> tuple[list[tuple[Path, str, str]],
                                                   list[RejectedFile], dict[str, Any]]:
    """Images to decode as ``(path, name, kind)``, rejected files and what was detected.

    Names are file stems; files are taken in sorted name order so a duplicate stem (IMG_1.dng
    and IMG_1.DNG) always rejects the same, later file. The detection dict holds ``kind``,
    ``requested``, ``counts``, ``note`` and ``ignored`` (files that are not images).
    """
    candidates = []
    ignored = []
    for path in sorted(folder.iterdir(), key=lambda p: p.name):
        if path.name.startswith(".") or not path.is_file():
            continue
        detected = detect_kind(path)
        if detected is None:
            ignored.append(path.name)
        else:
            candidates.append((path, detected))
    counts = {k: sum(1 for _, d in candidates if d == k) for k in KINDS}
    counts = {k: v for k, v in counts.items() if v}
    if not candidates:
        with_images = sorted(p.name for p in folder.iterdir() if p.is_dir() and any(
            detect_kind(f) for f in p.iterdir() if f.is_file()))
        hint = (f"; subfolders with images: {', '.join(with_images)} (use --subdir)"
                if with_images else "")
        raise PipelineError(f"{folder}: no image files (RAW, JPEG, PNG, TIFF) found{hint}")

    if kind == "auto":
        dataset_kind = next(k for k in KINDS if k in counts)
        note = f"detected {dataset_kind} from " + ", ".join(f"{v} {k}" for k, v in counts.items())
    else:
        dataset_kind = kind
        note = f"requested {kind}; found " + ", ".join(f"{v} {k}" for k, v in counts.items())
    selected: list[tuple[Path, str, str]] = []
    rejected: list[RejectedFile] = []
    taken: dict[str, str] = {}
    for path, detected in candidates:
        if kind == "auto" or dataset_kind == "raw":
            usable = detected == dataset_kind
        else:  # an explicit linear/srgb kind decides the transfer of any encoded file
            usable = detected != "raw"
        if not usable:
            rejected.append({"file": path.name, "reason": (
                f"{detected} file ({path.suffix}) in a dataset of kind {dataset_kind}; "
                f"only {dataset_kind} files are used (pass --kind to choose)")})
            continue
        if path.stem in taken:
            rejected.append({"file": path.name, "reason": (
                f"duplicate image name {path.stem!r}: {taken[path.stem]} already provides it")})
            continue
        taken[path.stem] = path.name
        selected.append((path, path.stem, dataset_kind))
    detection = {"kind": dataset_kind, "requested": kind, "counts": counts, "note": note,
                 "ignored": ignored}
    return selected, rejected, detection
