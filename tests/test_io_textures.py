"""seathru.io.textures: the simulator's texture photographs from scikit-image's sample images."""

from __future__ import annotations

import logging
import shutil

import numpy as np

from seathru.io import textures
from seathru.sim.scene import TEXTURE_LAYOUT


def test_sample_textures_are_srgb_uint8_and_cover_the_scene_layout():
    loaded = textures.load_sample_textures()
    assert set(loaded) <= set(textures.SKIMAGE_TEXTURES)
    assert set(textures.SKIMAGE_TEXTURES) == set(TEXTURE_LAYOUT)
    for name, image in loaded.items():
        assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3, name
    if "coral" in loaded:
        assert loaded["coral"].shape[:2] == (700, 700)  # the crop


def test_missing_files_are_left_out_with_a_warning(tmp_path, caplog):
    source = textures.skimage_data_dir() / "coffee.png"
    shutil.copy(source, tmp_path / "coffee.png")
    with caplog.at_level(logging.WARNING):
        loaded = textures.load_sample_textures(tmp_path)
    assert list(loaded) == ["coffee"]
    assert "texture cat: chelsea.png not found" in caplog.text
    # RGB order, not OpenCV's BGR: coffee is reddish brown
    mean = loaded["coffee"].reshape(-1, 3).mean(axis=0)
    assert mean[0] > mean[2]
