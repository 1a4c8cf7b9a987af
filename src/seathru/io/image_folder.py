"""The photos of a dataset folder: which files ingest decodes, which it rejects and why.

Kinds (``seathru.io.raw.detect_kind``): ``raw``, ``linear`` (16-bit/float PNG or TIFF), ``srgb``
(JPEG, 8-bit PNG/TIFF). With ``kind='auto'`` a folder that mixes kinds (RAW+JPEG pairs) uses
the preferred one (raw, then linear, then srgb) and rejects the other files; an explicit
``linear`` or ``srgb`` decides the transfer of every encoded file.

:func:`find_inputs` is the whole choice for the ingest step: a folder (or its subfolder), or the
images a posed dataset holds in its own layout (``seathru.io.dataset_readers.layout_images``).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypedDict

from seathru.errors import PipelineError
from seathru.io.dataset_readers import layout_images, not_a_folder
from seathru.io.raw import KINDS, UNREAD_FORMATS, detect_kind
from seathru.io.video import VideoFrames, is_video


class RejectedFile(TypedDict):
    """A file left out, with the reason (a manifest ``rejected`` entry)."""

    file: str
    reason: str


def resolve_input(folder: Path, subdir: str | None) -> Path:
    """The image folder: ``folder/subdir`` (case-insensitive match of ``subdir``) or ``folder``."""
    if not folder.is_dir():
        raise PipelineError(f"--input {folder}: {not_a_folder(folder)}")
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


#: ``images`` value that reads every image under the dataset's folder, subfolders included
#: (a camera card's ``DCIM/100XXXXX``, ``101XXXXX``, ...).
EVERY_FOLDER = "all"


def _visible_files(folder: Path) -> list[Path]:
    return [path for path in sorted(folder.iterdir(), key=lambda p: p.name)
            if not path.name.startswith(".") and path.is_file()]


def _visible_folders(folder: Path) -> list[Path]:
    return [path for path in sorted(folder.iterdir(), key=lambda p: p.name)
            if not path.name.startswith(".") and path.is_dir() and not path.is_symlink()]


def _folders_below(folder: Path, depth: int | None = None) -> list[Path]:
    """The visible subfolders of ``folder`` (links to folders skipped), level by level, at most
    ``depth`` levels down (None: all)."""
    found: list[Path] = []
    level = _visible_folders(folder)
    while level and (depth is None or depth > 0):
        found += level
        level = [deeper for sub in level for deeper in _visible_folders(sub)]
        depth = None if depth is None else depth - 1
    return found


def image_subfolders(folder: Path, depth: int = 3, videos: bool = False
                     ) -> list[tuple[str, int]]:
    """The subfolders of ``folder`` that hold image files (with ``videos``, or videos), at most
    ``depth`` levels down (hidden folders skipped): ``(relative POSIX path, file count)`` in
    path order."""
    counts = [(sub.relative_to(folder).as_posix(),
               sum(1 for f in _visible_files(sub) if detect_kind(f) or (videos and is_video(f))))
              for sub in _folders_below(folder, depth)]
    return sorted((name, count) for name, count in counts if count)


#: Files and folders of the posed layouts (llff, nerfstudio, colmap): a folder holding one is
#: not read as a plain folder of images without being asked.
POSED_LAYOUT_MARKS = ("poses_bounds.npy", "transforms.json", "sparse")


def _only_image_subfolder(folder: Path) -> str | None:
    """The one subfolder of ``folder`` that holds images or videos (3 levels down at most,
    relative POSIX path), or None where none or several do, or where ``folder`` holds a posed
    layout's files (:data:`POSED_LAYOUT_MARKS`)."""
    if any((folder / mark).exists() for mark in POSED_LAYOUT_MARKS):
        return None
    holding = image_subfolders(folder, videos=True)
    return holding[0][0] if len(holding) == 1 else None


def every_image_file(folder: Path) -> list[tuple[Path, str]]:
    """Every file under ``folder``, subfolders included (hidden ones and links to folders
    skipped), as ``(path, name)`` in path order. The name is the file's stem; where a stem
    appears in more than one folder (cameras that restart their numbering), every file is
    named by its path instead, as ``seathru.io.dataset_readers.frame_names`` does
    (``DCIM/101GOPRO/G0010.JPG``: ``DCIM__101GOPRO__G0010``). A RAW and a JPEG of one shot
    share a stem in one folder, which is not a repeat."""
    files = [path for sub in [folder, *_folders_below(folder)] for path in _visible_files(sub)]
    files.sort(key=lambda path: path.relative_to(folder).as_posix())
    folders_of: dict[str, set[Path]] = {}
    for path in files:
        folders_of.setdefault(path.stem, set()).add(path.parent)
    by_path = any(len(parents) > 1 for parents in folders_of.values())
    return [(path, "__".join(path.relative_to(folder).with_suffix("").parts)
             if by_path else path.stem) for path in files]


def folder_files(folder: Path, every_folder: bool = False) -> list[tuple[Path, str]]:
    """Every file of ``folder`` as ``(path, stem)``, or with ``every_folder`` of its subfolders
    too (:func:`every_image_file`)."""
    return every_image_file(folder) if every_folder else [
        (path, path.stem) for path in _visible_files(folder)]


