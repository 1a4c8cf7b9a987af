"""Colour planes by the scene's footprint against the capacity level's own, side by side.

``train.preset=auto`` raises the finest colour tri-plane to what the scene's pixel footprint can
use (``seathru.nerf.capacity.planes_for_footprint``). This benchmark measures what that costs
and what it buys, both arms in one run, interleaved:

1. step time: for each ``--cameras`` file, the training step at the final stage (the profiler
   of ``bench_profile.py``), with the level's planes and with the footprint's;
2. with ``--train-minutes`` (and the simulator's ``--truth``): the demo trained for that budget
   with each, then rendered and scored by the evaluate step: held-out PSNR, restored vs clean,
   the fitted water against the truth.

    python benchmarks/bench_planes.py --cameras results/demo/poses/cameras.json \\
        --truth results/demo/simulate/truth --train-minutes 3 --repeats 2

Writes ``benchmarks/results/planes.md``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from bench_profile import prepare_at_stage, profile
from bench_sooner import arm_table, run_once
from machine import cpu_name, load_average

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from seathru import settings  # noqa: E402
from seathru.nerf.config import TrainConfig  # noqa: E402
from seathru.nerf.training import Trainer  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "planes.md"


def build(cameras_path: Path, minutes: float, plane_res: list[int] | None, progress: float
          ) -> tuple[Trainer, dict]:
    """The run ``auto`` prepares for ``minutes`` of training, optionally with explicit planes,
    at the stage of ``progress``; and its capacity record."""
    overrides = {"field": {"plane_res": plane_res}} if plane_res else {}
    trainer, prepared = prepare_at_stage(
        cameras_path, {"preset": "auto", "max_minutes": minutes, **overrides}, progress)
    return trainer, prepared.capacity


def level_planes(capacity: dict) -> list[int]:
    """The chosen level's own planes (before the footprint raised them)."""
    level = settings.from_mapping(TrainConfig, {"preset": capacity["chosen"]})
    return list(level.field.plane_res)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cameras", type=Path, action="append", required=True,
                        help="a poses step's cameras.json (repeat for more scenes); the first "
                             "is trained with --train-minutes")
    parser.add_argument("--truth", type=Path, default=None, help="the first scene's simulator "
                        "truth folder (results/<dataset>/simulate/truth)")
    parser.add_argument("--minutes", type=float, default=3.0,
                        help="the budget the capacity choice is made for")
    parser.add_argument("--train-minutes", type=float, default=0.0,
                        help="train the first scene with each arm for this long (0: only time "
                             "the steps)")
    parser.add_argument("--also", nargs="*", default=[],
                        help="more explicit plane arms for the training, e.g. 96/224/512")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--work", type=Path, default=Path("/tmp/bench_planes"))
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    load_before = load_average()

    step_rows = []
    for cameras in args.cameras:
        _, capacity = build(cameras, args.minutes, None, 0.5)
        arms = {"level": level_planes(capacity),
                "footprint": capacity.get("changed", {}).get("field.plane_res",
                                                             level_planes(capacity))}
        times: dict[str, list[float]] = {arm: [] for arm in arms}
        for _ in range(args.repeats):
            for arm, planes in arms.items():
                trainer, _ = build(cameras, args.minutes, planes, 0.5)
                times[arm].append(profile(trainer, args.warmup, args.steps)["wall"])
                print(cameras.parent.parent.name, arm, planes, f"{1000 * times[arm][-1]:.1f} ms",
                      flush=True)
        best = {arm: min(values) for arm, values in times.items()}
        step_rows.append((cameras.parent.parent.name, capacity["chosen"],
                          capacity["scene"]["footprint_res"], arms, best))

    train_rows = []
    if args.train_minutes > 0:
        cameras = args.cameras[0]
        _, capacity = build(cameras, args.train_minutes, None, 0.5)
        arms = {"level": level_planes(capacity), "footprint": None,
                **{planes: [int(p) for p in planes.split("/")] for planes in args.also}}
        args.work.mkdir(parents=True, exist_ok=True)
        for repeat in range(args.repeats):
            for arm, planes in arms.items():
                extra = ("--field.plane-res", *map(str, planes)) if planes else ()
                train_rows.append((arm, run_once(f"{arm.replace('/', '-')}_{repeat}",
                                                 REPO / "src", args.train_minutes, cameras,
                                                 args.truth, args.work, args.threads, extra)))

    lines = ["# Colour planes by the footprint against the level's own (`benchmarks/"
             "bench_planes.py`)", "",
             f"Device: {cpu_name()}, {args.threads} thread(s), torch {torch.__version__}; load "
             f"average before/after: {load_before} / {load_average()}; "
             f"{time.strftime('%Y-%m-%d')}. Both arms side by side in one run, interleaved, "
             f"{args.repeats} time(s) each.", "",
             "## Step time at the final stage", "",
             f"The capacity `auto` chooses for a {args.minutes:g}-min budget; {args.warmup} "
             f"steps, then {args.steps} timed (wall, the best of the repeats).", "",
             "| scene | level | footprint (cells) | planes: level's | footprint's | ms/step, "
             "level's | footprint's | ratio |", "|---|---|---|---|---|---|---|---|"]
    for scene, level, footprint, arms, best in step_rows:
        lines.append(f"| {scene} | {level} | {footprint:.0f} | "
                     f"{'/'.join(map(str, arms['level']))} | "
                     f"{'/'.join(map(str, arms['footprint']))} | {1000 * best['level']:.1f} | "
                     f"{1000 * best['footprint']:.1f} | "
                     f"{best['footprint'] / best['level']:.2f} |")
    if train_rows:
        lines += ["", f"## Training, {args.train_minutes:g} min each", "",
                  f"Scene `{args.cameras[0]}`; scored by the evaluate step against the "
                  "simulator's truth (PSNR linear; water: signed error in %, R, G, B).", "",
                  *arm_table(train_rows)]
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
