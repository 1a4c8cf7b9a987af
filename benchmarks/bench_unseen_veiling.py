"""water.json's intervals with and without the allowance for the veiling light beyond the
farthest surfaces (``medium.interval_unseen_veiling``), on trained models, against the truth.

Arms (``--arms``, default ``without,analytic,with``): ``without`` the allowance; ``analytic``,
the allowance as it was until session 45 (``sigma_bs`` and ``c_med`` moved along the backscatter
curve, the attenuation left alone; rebuilt from the same assessment's comparisons);
``with``, the allowance as the train step makes it (the attenuation refitted with ``c_med``
held at each end of the slide: ``water_uncertainty.veiling_slide``); ``bent``, tried in session
37 and not kept: ``with`` plus an allowance for bent ranges (``BEND``; its figure in
``unseen_veiling.md`` was made on top of the analytic allowance, at commit 734721d).

For every model of a ``bench_water.py`` work folder (``--work``), the train step's final water
assessment is redone as it builds it (``bench_water_intervals.model_surfaces``: the model's
own training rays and surfaces, open water from the photographs and the horizon, the
regroupings of ``medium.interval_voxel_factors``; then ``water_fit.fit_surfaces`` and
``water_uncertainty.robust_halfwidths`` with the model's ``medium.interval_*`` settings), once
per arm. Each interval is centred on the trained value and
widened by its distance to the surface fit, as water.json's are
(``water_interval.interval_halfwidth``); flagged = not determined
(``water_uncertainty.interval_determined``). Per model: the truth held, the values more than
5% off and flagged, the values within 5% and flagged, for each arm.

    python benchmarks/bench_unseen_veiling.py --work /tmp/bench_water [--arms A,B] [--out FILE]

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
ARMS = ("without", "analytic", "with", "bent")
#: the "bent" arm (tried, not kept): "with", plus the move of the fit on ranges bent by
#: ``(z / median) ** +-BEND`` (far surfaces placed farther or shorter than near ones)
BEND = 0.1


def assess(sim: Path, train: Path, arms: list[str]) -> dict:
    from bench_water_intervals import model_surfaces
    from seathru.nerf.water_interval import interval_halfwidth
    from seathru.nerf.water_refit import medium_surface_fit
    from seathru.nerf.water_uncertainty import (far_surface_range, interval_determined,
                                                robust_halfwidths)

    data, model, truth, trained, _, regrouped = model_surfaces(sim, train, regroup=True)
    row = {"model": f"{sim.name}/{train.name}", "truth": truth, "trained": trained}
    if isinstance(data, str):
        return {**row, "skipped": data}
    medium = model.config.medium
    fit, used = medium_surface_fit(data, trained, medium, model.medium.colour_max)
    beyond = far_surface_range(used.ranges) if used.open_water_below_horizon else None
    row["surface_fit"] = {k: getattr(fit, k) for k in KEYS}
    row["open_water_pixels"] = int((~torch.isfinite(used.ranges)).sum())
    for arm in arms:
        started = time.perf_counter()
        spread = robust_halfwidths(
            fit, used.ranges, used.observed, used.ids, used.groups,
            colour_max=model.medium.colour_max, open_water_beyond=beyond,
            dark=used.dark if medium.dark_pixel_bound else None,
            range_error=medium.interval_range_error, min_relative=medium.interval_floor,
            regrouped=[(d.ranges, d.observed, d.ids, d.groups) for d in regrouped
                       if not isinstance(d, str)],
            unseen_veiling=arm != "without")
        if arm == "analytic":
            spread.halfwidth = _attenuation_not_slid(fit, spread, medium.interval_floor)
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
        row[arm] = {"seconds": time.perf_counter() - started,
                    "halfwidth": spread.halfwidth, "determined": determined,
                    "held": sum(held), "off": sum(off), "off_flagged": sum(off_flagged),
                    "good": 9 - sum(off), "good_flagged": sum(good_flagged)}
    return row


def _attenuation_not_slid(fit, spread, floor: float) -> dict[str, list[float]]:
    """``spread``'s half-widths with the unseen veiling light's comparison leaving the
    attenuation alone, as before session 45 (the other comparisons as they are)."""
    parts = [[(h / 1.96) ** 2 for h in halves] for name, halves in spread.splits.items()]
    for name, variance in zip(spread.splits, parts):
        if name == "veiling_beyond_surfaces":
            variance[0:3] = [0.0] * 3
    tau2 = [max(column) for column in zip(*parts)] if parts else [0.0] * 9
    return {key: [max(1.96 * math.sqrt((stat / 1.96) ** 2 + tau2[3 * i + ch]),
                      floor * abs(value))
                  for ch, (stat, value) in enumerate(zip(spread.statistical[key],
                                                         getattr(fit, key)))]
            for i, key in enumerate(KEYS)}


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
    arms, slash = args.arms, " / ".join(args.arms)
    lines = ["# The veiling light beyond the farthest surfaces in water.json's intervals "
             "(`benchmarks/bench_unseen_veiling.py`)", "",
             f"Models of {', '.join(f'`{w}`' for w in args.work)} (`bench_water.py`: 16 views "
             "at 160x120, true cameras, 3 min each); the train step's final water assessment "
             "redone on each under every arm (only where no open water is in view does the "
             "allowance change anything): without = no allowance; analytic = the allowance "
             "before session 45 (the attenuation left alone); with = the attenuation refitted at "
             "each end of the veiling light's slide (the train step's); bent = with, and the "
             f"move of the fit on ranges bent by (z / median)^(+-{BEND}) (tried, not kept). "
             "Intervals around the trained value, widened by its distance to the surface fit, "
             "as water.json's. held = intervals holding the truth; off flagged = values more "
             "than 5% off the truth flagged as not determined; good flagged = values within 5% "
             "flagged; `sigma_attn` half-width: the median over the model's three channels, as "
             "a share of the trained value; seconds: `robust_halfwidths` on one thread (the "
             "analytic arm runs the with arm's assessment and rebuilds its half-widths, so "
             "the refits' cost is with less without).", "",
             f"| model | open-water pixels | held ({slash}) | off flagged | good flagged | "
             "`sigma_attn` half-width | seconds |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        if "skipped" in r:
            lines.append(f"| {r['model']} | skipped: {r['skipped']} | | | | | |")
            continue
        first = r[arms[0]]
        seconds = " / ".join(f"{r[a]['seconds']:.1f}" for a in arms)
        lines.append(
            f"| {r['model']} | {r['open_water_pixels']} | "
            f"{' / '.join(str(r[a]['held']) for a in arms)} | "
            f"{' / '.join(str(r[a]['off_flagged']) for a in arms)} of {first['off']} | "
            f"{' / '.join(str(r[a]['good_flagged']) for a in arms)} of {first['good']} | "
            f"{' / '.join(_attenuation_width(r, a) for a in arms)} | {seconds} |")
    for prefix in sorted({r["model"].split("_")[0] for r in done}):
        part = [r for r in done if r["model"].split("_")[0] == prefix]
        total = {arm: {k: sum(r[arm][k] for r in part) for k in
                       ("held", "off", "off_flagged", "good", "good_flagged")} for arm in arms}
        first = total[arms[0]]

        def each(key: str) -> str:
            return ", ".join(f"{total[a][key]} {a}" for a in arms)

        lines += ["", f"- **{prefix}** ({len(part)} models, {9 * len(part)} values): intervals "
                  f"hold the truth in {each('held')}; of the {first['off']} values more than "
                  f"5% off, flagged: {each('off_flagged')}; of the {first['good']} within 5%, "
                  f"flagged: {each('good_flagged')}."]
    lines += ["", footer(load, started) + " 1 torch thread.", ""]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines))
    args.out.with_suffix(".json").write_text(json.dumps(rows, indent=1))
    print("\n".join(lines))


def _attenuation_width(row: dict, arm: str) -> str:
    shares = sorted(h / abs(t) if t else math.inf for h, t in zip(
        row[arm]["halfwidth"]["sigma_attn"], row["trained"]["sigma_attn"]))
    return f"{100 * shares[1]:.0f}%"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, nargs="+", required=True,
                        help="bench_water.py work folders with trained models")
    parser.add_argument("--arms", default="without,analytic,with",
                        help=f"comma-separated, of {', '.join(ARMS)}")
    parser.add_argument("--models", default="*",
                        help="dive folders to assess (a glob, e.g. 'transect_*')")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    args.arms = [a.strip() for a in args.arms.split(",") if a.strip()]
    unknown = set(args.arms) - set(ARMS)
    if unknown or not args.arms:
        parser.error(f"--arms: {sorted(unknown) or 'none given'}; choose from {', '.join(ARMS)}")
    torch.set_num_threads(1)
    started, load = time.time(), load_average()
    rows = []
    for work in args.work:
        for train in sorted(work.glob(f"{args.models}/train_*")):
            if (train / "model.pt").exists() and (train.parent / "truth" / "water.json").exists():
                rows.append(assess(train.parent, train, args.arms))
                print(rows[-1]["model"], rows[-1].get("skipped") or
                      {arm: rows[-1][arm]["held"] for arm in args.arms}, flush=True)
    write(rows, args, load, started)


if __name__ == "__main__":
    main()
