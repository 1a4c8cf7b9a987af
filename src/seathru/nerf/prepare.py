"""From a camera set's frames and images to a model, its training rays and held-out pixels."""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch

from seathru.errors import PipelineError
from seathru.nerf.capacity import choose_capacity, measure_scene, steps_for_passes
from seathru.nerf.config import TrainConfig, resolve_batch_rays
from seathru.nerf.model import SeaThruModel, scene_from_frames
from seathru.nerf.rays import RayBatch, RayDataset, depth_rays, frame_rays
from seathru.radiometry.deblur import deblurred
from seathru.radiometry.linearise import block_average
from seathru.radiometry.open_water import open_water_mask

log = logging.getLogger(__name__)


@dataclass
class PreparedRun:
    config: TrainConfig         # with batch_rays, steps (passes), capacity, colour_max resolved
    model: SeaThruModel
    data: RayDataset            # training rays
    test: RayBatch | None       # held-out pixels for the log's PSNR
    capacity: dict = dataclasses.field(default_factory=dict)  # the auto choice and evidence


def prepare_run(config: TrainConfig, cameras, train_frames, images, masks, test_frames=(),
                test_images=(), test_masks=(), device: torch.device | str = "cpu",
                track_change: dict | None = None, sparse_points=None) -> PreparedRun:
    """The model and data of a training run.

    Args:
        config: the training settings (``batch_rays`` may be automatic).
        cameras: the camera set (``near``, ``far``, ``centre``, ``scale``).
        train_frames, images, masks: training frames, their linear images (H, W, 3) and
            validity masks (H, W) or None.
        test_frames, test_images, test_masks: held-out frames (may be empty).
        device: the torch device.
        track_change: how the input colour changes with range along COLMAP tracks
            (``seathru.io.tracks.input_colour_change``), kept in the scene as evidence of
            water for the medium decision; None when there are no tracks.
        sparse_points: observations of sparse 3D points in the training views (``frames``
            (N,) indices into ``cameras.frames``, ``points`` (N, 3) normalised, ``observed``
            (N, 3) colours: ``seathru.io.tracks.training_depth_observations``) for the
            sparse-depth loss, or None.

    Returns:
        the resolved config (``passes`` turned into ``steps``; ``preset=auto`` into a capacity
        level, :func:`seathru.nerf.capacity.choose_capacity`), the model on ``device``, the
        training rays, held-out pixels and the capacity record.

    Example::

        run = prepare_run(TrainConfig(), cameras, frames, images, masks, device="cpu")
        Trainer(run.model, run.data, run.test, device="cpu").run()
    """
    device = torch.device(device)
    config = resolve_batch_rays(config, device.type)
    water_masks, water_share, in_view = open_water_in_view(config, images, masks)
    data = RayDataset(train_frames, images, masks, device=device,
                      open_water=water_masks if in_view else None,
                      deblurred=deblurred_images(config, train_frames, images))
    if len(data) == 0:
        raise PipelineError("the training images have no valid pixel (check the masks)")
    if sparse_points is not None and config.loss.sparse_depth_weight > 0:
        data.depth_rays = depth_rays(cameras.frames, sparse_points.frames, sparse_points.points,
                                     sparse_points.observed, device)
        log.info("sparse depth: %d rays towards COLMAP points",
                 0 if data.depth_rays is None else len(data.depth_rays))
    if data.dropped_nonfinite:
        log.warning("%d training pixels are NaN/Inf and are left out", data.dropped_nonfinite)
    test = None
    if len(test_frames):
        test = RayDataset(test_frames, list(test_images), list(test_masks)).fixed_subset(
            config.eval_rays, config.seed + 3)
    rgb = data.rgb
    # int32: the same permutation and random stream as int64, in half the memory
    draws = torch.randperm(len(rgb), dtype=torch.int32)[:200000].long()
    sample = rgb[draws.to(rgb.device)].float()
    high = float(torch.quantile(sample, 0.999))
    # Bright pixels need headroom above the sigmoid's default range of object colours.
    colour_max = max(config.field.colour_max, round(2.0 * high, 3))
    config = dataclasses.replace(config, field=dataclasses.replace(config.field,
                                                                  colour_max=colour_max))
    veiling = veiling_light_estimate(images, masks) if config.medium.veiling_light_init \
        else None
    scene = scene_from_frames(train_frames, cameras.near, cameras.far, cameras.centre,
                              cameras.scale, veiling if veiling is not None
                              else rgb.mean(0).tolist())
    scene["open_water_image_share"] = water_share
    if track_change is not None:
        scene["track_colour_change"] = track_change
    scene["open_water_direction_spread"] = open_water_direction_spread(
        train_frames, images, water_masks) if in_view else 0.0
    if config.passes > 0:
        config = dataclasses.replace(config, steps=steps_for_passes(
            config.passes, len(data), config.batch_rays))
    config, capacity = choose_capacity(
        config, measure_scene(train_frames, scene["box_min"], scene["box_max"], len(data)),
        device.type)
    if capacity.get("reason"):
        log.info("capacity %s", capacity["reason"])
    model = SeaThruModel(config, scene).to(device)
    return PreparedRun(config=config, model=model, data=data, test=test, capacity=capacity)


