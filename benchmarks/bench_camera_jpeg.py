"""What shooting camera JPEGs costs the water, against the truth: the demo's simulated survey
trained from its DNGs, from its camera JPEGs, and from JPEGs white-balanced frame by frame as a
camera's automatic white balance does (with and without ``train.frame_colour``), and both kinds
of JPEG with their colour at full resolution (4:4:4, where cameras write 4:2:0), each through
the whole workflow (simulate, ingest, COLMAP, train, render, evaluate) in one sheet.

    python benchmarks/bench_camera_jpeg.py --work /tmp/camera_jpeg

Writes ``benchmarks/results/camera_jpeg.md``: per arm the held-out PSNR, the restored render
against the clean truth (and on covered pixels), the restored photographs, the fitted water's
signed error per channel (``?``: flagged as not determined; ``!``: its interval misses the
truth), and the photographs' colour casts from frame to frame along the COLMAP tracks (the
evaluate step's ``track_colour_slope.frame_colour``). ``--summarise-only`` tabulates a finished
``--work``. Where ``../shared/data/d3_reef`` is present its real frames run too (row
``reef``, and ``reef_uncorrected`` with ``train.frame_colour=off``: no truth, so only the
held-out PSNR and the frame colour).
"""

from __future__ import annotations

import time
from pathlib import Path

from machine import footer, load_average
from workflow_sheet import (REPO, metric_mean, read_run, run_sheet, sheet_arguments,
                            unseen_cell, water_cells)

REEF = REPO.parent / "shared" / "data" / "d3_reef"
OUT = REPO / "benchmarks" / "results" / "camera_jpeg.md"
JPEG = "ingest.images=jpeg"
AUTO_BALANCE = "simulate.jpeg_white_balance=auto"
FULL_CHROMA = "simulate.jpeg_chroma=4:4:4"
ARMS = {
    "raw": "",
    "jpeg": JPEG,
    "jpeg_awb": f"{JPEG}; {AUTO_BALANCE}",
    "jpeg_awb_uncorrected": f"{JPEG}; {AUTO_BALANCE}; train.frame_colour=off",
    "jpeg_444": f"{JPEG}; {FULL_CHROMA}",
    "jpeg_awb_444": f"{JPEG}; {AUTO_BALANCE}; {FULL_CHROMA}",
}


def run_workflow(work: Path, cores: int) -> None:
    rows = [f"{name}\tsimulated\t\t{options}\t" for name, options in ARMS.items()]
    if REEF.is_dir():
        rows.append(f"reef\timages\t{REEF}\t\t")
        rows.append(f"reef_uncorrected\timages\t{REEF}\ttrain.frame_colour=off\t")
    run_sheet(work, rows, cores)


def arm_row(work: Path, name: str, options: str) -> str:
    finished = read_run(work, name)
    if finished is None:
        return f"| {name} | `{options}` | failed (see {work}/logs/{name}) |" + " |" * 9
    summary, rows = finished
    cast = (summary.get("track_colour_slope") or {}).get("frame_colour") or {}
    spread = ", ".join(f"{v:.3f}" for v in cast.get("spread") or []) or "-"
    corrected = (summary.get("medium_selection") or {}).get("frame_colour_correction")
    water = (summary.get("truth") or {}).get("water")
    return (f"| {name} | `{options}` | {metric_mean(rows, 'psnr_linear')} | "
            f"{metric_mean(rows, 'restored_psnr_linear')} "
            f"({metric_mean(rows, 'restored_psnr_linear_covered')}) "
            f"| {metric_mean(rows, 'photo_restored_psnr_linear')} | "
            + " | ".join(water_cells(water) if water else ["-"] * 3)
            + f" | {spread} | {'yes' if corrected else 'no'} | {unseen_cell(rows)} |")


def main() -> None:
    args = sheet_arguments(__doc__.splitlines()[0], Path("/tmp/camera_jpeg"), OUT)
    load_before, start = load_average(), time.time()
    if not args.summarise_only:
        run_workflow(args.work, args.cores)
    arms = {name: options or "(the DNGs)" for name, options in ARMS.items()}
    if (args.work / "results" / "reef").is_dir():
        arms["reef"] = f"images: {REEF.name}, the real frames"
    if (args.work / "results" / "reef_uncorrected").is_dir():
        arms["reef_uncorrected"] = f"images: {REEF.name}; train.frame_colour=off"
    lines = [
        "# Camera JPEGs and their white balance against the DNGs "
        "(`benchmarks/bench_camera_jpeg.py`)", "",
        "The demo's survey (default water, seed 0, 24 views at 320x240, 3 min of training) "
        "through the whole workflow per arm, one sheet. Means over the 3 held-out views; water "
        "as signed error against the truth (R, G, B; `?` flagged as not determined, `!` the "
        "interval misses the truth); frame colour: the root mean square of each frame's log "
        "red / green and blue / green beyond what the points and their ranges explain along "
        "the COLMAP tracks, against the median frame (`colour_varies_between_frames` above "
        "0.08); corrected: trained on "
        "the photographs brought to the median frame's cast (`train.frame_colour`); unseen: "
        "each held-out view's `unseen_surface_share` (its surface no training photograph "
        "sees, by the model's depth) with its held-out PSNR.", "",
        "| arm | options | held-out PSNR | restored render (covered) | restored photographs "
        "| `sigma_attn` | `sigma_bs` | `c_med` | frame colour | corrected | unseen (PSNR) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
        *(arm_row(args.work, name, options) for name, options in arms.items()), "",
        footer(load_before, start),
    ]
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
