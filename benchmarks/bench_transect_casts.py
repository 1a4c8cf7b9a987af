"""Frame-to-frame colour casts that the range term makes, on the water benchmark's dives: the
simulator's images have one white balance, so every cast found is the range term's misfit.

    python benchmarks/bench_transect_casts.py --work /tmp/bw/work [/tmp/other/work ...]

Reads each dive of ``bench_water.py``'s work folders (``truth/cameras.json`` and the true
surfaces' sparse model), finds the training frames' offsets as the train step does
(``seathru.eval.track_slope.frame_colour_offsets``) and writes
``benchmarks/results/transect_casts.md``: per dive the spread with every pattern of offsets
(what decided before session 46) and without the range-like ones (what decides now), the
least share of a pattern the range term leaves unexplained, and how the red offsets follow the
frame's place along the path and its median range (correlations over the training frames).
No training: a few seconds a dive.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from machine import footer, load_average

OUT = Path(__file__).resolve().parent / "results" / "transect_casts.md"


def dive_row(folder: Path) -> str:
    from seathru.eval.track_slope import frame_colour_offsets
    from seathru.io import tracks
    from seathru.io.cameras import read_cameras

    cameras = read_cameras(folder / "truth" / "cameras.json")
    obs = tracks.track_observations(cameras, folder / "truth" / "sparse")
    train = ~obs.held_out
    windows = tracks.track_windows(cameras, obs)
    args = (obs.track_ids[train], obs.frames[train], obs.ranges[train],
            windows.observed[train])
    cast = frame_colour_offsets(*args)
    before = frame_colour_offsets(*args, range_like=0.0)
    frames = obs.frames[train]
    median_range = np.array([np.median(obs.ranges[train][frames == f]) for f in cast.frames])
    red = cast.offsets[:, 0]
    along = np.corrcoef(cast.frames, red)[0, 1]
    ranged = np.corrcoef(median_range, red)[0, 1]
    pair = ", ".join
    return (f"| {folder.name} | {pair(f'{v:.3f}' for v in cast.spread)} | "
            f"{'yes' if before.varies else 'no'} | "
            f"{pair(f'{v:.3f}' for v in cast.range_free_spread)} | "
            f"{'yes' if cast.varies else 'no'} | "
            f"{pair(f'{v:.3f}' for v in cast.least_unexplained)} | {along:+.2f} | "
            f"{ranged:+.2f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, nargs="+", required=True,
                        help="bench_water.py work folders (one dive per subfolder)")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    load, start = load_average(), time.time()
    dives = sorted({d.name: d for work in args.work for d in work.iterdir()
                    if (d / "truth" / "sparse").is_dir()}.items())
    lines = ["# Colour casts the range term makes (`benchmarks/bench_transect_casts.py`)", "",
             "The water benchmark's dives (the simulator's images: no frame has a cast of its "
             "own), their training frames' offsets along the true surfaces' tracks as the train "
             "step finds them. Spreads: log red / green, log blue / green, root mean square "
             "against the median frame; every pattern: as decided before session 46; "
             "range-free: without the patterns the range term explains all but "
             "`FRAME_COLOUR_RANGE_LIKE` of (decides now); least unexplained: the smallest "
             "share of a pattern of offsets the range term leaves unexplained; the last two "
             "columns: the red offsets' correlation with the frame's place along the path and "
             "with its median range. Since session 46 the train step corrects none of these "
             "(`one_white_balance`: the simulator's images).", "",
             "| dive | spread, every pattern | varies | range-free spread | varies | least "
             "unexplained | red vs place | red vs range |",
             "|---|---|---|---|---|---|---|---|",
             *(dive_row(folder) for _, folder in dives), "",
             f"Work folders: {', '.join(str(w) for w in args.work)}.", "",
             footer(load, start)]
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
