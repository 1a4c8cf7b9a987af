"""What the sparse-depth rays cost per training step, side by side in one process.

Reads a workflow run's COLMAP-posed dataset (``results/<dataset>/poses``: ``cameras.json`` and
``sparse/``), prepares two training runs of the same model (``loss.sparse_depth_weight`` 0 and
the default) and times their optimisation steps in alternating blocks, so that both see the
same machine load. Reported: seconds per step of each and their ratio (median over the blocks),
and how many sparse-depth rays the dataset has. Writes ``benchmarks/results/sparse_depth.md``.

    python benchmarks/bench_sparse_depth.py --poses results/demo/poses [--blocks 8]
        [--steps 20] [--threads 2]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

from machine import cpu_name, load_average

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
OUT = REPO / "benchmarks" / "results" / "sparse_depth.md"


def trainer_for(weight: float, cameras):
    """A trainer of the default model on ``cameras`` with the given sparse-depth weight."""
    from seathru.io.tracks import training_depth_observations
    from seathru.io.training import read_frame_images
    from seathru.nerf.config import TrainConfig
    from seathru.nerf.prepare import prepare_run, seed_everything
    from seathru.nerf.training import Trainer

    seed_everything(0)
    base = TrainConfig(max_minutes=0, progress=False)
    config = dataclasses.replace(base, loss=dataclasses.replace(base.loss,
                                                                sparse_depth_weight=weight))
    frames = cameras.split("train")
    run = prepare_run(config, cameras, frames, *read_frame_images(cameras, frames),
                      sparse_points=training_depth_observations(cameras))
    return Trainer(run.model, run.data, device="cpu", frames=frames)


def main() -> None:
    import torch

    from seathru.io.cameras import read_cameras
    from seathru.nerf.config import TrainConfig

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=Path, required=True)
    parser.add_argument("--blocks", type=int, default=8)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    cameras = read_cameras(args.poses / "cameras.json")
    default = TrainConfig().loss.sparse_depth_weight
    trainers = {"without": trainer_for(0.0, cameras), "with": trainer_for(default, cameras)}
    rays = trainers["with"].data.depth_rays
    for trainer in trainers.values():        # warm-up: allocations, caches
        for _ in range(5):
            trainer._optimise_once()
    times = {name: [] for name in trainers}
    for _ in range(args.blocks):
        for name, trainer in trainers.items():
            start = time.perf_counter()
            for _ in range(args.steps):
                trainer._optimise_once()
            times[name].append((time.perf_counter() - start) / args.steps)
    per_step = {name: statistics.median(values) for name, values in times.items()}
    ratios = [w / o for w, o in zip(times["with"], times["without"])]
    batch = trainers["with"].config.batch_rays
    lines = [
        "# What the sparse-depth rays cost per training step (`benchmarks/bench_sparse_depth.py`)",
        "",
        f"Dataset `{args.poses}`: {0 if rays is None else len(rays)} sparse-depth rays (points "
        f"seen by 3+ training views); {batch} colour rays and "
        f"{trainers['with'].config.loss.sparse_depth_rays} sparse-depth rays per step "
        f"(weight {default}). {args.blocks} alternating blocks of {args.steps} steps each, "
        "from the first steps of training (the first stage's grids).",
        "",
        "| run | seconds per step (median of blocks) |",
        "|---|---|",
        f"| without (weight 0) | {per_step['without']:.4f} |",
        f"| with | {per_step['with']:.4f} |",
        "",
        f"Ratio with / without: {statistics.median(ratios):.2f} (median of the blocks; "
        f"range {min(ratios):.2f}-{max(ratios):.2f}).",
        "",
        f"Machine: {cpu_name()}; {args.threads} threads; load before {load_average()}; "
        f"{time.strftime('%Y-%m-%d')}.",
    ]
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
