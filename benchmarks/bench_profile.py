"""Where a training step's time goes, per component, for each preset, measured side by side.

Builds the training run of a camera set (the demo's ``results/demo/poses/cameras.json`` by
default) for each preset, trains it ``--warmup`` steps (so the occupancy grid has carved the
empty space, as in a real run at the final stage), then times ``--steps`` steps with the torch
profiler and groups the operator time by the component that issued it (``record_function``
labels in the model: sampler, density, colour, medium, loss; backward; optimiser). Usage::

    python benchmarks/bench_profile.py [--cameras results/demo/poses/cameras.json] \
        [--presets fast,balanced,quality] [--threads 2]

Writes ``benchmarks/results/profile.md``.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import torch

from machine import cpu_name, load_average

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from seathru.io.cameras import read_cameras  # noqa: E402
from seathru.io.training import read_frame_images  # noqa: E402
from seathru.nerf.config import TrainConfig  # noqa: E402
from seathru.nerf.prepare import prepare_run, seed_everything  # noqa: E402
from seathru.nerf.training import Trainer  # noqa: E402
from seathru import settings  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "profile.md"
COMPONENTS = ("sample", "density", "colour", "render")


def prepare_at_stage(cameras_path: Path, mapping: dict, progress: float):
    """The training run of ``mapping`` (TrainConfig settings) on a camera file, its trainer at
    the stage of ``progress``: ``(trainer, prepared)``."""
    config = settings.from_mapping(TrainConfig, {"progress": False, **mapping})
    seed_everything(0)
    cameras = read_cameras(cameras_path)
    train = cameras.split("train")
    prepared = prepare_run(config, cameras, train, *read_frame_images(cameras, train))
    trainer = Trainer(prepared.model, prepared.data, None, device="cpu", frames=train)
    # Train at the final stage's grids: the stage the run spends most steps in.
    trainer.step = int(progress * prepared.config.steps)
    trainer._swap_parameters(prepared.model.set_stage(
        prepared.model.stage_for_progress(progress)))
    trainer.optimizer = trainer._build_optimizer()
    return trainer, prepared


def build(cameras_path: Path, preset: str, progress: float) -> Trainer:
    """A trainer for ``preset`` at the stage of ``progress``."""
    return prepare_at_stage(cameras_path, {"preset": preset, "max_minutes": 0}, progress)[0]


def profile(trainer: Trainer, warmup: int, steps: int) -> dict[str, float]:
    model = trainer.model
    for _ in range(warmup):
        if trainer.step % trainer.config.sampler.occupancy_refresh_every == 0:
            model.refresh_occupancy()
        trainer._optimise_once()
        trainer.step += 1
    times = {name: 0.0 for name in (*COMPONENTS, "backward", "optimiser", "occupancy")}
    start = time.perf_counter()
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        for _ in range(steps):
            if trainer.step % trainer.config.sampler.occupancy_refresh_every == 0:
                with torch.profiler.record_function("occupancy"):
                    model.refresh_occupancy()
            with torch.profiler.record_function("step"):
                batch = trainer.data.sample(trainer.config.batch_rays, trainer.generator)
                loss, _, _ = trainer._loss(batch)
                trainer.optimizer.zero_grad(set_to_none=True)
                with torch.profiler.record_function("backward"):
                    loss.backward()
                    trainer._mask_density_gradients()
                with torch.profiler.record_function("optimiser"):
                    trainer.optimizer.step()
            trainer.step += 1
    wall = time.perf_counter() - start
    for event in prof.key_averages():
        key = event.key.removeprefix("seathru.")
        if key in times:
            times[key] += event.cpu_time_total / 1e6
    step_total = sum(e.cpu_time_total for e in prof.key_averages() if e.key == "step") / 1e6
    forward = sum(times[c] for c in COMPONENTS)
    times["other"] = max(0.0, step_total - forward - times["backward"] - times["optimiser"])
    times["wall"] = wall
    return {k: v / steps for k, v in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cameras", type=Path,
                        default=REPO / "results" / "demo" / "poses" / "cameras.json")
    parser.add_argument("--presets", default="fast,balanced,quality")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--warmup", type=int, default=30)
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--progress", type=float, default=0.5,
                        help="training progress whose stage is profiled")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    load_before = load_average()
    rows = {}
    for preset in args.presets.split(","):
        trainer = build(args.cameras, preset, args.progress)
        rows[preset] = profile(trainer, args.warmup, args.steps)
        print(preset, {k: round(v * 1000, 1) for k, v in rows[preset].items()}, flush=True)
    keys = (*COMPONENTS, "backward", "optimiser", "occupancy", "other", "wall")
    lines = ["# Training step profile per component (`benchmarks/bench_profile.py`)", "",
             f"Device: {cpu_name()}, {args.threads} thread(s), torch {torch.__version__}, "
             f"Python {platform.python_version()}; load average before/after: {load_before} / "
             f"{load_average()} (a shared machine). Camera set: `{args.cameras}`; each preset "
             f"trained {args.warmup} steps at the stage of progress {args.progress}, then "
             f"{args.steps} steps profiled (torch profiler, CPU time per step, ms; the "
             "components are the model's `record_function` ranges: sample (occupancy-guided "
             "sample placement), density, colour, render (compositing with the water); other = "
             "batch sampling, losses; occupancy = the cached grid's refresh, every few steps).", "",
             "| preset | " + " | ".join(keys) + " |", "|---" * (len(keys) + 1) + "|"]
    for preset, row in rows.items():
        lines.append(f"| {preset} | " + " | ".join(f"{row.get(k, 0.0) * 1000:.1f}"
                                                 for k in keys) + " |")
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
