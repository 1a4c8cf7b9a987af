"""Quality against training time: the model measured on whole held-out images during training.

The log's held-out PSNR (``train_log.csv``) is measured on a sample of pixels; a snapshot
renders every held-out view whole, at a reduced resolution, so the numbers can be put beside
the final evaluation and, for simulated dives, the restored views beside the clean truth (the
evaluate step does that from the renders the train step stores).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from seathru.nerf.inference import render_frame
from seathru.nerf.losses import psnr_from_mse
from seathru.radiometry.linearise import block_average


@dataclass
class QualitySnapshots:
    """Held-out frames and their images at ``downscale``; :meth:`measure` adds one row."""

    frames: list
    images: list[np.ndarray]
    downscale: int = 4
    rows: list[dict] = field(default_factory=list)
    renders: dict[int, dict[str, np.ndarray]] = field(default_factory=dict)  # step -> arrays

    @classmethod
    def from_full_images(cls, frames, images, downscale: int) -> "QualitySnapshots":
        return cls(list(frames), [block_average(image, downscale).astype(np.float32)
                                          for image in images], downscale)

    def measure(self, model, step: int, elapsed_s: float) -> dict:
        """Render every held-out view and record PSNR and the water at this point.

        Returns:
            the row: ``step``, ``elapsed_s``, ``test_psnr_images`` (all views pooled), the
            medium mode and its global parameters (normalised units).
        """
        squared, count = 0.0, 0
        rendered = {}
        for frame, target in zip(self.frames, self.images):
            out = render_frame(model, frame, downscale=self.downscale)
            squared += float(((out["rgb"] - target) ** 2).sum())
            count += target.size
            for key in ("rgb", "restored"):
                rendered[f"{frame.name}.{key}"] = out[key].astype(np.float16)
        water = model.water_parameters()
        row = {"step": int(step), "elapsed_s": round(float(elapsed_s), 3),
               "test_psnr_images": psnr_from_mse(squared / max(count, 1)) if count else None,
               "medium": water["mode"],
               **{f"{key}_{'rgb'[i]}": float(water[key][i])
                  for key in ("sigma_attn", "sigma_bs", "c_med") for i in range(3)}}
        self.rows.append(row)
        self.renders[int(step)] = rendered
        return row