def veiling_light_estimate(images, masks=None, block: int = 4, share: float = 0.1,
                           max_spread: float = 0.1) -> list[float] | None:
    """A first guess of the water's veiling light ``c_med`` from the training images.

    Open water and the far, hazy seabed are the smoothest parts of a dive photograph and their
    colour tends to the veiling light (``I -> c_med`` as the range grows); textured near
    surfaces are not. The median colour of the smoothest ``share`` of (``block``-averaged,
    valid) pixels over all images is the guess: a better start for the water than the mean
    image colour, which lets the object field explain open water with floating surfaces.

    Args:
        images: linear images (H, W, 3); masks: matching validity masks (H, W) or None.
        block: averaging block (noise suppression) before the gradients are taken.
        share: the share of smoothest pixels used.
        max_spread: the smooth pixels must agree on one colour: their median absolute
            deviation, relative to the median, below this in every channel. Smooth patches of a
            clear-water seabed differ in colour (measured 13-21% on simulated clear dives,
            0.4-1.5% on the open water of the survey demo); their median is no veiling light.

    Returns:
        the colour (3 floats), or None when the images are too small or the smoothest regions
        do not share one colour.
    """
    colours, smoothness = [], []
    for index, image in enumerate(images):
        small = torch.from_numpy(block_average(image[..., :3], block))
        if small.shape[0] < 3 or small.shape[1] < 3:
            continue
        dx = (small[1:-1, 2:] - small[1:-1, :-2]).abs().sum(-1)
        dy = (small[2:, 1:-1] - small[:-2, 1:-1]).abs().sum(-1)
        level = small[1:-1, 1:-1].sum(-1).clamp_min(1e-4)
        valid = torch.ones_like(level, dtype=torch.bool)
        mask = masks[index] if masks is not None and index < len(masks) else None
        if mask is not None:
            valid = torch.from_numpy(block_average(mask.astype(np.float64), block)
                                     [1:-1, 1:-1] >= 1.0 - 1e-4)
        colours.append(small[1:-1, 1:-1][valid])
        smoothness.append(((dx + dy) / level)[valid])
    if not colours:
        return None
    colour, rough = torch.cat(colours), torch.cat(smoothness)
    smooth = colour[rough <= torch.quantile(rough[torch.randperm(len(rough))[:500000]], share)]
    median = smooth.median(0).values
    spread = (smooth - median).abs().median(0).values / median.clamp_min(1e-3)
    if float(spread.max()) > max_spread:
        return None
    return [float(v) for v in median]


def deblurred_images(config: TrainConfig, frames, images) -> Iterator[np.ndarray] | None:
    """The training images with the blur of the pipeline's own processing (each frame's
    ``blur_px``) deconvolved, for the water fit (``medium.refit_deblur``), made one at a time
    as they are taken (:class:`seathru.nerf.rays.RayDataset` keeps only their valid pixels);
    None when off, when the medium is off, or when no frame records a blur."""
    if not config.medium.refit_deblur or config.medium.mode == "off" or \
            not any(max(f.blur_px or [0.0]) > 0 for f in frames):
        return None

    def one_by_one() -> Iterator[np.ndarray]:
        started = time.perf_counter()
        for frame, image in zip(frames, images):
            yield deblurred(image, frame.blur_px or [0.0, 0.0, 0.0])
        log.info("water fit: the demosaic's and undistortion's blur taken out of %d images "
                 "(sigma %s px) in %.1f s", len(frames), frames[0].blur_px,
                 time.perf_counter() - started)

    return one_by_one()


