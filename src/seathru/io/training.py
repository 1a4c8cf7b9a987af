"""Files of a training run: the frames' images, ``train_log.csv`` and resumable checkpoints.

``train_log.csv`` columns: ``step, wall_time_s, loss, train_psnr, test_psnr`` (empty cell =
not measured at that step). A checkpoint (``checkpoint.pt``, format
``seathru-train-checkpoint/1``) is ``Trainer.checkpoint_state()`` plus the scene; it resumes
only with the same settings (``TrainConfig.identity``) and the same scene.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from seathru.errors import PipelineError
from seathru.io.atomic import atomic_path, write_text
from seathru.io.cameras import CameraSet
from seathru.io.images import read_image, read_mask
from seathru.radiometry.glare import GlareCorrection, photograph_gain

log = logging.getLogger(__name__)

LOG_COLUMNS = ("step", "wall_time_s", "loss", "train_psnr", "test_psnr")
CHECKPOINT_NAME = "checkpoint.pt"


def read_frame_images(cameras: CameraSet, frames, glare: GlareCorrection | None = None,
                      gains: dict[str, list[float]] | None = None
                      ) -> tuple[list[np.ndarray], list[np.ndarray | None]]:
    """Linear RGB images (H, W, 3) and validity masks (H, W) or None of ``frames``, checked
    against the camera file's sizes; with ``glare`` (a
    ``seathru.radiometry.glare.GlareCorrection``), each image without it
    (:func:`without_glare`); with ``gains`` (R, G, B by frame name: its colour cast brought to
    the median frame's, ``seathru.io.tracks.frame_colour_gains``), each named image times its
    gains."""
    images, masks = [], []
    for frame in frames:
        image, mask = read_frame(cameras, frame)
        image = image if glare is None else without_glare(image, mask, glare)
        if gains and frame.name in gains:
            image = (image * np.asarray(gains[frame.name], np.float32)).astype(image.dtype)
        images.append(image)
        masks.append(mask)
    return images, masks


def read_frame(cameras: CameraSet, frame) -> tuple[np.ndarray, np.ndarray | None]:
    """One frame's linear RGB image (H, W, 3) and validity mask (H, W) or None, checked
    against the camera file's size."""
    path = cameras.image_path(frame)
    image = read_image(path)
    if image.ndim != 3 or image.shape[2] < 3:
        raise PipelineError(f"{path}: expected an RGB image, found shape {image.shape}")
    image = image[..., :3]
    if image.shape[:2] != (frame.height, frame.width):
        raise PipelineError(f"{path}: image is {image.shape[1]}x{image.shape[0]} but "
                            f"{cameras.root}/cameras.json says {frame.width}x{frame.height}")
    mask = None
    mask_path = cameras.mask_path(frame)
    if mask_path is not None:
        mask = read_mask(mask_path)
        if mask.ndim == 3:
            mask = mask[..., 0]
        if mask.shape != image.shape[:2]:
            raise PipelineError(f"{mask_path}: mask is {mask.shape[1]}x{mask.shape[0]}, its "
                                f"image {image.shape[1]}x{image.shape[0]}")
    return image, mask


@dataclass
class TrainingInputs:
    """What the train step reads before training (:func:`read_training_inputs`)."""

    train_images: list[np.ndarray]
    train_masks: list[np.ndarray | None]
    test_images: list[np.ndarray]
    test_masks: list[np.ndarray | None]
    track_change: dict | None     # seathru.io.tracks.input_colour_change
    glare: GlareCorrection | None  # the correction applied to every image, or None
    frame_gains: dict[str, list[float]] | None = None   # the training frames' colour gains

    def release_images(self) -> None:
        """Let the photographs go once training has taken what it needs from them (its rays'
        colours, the held-out probe, the snapshots' small copies): kept, they would double the
        memory that training holds."""
        self.train_images, self.test_images = [], []

    def corrections(self) -> dict:
        """``selection.json``'s record of what the photographs were trained without."""
        cast = (self.track_change or {}).get("frame_colour")
        return {"glare_correction": self.glare and self.glare.to_dict(),
                "frame_colour_correction": None if not self.frame_gains else {
                    "gains": self.frame_gains, "spread": cast and cast.get("spread")}}


def read_training_inputs(cameras: CameraSet, train_frames, test_frames,
                         glare: str = "auto", frame_colour: str = "auto") -> TrainingInputs:
    """The frames' images and masks, the track evidence of water and, with ``glare`` auto,
    the glare correction it supports, applied to every image (``TrainConfig.glare``); with
    ``frame_colour`` auto, where the training frames' colour casts vary, each training image
    brought to the median frame's (``TrainConfig.frame_colour``; the held-out images stay as
    they are: the evaluation measures against the photographs)."""
    from seathru.io.tracks import frame_colour_gains, glare_correction, input_colour_change

    track_change = input_colour_change(cameras, near_open_water=glare == "auto")
    correction = glare_correction(track_change)
    if correction is not None:
        log.info("the photographs are brighter next to the open water (%+.2f log colour per "
                 "unit of log distance); training on them without it", correction.coefficient)
    gains = frame_colour_gains(track_change) if frame_colour == "auto" else None
    if gains:
        log.info("the training photographs' colour cast varies from frame to frame (robust "
                 "spread %s of log red / green, blue / green); training on each brought to "
                 "the median frame's", track_change["frame_colour"]["spread"])
    return TrainingInputs(*read_frame_images(cameras, train_frames, correction, gains),
                          *read_frame_images(cameras, test_frames, correction), track_change,
                          correction, gains)


def without_glare(image: np.ndarray, mask: np.ndarray | None,
                  glare: GlareCorrection) -> np.ndarray:
    """``image`` (H, W, 3) divided by the ``glare`` correction's gain (:func:`glare_gain_of`),
    in the image's own dtype."""
    gain = glare_gain_of(image, mask, glare)
    return (image / gain[..., None]).astype(image.dtype, copy=False)


def glare_gain_of(image: np.ndarray, mask: np.ndarray | None,
                  glare: GlareCorrection) -> np.ndarray:
    """The ``glare`` correction's gain (H, W) around the open water ``image`` (H, W, 3) shows
    on its valid pixels: finite, and inside ``mask`` (H, W) where there is one
    (``seathru.radiometry.glare.photograph_gain``)."""
    valid = np.isfinite(image).all(-1)
    if mask is not None:
        valid &= mask > 0
    return photograph_gain(image, glare, valid)


def write_log_csv(path: Path, rows: list[dict]) -> None:
    """``train_log.csv`` from the trainer's log rows (atomic)."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(LOG_COLUMNS)
    for row in rows:
        out = []
        for key in LOG_COLUMNS:
            value = row.get(key)
            if value is None or (isinstance(value, float) and not math.isfinite(value)):
                out.append("")
            elif isinstance(value, float):
                out.append(f"{value:.6g}")
            else:
                out.append(str(value))
        writer.writerow(out)
    write_text(path, buffer.getvalue())


def save_checkpoint(path: Path, state: dict) -> None:
    """Write a training checkpoint atomically (a kill never leaves half a file)."""
    import torch

    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def load_checkpoint(path: Path, identity: dict, scene: dict, device) -> tuple[dict | None, str]:
    """The checkpoint at ``path`` if it can be resumed with these settings and scene.

    Args:
        path: the checkpoint file (may be missing).
        identity: ``TrainConfig.identity()`` of the run about to start.
        scene: the model's scene dict of the run about to start.
        device: where to load tensors.

    Returns:
        ``(checkpoint, "")`` when it can be resumed, else ``(None, why not)``.
    """
    import torch

    from seathru.nerf.config import TrainConfig
    from seathru.nerf.training import CHECKPOINT_FORMAT

    if not Path(path).exists():
        return None, "no checkpoint"
    try:
        ckpt = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # truncated or foreign file
        return None, f"unreadable ({exc})"
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        return None, f"not a {CHECKPOINT_FORMAT} file"
    try:
        theirs = TrainConfig.from_dict(ckpt.get("config", {})).identity()
    except PipelineError as exc:
        return None, f"its settings are not valid now ({exc})"
    changed = sorted(k for k in identity if theirs.get(k) != identity[k])
    if changed:
        return None, "settings changed: " + ", ".join(
            f"{k} {theirs.get(k)!r} -> {identity[k]!r}" for k in changed[:6])
    if json.dumps(ckpt.get("scene"), sort_keys=True) != json.dumps(scene, sort_keys=True):
        return None, "the camera file (scene box or normalisation) changed"
    return ckpt, ""


SNAPSHOT_COLUMNS = ("step", "elapsed_s", "test_psnr_images", "medium",
                    *(f"{key}_{c}" for key in ("sigma_attn", "sigma_bs", "c_med") for c in "rgb"))


def write_snapshots(out: Path, rows: list[dict], renders: dict[int, dict[str, np.ndarray]],
                    downscale: int) -> None:
    """``snapshots.csv`` (one row per quality snapshot; water in normalised units) and
    ``snapshots/step_NNNNNNN.npz`` (held-out renders at ``downscale``: ``<view>.rgb`` and
    ``<view>.restored``, float16), written atomically."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow([*SNAPSHOT_COLUMNS, "downscale"])
    for row in rows:
        cells = []
        for key in SNAPSHOT_COLUMNS:
            value = row.get(key)
            cells.append("" if value is None else f"{value:.6g}" if isinstance(value, float)
                         else str(value))
        writer.writerow([*cells, downscale])
    write_text(Path(out) / "snapshots.csv", buffer.getvalue())
    (Path(out) / "snapshots").mkdir(parents=True, exist_ok=True)
    for step, arrays in renders.items():
        with atomic_path(snapshot_path(out, step)) as tmp:
            with open(tmp, "wb") as handle:
                np.savez_compressed(handle, **arrays)


def read_snapshots(out: Path) -> list[dict]:
    """The rows of ``snapshots.csv`` (numbers as floats, empty cells as None); [] if absent."""
    path = Path(out) / "snapshots.csv"
    if not path.is_file():
        return []
    rows = []
    with open(path, newline="") as handle:
        for raw in csv.DictReader(handle):
            row = {}
            for key, value in raw.items():
                if value == "" or value is None:
                    row[key] = None
                elif key == "medium":
                    row[key] = value
                else:
                    try:
                        row[key] = float(value)
                    except ValueError:
                        raise PipelineError(f"{path}: column {key!r} holds {value!r}, not a "
                                            "number; re-run the 'train' step") from None
            rows.append(row)
    return rows


def snapshot_path(train_dir: str | os.PathLike, step: int) -> Path:
    """``train/snapshots/step_NNNNNNN.npz`` of a snapshot."""
    return Path(train_dir) / "snapshots" / f"step_{int(step):07d}.npz"


def read_snapshot_renders(train_dir: str | os.PathLike,
                          step: int) -> dict[str, dict[str, np.ndarray]] | None:
    """A snapshot's held-out renders: view -> {"rgb", "restored"} -> ``(h, w, 3)`` float32;
    None when the file does not exist.

    Raises:
        PipelineError: naming the file when it is not a snapshot archive.
    """
    path = snapshot_path(train_dir, step)
    if not path.is_file():
        return None
    views: dict[str, dict[str, np.ndarray]] = {}
    try:
        with np.load(path, allow_pickle=False) as archive:
            for key in archive.files:
                view, _, kind = key.rpartition(".")
                if view and kind in ("rgb", "restored"):
                    views.setdefault(view, {})[kind] = archive[key].astype(np.float32)
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise PipelineError(f"{path}: not a snapshot archive ({exc}); re-run the 'train' "
                            "step") from None
    return views
