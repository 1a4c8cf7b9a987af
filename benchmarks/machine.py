"""What the benchmarks ran on, for the headers of their result files."""

from __future__ import annotations

import platform
from pathlib import Path


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def load_average() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "n/a"


def footer(load: str, started: float) -> str:
    """The last line of a result file: machine, load before the run, date, minutes taken."""
    import time

    return (f"Machine: {cpu_name()}; load {load}; {time.strftime('%Y-%m-%d')}; "
            f"{(time.time() - started) / 60:.0f} min.")
