"""Device choice and the train step's memory check (seathru.nerf.device)."""

from __future__ import annotations

import sys
from types import SimpleNamespace

import pytest
import torch

from seathru.errors import PipelineError
from seathru.nerf import device as device_module
from seathru.nerf.device import (BYTES_PER_TRAINING_PIXEL, TRAINING_MEMORY_BASE,
                                 available_memory_bytes, check_training_memory, select_device)


def _frames(count: int, width: int, height: int) -> list:
    return [SimpleNamespace(width=width, height=height) for _ in range(count)]


def test_select_device_names_what_it_cannot_use():
    assert select_device("cpu").type == "cpu"
    assert select_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(PipelineError, match="not a torch device"):
        select_device("gpu0")
    if not torch.cuda.is_available():
        with pytest.raises(PipelineError, match="no CUDA device"):
            select_device("cuda")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/meminfo")
def test_available_memory_is_read_on_linux():
    available = available_memory_bytes()
    assert available is not None and 0 < available < 1 << 50


def test_a_control_group_limit_counts_what_its_processes_hold_not_their_cache(tmp_path):
    meminfo = tmp_path / "meminfo"
    meminfo.write_text("MemTotal:       65000000 kB\nMemAvailable:   60000000 kB\n")
    v2 = tmp_path / "v2"
    v2.mkdir()
    (v2 / "memory.max").write_text("16000000000\n")
    (v2 / "memory.stat").write_text("anon 4000000000\nfile 9000000000\n")
    assert available_memory_bytes(meminfo, v2) == 12_000_000_000
    (v2 / "memory.max").write_text("max\n")   # no limit: the machine's
    assert available_memory_bytes(meminfo, v2) == 60_000_000 * 1024
    v1 = tmp_path / "v1"
    (v1 / "memory").mkdir(parents=True)
    (v1 / "memory" / "memory.limit_in_bytes").write_text("8000000000\n")
    (v1 / "memory" / "memory.stat").write_text("cache 5000000000\ntotal_rss 3000000000\n")
    assert available_memory_bytes(meminfo, v1) == 5_000_000_000
    assert available_memory_bytes(tmp_path / "none", tmp_path / "none") is None


def test_a_dive_of_full_size_frames_fails_before_reading_with_a_size_that_fits():
    frames = _frames(40, 6000, 4000)   # 24 MP frames
    available = 16_000_000_000
    with pytest.raises(PipelineError) as error:
        check_training_memory(frames, "dive/poses/cameras.json", available=available)
    message = str(error.value)
    assert message.startswith("dive/poses/cameras.json: training on 960 million pixels")
    suggested = int(message.split("ingest.max_size=")[1].split()[0])
    # The suggested long edge fits with a fifth to spare, and 100 px more would not.
    scale = suggested / 6000
    fitting = _frames(40, int(6000 * scale), int(4000 * scale))
    assert check_training_memory(fitting, "x", available=available) <= 0.8 * available
    assert TRAINING_MEMORY_BASE + BYTES_PER_TRAINING_PIXEL * 40 * (suggested + 100) ** 2 \
        * 4000 / 6000 > 0.8 * available


def test_a_dataset_that_fits_passes_and_reports_its_estimate():
    frames = _frames(20, 720, 540)
    need = check_training_memory(frames, "x", available=8_000_000_000)
    assert need == TRAINING_MEMORY_BASE + BYTES_PER_TRAINING_PIXEL * 20 * 720 * 540


def test_the_check_reads_the_machine_when_not_told(monkeypatch):
    monkeypatch.setattr(device_module, "available_memory_bytes", lambda: 10)
    with pytest.raises(PipelineError, match="GB is available"):
        check_training_memory(_frames(1, 64, 48), "x")
