"""``model.pt``: the trained model the train step writes and the render step reads.

A ``torch.save``d dict, loadable with ``torch.load(weights_only=True)`` (plain tensors, numbers,
strings, lists and dicts only): ``format`` (``seathru.nerf.model.MODEL_FORMAT``), ``config``,
``state_dict`` and ``scene`` (see :meth:`seathru.nerf.model.SeaThruModel.export`), plus what the
train step records (``training``; ``glare``: the ``seathru.radiometry.glare.GlareCorrection``
it trained with, as a dict, or None). Training checkpoints (``config``, ``model``, ``scene``, ...)
load too.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from seathru.errors import PipelineError
from seathru.io.atomic import atomic_path


def save_model(path: str | os.PathLike, export: dict) -> None:
    """Write the model dict ``export`` (``SeaThruModel.export()`` plus records) atomically."""
    with atomic_path(path) as tmp:
        torch.save(export, tmp)


def load_model(path: str | os.PathLike, device: torch.device | str = "cpu"):
    """The ``SeaThruModel`` of ``model.pt`` on ``device``, in eval mode.

    Args:
        path: ``model.pt`` from the train step (or a training checkpoint).
        device: where to put it (``seathru.nerf.device.select_device`` chooses one).

    Returns:
        the model.

    Raises:
        PipelineError: the file is missing, not a torch file, or not a model (names the file).

    Example::

        model = load_model("results/demo/train/model.pt", select_device("auto"))
    """
    from seathru.nerf.model import SeaThruModel

    path = Path(path)
    if not path.is_file():
        raise PipelineError(f"{path}: model file not found; run the 'train' step first")
    try:
        checkpoint = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # a truncated or foreign file: say which file, not a traceback
        raise PipelineError(f"{path}: cannot be read as a model checkpoint ({exc}); re-run the "
                            "'train' step") from None
    if not isinstance(checkpoint, dict) or "config" not in checkpoint or "scene" not in checkpoint:
        raise PipelineError(f"{path}: not a seathru model (no config and scene); re-run the "
                            "'train' step")
    try:
        model = SeaThruModel.from_checkpoint(checkpoint, device)
    except (KeyError, ValueError, TypeError, RuntimeError) as exc:
        raise PipelineError(f"{path}: the model cannot be rebuilt ({type(exc).__name__}: "
                            f"{exc}); re-run the 'train' step") from None
    model.eval()
    return model


def read_training_record(path: str | os.PathLike) -> dict | None:
    """What the train step recorded of a run in ``model.pt``, without building the model: its
    ``training`` record (``steps``, ``elapsed_s``, ``stopped_by``, ...) and, from its config,
    ``batch_rays`` and ``preset``, and the ``glare`` correction the photographs were trained
    with (keys absent where the file lacks them: older models, no correction).

    The weights are memory-mapped, not read: the report calls this for every run.

    Returns:
        the record, or None when the file does not exist.

    Raises:
        PipelineError: the file is not a torch file or not a model (names the file).

    Example::

        read_training_record("results/demo/train/model.pt")
        # {"steps": 3000, "elapsed_s": 118.2, "stopped_by": "steps", "batch_rays": 1024, ...}
    """
    path = Path(path)
    if not path.is_file():
        return None
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception as exc:  # a truncated or foreign file: say which file, not a traceback
        raise PipelineError(f"{path}: cannot be read as a model checkpoint ({exc})") from None
    if not isinstance(checkpoint, dict) or not isinstance(checkpoint.get("config"), dict):
        raise PipelineError(f"{path}: not a seathru model (no config)")
    training = checkpoint.get("training")
    record = dict(training) if isinstance(training, dict) else {}
    record.update({key: checkpoint["config"][key] for key in ("batch_rays", "preset")
                   if key in checkpoint["config"]})
    if isinstance(checkpoint.get("glare"), dict):
        record["glare"] = dict(checkpoint["glare"])
    return record
