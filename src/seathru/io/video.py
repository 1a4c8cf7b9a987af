"""Dive videos as photo sets: the sharpest frame of every interval, staged for the ingest step.

A folder that holds video files (:data:`VIDEO_SUFFIXES`) and no photographs is ingested from
its videos: each is read once to score every frame's sharpness (the variance of the Laplacian of
a grey copy, the usual focus measure: motion blur and defocus lower it), then once more to write
the sharpest frame of each ``interval`` seconds as a lossless 8-bit PNG in a staging folder the
ingest step decodes like any sRGB photograph and then removes. Frame names are
``<video stem>_<frame index, 6 digits>``, so they sort in time order and the every-8th held-out
split spreads over the dive. Decoding is OpenCV's (FFmpeg); frames come out in the orientation
the file's rotation metadata gives.

The manifest keeps where each frame came from (:class:`VideoFrameRecord`) and a summary per
video (:class:`VideoRecord`).
"""

from __future__ import annotations

import contextlib
import logging
import math
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TypedDict

import cv2
import numpy as np

from seathru.errors import PipelineError

log = logging.getLogger(__name__)

VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".mts", ".m2ts", ".webm")
#: long edge of the grey copy the sharpness is scored on: a 4K frame is scored as fast as a
#: small one, and sensor noise weighs less than at full size
SHARPNESS_EDGE = 640


class VideoFrameRecord(TypedDict):
    """Where a frame of the manifest came from (``images[].video_frame``)."""

    video: str                  # the video file's name
    index: int                  # frame number in the video, from 0
    time_s: float               # index / the video's frame rate
    sharpness: float            # variance of the Laplacian of the grey copy


class VideoRecord(TypedDict):
    """One video of the input (manifest ``input.videos``)."""

    file: str
    fps: float
    frames: int                 # frames decoded
    duration_s: float
    interval_s: float           # one frame taken per interval (widened to fit max_frames)
    taken: int


@dataclass
class VideoFrames:
    """The frames staged from a folder's videos: ``files`` ``(path, name)`` to decode as sRGB,
    ``frames`` and ``sources`` (the video's resolved path) by frame name, ``videos`` one record
    each."""

    files: list[tuple[Path, str]]
    frames: dict[str, VideoFrameRecord]
    sources: dict[str, str]
    videos: list[VideoRecord]


def is_video(path: Path) -> bool:
    return path.suffix.lower() in VIDEO_SUFFIXES


def sharpness(frame: np.ndarray) -> float:
    """Variance of the Laplacian of a grey copy of ``frame`` ((H, W, 3) BGR or (H, W), 8-bit),
    its long edge brought down to :data:`SHARPNESS_EDGE`: higher is sharper."""
    grey = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    scale = SHARPNESS_EDGE / max(grey.shape[:2])
    if scale < 1.0:
        grey = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def _frames(path: Path) -> Iterator[np.ndarray]:
    capture = cv2.VideoCapture(str(path))
    try:
        if not capture.isOpened():
            raise PipelineError(
                f"{path}: OpenCV (FFmpeg) cannot open this video; convert it, e.g. "
                f"'ffmpeg -i {path.name} -c:v libx264 {path.stem}.mp4', or extract its frames "
                "to images")
        while True:
            ok, frame = capture.read()
            if not ok:
                return
            yield frame
    finally:
        capture.release()


class _ForwardReader:
    """One video decoded in order, left open between reads: frames asked for in time order
    (the held-out and the training frames, by name) cost one pass over the video, not one
    partial pass each."""

    def __init__(self, path: Path):
        self.path, self.frames, self.next_index = path, _frames(path), 0

    def read(self, index: int) -> np.ndarray | None:
        for frame in self.frames:
            self.next_index += 1
            if self.next_index - 1 == index:
                return frame
        return None

    def close(self) -> None:
        self.frames.close()


_reader: _ForwardReader | None = None


def read_video_frame(path: Path, index: int) -> np.ndarray:
    """Frame ``index`` (from 0) of the video at ``path``, (H, W, 3) BGR uint8, decoded in order
    (seeking by frame number is not exact in every container). The video is kept open: a later
    frame of the same video continues from here; an earlier one, or another video, starts over.

    Raises:
        PipelineError: the video cannot be opened or is shorter than ``index + 1`` frames.
    """
    global _reader
    path = Path(path)
    if _reader is None or _reader.path != path or _reader.next_index > index:
        if _reader is not None:
            _reader.close()
        _reader = _ForwardReader(path)
    frame = _reader.read(index)
    if frame is None:
        _reader.close()
        _reader = None
        raise PipelineError(f"{path}: has no frame {index}; the video changed since ingest")
    return frame


