"""The simulator's texture photographs: sample images shipped inside the scikit-image wheel.

Read straight from the installed package (never downloaded), as sRGB ``uint8`` ``(H, W, 3)``
arrays keyed by the texture names of ``seathru.sim.scene.TEXTURE_LAYOUT``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

log = logging.getLogger(__name__)

# Texture name -> (file in skimage/data, crop (rows, columns) or None). Only files that ship
# inside the scikit-image wheel; a missing file falls back to procedural noise.
SKIMAGE_TEXTURES = {
    "seabed_a": ("gravel.png", None),
    "seabed_b": ("moon.png", None),
    "algae": ("grass.png", None),
    "rock": ("moon.png", None),
    "gravel": ("gravel.png", None),
    "coffee": ("coffee.png", None),
    "astronaut": ("astronaut.png", None),
    "coral": ("retina.jpg", (slice(350, 1050), slice(350, 1050))),
    "cat": ("chelsea.png", None),
    "rocket": ("rocket.jpg", None),
}


def skimage_data_dir() -> Path:
    """The folder of scikit-image's bundled sample images."""
    import skimage.data

    return Path(skimage.data.__file__).parent


def load_sample_textures(data_dir: Path | None = None) -> dict[str, np.ndarray]:
    """sRGB ``uint8`` textures from ``data_dir`` (default: scikit-image's sample images); names
    whose file is absent are left out (the scene then uses procedural noise) with a warning."""
    data_dir = skimage_data_dir() if data_dir is None else Path(data_dir)
    textures = {}
    for name, (filename, crop) in SKIMAGE_TEXTURES.items():
        image = cv2.imread(str(data_dir / filename), cv2.IMREAD_COLOR)
        if image is None:
            log.warning("texture %s: %s not found in %s, using procedural noise", name, filename,
                        data_dir)
            continue
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
        textures[name] = image[crop] if crop is not None else image
    return textures