#: What ingest reads, as its messages name it.
READ_FORMATS = "RAW, JPEG, PNG, TIFF, HEIC, WebP"


def _unread_hint(files: list[tuple[Path, str]]) -> str:
    """What the files hold that ingest does not read, and what to do: '' where nothing."""
    counts: dict[str, int] = {}
    for path, _ in files:
        suffix = path.suffix.lower()
        if suffix in UNREAD_FORMATS:
            name = f"{UNREAD_FORMATS[suffix]} ({suffix})"
            counts[name] = counts.get(name, 0) + 1
    if not counts:
        return ""
    listed = ", ".join(f"{count} {name}" for name, count in counts.items())
    return (f"; it holds {listed} files, a format ingest does not read: convert them to JPEG, "
            f"or to 16-bit TIFF to keep their depth")


def select_files(folder: Path, kind: str, every_folder: bool = False,
                 files: list[tuple[Path, str]] | None = None
                 ) -> tuple[list[tuple[Path, str, str]], list[RejectedFile], dict[str, Any]]:
    """Images of ``folder`` (with ``every_folder``, of its subfolders too:
    :func:`every_image_file`) to decode as ``(path, name, kind)``, rejected files and what was
    detected (:func:`select_paths`; names are file stems). ``files``: the folder's listing
    (:func:`folder_files`) where the caller has it already.

    Raises:
        PipelineError: no image file found (naming the subfolders that hold some).
    """
    files = folder_files(folder, every_folder) if files is None else files
    if not any(detect_kind(path) for path, _ in files):
        with_images = image_subfolders(folder)
        listed = ", ".join(f"{name} ({count})" for name, count in with_images[:8])
        hint = (f"; subfolders with images: {listed}{' ...' if len(with_images) > 8 else ''}"
                f" (choose one with the sheet's options ingest.images=<subfolder>, take them "
                f"all with ingest.images={EVERY_FOLDER}, or use the sheet's source llff, "
                f"colmap or nerfstudio for those layouts)" if with_images else "")
        raise PipelineError(f"{folder}: no image files ({READ_FORMATS}) found"
                            f"{_unread_hint(files)}{hint}")
    return select_paths(files, kind)


