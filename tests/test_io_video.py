"""Tests for seathru.io.video: dive videos as photo sets (the sharpest frame of each interval),
through the ingest step."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from seathru.errors import PipelineError
from seathru.io import video
from seathru.io.stored_views import read_stored_codes, read_stored_views
from tests.test_ingest import run_ingest

FPS = 10.0
SIZE = (64, 48)   # width, height


def _texture(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = rng.integers(30, 220, (SIZE[1] // 4, SIZE[0] // 4, 3), dtype=np.uint8)
    return cv2.resize(small, SIZE, interpolation=cv2.INTER_NEAREST)


def _write_video(path: Path, sharp: set[int], frames: int = 30) -> None:
    """``frames`` frames of one texture, blurred except at the indices in ``sharp``."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS, SIZE)
    assert writer.isOpened()
    texture = _texture(0)
    blurred = cv2.GaussianBlur(texture, (0, 0), 3.0)
    for index in range(frames):
        writer.write(texture if index in sharp else blurred)
    writer.release()


@settings(max_examples=100, deadline=None)
@given(scores=st.lists(st.floats(0.0, 100.0), min_size=1, max_size=60),
       window=st.integers(1, 20))
def test_one_frame_per_window_the_highest_scoring(scores, window):
    scores = np.array(scores)
    chosen = video.sharpest_per_interval(scores, window)
    assert len(chosen) == -(-len(scores) // window)
    for number, index in enumerate(chosen):
        start = number * window
        part = scores[start:start + window]
        assert start <= index < start + len(part)
        assert scores[index] == part.max()


def test_blur_lowers_the_sharpness():
    texture = _texture(1)
    scores = [video.sharpness(cv2.GaussianBlur(texture, (0, 0), sigma)) if sigma else
              video.sharpness(texture) for sigma in (0, 1.0, 2.0, 4.0)]
    assert scores == sorted(scores, reverse=True)
    assert scores[0] > 3 * scores[-1]


def test_the_sharpest_frame_of_each_second_is_staged(tmp_path):
    _write_video(tmp_path / "dive.avi", sharp={4, 13, 27})
    staged = tmp_path / "staged"
    staged.mkdir()
    frames = video.stage_frames([(tmp_path / "dive.avi", "dive")], staged, 1.0, 100)
    assert [name for _, name in frames.files] == ["dive_000004", "dive_000013", "dive_000027"]
    assert all(path.is_file() and path.parent == staged for path, _ in frames.files)
    assert frames.frames["dive_000013"]["time_s"] == pytest.approx(1.3)
    assert frames.videos[0]["frames"] == 30 and frames.videos[0]["taken"] == 3
    image = cv2.imread(str(frames.files[0][0]))
    assert image.shape == (SIZE[1], SIZE[0], 3) and image.dtype == np.uint8


def test_the_interval_widens_to_keep_within_the_frame_limit(tmp_path):
    _write_video(tmp_path / "dive.avi", sharp={7, 22})
    indices, scores, fps, interval = video.choose_frames(tmp_path / "dive.avi", 0.1, 2)
    assert len(scores) == 30 and fps == pytest.approx(FPS)
    assert interval == pytest.approx(1.5) and indices == [7, 22]


def test_a_folder_of_videos_is_ingested_as_their_frames(tmp_path):
    folder = tmp_path / "dive"
    folder.mkdir()
    _write_video(folder / "GX010001.avi", sharp={3, 12, 25})
    (folder / "notes.txt").write_text("site B")
    out = tmp_path / "ingest"
    manifest = run_ingest("--input", folder, "--out", out, "--workers", 1,
                          "--video-interval", 1.0)
    names = [image["name"] for image in manifest["images"]]
    assert names == ["GX010001_000003", "GX010001_000012", "GX010001_000025"]
    assert all(image["source"] == "GX010001.avi" and image["kind"] == "srgb"
               for image in manifest["images"])
    assert manifest["images"][1]["video_frame"]["index"] == 12
    assert Path(manifest["images"][0]["source_path"]) == (folder / "GX010001.avi").resolve()
    assert manifest["input"]["videos"][0]["taken"] == 3
    assert manifest["input"]["ignored"] == ["notes.txt"]
    assert all((out / "linear" / f"{name}.tiff").is_file() for name in names)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".ingest.video-")]
    # the evaluation compares renders with the stored image: here the video's own frame
    view = read_stored_views(out)["GX010001_000012"]
    assert view.video_frame == 12 and view.encoding == "srgb"
    assert view.file_name == "GX010001_000012"   # the protocol sorts frames by it
    codes = read_stored_codes(view)
    expected = cv2.cvtColor(video.read_video_frame(folder / "GX010001.avi", 12), cv2.COLOR_BGR2RGB)
    assert codes.dtype == np.uint8 and np.array_equal(codes, expected)
    assert not np.array_equal(codes, cv2.cvtColor(video.read_video_frame(
        folder / "GX010001.avi", 11), cv2.COLOR_BGR2RGB))
    with pytest.raises(PipelineError, match="no frame 30"):
        video.read_video_frame(folder / "GX010001.avi", 30)


