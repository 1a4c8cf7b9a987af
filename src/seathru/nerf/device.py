"""Choosing the torch device and CPU thread count for training and rendering."""

from __future__ import annotations

import torch

from seathru.errors import PipelineError


def select_device(name: str = "auto", threads: int | None = None) -> torch.device:
    """The torch device named by a ``--device`` setting, checked against this machine.

    Args:
        name: ``auto`` (CUDA when torch sees it, else CPU), ``cpu``, ``cuda`` or ``cuda:N``.
        threads: torch CPU threads to use (None or 0 leaves torch's choice).

    Returns:
        the device.

    Raises:
        PipelineError: an unknown device name, or CUDA asked for where there is none.

    Example::

        device = select_device("auto", threads=2)
    """
    if threads:
        torch.set_num_threads(threads)
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError as exc:
        raise PipelineError(f"device {name!r} is not a torch device ({exc}); use auto, cpu "
                            "or cuda[:N]") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise PipelineError(f"device {name}: no CUDA device is available here; use cpu or auto")
    return device
