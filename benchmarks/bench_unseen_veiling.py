"""water.json's intervals with and without the allowance for the veiling light beyond the
farthest surfaces (``medium.interval_unseen_veiling``), on trained models, against the truth;
and, tried and not kept, with an allowance for bent ranges on top (``BEND``).

For every model of a ``bench_water.py`` work folder (``--work``), the train step's final water
assessment is redone as it builds it (``bench_water_intervals.model_surfaces``: the model's
own training rays and surfaces, open water from the photographs and the horizon, the
regroupings of ``medium.interval_voxel_factors``; then ``water_fit.fit_surfaces`` and
``water_uncertainty.robust_halfwidths`` with the model's ``medium.interval_*`` settings), once
without the allowance and once with it. Each interval is centred on the trained value and
widened by its distance to the surface fit, as water.json's are
(``water_interval.interval_halfwidth``); flagged = not determined
(``water_uncertainty.interval_determined``). Per model: the truth held, the values more than
5% off and flagged, the values within 5% and flagged, for both.

    python benchmarks/bench_unseen_veiling.py --work /tmp/bench_water [--out FILE]

Writes benchmarks/results/unseen_veiling.md (and .json with every interval).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch

from machine import footer, load_average

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
RESULTS = REPO / "benchmarks" / "results" / "unseen_veiling.md"
KEYS = ("sigma_attn", "sigma_bs", "c_med")
ARMS = {"without": False, "with": True, "bent": True}
#: the "bent" arm (tried, not kept): "with", plus the move of the fit on ranges bent by
#: ``(z / median) ** +-BEND`` (far surfaces placed farther or shorter than near ones)
BEND = 0.1


def assess(sim: Path, train: Path) -> dict:
    from bench_water_intervals import model_surfaces
    from seathru.nerf.water_fit import fit_surfaces
    from seathru.nerf.water_interval import interval_halfwidth
    from seathru.nerf.water_uncertainty import (far_surface_range, interval_determined,
                                                robust_halfwidths)

    data, model, truth, trained, _, regrouped = model_surfaces(sim, train, regroup=True)
    row = {"model": sim.name, "truth": truth, "trained": trained}
    if isinstance(data, str):
        return {**row, "skipped": data}
    medium = model.config.medium
    fit, used = fit_surfaces(data, trained, medium.refit_steps, model.medium.colour_max,
                             medium.dark_pixel_bound, medium.balance_brightness,
                             medium.refit_trim)
    beyond = far_surface_range(used.ranges) if used.open_water_below_horizon else None
    row["surface_fit"] = {k: getattr(fit, k) for k in KEYS}
    row["open_water_pixels"] = int((~torch.isfinite(used.ranges)).sum())
    for arm, unseen in ARMS.items():
        spread = robust_halfwidths(
            fit, used.ranges, used.observed, used.ids, used.groups,
            colour_max=model.medium.colour_max, open_water_beyond=beyond,
            dark=used.dark if medium.dark_pixel_bound else None,
            range_error=medium.interval_range_error, min_relative=medium.interval_floor,
            regrouped=[(d.ranges, d.observed, d.ids, d.groups) for d in regrouped
                       if not isinstance(d, str)],
            unseen_veiling=unseen)
        if arm == "bent":
            spread.halfwidth = _with_bend(fit, used, spread, model.medium.colour_max,
                                          medium.balance_brightness, medium.interval_floor)
        determined = interval_determined(trained, fit, spread.halfwidth)
        held, off_flagged, good_flagged, off = [], [], [], []
        for key in KEYS:
            for ch in range(3):
                t, f, true = trained[key][ch], getattr(fit, key)[ch], truth[key][ch]
                half = interval_halfwidth(t, f, spread.halfwidth[key][ch])
                held.append(abs(t - true) <= half)
                far_off = abs(t - true) > 0.05 * abs(true)
                off.append(far_off)
                (off_flagged if far_off else good_flagged).append(not determined[key][ch])
        row[arm] = {"halfwidth": spread.halfwidth, "determined": determined,
                    "held": sum(held), "off": sum(off), "off_flagged": sum(off_flagged),
                    "good": 9 - sum(off), "good_flagged": sum(good_flagged)}
    return row


def _with_bend(fit, used, spread, colour_max: float, balance: bool,
               floor: float) -> dict[str, list[float]]:
    """``spread``'s half-widths with the larger move of the fit on ranges bent by
    ``(z / median) ** +-BEND`` as one more systematic part (fitted without the dark bound, as
    robust_halfwidths' own refits)."""
    from seathru.nerf.water_fit import fit_water, water_start, water_vector

    ranges, observed = used.ranges.double(), used.observed.double()
    finite = torch.isfinite(ranges)
    middle = ranges[finite].median()
    whole = water_vector(fit_water(ranges, observed, used.ids, used.groups, water_start(fit),
                                   100, colour_max, balance_brightness=balance))
    moves = []
    for bend in (-BEND, BEND):
        bent = torch.where(finite, ranges * (ranges / middle).clamp_min(1e-6) ** bend, ranges)
        moves.append(water_vector(fit_water(bent, observed, used.ids, used.groups,
                                            water_start(fit), 100, colour_max,
                                            balance_brightness=balance)) - whole)
    move = (1.96 * torch.stack(moves).abs().amax(0)).tolist()
    return {key: [max(math.hypot(stat, max(sys, move[3 * i + ch])), floor * abs(value))
                  for ch, (stat, sys, value) in enumerate(zip(
                      spread.statistical[key], spread.systematic[key], getattr(fit, key)))]
            for i, key in enumerate(KEYS)}


def write(rows: list[dict], args, load: str, started: float) -> None:
    done = [r for r in rows if "skipped" not in r]
    lines = ["# The veiling light beyond the farthest surfaces in water.json's intervals "
             "(`benchmarks/bench_unseen_veiling.py`)", "",
             f"Models of `{args.work}` (`bench_water.py`: 16 views at 160x120, true cameras, "
             "3 min each); the train step's final water assessment redone on each, without and "
             "with `medium.interval_unseen_veiling` (only where no open water is in view does "
             "it change anything). Intervals around the trained value, widened by its distance "
             "to the surface fit, as water.json's. held = intervals holding the truth; off "
             "flagged = values more than 5% off the truth flagged as not determined; good "
             "flagged = values within 5% flagged.", "",
             f"bent: with, and the move of the fit on ranges bent by (z / median)^(+-{BEND}) as "
             "one more systematic part (tried, not kept).", "",
             "| model | open-water pixels | held (without / with / bent) | off flagged | "
             "good flagged |", "|---|---|---|---|---|"]
    for r in rows:
        if "skipped" in r:
            lines.append(f"| {r['model']} | skipped: {r['skipped']} | | | |")
            continue
        a, b, c = (r[arm] for arm in ARMS)
        lines.append(f"| {r['model']} | {r['open_water_pixels']} | {a['held']} / {b['held']} / "
                     f"{c['held']} | {a['off_flagged']} / {b['off_flagged']} / "
                     f"{c['off_flagged']} of {a['off']} | {a['good_flagged']} / "
                     f"{b['good_flagged']} / {c['good_flagged']} of {a['good']} |")
    for prefix in sorted({r["model"].split("_")[0] for r in done}):
        part = [r for r in done if r["model"].split("_")[0] == prefix]
        total = {arm: {k: sum(r[arm][k] for r in part) for k in
                       ("held", "off", "off_flagged", "good", "good_flagged")} for arm in ARMS}
        a, b, c = (total[arm] for arm in ARMS)
        lines += ["", f"- **{prefix}** ({len(part)} models, {9 * len(part)} values): intervals "
                  f"hold the truth in {a['held']} without, {b['held']} with, {c['held']} bent; "
                  f"of the {a['off']} values more than 5% off, {a['off_flagged']} flagged "
                  f"without, {b['off_flagged']} with, {c['off_flagged']} bent; of the "
                  f"{a['good']} within 5%, {a['good_flagged']} flagged without, "
                  f"{b['good_flagged']} with, {c['good_flagged']} bent."]
    lines += ["", footer(load, started) + " 1 torch thread.", ""]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines))
    args.out.with_suffix(".json").write_text(json.dumps(rows, indent=1))
    print("\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, required=True,
                        help="a bench_water.py work folder with trained models")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    torch.set_num_threads(1)
    started, load = time.time(), load_average()
    rows = []
    for train in sorted(args.work.glob("*/train_*")):
        if (train / "model.pt").exists() and (train.parent / "truth" / "water.json").exists():
            rows.append(assess(train.parent, train))
            print(rows[-1]["model"], rows[-1].get("skipped") or
                  {arm: rows[-1][arm]["held"] for arm in ARMS}, flush=True)
    write(rows, args, load, started)


if __name__ == "__main__":
    main()
