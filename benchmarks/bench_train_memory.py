"""Peak memory of the train step against the pixels it reads, this checkout beside a baseline
revision, measured side by side in one run. Usage::

    python benchmarks/bench_train_memory.py [--cameras results/demo/poses/cameras.json] \\
        [--scales 1,2,4] [--baseline 2e1c472] [--seconds 20] \\
        [--out benchmarks/results/train_memory.md]

Each scale is a copy of the camera set with its photographs and masks upscaled and its
intrinsics scaled with them (the pixels a camera of that resolution would give; the sparse
model is left out, so no track evidence enters either arm). The train step runs as the workflow
runs it, for ``--seconds`` of training, each run its own process; its peak resident memory is
the kernel's (``wait4``), the figure ``train.benchmark.tsv``'s ``max_rss`` gives in a workflow
run. The per-pixel cost is the slope between the smallest and the largest scale, the base what
is left at zero pixels: ``seathru.nerf.device``'s estimate should lie above both arms' rows.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from machine import cpu_name, load_average

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from seathru.nerf.device import BYTES_PER_TRAINING_PIXEL, TRAINING_MEMORY_BASE  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "train_memory.md"


def upscaled_copy(cameras: Path, scale: int, folder: Path) -> int:
    """A copy of the camera set at ``folder`` with every image and mask ``scale`` times larger
    and the intrinsics to match; returns its pixel count."""
    record = json.loads(cameras.read_text())
    folder.mkdir(parents=True, exist_ok=True)
    pixels = 0
    for frame in record["frames"]:
        for key, interpolation in (("image", cv2.INTER_LINEAR), ("mask", cv2.INTER_NEAREST)):
            if frame.get(key) is None:
                continue
            array = cv2.imread(str(cameras.parent / frame[key]), cv2.IMREAD_UNCHANGED)
            target = folder / frame[key]
            target.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(target), array if scale == 1 else cv2.resize(
                array, None, fx=scale, fy=scale, interpolation=interpolation))
        # pixel centres at (u + 0.5, v + 0.5): the principal point scales with the image
        for key in ("width", "height"):
            frame[key] = int(frame[key]) * scale
        for key in ("fx", "fy", "cx", "cy"):
            frame[key] = float(frame[key]) * scale
        if frame.get("blur_px"):
            frame["blur_px"] = [float(v) * scale for v in frame["blur_px"]]
        pixels += frame["width"] * frame["height"]
    (folder / "cameras.json").write_text(json.dumps(record))
    return pixels


def peak_memory(source: Path, cameras: Path, out: Path, seconds: float) -> tuple[float, float]:
    """The train step's peak resident memory in bytes, run from ``source``'s package, and the
    rays a second its log reports."""
    env = {**os.environ, "PYTHONPATH": str(source), "OMP_NUM_THREADS": "2"}
    command = [sys.executable, "-m", "seathru.cli", "train", "--cameras", str(cameras),
               "--out", str(out), "--checkpoint-dir", str(out / "checkpoints"), "--threads",
               "2", "--max-minutes", str(seconds / 60.0)]
    with open(out.parent / f"{out.name}.log", "w") as log:
        process = subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(process.pid, 0)
    log_text = (out.parent / f"{out.name}.log").read_text()
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"train failed from {source}:\n{log_text[-2000:]}")
    rate = re.findall(r"steps/s, (\d+) rays/s\)", log_text)
    return usage.ru_maxrss * 1024.0, float(rate[-1]) if rate else float("nan")


def sampling_times(source: Path, cameras: Path, batch: int = 1024, repeats: int = 5,
                   draws: int = 200) -> dict[str, float]:
    """Seconds per ``RayDataset.sample(batch)`` of this checkout's training set and of the
    one in ``source`` (its ``seathru/nerf/rays.py``) on the same images, timed in turns."""
    import importlib.util

    import torch

    from seathru.io.cameras import read_cameras
    from seathru.io.images import read_image
    from seathru.nerf import rays

    spec = importlib.util.spec_from_file_location("baseline_rays",
                                                  source / "seathru" / "nerf" / "rays.py")
    baseline = importlib.util.module_from_spec(spec)
    sys.modules["baseline_rays"] = baseline
    spec.loader.exec_module(baseline)
    camera_set = read_cameras(cameras)
    frames = camera_set.split("train")
    images = [read_image(camera_set.image_path(f)) for f in frames]
    sets = {"baseline": baseline.RayDataset(frames, images),
            "this checkout": rays.RayDataset(frames, images)}
    totals = dict.fromkeys(sets, 0.0)
    for repeat in range(repeats):
        for name, data in sets.items():
            generator = torch.Generator().manual_seed(repeat)
            start = time.perf_counter()
            for _ in range(draws):
                data.sample(batch, generator)
            totals[name] += time.perf_counter() - start
    return {name: total / (repeats * draws) for name, total in totals.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cameras", type=Path,
                        default=REPO / "results" / "demo" / "poses" / "cameras.json")
    parser.add_argument("--scales", default="1,2,4")
    parser.add_argument("--baseline", default="2e1c472",
                        help="git revision to compare with (its src/ is exported)")
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    scales = [int(s) for s in args.scales.split(",")]
    work = Path(tempfile.mkdtemp(prefix="train_memory_"))
    try:
        baseline = work / "baseline"
        baseline.mkdir()
        archive = subprocess.run(["git", "-C", str(REPO), "archive", args.baseline, "src"],
                                 check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(baseline)], input=archive, check=True)
        arms = {f"baseline {args.baseline}": baseline / "src", "this checkout": REPO / "src"}
        rows = []
        for scale in scales:
            pixels = upscaled_copy(args.cameras, scale, work / f"x{scale}")
            for arm, source in arms.items():
                name = f"x{scale}-{arm.split()[0]}"
                peak, rate = peak_memory(source, work / f"x{scale}" / "cameras.json",
                                         work / name, args.seconds)
                rows.append((scale, pixels, arm, peak, rate))
                print(f"x{scale} {pixels / 1e6:.1f} Mpx {arm}: {peak / 1e9:.2f} GB, "
                      f"{rate:.0f} rays/s", flush=True)
        lines = [
            "# Train step peak memory against pixels read", "",
            f"`python benchmarks/bench_train_memory.py --cameras {args.cameras.name} "
            f"--scales {args.scales} --baseline {args.baseline} --seconds {args.seconds:g}`; "
            f"{cpu_name()}, load {load_average()}; the camera set "
            f"`{args.cameras.parent.parent.name}` upscaled (no sparse model). The estimate is "
            f"`seathru.nerf.device`'s ({BYTES_PER_TRAINING_PIXEL} bytes a pixel + "
            f"{TRAINING_MEMORY_BASE / 1e9:.1f} GB).", "",
            "| scale | pixels (M) | arm | peak (GB) | estimate (GB) | training rays/s |",
            "|---:|---:|---|---:|---:|---:|"]
        for scale, pixels, arm, peak, rate in rows:
            estimate = TRAINING_MEMORY_BASE + BYTES_PER_TRAINING_PIXEL * pixels
            lines.append(f"| {scale} | {pixels / 1e6:.1f} | {arm} | {peak / 1e9:.2f} | "
                         f"{estimate / 1e9:.2f} | {rate:.0f} |")
        lines += ["", "| arm | bytes a pixel (slope) | base (GB) |", "|---|---:|---:|"]
        for arm in arms:
            points = [(p, m) for _, p, a, m, _ in rows if a == arm]
            slope, base = np.polyfit([p for p, _ in points], [m for _, m in points], 1)
            lines.append(f"| {arm} | {slope:.0f} | {base / 1e9:.2f} |")
        largest = work / f"x{max(scales)}" / "cameras.json"
        times = sampling_times(baseline / "src", largest)
        lines += ["", f"Drawing a batch of 1,024 training rays (`RayDataset.sample`, in turns, "
                  f"1,000 draws each, x{max(scales)}): baseline {times['baseline'] * 1e3:.3f} "
                  f"ms, this checkout {times['this checkout'] * 1e3:.3f} ms (ratio "
                  f"{times['this checkout'] / times['baseline']:.2f}), against "
                  f"{1024 / rows[-1][4] * 1e3:.0f} ms a training step at that size (its rays/s "
                  "above): the rays/s column's differences are not the drawing's."]
        args.out.write_text("\n".join(lines) + "\n")
        print("\n".join(lines))
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