def _property(path: Path, which: int) -> float:
    capture = cv2.VideoCapture(str(path))
    try:
        value = float(capture.get(which) or 0.0)
    finally:
        capture.release()
    return value if math.isfinite(value) else 0.0


def _frame_rate(path: Path) -> float:
    fps = _property(path, cv2.CAP_PROP_FPS)
    return fps if fps > 0 else 30.0


def sharpest_per_interval(scores: np.ndarray, window: int) -> list[int]:
    """Indices of the highest score in each run of ``window`` consecutive frames (the last run
    may be shorter), in order.

    Example::

        sharpest_per_interval(np.array([1., 5., 2., 2., 9., 1., 3.]), 3)   # [1, 4, 6]
    """
    window = max(1, int(window))
    return [start + int(np.argmax(scores[start:start + window]))
            for start in range(0, len(scores), window)]


def choose_frames(path: Path, interval_s: float, max_frames: int
                  ) -> tuple[list[int], np.ndarray, float, float]:
    """The frames of one video to take: the sharpest of every ``interval_s`` seconds, the
    interval widened so that at most ``max_frames`` are taken.

    Returns:
        ``(indices, scores, fps, interval_s used)``; scores ``(frames,)`` (:func:`sharpness`).

    Raises:
        PipelineError: the video cannot be opened or holds no frame.
    """
    fps = _frame_rate(path)
    scores = np.array([sharpness(frame) for frame in _frames(path)])
    if scores.size == 0:
        raise PipelineError(f"{path}: no frame could be decoded (empty or damaged video)")
    interval_s = max(interval_s, scores.size / fps / max(1, max_frames))
    window = max(1, round(interval_s * fps))
    if math.ceil(scores.size / window) > max_frames:
        window = math.ceil(scores.size / max_frames)
    return sharpest_per_interval(scores, window), scores, fps, window / fps


def stage_frames(videos: list[tuple[Path, str]], staging: Path, interval_s: float,
                 max_frames: int) -> VideoFrames:
    """Write the chosen frames of ``videos`` (``(path, name)``, name = the stem the frames are
    named after) into ``staging`` as 8-bit PNGs; ``max_frames`` is shared between the videos in
    proportion to their length."""
    lengths = [max(1.0, _property(path, cv2.CAP_PROP_FRAME_COUNT)) for path, _ in videos]
    files, frames, sources, records = [], {}, {}, []
    for (path, stem), length in zip(videos, lengths):
        share = max(1, int(max_frames * length / max(sum(lengths), 1.0)))
        indices, scores, fps, used = choose_frames(path, interval_s, share)
        wanted = set(indices)
        for index, frame in enumerate(_frames(path)):
            if index > indices[-1]:
                break
            if index not in wanted:
                continue
            name = f"{stem}_{index:06d}"
            target = staging / f"{name}.png"
            if not cv2.imwrite(str(target), frame):
                raise PipelineError(f"{target}: could not write a staged video frame "
                                    "(disk full?)")
            files.append((target, name))
            frames[name] = {"video": path.name, "index": index, "time_s": index / fps,
                            "sharpness": float(scores[index])}
            sources[name] = str(path.resolve())
        records.append({"file": path.name, "fps": fps, "frames": int(scores.size),
                        "duration_s": scores.size / fps, "interval_s": used,
                        "taken": len(indices)})
        log.info("%s: %d frames at %.3g fps; took the sharpest of every %.3g s: %d frames",
                 path.name, scores.size, fps, used, len(indices))
    return VideoFrames(files, frames, sources, records)


@contextlib.contextmanager
def staged_video_frames(videos: list[tuple[Path, str]], next_to: Path, interval_s: float,
                        max_frames: int) -> Iterator[VideoFrames | None]:
    """:func:`stage_frames` into a hidden folder beside ``next_to`` (the step's output, on the
    same disk), removed on exit; None when there are no videos."""
    if not videos:
        yield None
        return
    next_to.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f".{next_to.name}.video-",
                                     dir=next_to.parent) as staging:
        yield stage_frames(videos, Path(staging), interval_s, max_frames)
