"""The photos of a dataset folder: which files ingest decodes, which it rejects and why.

Kinds (``seathru.io.raw.detect_kind``): ``raw``, ``linear`` (16-bit/float PNG or TIFF), ``srgb``
(JPEG, 8-bit PNG/TIFF). With ``kind='auto'`` a folder that mixes kinds (RAW+JPEG pairs) uses
the preferred one (raw, then linear, then srgb) and rejects the other files; an explicit
``linear`` or ``srgb`` decides the transfer of every encoded file.

:func:`find_inputs` is the whole choice for the ingest step: a folder (or its subfolder), or the
images a posed dataset holds in its own layout (``seathru.io.dataset_readers.layout_images``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypedDict

from seathru.errors import PipelineError
from seathru.io.dataset_readers import layout_images
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
    """Images of ``folder`` to decode as ``(path, name, kind)``, rejected files and what was
    detected (:func:`select_paths` on the folder's files, names = file stems).

    Raises:
        PipelineError: the folder holds no image file (naming its subfolders that do).
    """
    files = [path for path in sorted(folder.iterdir(), key=lambda p: p.name)
             if not path.name.startswith(".") and path.is_file()]
    if not any(detect_kind(path) for path in files):
        with_images = sorted(p.name for p in folder.iterdir() if p.is_dir() and any(
            detect_kind(f) for f in p.iterdir() if f.is_file()))
        hint = (f"; subfolders with images: {', '.join(with_images)} (use --subdir, or the "
                f"sheet's source llff, colmap or nerfstudio for those layouts)"
                if with_images else "")
        raise PipelineError(f"{folder}: no image files (RAW, JPEG, PNG, TIFF) found{hint}")
    return select_paths([(path, path.stem) for path in files], kind)


def select_paths(files: list[tuple[Path, str]], kind: str
                 ) -> tuple[list[tuple[Path, str, str]], list[RejectedFile], dict[str, Any]]:
    """Images to decode as ``(path, name, kind)``, rejected files and what was detected.

    ``files``: ``(path, name)`` in the order names are given priority (a duplicate name, e.g.
    IMG_1.dng and IMG_1.DNG, rejects the later file). The detection dict holds ``kind``,
    ``requested``, ``counts``, ``note`` and ``ignored`` (files that are not images).

    Raises:
        PipelineError: no file is an image.
    """
    candidates = []
    ignored = []
    for path, name in files:
        detected = detect_kind(path)
        if detected is None:
            ignored.append(path.name)
        else:
            candidates.append((path, name, detected))
    counts = {k: sum(1 for *_, d in candidates if d == k) for k in KINDS}
    counts = {k: v for k, v in counts.items() if v}
    if not candidates:
        listed = ", ".join(str(path) for path, _ in files[:5]) or "none"
        raise PipelineError(f"no image files (RAW, JPEG, PNG, TIFF) among the {len(files)} "
                            f"given ({listed})")

    if kind == "auto":
        dataset_kind = next(k for k in KINDS if k in counts)
        note = f"detected {dataset_kind} from " + ", ".join(f"{v} {k}" for k, v in counts.items())
    else:
        dataset_kind = kind
        note = f"requested {kind}; found " + ", ".join(f"{v} {k}" for k, v in counts.items())
    selected: list[tuple[Path, str, str]] = []
    rejected: list[RejectedFile] = []
    taken: dict[str, str] = {}
    for path, name, detected in candidates:
        if kind == "auto" or dataset_kind == "raw":
            usable = detected == dataset_kind
        else:  # an explicit linear/srgb kind decides the transfer of any encoded file
            usable = detected != "raw"
        if not usable:
            rejected.append({"file": path.name, "reason": (
                f"{detected} file ({path.suffix}) in a dataset of kind {dataset_kind}; "
                f"only {dataset_kind} files are used (pass --kind to choose)")})
            continue
        if name in taken:
            rejected.append({"file": path.name, "reason": (
                f"duplicate image name {name!r}: {taken[name]} already provides it")})
            continue
        taken[name] = path.name
        selected.append((path, name, dataset_kind))
    detection = {"kind": dataset_kind, "requested": kind, "counts": counts, "note": note,
                 "ignored": ignored}
    return selected, rejected, detection


@dataclass
class InputImages:
    """What the ingest step decodes: ``selected`` ``(path, name, kind)``, ``rejected`` files,
    the ``detection`` dict (:func:`select_paths`), the ``folder`` read, the ``subdir`` (image
    folder) used, and for a posed layout its ``layout`` record, ``reason`` and the ``masks`` its
    frames name (view name -> file: nerfstudio ``mask_path``)."""

    folder: Path
    subdir: str | None
    selected: list[tuple[Path, str, str]]
    rejected: list[RejectedFile]
    detection: dict[str, Any]
    layout: dict | None = None
    reason: str = ""
    masks: dict[str, str] = field(default_factory=dict)


def find_inputs(given: Path, subdir: str | None, layout: str | None, images: str,
                kind: str) -> InputImages:
    """The images of ``given``: with ``layout`` (llff, colmap, nerfstudio) those the dataset
    holds in that layout, ``images`` choosing the folder (``auto`` or a name); otherwise the
    files of ``given/subdir`` (``subdir`` or, unless ``auto``, ``images``; else ``given``).
    ``kind`` ``auto`` becomes ``linear`` for a layout folder documented as linear (images_wb).
    """
    if layout is None:
        folder = resolve_input(Path(given), subdir or (None if images == "auto" else images))
        return InputImages(folder, subdir or (None if images == "auto" else images),
                           *select_files(folder, kind))
    found = layout_images(layout, Path(given), images)
    kind = found.kind if found.kind and kind == "auto" else kind
    return InputImages(found.root, found.folder, *select_paths(found.files, kind),
                       layout=found.record(), reason=found.reason,
                       masks={name: str(path) for name, path in found.masks.items()})
