"""When can the view-dependence trial see what view-dependent colour adds? (a script)

A small simulated dive (16 views at 64x48, default water, true cameras; Lambertian, as every
simulated reef) is trained for 300 steps, plain and with every pixel tinted by ``1 + t d_x``
(brighter seen towards +x: a colour that really changes with direction), and the trial of
``Trainer.select_view_dependence`` is run at two points of the run. Printed per case: the trial's
held-out gain with the direction (dB) over several initial weights, and what the default margin
(``field.view_margin_db``) would choose. The trial must see the tint (gain above the margin) and
must not see the plain scene (gain near 0). Writes benchmarks/results/view_trial.md.

    python benchmarks/bench_view_trial.py [--seeds 4] [--tint 0.6]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from machine import cpu_name, load_average

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
RESULTS = REPO / "benchmarks" / "results" / "view_trial.md"


def trial_gain(scene: Path, tint: float, select_at: float, seed: int) -> float:
    from seathru import settings
    from seathru.io.cameras import read_cameras
    from seathru.io.images import read_image
    from seathru.nerf.config import TrainConfig
    from seathru.nerf.model import SeaThruModel, scene_from_frames
    from seathru.nerf.rays import RayDataset
    from seathru.nerf.training import Trainer

    cameras = read_cameras(scene / "cameras.json")
    train = cameras.split("train")
    data = RayDataset(train, [read_image(cameras.image_path(f)) for f in train])
    directions = data.batch(torch.arange(len(data))).directions
    data.rgb = data.rgb * (1 + tint * directions[:, :1])
    description = scene_from_frames(train, cameras.near, cameras.far, cameras.centre,
                                    cameras.scale, data.rgb.mean(0).tolist())
    config = settings.from_mapping(TrainConfig, {
        "preset": "balanced", "steps": 300, "max_minutes": 0, "batch_rays": 256,
        "eval_rays": 256, "medium": {"mode": "global"},
        "field": {"density_res": [32, 48, 64], "plane_res": [128, 192, 256],
                  "plane_coarse_res": 32, "density_coarse_res": 16,
                  "view_select_at": select_at, "view_trial_share": 0.2},
        "sampler": {"samples_per_ray": 12}})
    torch.manual_seed(seed)
    trainer = Trainer(SeaThruModel(config, description), data, frames=train)
    trainer.run()
    chosen = trainer.view_selection
    return chosen["validation_psnr_on"] - chosen["validation_psnr_off"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--tint", type=float, default=0.6)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    from seathru.nerf.config import FieldConfig
    from seathru.steps.simulate import Settings, simulate

    torch.set_num_threads(1)
    margin = FieldConfig().view_margin_db
    started = time.time()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        simulate(Path(tmp), Settings(views=16, width=64, height=48, water="default",
                                     supersample=3, test_every=8, seed=1))
        for tint in (0.0, args.tint):
            for select_at in (0.1, 0.3):
                gains = [trial_gain(Path(tmp) / "truth", tint, select_at, seed)
                         for seed in range(args.seeds)]
                kept = sum(g > margin for g in gains)
                rows.append(f"| {tint:g} | {select_at:g} | "
                            f"{', '.join(f'{g:+.2f}' for g in gains)} | {np.mean(gains):+.2f} | "
                            f"{kept} of {len(gains)} |")
                print(rows[-1], flush=True)
    lines = ["# The view-dependence trial (`benchmarks/bench_view_trial.py`)", "",
             "A 16-view 64x48 simulated dive (Lambertian), 300 steps, trial of 20% of the run "
             "per branch at the given progress; tint t: every pixel times 1 + t d_x. Gain: "
             "held-out PSNR with the view direction minus without, per initial weights (seed). "
             f"Kept: gain above the default margin ({margin:g} dB).", "",
             "| tint | trial at | gain per seed (dB) | mean | kept |", "|---|---|---|---|---|",
             *rows, "",
             f"Machine: {cpu_name()}, 1 torch thread; load {load_average()}; "
             f"{time.strftime('%Y-%m-%d')}; {(time.time() - started) / 60:.0f} min in all.", ""]
    args.out.write_text("\n".join(lines))


if __name__ == "__main__":
    main()
