"""Where the photographs' open water looks: above or below the horizon the cameras imply (a script).

For simulated dives (the water benchmark's: 16 views at 160x120, true cameras) the open-water
mask (``seathru.nerf.prepare.open_water_in_view``, as training uses it) is split by the
simulator's true depth into real open water (no surface) and surfaces taken for it; for each,
the angle of the pixels' rays above the horizon of ``seathru.geometry.upright.estimate_up``
(5th, 50th, 95th percentile) and the share more than ``medium.horizon_margin`` below it. The
estimated vertical is compared with the simulator's (its world z axis; the camera file only
moves and scales it). With ``--colmap CAMERAS``, the same for a real dataset's camera file
(no truth: all flagged pixels together).

    python benchmarks/bench_horizon.py [--paths orbit,transect,survey]
        [--waters default,turbid,coastal_3c] [--work DIR] [--colmap results/d3_reef/poses/cameras.json]

Writes benchmarks/results/horizon.md. Needs no training (about a minute a dive to simulate).
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from machine import cpu_name

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
RESULTS = REPO / "benchmarks" / "results" / "horizon.md"


def elevations(cameras_path: Path, truth: Path | None) -> dict:
    """Per-pixel elevations (degrees) of the flagged open water, split by the true depth."""
    from seathru.geometry.upright import estimate_up
    from seathru.io.cameras import read_cameras
    from seathru.io.evaluation import read_truth_image
    from seathru.io.training import read_frame_images
    from seathru.nerf.config import TrainConfig
    from seathru.nerf.prepare import open_water_in_view
    from seathru.nerf.rays import frame_rays

    cameras = read_cameras(cameras_path)
    frames = cameras.split("train")
    up = estimate_up(np.stack([f.c2w_array for f in frames]))
    record = {"method": "none (cameras disagree)" if up is None else up.method}
    if up is None:
        return record
    vertical = np.array(up.vector)
    record["tilt_deg"] = math.degrees(math.acos(np.clip(vertical[2], -1.0, 1.0))) \
        if truth is not None else None
    images, masks = read_frame_images(cameras, frames)
    water_masks, share, _ = open_water_in_view(TrainConfig(), images, masks)
    record["flagged_share"] = share
    groups: dict[str, list[np.ndarray]] = {"open water": [], "surface": [], "flagged": []}
    for frame, mask in zip(frames, water_masks):
        _, directions = frame_rays(frame)
        angle = np.degrees(np.arcsin(np.clip(directions.numpy().astype(np.float64) @ vertical,
                                             -1.0, 1.0))).reshape(mask.shape)
        if truth is None:
            groups["flagged"].append(angle[mask])
            continue
        depth = read_truth_image(truth, "depth", frame.name)
        depth = depth[..., 0] if depth.ndim == 3 else depth
        infinite = ~np.isfinite(depth) | (depth > 1e3)
        groups["open water"].append(angle[mask & infinite])
        groups["surface"].append(angle[mask & ~infinite])
    record["groups"] = {name: np.concatenate(parts) for name, parts in groups.items() if parts}
    return record


def row(name: str, record: dict, margin: float) -> list[str]:
    lines = []
    tilt = record.get("tilt_deg")
    tilt_text = "" if tilt is None else f"{tilt:.1f}"
    for group, values in record.get("groups", {}).items():
        if len(values) == 0:
            continue
        low, mid, high = np.percentile(values, [5, 50, 95])
        lines.append(f"| {name} | {record['method']} | {tilt_text} | "
                     f"{100 * record['flagged_share']:.1f}% | {group} | {len(values)} | "
                     f"{low:+.1f}, {mid:+.1f}, {high:+.1f} | "
                     f"{100 * float(np.mean(values < -margin)):.1f}% |")
    if not lines:
        lines.append(f"| {name} | {record['method']} | {tilt_text} | "
                     f"{100 * record.get('flagged_share', 0.0):.1f}% | none | 0 | | |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--paths", default="orbit,transect,survey")
    parser.add_argument("--waters", default="default,turbid,coastal_3c")
    parser.add_argument("--views", type=int, default=16)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work", type=Path, default=None,
                        help="folder of simulated dives <path>_<water> (made where missing)")
    parser.add_argument("--colmap", type=Path, action="append", default=[],
                        help="a real dataset's camera file (the poses step's cameras.json)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    from bench_water import simulate
    from seathru.nerf.config import MediumConfig

    margin = MediumConfig().horizon_margin
    started = time.perf_counter()
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_horizon_"))
    lines = ["# Open water above and below the horizon (`benchmarks/bench_horizon.py`)", "",
             f"Open-water mask as training uses it; elevation of its pixels' rays above the "
             f"horizon of `seathru.geometry.upright.estimate_up` (degrees, 5th/50th/95th "
             f"percentile); below: the share more than `medium.horizon_margin` "
             f"({margin:g} degrees) below. Simulated dives ({args.views} views at "
             f"{args.width}x{args.height}, true cameras): the flagged pixels split by the "
             f"simulator's true depth; tilt: angle between the estimated and the simulator's "
             f"vertical.", "",
             "| dive | vertical from | tilt (deg) | flagged pixels | group | pixels | "
             "elevation (deg) | below |", "|---|---|---|---|---|---|---|---|"]
    for path in args.paths.split(","):
        for water in args.waters.split(","):
            sim = simulate(work, path, water, args)
            record = elevations(sim / "truth" / "cameras.json", sim / "truth")
            lines += row(f"{path} {water}", record, margin)
            print(lines[-1], flush=True)
    for cameras in args.colmap:
        record = elevations(cameras, None)
        lines += row(cameras.parent.parent.name, record, margin)
        print(lines[-1], flush=True)
    lines += ["", f"Machine: {cpu_name()}; {time.strftime('%Y-%m-%d')}; "
              f"{(time.perf_counter() - started) / 60:.1f} min in all."]
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
