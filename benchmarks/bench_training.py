"""Training benchmark: the fast model against the paper-faithful configuration, same scene, same
machine, same wall time, one after the other in one run.

Scene: the demo dive (``seathru simulate``: 24 views, 320x240, orbit, default water, seed 0), or
an existing simulation (``--sim DIR``, the folder holding ``truth/``). Both models train with
``seathru train`` (a subprocess each, ``--threads`` CPU threads) for ``--minutes`` of training
time (held-out evaluations for the log are not counted):

- ours: the defaults (density grid + tri-plane colour, occupancy-guided samples, closed-form
  water, ``medium.mode=auto``);
- paper: positional-encoding MLP 8 x 256, 128 coarse + 32 fine samples per ray (hierarchical,
  the fine pass on all 160), view-dependent medium MLP, the paper's discretisation with water
  only between the samples, Adam lr 5e-4, 1024 rays per step.

Reported (``benchmarks/results/training.md``): steps and rays per second, held-out PSNR against
time from the training logs and the time ours needs to reach the paper configuration's final
held-out PSNR; on common held-out pixels: PSNR of the full rendering against the water images
and of the restored rendering against the simulator's clean images (all finite pixels, and
those closer than 6 m); the fitted water against the truth. Usage::

    python benchmarks/bench_training.py [--sim DIR] [--minutes 3] [--threads 2]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from machine import cpu_name, load_average


REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "training.md"
PAPER_FLAGS = ["--preset", "paper", "--steps", "1000000"]  # nerf/config.py TRAIN_PRESETS
PSNR_LEVELS = (20.0, 22.0, 24.0, 25.0, 26.0, 28.0, 30.0)
NEAR_RANGE_M = 6.0


def device_name(device: str) -> str:
    if device.startswith("cuda"):
        import torch

        return f"{torch.cuda.get_device_name(0)} (CUDA), host CPU {cpu_name()}"
    return cpu_name()


def simulate_demo(root: Path) -> Path:
    from seathru.steps.simulate import Settings, simulate

    out = root / "demo"
    if not (out / "truth" / "cameras.json").exists():
        print("simulating the demo dive (24 views, 320x240, orbit, default water)...", flush=True)
        simulate(out, Settings(views=24, width=320, height=240, path="orbit",
                                        water="default", seed=0, workers=2))
    return out


def train(name: str, cameras: Path, work: Path, minutes: float, threads: int,
          extra: list[str], device: str = "cpu") -> dict:
    out, ckpt = work / name, work / f"{name}_checkpoints"
    shutil.rmtree(out, ignore_errors=True)
    shutil.rmtree(ckpt, ignore_errors=True)
    # the train step alone: a GPU node may lack the other steps' dependencies (pycolmap, rawpy)
    command = [sys.executable, "-c", "import sys; from seathru.cli import main; "
               "sys.exit(main(only='train'))", "--cameras", str(cameras),
               "--out", str(out), "--checkpoint-dir", str(ckpt), "--threads", str(threads),
               "--max-minutes", str(minutes), "--eval-rays", "1024", "--no-progress",
               "--device", device, *extra]
    env = dict(os.environ, PYTHONPATH=str(REPO / "src"))
    print(f"training {name} for {minutes} min on {threads} thread(s)...", flush=True)
    started = time.perf_counter()
    result = subprocess.run(command, env=env, capture_output=True, text=True)
    if result.returncode != 0:
        raise SystemExit(f"{name} training failed:\n{result.stdout}\n{result.stderr}")
    with open(out / "train_log.csv") as fh:
        rows = [{k: (float(v) if v else None) for k, v in row.items()}
                for row in csv.DictReader(fh)]
    import torch

    model = torch.load(out / "model.pt", weights_only=True)
    return {"name": name, "out": out, "rows": rows, "training": model["training"],
            "process_s": time.perf_counter() - started, "log": result.stderr}


def time_to(rows: list[dict], level: float) -> float | None:
    """Training time at which the held-out PSNR first reaches ``level`` (linear in between)."""
    previous = None
    for row in rows:
        if row["test_psnr"] is None:
            continue
        if row["test_psnr"] >= level:
            if previous is None or previous["test_psnr"] >= level:
                return row["wall_time_s"]
            frac = (level - previous["test_psnr"]) / (row["test_psnr"] - previous["test_psnr"])
            return previous["wall_time_s"] + frac * (row["wall_time_s"] - previous["wall_time_s"])
        previous = row
    return None


def evaluate(run: dict, truth: Path, pixels: int, seed: int, threads: int,
             device: str = "cpu") -> dict:
    """PSNRs on common held-out pixels (the same for every model)."""
    import torch

    from seathru.nerf.inference import render_rays
    from seathru.eval.metrics import psnr
    from seathru.nerf.model import SeaThruModel
    from seathru.nerf.rays import frame_rays
    from seathru.io.cameras import read_cameras
    from seathru.io.images import read_image

    torch.set_num_threads(threads)
    cameras = read_cameras(truth / "cameras.json")
    model = SeaThruModel.from_checkpoint(torch.load(run["out"] / "model.pt", weights_only=True))
    model = model.to(device)
    rng = np.random.default_rng(seed)
    origins, dirs, near, far, water, clean, depth = [], [], [], [], [], [], []
    for frame in cameras.split("test"):
        o, d = frame_rays(frame)
        pick = rng.choice(o.shape[0], size=pixels // len(cameras.split("test")), replace=False)
        origins.append(o[pick])
        dirs.append(d[pick])
        near.append(torch.full((len(pick),), frame.near))
        far.append(torch.full((len(pick),), frame.far))
        water.append(read_image(cameras.image_path(frame)).reshape(-1, 3)[pick])
        clean.append(read_image(truth / "clean" / f"{frame.name}.tiff").reshape(-1, 3)[pick])
        depth.append(read_image(truth / "depth" / f"{frame.name}.tiff").reshape(-1)[pick])
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    started = time.perf_counter()
    out = render_rays(model, torch.cat(origins), torch.cat(dirs), torch.cat(near),
                      torch.cat(far), chunk=2048)
    seconds = time.perf_counter() - started
    water, clean, depth = np.concatenate(water), np.concatenate(clean), np.concatenate(depth)
    rgb, restored = out["rgb"].numpy(), out["restored"].numpy()
    finite = np.isfinite(clean).all(-1) & np.isfinite(depth)
    near_mask = finite & (depth < NEAR_RANGE_M)

    return {"pixels": len(water), "render_s": seconds,
            "psnr_full": psnr(rgb, water),
            "psnr_restored": psnr(restored[finite], clean[finite]),
            "psnr_restored_near": psnr(restored[near_mask], clean[near_mask]),
            "near_share": float(near_mask.mean())}


def water_table(runs: list[dict], truth: dict) -> list[str]:
    lines = ["| model | parameter | fitted (R, G, B) | truth (R, G, B) | relative error |",
             "|---|---|---|---|---|"]
    for run in runs:
        fitted = json.loads((run["out"] / "water.json").read_text())
        for key in ("sigma_attn", "sigma_bs", "c_med"):
            values = np.asarray(fitted[key], float)
            true = np.asarray(truth[key], float)
            err = np.abs(values - true) / np.abs(true)
            lines.append(f"| {run['name']} ({fitted['mode']}) | {key} | "
                         f"{', '.join(f'{v:.3f}' for v in values)} | "
                         f"{', '.join(f'{v:.3f}' for v in true)} | "
                         f"{', '.join(f'{100 * e:.0f}%' for e in err)} |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sim", type=Path, help="existing simulate output (holds truth/)")
    parser.add_argument("--minutes", type=float, default=3.0, help="training time per model")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--work", type=Path, default=None, help="scratch folder (default: tmp)")
    parser.add_argument("--eval-pixels", type=int, default=3072)
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--device", default="cpu", help="cpu | cuda (training and evaluation)")
    parser.add_argument("--ours-flags", default="",
                        help="extra train flags for our model, e.g. '--batch-rays 4096' on a GPU")
    args = parser.parse_args()

    sys.path.insert(0, str(REPO / "src"))
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_training_"))
    work.mkdir(parents=True, exist_ok=True)
    load_before = load_average()
    sim = args.sim or simulate_demo(work)
    truth = sim / "truth"
    cameras = truth / "cameras.json"

    ours_flags = args.ours_flags.split()
    runs = [train("ours", cameras, work, args.minutes, args.threads, ours_flags, args.device),
            train("paper", cameras, work, args.minutes, args.threads, PAPER_FLAGS, args.device)]
    for run in runs:
        run["eval"] = evaluate(run, truth, args.eval_pixels, 0, args.threads, args.device)
        print(run["name"], run["training"], run["eval"], flush=True)
    load_after = load_average()
    ours, paper = runs
    paper_final = paper["training"]["final_test_psnr"]
    reach = time_to(ours["rows"], paper_final)
    ratio = paper["training"]["elapsed_s"] / reach if reach else None
    truth_water = json.loads((truth / "water.json").read_text())
    selection = json.loads((ours["out"] / "selection.json").read_text())

    import torch

    lines = [
        "# Training benchmark: fast model vs paper-faithful configuration",
        "",
        f"Device: {device_name(args.device)}, {args.threads} CPU thread(s) requested (ours "
        f"picks 1 or {args.threads} by measuring on CPU), torch {torch.__version__}, "
        f"Python {platform.python_version()}"
        f"; load average before/after: {load_before} / {load_after}. Scene: "
        f"`{sim}` (demo dive: 24 views 320x240 orbit, default water, 21 train / 3 test views). "
        f"Each model trained {args.minutes} min of training time (log evaluations excluded), one "
        "after the other, written by `benchmarks/bench_training.py`"
        + (f"; ours with `{args.ours_flags}`." if ours_flags else "."),
        "",
        "| | ours | paper-faithful |",
        "|---|---|---|",
        f"| steps | {ours['training']['steps']} | {paper['training']['steps']} |",
        f"| steps/s | {ours['training']['steps_per_s']:.2f} | "
        f"{paper['training']['steps_per_s']:.3f} |",
        f"| rays/s | {ours['training']['rays_per_s']:.0f} | {paper['training']['rays_per_s']:.0f} |",
        f"| CPU threads at the end | {ours['training']['threads']} | "
        f"{paper['training']['threads']} |",
        f"| final held-out PSNR (log, 1024 test pixels) | {ours['training']['final_test_psnr']:.2f}"
        f" dB | {paper_final:.2f} dB |",
        f"| held-out PSNR, full rendering vs water images ({ours['eval']['pixels']} test pixels) "
        f"| {ours['eval']['psnr_full']:.2f} dB | {paper['eval']['psnr_full']:.2f} dB |",
        f"| restored vs clean truth, all surface pixels | {ours['eval']['psnr_restored']:.2f} dB "
        f"| {paper['eval']['psnr_restored']:.2f} dB |",
        f"| restored vs clean truth, range < {NEAR_RANGE_M:g} m "
        f"({100 * ours['eval']['near_share']:.0f}% of pixels) | "
        f"{ours['eval']['psnr_restored_near']:.2f} dB | "
        f"{paper['eval']['psnr_restored_near']:.2f} dB |",
        f"| render time for those pixels | {ours['eval']['render_s']:.2f} s | "
        f"{paper['eval']['render_s']:.2f} s |",
        "",
        f"Ours reaches the paper configuration's final held-out PSNR ({paper_final:.2f} dB) after "
        + (f"{reach:.1f} s of training: {ratio:.0f}x sooner than its {paper['training']['elapsed_s']:.0f} s "
           "(target >= 20x)." if reach else "— never (target missed)."),
        "",
        "Time (training seconds) to reach a held-out PSNR:",
        "",
        "| PSNR | " + " | ".join(f"{lvl:g} dB" for lvl in PSNR_LEVELS) + " |",
        "|---|" + "---|" * len(PSNR_LEVELS),
    ]
    for run in runs:
        cells = [time_to(run["rows"], lvl) for lvl in PSNR_LEVELS]
        lines.append(f"| {run['name']} | " + " | ".join("—" if c is None else f"{c:.1f}"
                                                     for c in cells) + " |")
    lines += ["", "Held-out PSNR against training time (ours):", "",
              "| step | s | test PSNR |", "|---|---|---|"]
    for row in ours["rows"]:
        if row["test_psnr"] is not None:
            lines.append(f"| {int(row['step'])} | {row['wall_time_s']:.1f} | "
                         f"{row['test_psnr']:.2f} |")
    lines += ["", f"Medium selection (ours, `medium.mode=auto`): **{selection['chosen']}** — "
              f"{selection['reason']}", "", "Fitted water against the truth (1/m; c_med linear):",
              "", *water_table(runs, truth_water), ""]
    text = "\n".join(lines) + "\n"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)
    print(f"written to {args.out}; work folder {work}")


if __name__ == "__main__":
    main()
