"""Which fitted water values does water.json flag as not determined by the views, rule by rule?

The train step's final assessment (``water_refit.assess_water``) flags a value when its 95%
interval reaches further than 25% of it either side, and (since session 47) when the part of
the interval that comes from what the images cannot tell apart -- the veiling light beyond the
farthest surfaces where no open water is in view, open water that may be far seabed
(``water_uncertainty.ambiguity_halfwidths``) -- exceeds ``medium.determined_ambiguity`` of it.
This benchmark redoes that assessment on the trained models of ``bench_water.py`` work folders
(their surfaces rebuilt as ``bench_water_intervals.py`` does) and counts, per camera path, how
many values more than 5% off the simulator's truth each rule flags, and how many within 5%.
The goal (issue 11): on orbits, every value outside 5% flagged; on surveys, few false alarms.
With ``--compare-open-water-surfaces`` every model is assessed a second time with the
photographs' open water kept as open water where the model renders a surface in it
(``medium.open_water_surfaces_from`` above 1), and the surface fits of both are compared.

    python benchmarks/bench_determined.py --work /tmp/bw/work [--work DIR ...] [--jobs 2]
                                          [--work /tmp/bw/work/orbit_default ...]
                                          [--compare-open-water-surfaces]
    python benchmarks/bench_determined.py --summarise-only     # from the saved .json

Writes benchmarks/results/determined.md and .json (every model's values, intervals and splits).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from functools import partial
from multiprocessing import Pool
from pathlib import Path

from machine import footer, load_average

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
RESULTS = REPO / "benchmarks" / "results" / "determined.md"
KEYS = ("sigma_attn", "sigma_bs", "c_med")
OFF = 0.05                                  # the goal: a determined value is within 5%
PATHS = ("orbit", "transect", "survey")
# (label, largest interval as a share of the value, largest ambiguity part as a share)
RULES = [("width <= 25% (before)", 0.25, None), ("width <= 25%, ambiguity <= 5% (default)",
                                                  0.25, 0.05),
         ("width <= 25%, ambiguity <= 3%", 0.25, 0.03), ("width <= 25%, ambiguity <= 10%",
                                                          0.25, 0.10),
         ("width <= 25%, ambiguity <= 15%", 0.25, 0.15), ("width <= 20%", 0.20, None),
         ("width <= 15%", 0.15, None)]


def assess(model_dir: str, stored_up: bool = False, open_water_surfaces: bool = True) -> dict:
    """One trained model's final assessment redone: per value the truth, trained value,
    surface fit, widened 95% half-width, ambiguity part and every split (normalised units)."""
    import torch

    from bench_water_intervals import model_surfaces
    from seathru.nerf.water_interval import interval_halfwidth
    from seathru.nerf.water_refit import assessment_spread, medium_surface_fit
    from seathru.nerf.water_uncertainty import ambiguity_halfwidths

    torch.set_num_threads(1)
    train = Path(model_dir)
    sim = train.parent
    path, water = sim.name.split("_", 1)
    record = {"model": f"{sim.name}/{train.name}", "path": path, "water": water,
              "up": "stored" if stored_up else "this code's",
              "open_water_surfaces": open_water_surfaces}
    data, model, truth, trained, _, regrouped = model_surfaces(sim, train, regroup=True,
                                                               up_now=not stored_up,
                                                               open_water_surfaces=
                                                               open_water_surfaces)
    if isinstance(data, str):
        return {**record, "skipped": data}
    medium = model.config.medium
    fit, data = medium_surface_fit(data, trained, medium, model.medium.colour_max)
    spread, _ = assessment_spread(fit, data, regrouped, medium, model.medium.colour_max)
    ambiguity = ambiguity_halfwidths(spread)
    params = []
    for i, key in enumerate(KEYS):
        for c in range(3):
            fitted, half = getattr(fit, key)[c], spread.halfwidth[key][c]
            params.append({
                "parameter": key, "channel": "RGB"[c], "truth": truth[key][c],
                "trained": trained[key][c], "surface_fit": fitted,
                "halfwidth": interval_halfwidth(trained[key][c], fitted, half),
                "ambiguity": ambiguity[key][c],
                "splits": {name: part[3 * i + c] for name, part in spread.splits.items()}})
    return {**record, "open_water": bool((~torch.isfinite(data.ranges)).any()),
            "open_water_below_horizon": bool(data.open_water_below_horizon), "params": params}


def determined(value: dict, width: float, ambiguity: float | None) -> bool:
    scale = abs(value["trained"])
    return (value["halfwidth"] <= width * scale
            and (ambiguity is None or value["ambiguity"] <= ambiguity * scale))


def relative_error(value: dict) -> float:
    return abs(value["trained"] - value["truth"]) / abs(value["truth"])


def surface_fit_table(rows: list[dict]) -> list[str]:
    """The surface fit against the truth per path, with the photographs' open water that
    the model renders as a near surface taken as that surface and without."""
    lines = ["", "The final surface fit itself (not the trained value) against the truth, with "
             "the photographs' open water that the model renders as an opaque surface short of "
             "0.9 of the far bound taken as that surface (`medium.open_water_surfaces_from`) "
             "and without:", "",
             "| path | arm | within 5% | median error: sigma_attn | sigma_bs | c_med | "
             "intervals hold the truth |", "|---|---|---|---|---|---|---|"]
    for path in PATHS:
        for arm in (True, False):
            values = [v for r in rows if "params" in r and r["path"] == path
                      and r.get("open_water_surfaces", True) == arm for v in r["params"]]
            if not values:
                continue
            errors = {k: sorted(abs(v["surface_fit"] - v["truth"]) / abs(v["truth"])
                                for v in values if v["parameter"] == k) for k in KEYS}
            near = sum(abs(v["surface_fit"] - v["truth"]) <= OFF * abs(v["truth"])
                       for v in values)
            held = sum(abs(v["trained"] - v["truth"]) <= v["halfwidth"] for v in values)
            lines.append(f"| {path} | {'taken as surfaces' if arm else 'open water'} | "
                         f"{near}/{len(values)} | " + " | ".join(
                             f"{100 * errors[k][len(errors[k]) // 2]:.1f}%" for k in KEYS)
                         + f" | {held}/{len(values)} |")
    return lines


def summarise(rows: list[dict], sources: list[str], machine: str, out: Path) -> None:
    compared = [r for r in rows if not r.get("open_water_surfaces", True)]
    rows, all_rows = [r for r in rows if r.get("open_water_surfaces", True)], rows
    done = [r for r in rows if "params" in r]
    lines = ["# Which water values are flagged as not determined? "
             "(`benchmarks/bench_determined.py`)", "",
             "The train step's final water assessment redone on trained models of "
             "`bench_water.py` (16 views at 160x120, 3 min on the true cameras), and every "
             "value judged by each rule: *off* = more than 5% from the simulator's truth, "
             "*flagged* = not determined. Width: the 95% interval around the trained value as "
             "a share of it; ambiguity: the part of it from what the images cannot tell apart "
             "(the veiling light beyond the farthest surfaces with no open water in view; open "
             "water that may be far seabed).", "",
             "| rule | " + " | ".join(f"{p}: off flagged | {p}: within 5% flagged"
                                      for p in PATHS) + " |",
             "|---|" + "---|---|" * len(PATHS)]
    for label, width, ambiguity in RULES:
        cells = []
        for path in PATHS:
            values = [v for r in done if r["path"] == path for v in r["params"]]
            off = [v for v in values if relative_error(v) > OFF]
            near = [v for v in values if relative_error(v) <= OFF]
            cells += [f"{sum(not determined(v, width, ambiguity) for v in off)}/{len(off)}",
                      f"{sum(not determined(v, width, ambiguity) for v in near)}/{len(near)}"]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    held = sum(abs(v["trained"] - v["truth"]) <= v["halfwidth"] for r in done
               for v in r["params"])
    ups = sorted({r.get("up", "stored") for r in done})
    below = {p: f"{sum(r.get('open_water_below_horizon', False) for r in done if r['path'] == p)}"
                f" of {sum(r['path'] == p for r in done)}" for p in PATHS}
    lines += ["", f"Intervals (the same under every rule) hold the truth in {held} of "
              f"{9 * len(done)} values ({len(done)} models). Open water that all looks below "
              f"the horizon (the vertical: {', '.join(ups)}), whose intervals allow for seabed "
              "behind it: " + ", ".join(f"{p} {n}" for p, n in below.items()) + ".", "",
              "Values more than 5% off that the default rule leaves determined:", ""]
    missed = [(r, v) for r in done for v in r["params"]
              if relative_error(v) > OFF and determined(v, *RULES[1][1:])]
    for r, v in missed:
        largest = max(v["splits"].items(), key=lambda item: item[1], default=("-", 0.0))
        lines.append(f"- {r['model']} {v['parameter']}[{v['channel']}]: "
                     f"{(v['trained'] - v['truth']) / v['truth']:+.1%} off, interval "
                     f"+-{v['halfwidth'] / abs(v['trained']):.0%}, ambiguity "
                     f"{v['ambiguity'] / abs(v['trained']):.1%}; largest part {largest[0]} "
                     f"{largest[1] / abs(v['trained']):.0%}")
    if not missed:
        lines.append("- none")
    if compared:
        lines += surface_fit_table(all_rows)
    skipped = [r for r in rows if "skipped" in r]
    lines += [""] + [f"Skipped {r['model']}: {r['skipped']}" for r in skipped]
    folders: dict[str, list[str]] = {}
    for source in map(Path, sources):
        if (source / "truth").is_dir() or not source.exists():
            folders.setdefault(str(source.parent), []).append(source.name)
        else:
            folders.setdefault(str(source), [])
    lines += ["", "Work folders: " + "; ".join(
        f"`{folder}`" + (f" ({', '.join(names)})" if names else "")
        for folder, names in folders.items()) + ".", "",
              machine, ""]
    out.write_text("\n".join(lines))
    out.with_suffix(".json").write_text(json.dumps({"sources": sources, "machine": machine,
                                                    "models": all_rows}, indent=1))
    print("\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, action="append", default=[],
                        help="a bench_water.py work folder, or one dive in it (repeat for "
                             "several)")
    parser.add_argument("--variant", default="cues", help="which trainings (train_VARIANT)")
    parser.add_argument("--jobs", type=int, default=1, help="models assessed at a time")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--stored-up", action="store_true",
                        help="tell open water below the horizon by the vertical each model was "
                             "saved with (default: estimated from its cameras by this code)")
    parser.add_argument("--compare-open-water-surfaces", action="store_true",
                        help="assess every model a second time with the photographs' open "
                             "water taken as open water wherever the model renders it")
    parser.add_argument("--summarise-only", action="store_true",
                        help="rewrite the table from the saved .json")
    args = parser.parse_args()
    load, started = load_average(), time.time()
    if args.summarise_only:
        saved = json.loads(args.out.with_suffix(".json").read_text())
        summarise(saved["models"], saved["sources"], saved["machine"], args.out)
        return
    dives = [d for work in args.work
             for d in ([work] if (work / "truth").is_dir() else sorted(work.glob("*_*")))]
    models = [str(d / f"train_{args.variant}") for d in dives
              if (d / f"train_{args.variant}" / "model.pt").exists()
              and (d / "truth" / "water.json").exists()]
    if not models:
        parser.error("no trained models with a truth water under --work")
    with Pool(args.jobs) as pool:
        rows = []
        arms = (True, False) if args.compare_open_water_surfaces else (True,)
        for arm in arms:
            for row in pool.imap(partial(assess, stored_up=args.stored_up,
                                         open_water_surfaces=arm), models):
                rows.append(row)
                print(row["model"], row.get("skipped", "assessed"), flush=True)
    summarise(rows, [str(w) for w in args.work], footer(load, started), args.out)


if __name__ == "__main__":
    main()