def select_paths(files: list[tuple[Path, str]], kind: str
                 ) -> tuple[list[tuple[Path, str, str]], list[RejectedFile], dict[str, Any]]:
    """Images to decode as ``(path, name, kind)``, rejected files and what was detected.

    ``files``: ``(path, name)`` in the order names are given priority (a duplicate name, e.g.
    IMG_1.dng and IMG_1.DNG, rejects the later file, and so does a byte-for-byte copy of a
    file already taken: one photograph twice is two cameras at one place, which COLMAP cannot
    pose). The detection dict holds ``kind``,
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
        raise PipelineError(f"no image files ({READ_FORMATS}){_unread_hint(files)} among the "
                            f"{len(files)} given ({listed})")

    if kind == "auto":
        dataset_kind = next(k for k in KINDS if k in counts)
        note = f"detected {dataset_kind} from " + ", ".join(f"{v} {k}" for k, v in counts.items())
    else:
        dataset_kind = kind
        note = f"requested {kind}; found " + ", ".join(f"{v} {k}" for k, v in counts.items())
    selected: list[tuple[Path, str, str]] = []
    rejected: list[RejectedFile] = []
    taken: dict[str, str] = {}
    usable_paths = [path for path, _, detected in candidates
                    if _usable(detected, dataset_kind, kind)]
    originals = _originals(usable_paths)
    for path, name, detected in candidates:
        if not _usable(detected, dataset_kind, kind):
            rejected.append({"file": path.name, "reason": (
                f"{detected} file ({path.suffix}) in a dataset of kind {dataset_kind}; "
                f"only {dataset_kind} files are used (pass --kind to choose)")})
            continue
        if name in taken:
            rejected.append({"file": path.name, "reason": (
                f"duplicate image name {name!r}: {taken[name]} already provides it")})
            continue
        original = originals.get(path, path)
        if original != path:
            rejected.append({"file": path.name, "reason": (
                f"a byte-for-byte copy of {original.name}, which is used; the same "
                f"photograph twice cannot be posed (remove the copy)")})
            continue
        taken[name] = path.name
        selected.append((path, name, dataset_kind))
    detection = {"kind": dataset_kind, "requested": kind, "counts": counts, "note": note,
                 "ignored": ignored}
    return selected, rejected, detection


def _usable(detected: str, dataset_kind: str, kind: str) -> bool:
    if kind == "auto" or dataset_kind == "raw":
        return detected == dataset_kind
    return detected != "raw"  # an explicit linear/srgb kind decides the transfer of any file


def _originals(paths: list[Path]) -> dict[Path, Path]:
    """Each of ``paths`` whose bytes another one has too -> the one of them kept: the shortest
    file name, then the first (``IMG_2.png`` before ``IMG_2 (1).png``)."""
    groups: dict[str, list[Path]] = {}
    for path in paths:
        groups.setdefault(file_digest(path), []).append(path)
    return {path: min(group, key=lambda p: len(p.name))
            for group in groups.values() if len(group) > 1 for path in group}


def file_digest(path: Path) -> str:
    """SHA-1 of the file's bytes; a file that cannot be read gets its path instead (its
    decoding then says what is wrong)."""
    try:
        with open(path, "rb") as handle:
            return hashlib.file_digest(handle, "sha1").hexdigest()
    except OSError:
        return f"unreadable:{path}"


@dataclass
class InputImages:
    """What the ingest step decodes: ``selected`` ``(path, name, kind)``, ``rejected`` files,
    the ``detection`` dict (:func:`select_paths`), the ``folder`` read, the ``subdir`` (image
    folder) used, and for a posed layout its ``layout`` record, ``reason`` and the ``masks`` its
    frames name (view name -> file: nerfstudio ``mask_path``). A folder of videos and no
    photographs has ``videos`` ``(path, name)`` and nothing ``selected`` until the ingest step
    stages their frames (``seathru.io.video``, recorded in ``video``)."""

    folder: Path
    subdir: str | None
    selected: list[tuple[Path, str, str]]
    rejected: list[RejectedFile]
    detection: dict[str, Any]
    layout: dict | None = None
    reason: str = ""
    masks: dict[str, str] = field(default_factory=dict)
    videos: list[tuple[Path, str]] = field(default_factory=list)
    video: VideoFrames | None = None

    def with_video(self, video: VideoFrames | None) -> "InputImages":
        """These inputs with the frames staged from their ``videos`` selected (as sRGB)."""
        if video is not None:
            self.selected = [(path, name, "srgb") for path, name in video.files]
            self.video = video
        return self


def find_inputs(given: Path, subdir: str | None, layout: str | None, images: str,
                kind: str) -> InputImages:
    """The images of ``given``: with ``layout`` (llff, colmap, nerfstudio) those the dataset
    holds in that layout, ``images`` choosing the folder (``auto`` or a name); otherwise the
    files of ``given/subdir`` (``subdir`` or, unless ``auto`` or :data:`EVERY_FOLDER`,
    ``images``; else ``given``), and with ``images`` :data:`EVERY_FOLDER` those of its
    subfolders too.
    With ``images`` ``auto``, a folder holding no images of its own but one subfolder that does
    (a camera card's ``DCIM/100GOPRO``) gives that subfolder's (``reason`` says so).
    ``kind`` ``auto`` becomes ``linear`` for a layout folder documented as linear (images_wb).
    A folder of videos and no photographs gives their frames (:class:`InputImages` ``videos``).
    """
    if layout is None:
        every_folder = images == EVERY_FOLDER
        named = subdir or (None if images in ("auto", EVERY_FOLDER) else images)
        folder = resolve_input(Path(given), named)
        files = folder_files(folder, every_folder)
        reason = ""
        if named is None and images == "auto" and not any(
                detect_kind(path) or is_video(path) for path, _ in files):
            only = _only_image_subfolder(folder)
            if only is not None:
                # a camera card (DCIM/100GOPRO): one folder of images is what was meant
                named, folder = only, folder / only
                files = folder_files(folder)
                reason = (f"ingest.images auto: {only}, the only subfolder with images "
                          f"(ingest.images=all to take every subfolder)")
        videos = [(path, name) for path, name in files if is_video(path)]
        if videos and not any(detect_kind(path) for path, _ in files):
            found = _video_inputs(folder, named, files, videos, kind)
            found.reason = reason
            return found
        photos = [(path, name) for path, name in files if not is_video(path)]
        found = InputImages(folder, named, *select_files(folder, kind, every_folder, photos),
                            reason=reason)
        found.rejected += [{"file": path.name, "reason": (
            "a video beside photographs: the photographs are used (give the video a dataset "
            "row of its own to take frames from it)")} for path, _ in videos]
        return found
    found = layout_images(layout, Path(given), images)
    kind = found.kind if found.kind and kind == "auto" else kind
    return InputImages(found.root, found.folder, *select_paths(found.files, kind),
                       layout=found.record(), reason=found.reason,
                       masks={name: str(path) for name, path in found.masks.items()})


def _video_inputs(folder: Path, named: str | None, files: list[tuple[Path, str]],
                  videos: list[tuple[Path, str]], kind: str) -> InputImages:
    if kind not in ("auto", "srgb"):
        raise PipelineError(f"{folder}: holds videos, whose frames are 8-bit sRGB, but "
                            f"ingest.kind is {kind}; set ingest.kind to auto or srgb")
    ignored = [path.name for path, _ in files if not is_video(path)]
    detection = {"kind": "srgb", "requested": kind, "counts": {"video": len(videos)},
                 "note": f"{len(videos)} video(s), no photographs: the sharpest frame of every "
                         "interval is taken (ingest.video_interval, ingest.video_max_frames)",
                 "ignored": ignored}
    return InputImages(folder, named, [], [], detection, videos=videos)
