"""What the water does after its last refit: the refit's values against the trained ones.

A refit holds only the values it determines within ``medium.hold_max_relative``; the others
keep training until the end. For every ``*/train_*`` run of a ``bench_water.py`` work folder,
the last refit's values (``selection.json`` ``water_refits``, after acceptance) and the final
trained water (``water.json``), both as % error against the simulator's water, with whether
the refit accepted each value. Reads finished runs only; trains nothing.

    python benchmarks/bench_refit_drift.py --work /tmp/bench_water [--out FILE]

Writes benchmarks/results/refit_drift.md.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "refit_drift.md"
KEYS = ("sigma_attn", "sigma_bs")


def errors(values, truth, factor: float) -> str:
    return " ".join(f"{100 * (v * factor / t - 1):+.0f}" for v, t in zip(values, truth))


def run_row(train: Path) -> str | None:
    selection = json.loads((train / "selection.json").read_text())
    refits = selection.get("water_refits") or []
    if not refits:
        return None
    water = json.loads((train / "water.json").read_text())
    truth = json.loads((train.parent / "truth" / "water.json").read_text())
    factor = water["scale"] / water.get("metres_per_source_unit", 1.0)
    last = refits[-1]
    cells = [f"{train.parent.name}/{train.name}", f"{last['progress']:.2f}"]
    for key in KEYS:
        accepted = last.get("accepted", {}).get(key) or []
        cells += [errors(last.get("after", last["fitted"])[key], truth[key], factor),
                  errors(water["normalised"][key], truth[key], factor),
                  "".join("y" if a else "n" for a in accepted)]
    return "| " + " | ".join(cells) + " |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    rows = [row for train in sorted(args.work.glob("*/train_*"))
            if (train / "water.json").exists() and (row := run_row(train))]
    lines = ["# The water after its last refit (`benchmarks/bench_refit_drift.py`)", "",
             f"Runs: `{args.work}`. Errors in % of the simulator's water (R G B); accepted: "
             "whether the last refit took each value (a value is held to the end only if "
             "also determined within `medium.hold_max_relative`).", "",
             "| run | last refit at | `sigma_attn` at the refit | at the end | accepted | "
             "`sigma_bs` at the refit | at the end | accepted |",
             "|---|---|---|---|---|---|---|---|", *rows, "",
             f"{time.strftime('%Y-%m-%d')}.", ""]
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
