"""From a camera set's frames and images to a model, its training rays and held-out pixels."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np
import torch

from seathru.errors import PipelineError
from seathru.nerf.config import TrainConfig, resolve_batch_rays
from seathru.nerf.model import SeaThruModel, scene_from_frames
from seathru.nerf.rays import RayBatch, RayDataset

log = logging.getLogger(__name__)


@dataclass
class PreparedRun:
    config: TrainConfig         # with batch_rays and colour_max resolved
    model: SeaThruModel
    data: RayDataset            # training rays
    test: RayBatch | None       # held-out pixels for the log's PSNR


def prepare_run(config: TrainConfig, cameras, train_frames, images, masks, test_frames=(),
                test_images=(), test_masks=(), device: torch.device | str = "cpu") -> PreparedRun:
    """The model and data of a training run.

    Args:
        config: the training settings (``batch_rays`` may be automatic).
        cameras: the camera set (``near``, ``far``, ``centre``, ``scale``).
        train_frames, images, masks: training frames, their linear images (H, W, 3) and
            validity masks (H, W) or None.
        test_frames, test_images, test_masks: held-out frames (may be empty).
        device: the torch device.

    Returns:
        the resolved config, the model on ``device``, the training rays and held-out pixels.

    Example::

        run = prepare_run(TrainConfig(), cameras, frames, images, masks, device="cpu")
        Trainer(run.model, run.data, run.test, device="cpu").run()
    """
    device = torch.device(device)
    config = resolve_batch_rays(config, device.type)
    data = RayDataset(train_frames, images, masks, device=device)
    if len(data) == 0:
        raise PipelineError("the training images have no valid pixel (check the masks)")
    if data.dropped_nonfinite:
        log.warning("%d training pixels are NaN/Inf and are left out", data.dropped_nonfinite)
    test = None
    if len(test_frames):
        test = RayDataset(test_frames, list(test_images), list(test_masks)).fixed_subset(
            config.eval_rays, config.seed + 3)
    rgb = data.rays.rgb
    sample = rgb[torch.randperm(len(rgb))[:200000].to(rgb.device)].float()
    high = float(torch.quantile(sample, 0.999))
    # Bright pixels need headroom above the sigmoid's default range of object colours.
    colour_max = max(config.field.colour_max, round(2.0 * high, 3))
    config = dataclasses.replace(config, field=dataclasses.replace(config.field,
                                                                  colour_max=colour_max))
    scene = scene_from_frames(train_frames, cameras.near, cameras.far, cameras.centre,
                              cameras.scale, rgb.mean(0).tolist())
    model = SeaThruModel(config, scene).to(device)
    return PreparedRun(config=config, model=model, data=data, test=test)


def seed_everything(seed: int) -> None:
    """Seed torch and numpy (the trainer's own generators are seeded from the config)."""
    torch.manual_seed(seed)
    np.random.seed(seed)