def test_a_video_beside_photographs_is_rejected_with_the_reason(tmp_path):
    folder = tmp_path / "dive"
    folder.mkdir()
    for index in range(3):
        cv2.imwrite(str(folder / f"IMG_{index}.png"), _texture(index + 2))
    _write_video(folder / "clip.avi", sharp={1})
    manifest = run_ingest("--input", folder, "--out", tmp_path / "ingest", "--workers", 1)
    assert [image["name"] for image in manifest["images"]] == ["IMG_0", "IMG_1", "IMG_2"]
    reasons = {r["file"]: r["reason"] for r in manifest["rejected"]}
    assert "photographs are used" in reasons["clip.avi"]
    assert "videos" not in manifest["input"]


def test_videos_that_cannot_be_used_say_why(tmp_path):
    folder = tmp_path / "dive"
    folder.mkdir()
    _write_video(folder / "clip.avi", sharp={1})
    with pytest.raises(PipelineError, match="ingest.kind is linear"):
        run_ingest("--input", folder, "--out", tmp_path / "a", "--kind", "linear")
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "GOPR0001.MP4").write_bytes(b"\x00not a video" * 100)
    with pytest.raises(PipelineError, match="GOPR0001.MP4: OpenCV"):
        run_ingest("--input", broken, "--out", tmp_path / "b", "--workers", 1)
    assert not (tmp_path / "b").exists()


def test_frames_read_in_time_order_cost_one_pass_and_earlier_ones_start_over(tmp_path,
                                                                           monkeypatch):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS, SIZE)
    for index in range(20):  # each frame's grey level names it
        writer.write(np.full((SIZE[1], SIZE[0], 3), 10 * index + 20, np.uint8))
    writer.release()
    other = tmp_path / "other.avi"
    _write_video(other, sharp=set(), frames=5)

    def level(frame: np.ndarray) -> int:
        return int(round((float(frame.mean()) - 20) / 10))

    decoded = []
    every_frame = video._frames

    def counted(where):
        for frame in every_frame(where):
            decoded.append(where)
            yield frame

    monkeypatch.setattr(video, "_frames", counted)
    assert [level(video.read_video_frame(path, i)) for i in (3, 7, 12)] == [3, 7, 12]
    assert len(decoded) == 13                           # one pass, not 4 + 8 + 13 frames
    assert level(video.read_video_frame(path, 2)) == 2  # an earlier frame starts over
    assert len(decoded) == 16
    video.read_video_frame(other, 1)                    # another video, then back
    assert level(video.read_video_frame(path, 5)) == 5
    with pytest.raises(PipelineError, match="has no frame 25"):
        video.read_video_frame(path, 25)
    assert level(video.read_video_frame(path, 0)) == 0
