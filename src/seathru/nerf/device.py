"""Choosing the torch device and CPU thread count for training and rendering."""

from __future__ import annotations

import math
from pathlib import Path

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


# Peak resident memory of the train step per pixel of the images it reads, above its fixed
# part: the photographs (12 bytes a pixel) while the training set gathers their pixels (each
# pixel's index and colour, its deblurred colour and open-water flag: 33 bytes; rays are made
# when drawn, seathru.nerf.rays.RayDataset). benchmarks/results/train_memory.md: 46 bytes a
# pixel over the demo's frames as they are and upscaled 2x and 4x (1.8 to 29.3 million
# pixels; 30-s runs); the whole demo workflow's train step peaks at 1.04 GB (max_rss in
# logs/demo/train.benchmark.tsv). The estimate lies 6% above the workflow's peak and 35-49%
# above the short runs' (no refits or trials yet: a smaller fixed part).
BYTES_PER_TRAINING_PIXEL = 55
TRAINING_MEMORY_BASE = 1_000_000_000   # torch, the model, the water fits


def available_memory_bytes(meminfo: Path = Path("/proc/meminfo"),
                           cgroup: Path = Path("/sys/fs/cgroup")) -> int | None:
    """Memory this process may still take: the smaller of the machine's available memory and
    what its control group (a SLURM job's allocation, a container's limit; cgroup v2 or v1)
    leaves beside the memory its processes hold (their page cache left out: the kernel
    reclaims it); None where neither can be read (not Linux)."""
    limits = []
    machine = _fields(meminfo)
    if "MemAvailable:" in machine:
        limits.append(machine["MemAvailable:"] * 1024)
    for folder, limit_name, held_name in ((cgroup, "memory.max", "anon"),
                                          (cgroup / "memory", "memory.limit_in_bytes",
                                           "total_rss")):
        try:
            limit = (folder / limit_name).read_text().strip()
        except OSError:
            continue
        held = _fields(folder / "memory.stat").get(held_name)
        if limit.isdigit() and int(limit) < 1 << 60 and held is not None:
            limits.append(max(0, int(limit) - held))
    return min(limits) if limits else None


def _fields(path: Path) -> dict[str, int]:
    """``name value`` lines of a /proc or cgroup file as a dict ({} where it cannot be read)."""
    try:
        lines = path.read_text().splitlines()
    except OSError:
        return {}
    fields = {}
    for line in lines:
        parts = line.split()
        if len(parts) >= 2 and parts[1].isdigit():
            fields[parts[0]] = int(parts[1])
    return fields


def check_training_memory(frames, where: str, available: int | None = None) -> int:
    """Fail before any image is read where the training data would not fit in memory.

    Args:
        frames: the frames the train step reads (``width``, ``height``), training and held out.
        where: the camera file, for the message.
        available: bytes free; None: :func:`available_memory_bytes` (no check where that
            cannot be read).

    Returns:
        the estimated peak memory in bytes.

    Raises:
        PipelineError: the estimate exceeds the memory available, with what to do.

    Example::

        check_training_memory(cameras.frames, "results/dive/poses/cameras.json")
    """
    pixels = sum(int(f.width) * int(f.height) for f in frames)
    need = TRAINING_MEMORY_BASE + BYTES_PER_TRAINING_PIXEL * pixels
    available = available_memory_bytes() if available is None else available
    if available is not None and need > available:
        largest = max(max(int(f.width), int(f.height)) for f in frames)
        # a fifth kept back: the estimate is a peak measured on two dives, not a bound
        fits = largest * math.sqrt(max(0, 0.8 * available - TRAINING_MEMORY_BASE)
                                   / (BYTES_PER_TRAINING_PIXEL * pixels))
        raise PipelineError(
            f"{where}: training on {pixels / 1e6:.0f} million pixels ({len(frames)} images, "
            f"long edge up to {largest} px) needs about {need / 1e9:.1f} GB of memory and "
            f"{available / 1e9:.1f} GB is available; downscale the photographs (the sheet's "
            f"options: ingest.max_size={max(100, int(fits // 100 * 100))} or less), train "
            "on fewer of them, or run where there is more memory (the SLURM profile: "
            "resources.train.mem_mb)")
    return need
