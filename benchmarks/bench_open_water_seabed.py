"""How much of the photographs' open water is seabed, by the truth and by the trained model?

The photographs' open-water detector (``seathru.radiometry.open_water``: smooth regions
reaching the top of the frame) also takes turbid water's far seabed. Refits from
``medium.open_water_surfaces_from`` take a pixel of it that the model renders as an opaque
surface short of its far bound as that surface (``water_surfaces.surface_data``). This checks
the premise on ``bench_water.py`` dives: per dive, the share of the mask's training pixels
with a surface in the simulator's true depth, against the share the trained model renders
opaque (object opacity above ``medium.refit_opacity``) short of
``medium.open_water_surface_share`` of the far bound, and the share it renders empty.

    python benchmarks/bench_open_water_seabed.py --work /tmp/bw/work/transect_turbid [...]

Writes benchmarks/results/open_water_seabed.md.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from machine import footer, load_average

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
RESULTS = REPO / "benchmarks" / "results" / "open_water_seabed.md"


def seabed_shares(sim: Path, variant: str = "cues") -> dict:
    """Shares of the photographs' open-water training pixels of one dive: with a true surface,
    rendered as a near surface, rendered empty (every pixel of the mask, every training view)."""
    from bench_water_intervals import trained_dive
    from seathru.geometry.upright import estimate_up
    from seathru.io.images import read_image
    from seathru.nerf.rays import frame_rays

    model, _, frames, images, masks, water_masks, in_view = trained_dive(
        sim, sim / f"train_{variant}")
    medium = model.config.medium
    flagged = seabed = surface = empty = 0
    for frame, image, water in zip(frames, images, water_masks):
        if water is None or not np.asarray(water).any():
            continue
        water = np.asarray(water, dtype=bool)
        truth = read_image(sim / "truth" / "depth" / f"{frame.name}.tiff")
        truth = truth[..., 0] if truth.ndim == 3 else truth
        rows, cols = np.nonzero(water)
        origins, directions = frame_rays(frame)
        index = torch.from_numpy(rows * water.shape[1] + cols)
        near = torch.full((len(rows),), float(frame.near))
        far = torch.full((len(rows),), float(frame.far))
        with torch.no_grad():
            render = model(origins[index], directions[index], near, far).render
        opaque = render.opacity > medium.refit_opacity
        short = render.depth_median < medium.open_water_surface_share * far
        flagged += len(rows)
        seabed += int(np.isfinite(truth[rows, cols]).sum())
        surface += int((opaque & short).sum())
        empty += int((render.opacity < medium.open_water_opacity).sum())
    share = (lambda n: n / flagged) if flagged else (lambda n: float("nan"))
    up = estimate_up(np.stack([f.c2w_array for f in frames]))
    # the simulator's world is z up, and the true cameras differ from it by a scale and shift
    tilt = float("nan") if up is None else float(np.degrees(np.arccos(np.clip(up.vector[2],
                                                                                -1, 1))))
    return {"dive": sim.name, "open_water_in_view": bool(in_view), "flagged": flagged,
            "vertical": "none" if up is None else up.method, "vertical_error_deg": tilt,
            "seabed_truth": share(seabed), "rendered_surface": share(surface),
            "rendered_empty": share(empty)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, action="append", required=True,
                        help="a bench_water.py dive folder (repeat for several)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    torch.set_num_threads(1)
    load, started = load_average(), time.time()
    rows = []
    for dive in args.work:
        rows.append(seabed_shares(dive))
        print(rows[-1], flush=True)
    lines = ["# The photographs' open water: seabed by the truth and by the trained model "
             "(`benchmarks/bench_open_water_seabed.py`)", "",
             "Every training pixel of each dive's photographs' open-water mask: the share with "
             "a surface in the simulator's true depth, the share the trained model renders as "
             "an opaque surface short of 0.9 of its far bound (what the refits from "
             "`medium.open_water_surfaces_from` take as surfaces), and the share it renders "
             "empty (object opacity below 0.1); and the vertical `geometry.upright` "
             "estimates from the training cameras, with its angle to the true one.", "",
             "| dive | mask pixels | seabed (truth) | rendered as a near surface | "
             "rendered empty | vertical (method, degrees off) |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['dive']} | {r['flagged']} | {100 * r['seabed_truth']:.0f}% | "
                     f"{100 * r['rendered_surface']:.0f}% | {100 * r['rendered_empty']:.0f}% | "
                     f"{r['vertical']}, {r['vertical_error_deg']:.1f} |")
    lines += ["", "Dives: " + ", ".join(f"`{d}`" for d in args.work) + ".", "",
              footer(load, started), ""]
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