def open_water_in_view(config: TrainConfig, images, masks=None
                       ) -> tuple[list[np.ndarray], float, bool]:
    """The photographs' open water (``seathru.radiometry.open_water``) as training uses it.

    Returns:
        the masks (H, W) per image, their share of the valid pixels
        (:func:`open_water_share`), and whether that share is above
        ``medium.auto_open_water_share`` (below it, a few smooth blocks at the top of the
        frames are far haze, not open water in view: the rays get no open-water flags).

    Example::

        water_masks, share, in_view = open_water_in_view(config, images, masks)
    """
    water_masks = [open_water_mask(image, valid=masks[i] if masks is not None and i < len(masks)
                                   else None,
                                   min_brightness=config.medium.auto_veiling_brightness)
                   for i, image in enumerate(images)]
    share = open_water_share(water_masks, masks)
    return water_masks, share, share > config.medium.auto_open_water_share


def open_water_share(water_masks, masks=None) -> float:
    """The share of the valid training pixels that show open water (``water_masks`` from
    :func:`seathru.radiometry.open_water.open_water_mask`): evidence of water for the medium
    decision that does not depend on the half-trained model."""
    water = total = 0
    for index, mask in enumerate(water_masks):
        valid = masks[index] if masks is not None and index < len(masks) else None
        water += int(mask.sum())
        total += int(valid.sum()) if valid is not None else mask.size
    return water / total if total else 0.0


def open_water_direction_spread(frames, images, water_masks, max_pixels: int = 200_000,
                                seed: int = 0) -> float:
    """How much the open water's colour changes with view direction: the standard deviation of
    a per-channel linear fit of colour on the ray direction over the open-water pixels, as a
    share of the water's brightness (both as lengths of RGB vectors). Uniform water gives the
    noise level (about 0); real open water is brighter towards the surface (0.27 on d3_reef;
    0.045 on the survey demo, whose simulated water is uniform but whose open water borders
    hazy seabed). Measured against the whole colour, not channel by channel, so that the noise
    of a channel the water nearly extinguishes (red in clear blue water) does not read as a
    veiling light that changes with direction (`docs/water.md`).

    Args:
        frames: the training frames; images: their linear images (H, W, 3); water_masks:
            (H, W) bool open-water masks.
        max_pixels: at most this many pixels, drawn at random, enter the fit.

    Returns:
        the relative spread (0 when there is no open water).
    """
    flats = [None if mask is None else np.flatnonzero(mask) for mask in water_masks]
    counts = np.array([0 if flat is None else len(flat) for flat in flats])
    if counts.sum() == 0:
        return 0.0
    # drawn over all frames' open water, then gathered frame by frame (not all of it at once)
    pick = np.random.default_rng(seed).choice(counts.sum(), max_pixels, replace=False) \
        if counts.sum() > max_pixels else np.arange(counts.sum())
    dirs, rgb = np.empty((len(pick), 3)), np.empty((len(pick), 3))
    starts = np.concatenate([[0], np.cumsum(counts)])
    for index, (frame, image, flat) in enumerate(zip(frames, images, flats)):
        rows = np.flatnonzero((pick >= starts[index]) & (pick < starts[index + 1]))
        if len(rows):
            chosen = flat[pick[rows] - starts[index]]
            dirs[rows] = frame_rays(frame)[1].numpy().reshape(-1, 3)[chosen]
            rgb[rows] = np.asarray(image, np.float64)[..., :3].reshape(-1, 3)[chosen]
    design = np.concatenate([np.ones((len(dirs), 1)), dirs], axis=1)
    coefficients, *_ = np.linalg.lstsq(design, rgb, rcond=None)
    predicted = design @ coefficients
    brightness = max(float(np.linalg.norm(rgb.mean(0))), 1e-6)
    return float(np.linalg.norm(predicted.std(0)) / brightness)


def seed_everything(seed: int) -> None:
    """Seed torch and numpy (the trainer's own generators are seeded from the config)."""
    torch.manual_seed(seed)
    np.random.seed(seed)
