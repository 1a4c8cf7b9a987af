"""seathru.io.renders: the render folder's files, videos and render_stats.json contract."""

from __future__ import annotations

import json

import numpy as np
import pytest

from seathru.errors import PipelineError
from seathru.io import renders
from seathru.io.cameras import CameraSet, Frame
from seathru.io.images import read_image, write_float_tiff


def _images(height: int, width: int, seed: int = 0, opacity: bool = True) -> dict:
    rng = np.random.default_rng(seed)
    out = {key: rng.random((height, width, 3), dtype=np.float32)
           for key in ("rgb", "restored", "direct", "backscatter")}
    out["depth"] = rng.random((height, width), dtype=np.float32) + 1.0
    if opacity:
        out["opacity"] = np.ones((height, width), np.float32)
    return out


def _stats(frames: list) -> dict:
    cameras = CameraSet(frames=[], near=0.1, far=2.0, centre=[1.0, 2.0, 3.0], scale=0.5)
    return renders.render_stats(frames, [], renders.display_record(2.0, "training images",
                                                                   (0.5, 1.5), "turbo"),
                                cameras, {}, {"downscale": 1})


def test_test_view_layout(tmp_path):
    images = _images(5, 7)
    shown = {name: np.full((5, 7, 3), 0.5, np.float32) for name in renders.COMPONENTS}
    renders.write_test_view(tmp_path, "v1", images, shown)
    folder = tmp_path / "test" / "v1"
    assert sorted(p.name for p in folder.iterdir()) == sorted(
        [f"{n}.tiff" for n in renders.COMPONENTS] + [f"{n}.png" for n in renders.COMPONENTS]
        + ["depth.tiff", "opacity.tiff"])
    np.testing.assert_array_equal(read_image(folder / "full.tiff"), images["rgb"])
    np.testing.assert_array_equal(read_image(renders.render_path(tmp_path, "v1", "depth")),
                                  images["depth"])
    assert read_image(folder / "restored.png") == pytest.approx(128 / 255)
    renders.write_test_view(tmp_path, "v2", _images(5, 7, opacity=False),
                            {**shown, "gt": shown["full"]})
    assert (tmp_path / "test" / "v2" / "gt.png").is_file()
    assert not (tmp_path / "test" / "v2" / "opacity.tiff").exists()


def test_videos_read_back_with_every_frame_and_odd_sizes_padded(tmp_path):
    def three_frames(folder):
        with renders.PathVideos(folder, fps=5.0) as videos:
            for level in (0.2, 0.5, 0.8):
                videos.write({name: np.full((9, 11, 3), level, np.float32)
                              for name in renders.VIDEO_OUTPUTS})
        return videos

    record = three_frames(tmp_path / "path").check(3)
    assert record == {name: {"file": f"path/{name}.mp4", "frames": 3}
                      for name in renders.VIDEO_OUTPUTS}
    assert renders.count_video_frames(tmp_path / "path" / "full.mp4") == 3
    with pytest.raises(PipelineError, match="reads back 3 of 4 frames"):
        three_frames(tmp_path / "short").check(4)
    (tmp_path / "not_a_video.mp4").write_bytes(b"nothing")
    assert renders.count_video_frames(tmp_path / "not_a_video.mp4") == 0


def test_summary_of_frame_times():
    frames = [renders.frame_record(f"v{i}", "test", seconds, _images(4, 6))
              for i, seconds in enumerate([0.5, 1.5])]
    summary = renders.summarise(frames)
    assert summary == {"count": 2, "seconds_per_frame": 1.0, "fps": 1.0, "resolution": [6, 4],
                       "total_seconds": 2.0}
    frames.append(renders.frame_record("p", "path", 1.0, _images(2, 3)))
    assert renders.summarise(frames)["resolution"] == [[3, 2], [6, 4]]
    assert renders.summarise([])["fps"] is None


def test_render_stats_round_trip(tmp_path):
    stats = _stats([renders.frame_record("v0", "test", 0.25, _images(4, 6))])
    renders.write_render_stats(tmp_path, stats)
    assert renders.read_render_stats(tmp_path) == stats
    assert stats["fps"] == 4.0 and stats["resolution"] == [6, 4]
    assert stats["normalisation"] == {"centre": [1.0, 2.0, 3.0], "scale": 0.5}


@pytest.mark.parametrize("damage", ["format", "missing", "not json", "absent"])
def test_malformed_render_stats_are_refused_naming_the_file(tmp_path, damage):
    stats = _stats([])
    path = tmp_path / renders.STATS_NAME
    if damage == "format":
        path.write_text(json.dumps({**stats, "format": "seathru-render-stats/0"}))
    elif damage == "missing":
        path.write_text(json.dumps({k: v for k, v in stats.items() if k != "display"}))
    elif damage == "not json":
        path.write_text("{")
    with pytest.raises(PipelineError, match=renders.STATS_NAME):
        renders.read_render_stats(tmp_path)


def test_exposure_references_spread_over_training_images_and_skip_unreadable(tmp_path, caplog):
    frames = []
    for i in range(30):
        name = f"im{i:02d}"
        if i != 0:  # the first one is missing on disk
            write_float_tiff(tmp_path / f"{name}.tiff", np.full((2, 2, 3), i, np.float32))
        frames.append(Frame(name=name, image=f"{name}.tiff", width=2, height=2, fx=1, fy=1,
                            cx=1, cy=1, c2w=np.eye(4).tolist(), near=0.1, far=1.0))
    cameras = CameraSet(frames=frames, near=0.1, far=1.0, root=tmp_path)
    values = [float(image[0, 0, 0]) for image in renders.exposure_references(cameras, 10)]
    assert len(values) == 9 and values == sorted(values) and values[-1] == 29
    assert "skipping im00" in caplog.text
    assert renders.read_view_photograph(cameras, frames[0]) == (None, None)
