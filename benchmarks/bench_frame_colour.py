"""How well the photographs' frame-to-frame colour casts are found, against the truth: simulated
dives whose camera JPEGs are white-balanced frame by frame (``simulate.jpeg_white_balance=auto``),
through ingest and COLMAP (no training), then ``seathru.eval.track_slope.frame_colour_offsets``
on the training frames' tracks as the train step calls it, against the gains the simulator
applied (recomputed from its DNGs as it developed them).

    python benchmarks/bench_frame_colour.py --work /tmp/frame_colour

Writes ``benchmarks/results/frame_colour.md``: per dive the spread of the true casts and of
those found, the error of the offsets found (root mean square and largest, log red / green and
blue / green, against the median frame), and whether the cast is judged to vary. Where
``../shared/data/d3_reef`` is present its real frames run too (no truth: the spread only).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from machine import footer, load_average
from workflow_sheet import REPO, run_sheet, sheet_arguments

REEF = REPO.parent / "shared" / "data" / "d3_reef"
OUT = REPO / "benchmarks" / "results" / "frame_colour.md"
BALANCED = "ingest.images=jpeg; simulate.jpeg_white_balance=auto"
DIVES = {
    "survey_seed0": f"{BALANCED}; simulate.seed=0",
    "survey_seed1": f"{BALANCED}; simulate.seed=1",
    "survey_seed2": f"{BALANCED}; simulate.seed=2",
    "survey_turbid": f"{BALANCED}; simulate.water=turbid",
    "transect": f"{BALANCED}; simulate.path=transect",
    "transect_turbid": f"{BALANCED}; simulate.path=transect; simulate.water=turbid",
    "orbit": f"{BALANCED}; simulate.path=orbit",
    "survey_plain_jpeg": "ingest.images=jpeg",
    "transect_plain_jpeg": "ingest.images=jpeg; simulate.path=transect",
    "transect_turbid_plain_jpeg": "ingest.images=jpeg; simulate.path=transect; "
                                  "simulate.water=turbid",
}



def run_poses(work: Path, cores: int) -> None:
    rows = [f"{name}\tsimulated\t\t{options}\t" for name, options in DIVES.items()]
    targets = [f"results/{name}/poses" for name in DIVES]
    if REEF.is_dir():
        rows.append(f"reef\timages\t{REEF}\t\t")
        targets.append("results/reef/poses")
    run_sheet(work, rows, cores, tuple(targets))


def true_offsets(root: Path) -> dict[str, np.ndarray]:
    """Each simulated frame's white balance as log red / green and blue / green, developed
    from its DNG as ``seathru.sim.sensor.develop_jpeg`` does."""
    import rawpy

    from seathru.sim import sensor

    recorded = json.loads((root / "simulate" / "truth" / "sensor.json").read_text())
    config = sensor.SensorConfig(black_level=recorded["black_level"],
                                 white_level=recorded["white_level"],
                                 jpeg_white_balance=recorded["jpeg_white_balance"])
    offsets = {}
    for path in sorted((root / "simulate" / "raw").glob("*.dng")):
        with rawpy.imread(str(path)) as raw:
            mosaic = raw.raw_image_visible.copy()
        gains = np.ones(3)
        if config.jpeg_white_balance == "auto":
            gains = sensor.auto_white_balance_gains(
                sensor.normalise_raw(sensor.demosaic_bilinear(mosaic), config))
        offsets[path.stem] = np.log([gains[0] / gains[1], gains[2] / gains[1]])
    return offsets


def found_offsets(root: Path):
    """The training frames' casts as the train step finds them
    (``seathru.io.tracks.input_colour_change``), the same decided on every pattern of offsets
    (``range_like=0``, as before session 46), and the frames' names."""
    from seathru.eval.track_slope import frame_colour_offsets
    from seathru.io import tracks
    from seathru.io.cameras import read_cameras

    cameras = read_cameras(root / "poses" / "cameras.json")
    obs = tracks.track_observations(cameras, cameras.root / tracks.SPARSE_DIR)
    windows = tracks.track_windows(cameras, obs)
    train = ~obs.held_out
    args = (obs.track_ids[train], obs.frames[train], obs.ranges[train],
            windows.observed[train])
    return (frame_colour_offsets(*args), frame_colour_offsets(*args, range_like=0.0),
            obs.names)


def _pair(values) -> str:
    return ", ".join(f"{v:.3f}" for v in values)


def dive_row(work: Path, name: str) -> str:
    root = work / "results" / name
    if not (root / "poses" / "cameras.json").is_file():
        return f"| {name} | no poses (see {work}/logs/{name}) |" + " |" * 7
    cast, before, names = found_offsets(root)
    verdicts = " | ".join("yes" if c.varies else "no" for c in (cast, before))
    free = f"{_pair(cast.range_free_spread)} | {_pair(cast.least_unexplained)}"
    if name == "reef":
        return (f"| reef (d3_reef, no truth) | - | {_pair(cast.spread)} | - | - | {free} | "
                f"{verdicts} |")
    truth = true_offsets(root)
    on_frames = np.array([truth[Path(names[int(f)]).stem] for f in cast.frames])
    on_frames -= np.median(on_frames, axis=0)
    spread = np.sqrt(np.mean(on_frames ** 2, axis=0))       # as FrameColour.spread
    error = cast.offsets - on_frames
    error -= np.median(error, axis=0)
    return (f"| {name} | {_pair(spread)} | {_pair(cast.spread)} | "
            f"{_pair(np.sqrt((error ** 2).mean(axis=0)))} | {_pair(np.abs(error).max(axis=0))} "
            f"| {free} | {verdicts} |")


def main() -> None:
    args = sheet_arguments(__doc__.splitlines()[0], Path("/tmp/frame_colour"), OUT)
    load_before, start = load_average(), time.time()
    if not args.summarise_only:
        run_poses(args.work, args.cores)
    names = list(DIVES) + (["reef"] if (args.work / "results" / "reef").is_dir() else [])
    lines = [
        "# Frame-to-frame colour casts found against the truth "
        "(`benchmarks/bench_frame_colour.py`)", "",
        "Simulated dives (24 views at 320x240) whose camera JPEGs are white-balanced frame by "
        "frame (grey world within 4x), through ingest and COLMAP; the training frames' casts "
        "(`frame_colour_offsets`, as the train step calls it) against the simulator's gains. "
        "Errors in log red / green, blue / green, both sides against their median frame; "
        "spread: the root mean square of the true casts and of those found over the training "
        "frames, against the median frame; varies: judged to vary (the train step corrects "
        "it). `survey_plain_jpeg`, `transect_plain_jpeg`, `transect_turbid_plain_jpeg`: no "
        "white balance (the true casts are all zero). Range-free spread: the spread of the "
        "offsets without their range-like patterns (those the range term explains all but "
        "`FRAME_COLOUR_RANGE_LIKE` of), which decides whether the cast varies; least "
        "unexplained: the smallest share of a pattern of offsets the range term leaves "
        "unexplained; varies before: decided on the whole spread, as before session 46.", "",
        "| dive | true spread | spread found | error: rms | largest | range-free spread | "
        "least unexplained | varies | varies before |",
        "|---|---|---|---|---|---|---|---|---|",
        *(dive_row(args.work, name) for name in names), "",
        footer(load_before, start),
    ]
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
