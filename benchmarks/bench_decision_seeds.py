"""The medium decision of one simulated scene over several training seeds: how often each answer
comes, with the evidence and the race behind it. Usage::

    python benchmarks/bench_decision_seeds.py --water clear --size 64x48 --steps 500 \\
        --seeds 0,1,2,3,4,5 [--path orbit] [--sparse] [--minutes 3] [--preset toy] \\
        [--supersample 3] [--train-args '--medium.auto-race-without-evidence'] \\
        [--out benchmarks/results/decision_seeds.md]

``--preset toy`` trains with ``tests/test_train.py``'s small grids and batches (its clear-water
test is 16 views of 64x48, 500 steps, seed 0); ``--preset shipped`` with the shipped defaults,
as the water benchmark does. The scene is simulated once (simulator seed ``--scene-seed``);
each training seed is its own run, one thread each, two at a time. A result file is appended
to, one table a call.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from machine import cpu_name

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from seathru import settings  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "decision_seeds.md"
TOY = {"preset": "balanced", "field": {"density_res": [32, 48, 64],
                                       "plane_res": [128, 192, 256], "plane_coarse_res": 32,
                                       "density_coarse_res": 16},
       "sampler": {"samples_per_ray": 12}, "batch_rays": 512}


def scene(work: Path, args) -> Path:
    """The simulated dive's true cameras (with COLMAP-like sparse points with ``--sparse``)."""
    from seathru.io.truth import write_truth_sparse_model
    from seathru.steps.simulate import Settings, simulate

    width, height = (int(v) for v in args.size.split("x"))
    out = work / f"{args.path}_{args.water}_{args.size}_{args.scene_seed}"
    if not (out / "truth" / "cameras.json").exists():
        simulate(out, Settings(views=16, width=width, height=height, path=args.path,
                               water=args.water, seed=args.scene_seed, workers=1,
                               supersample=args.supersample, test_every=8))
    if args.sparse and not (out / "truth" / "sparse").is_dir():
        write_truth_sparse_model(out, seed=args.scene_seed)
    return out


def decide(sim: Path, seed: int, args) -> dict:
    """One training run's ``selection.json`` (run if not there yet)."""
    extra = shlex.split(args.train_args)
    tag = "".join(c for c in args.train_args if c.isalnum())[:40]
    out = sim / f"train_{args.preset}_{args.steps or args.minutes}{tag and '_' + tag}_{seed}"
    if not (out / "selection.json").exists():
        budget = ["--steps", str(args.steps), "--max-minutes", "0"] if args.steps else \
            ["--max-minutes", str(args.minutes)]
        flags = settings.cli_flags(TOY) if args.preset == "toy" else []
        done = subprocess.run(
            [sys.executable, "-m", "seathru.cli", "train", "--cameras",
             str(sim / "truth" / "cameras.json"), "--out", str(out), "--checkpoint-dir",
             str(out.parent / f"{out.name}_ckpt"), "--threads", "1", "--no-progress",
             "--seed", str(seed), *budget, *flags, *extra], capture_output=True, text=True)
        if done.returncode != 0:
            raise SystemExit(f"training seed {seed} failed:\n{done.stderr[-2000:]}")
    return json.loads((out / "selection.json").read_text())


def row(seed: int, selection: dict) -> str:
    stats = selection["statistics"]
    race = "-" if stats.get("validation_psnr_off") is None else (
        f"{stats['validation_psnr_water']:.2f} / {stats['validation_psnr_off']:.2f}"
        + ("" if stats.get("validation_psnr_off_second_trial") is None else
           f" / {stats['validation_psnr_off_second_trial']:.2f}"))
    fading = stats.get("surface_attenuation_over_depth")
    lower = stats.get("surface_attenuation_over_depth_lower")
    front = stats.get("backscatter_in_front_share")
    return (f"| {seed} | {selection['chosen']} | {selection['decided_at_step']} | "
            f"{100 * stats['backscatter_share']:.0f}% | "
            f"{'-' if front is None else f'{100 * front:.0f}%'} | "
            f"{100 * stats['object_hit_share']:.0f}% | "
            f"{'-' if fading is None else f'{100 * fading:.0f}%'}"
            f"{'' if lower is None else f' ({100 * lower:.0f}%)'} | {race} | "
            f"{'; '.join(stats['evidence_of_water']) or 'none'} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--water", default="clear")
    parser.add_argument("--path", default="orbit")
    parser.add_argument("--size", default="64x48")
    parser.add_argument("--scene-seed", type=int, default=1)
    parser.add_argument("--supersample", type=int, default=3,
                        help="3 as the tests' scenes, 2 as the water benchmark's")
    parser.add_argument("--seeds", default="0,1,2,3,4,5")
    parser.add_argument("--steps", type=int, default=0, help="a step budget (0: --minutes)")
    parser.add_argument("--minutes", type=float, default=3.0)
    parser.add_argument("--preset", choices=("toy", "shipped"), default="toy")
    parser.add_argument("--sparse", action="store_true")
    parser.add_argument("--train-args", default="", help="more flags for the train step")
    parser.add_argument("--work", type=Path, default=Path("/tmp/bench_decision_seeds"))
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    started = time.perf_counter()
    sim = scene(args.work, args)
    seeds = [int(s) for s in args.seeds.split(",")]
    with ThreadPoolExecutor(2) as pool:
        selections = list(pool.map(lambda s: decide(sim, s, args), seeds))
    answers = [s["chosen"] for s in selections]
    budget = f"{args.steps} steps" if args.steps else f"{args.minutes:g} min"
    lines = [f"## {args.water} water, {args.path}, 16 views of {args.size}, {budget}, "
             f"{args.preset} settings{', sparse points' if args.sparse else ''}", "",
             f"`python benchmarks/bench_decision_seeds.py {' '.join(sys.argv[1:])}`; "
             f"{cpu_name()}; {time.perf_counter() - started:.0f} s. No water at "
             f"{answers.count('off')} of {len(answers)} seeds.", "",
             "| seed | chosen | at step | backscatter share | in front of surfaces | "
             "rays meeting a surface | surface fading (its lower end) | "
             "race: water / no water / its second trial (dB) | evidence |",
             "|---:|---|---:|---:|---:|---:|---:|---|---|",
             *(row(seed, s) for seed, s in zip(seeds, selections)), ""]
    with open(args.out, "a") as out:
        out.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
