"""How the colour of a real dive's COLMAP tracks changes with range, and what could explain it.

Reads one finished workflow run of a real dive (``--run``: the dataset's results folder, with
``poses/`` from COLMAP and, optionally, ``train/model.pt``) and writes
``benchmarks/results/reef_tracks.md``: the within-track slope of log colour against range
(``seathru.eval.track_slope``) of the input images,

- at the feature points' own pixels, over a window fixed in pixels and over the evaluate step's
  windows (the same patch of surface in every view: ``seathru.io.tracks.track_windows``);
- for tracks whose nearest view shows a dark blob or a bright one (the pixel more than 5% below
  or above the mean of a 9-pixel box around it, green);
- by the tracks' brightness (thirds of their median green) beside the open water's colour
  (``seathru.radiometry.open_water``);
- by where the rays look (thirds of elevation above the horizontal; "up" is the mean of the
  cameras' up axes);
- in linear colour with and without one additive offset per frame (glare or a tone curve that
  lifts each frame by its own amount);
- as reproduced by the best water of the model's form per channel with the veiling light held
  at the open water's colour (one clean colour per track, relative residuals, ``--veiling``
  multiples of it);
- and, with a trained model, the part of the slope the trained water itself makes (its water
  applied to the restored colour at each observation's range, per ray).

Usage::

    python benchmarks/bench_reef_tracks.py --run /tmp/reef/results/d3_reef [--out FILE]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from machine import cpu_name

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
RESULTS = REPO / "benchmarks" / "results" / "reef_tracks.md"


def _slopes(obs, colours, keep=None) -> np.ndarray:
    from seathru.eval.track_slope import track_slope

    keep = np.ones(len(obs.rows), bool) if keep is None else keep
    return track_slope(obs.track_ids[keep], obs.ranges[keep], colours[keep]).slope


def _fmt(values) -> str:
    return ", ".join(f"{v:.3f}" for v in values)


def _box_means(cameras, obs, sides: np.ndarray) -> np.ndarray:
    """(N, 3) mean of the input image over a square of ``sides`` (N,) pixels (odd, rounded)."""
    from seathru.io.images import read_image

    out = np.zeros((len(obs.rows), 3))
    for index, frame in enumerate(cameras.frames):
        here = np.flatnonzero(obs.frames == index)
        if here.size == 0:
            continue
        image = np.nan_to_num(np.asarray(read_image(cameras.image_path(frame))[..., :3],
                                         np.float64))
        for k in here:
            half = max(0, int(round((sides[k] - 1) / 2)))
            r, c = obs.rows[k], obs.cols[k]
            out[k] = image[max(r - half, 0):r + half + 1,
                           max(c - half, 0):c + half + 1].reshape(-1, 3).mean(0)
    return out


def _ray_directions(cameras, obs) -> np.ndarray:
    from seathru.io.tracks import observation_rays

    directions = np.zeros((len(obs.rows), 3))
    for here, _, rays, _, _ in observation_rays(cameras, obs):
        directions[here] = rays.numpy()
    return directions


def _open_water(cameras, obs) -> tuple[np.ndarray, list[float], np.ndarray]:
    """Median open-water colour of the training views, each frame's open-water share and each
    observation's distance in its image to the nearest open-water pixel (pixels; inf in a frame
    without open water)."""
    from scipy.ndimage import distance_transform_edt

    from seathru.io.images import read_image
    from seathru.radiometry.open_water import open_water_mask

    pixels, shares = [], []
    distance = np.full(len(obs.rows), np.inf)
    for index, frame in enumerate(cameras.frames):
        image = np.asarray(read_image(cameras.image_path(frame))[..., :3], np.float64)
        mask = open_water_mask(image)
        shares.append(float(mask.mean()))
        if frame.split == "train" and mask.any():
            pixels.append(image[mask][:: max(1, int(mask.sum()) // 5000)])
        here = obs.frames == index
        if mask.any() and here.any():
            distance[here] = distance_transform_edt(~mask)[obs.rows[here], obs.cols[here]]
    colour = np.median(np.concatenate(pixels), 0) if pixels else np.full(3, np.nan)
    return colour, shares, distance


def _with_covariates(obs, colours, covariates: dict[str, np.ndarray]) -> list[str]:
    """Rows of a table: the within-track slope of log colour on range alone
    (``track_slope``) and beside each covariate (``slope_beside``), per channel, with the
    covariate's own coefficient."""
    from seathru.eval.track_slope import slope_beside

    rows = [f"| range alone | {_fmt(_slopes(obs, colours))} | — |"]
    for name, covariate in covariates.items():
        fit = slope_beside(obs.track_ids, obs.ranges, colours, covariate)
        rows.append(f"| {name} | {_fmt(fit.slope)} | {_fmt(fit.coefficient)} |")
    return rows


def _offset_fit(obs, colours, shares) -> list[str]:
    """Linear colour: the slope with one intercept per track, and with one additive offset per
    frame as well; the offsets' correlation with the frame's open water and mean range."""
    from scipy.sparse import csr_matrix, hstack
    from scipy.sparse.linalg import lsqr

    _, track, counts = np.unique(obs.track_ids, return_inverse=True, return_counts=True)
    keep = counts[track] >= 2
    _, track = np.unique(track[keep], return_inverse=True)
    frames, ranges, values = obs.frames[keep], obs.ranges[keep], colours[keep]
    n, frame_count = len(track), len(shares)
    tracks_part = csr_matrix((np.ones(n), (np.arange(n), track)))
    frames_part = csr_matrix((np.ones(n), (np.arange(n), frames)),
                             shape=(n, frame_count))[:, 1:]
    range_part = csr_matrix(ranges[:, None])
    mean_range = np.array([ranges[frames == i].mean() if (frames == i).any() else np.nan
                           for i in range(frame_count)])
    lines = []
    for channel, name in ((1, "green"), (2, "blue")):
        alone = lsqr(hstack([tracks_part, range_part]).tocsr(), values[:, channel],
                     atol=1e-12, btol=1e-12, iter_lim=20000)[0]
        both = lsqr(hstack([tracks_part, frames_part, range_part]).tocsr(), values[:, channel],
                    atol=1e-12, btol=1e-12, iter_lim=20000)[0]
        offsets = np.concatenate([[0.0], both[-frame_count:-1]])
        seen = np.isfinite(mean_range)
        lines.append(
            f"| {name} | {alone[-1]:.4f} | {both[-1]:.4f} | "
            f"{np.corrcoef(offsets[seen], np.asarray(shares)[seen])[0, 1]:.2f} | "
            f"{np.corrcoef(offsets[seen], mean_range[seen])[0, 1]:.2f} |")
    return lines


def _held_veiling_fit(obs, colours, channel: int, veiling: float) -> tuple[float, float, float]:
    """Per channel: I = J_track exp(-a z) + veiling (1 - exp(-b z)) fitted by L-BFGS over a, b
    (J in closed form, non-negative); (a, b, slope of the fitted colour)."""
    _, track, counts = np.unique(obs.track_ids, return_inverse=True, return_counts=True)
    keep = counts[track] >= 2
    _, track = np.unique(track[keep], return_inverse=True)
    groups = int(track.max()) + 1
    ids = torch.tensor(track)
    z = torch.tensor(obs.ranges[keep])
    y = torch.tensor(colours[keep, channel])
    raw_a = torch.zeros((), dtype=torch.float64, requires_grad=True)
    raw_b = torch.full((), -4.0, dtype=torch.float64, requires_grad=True)

    def model():
        a, b = torch.nn.functional.softplus(raw_a) * 0.1, torch.exp(raw_b)
        transmission, back = torch.exp(-a * z), veiling * (1 - torch.exp(-b * z))
        numerator = torch.zeros(groups, dtype=torch.float64).index_add(
            0, ids, transmission * (y - back))
        denominator = torch.zeros(groups, dtype=torch.float64).index_add(
            0, ids, transmission ** 2)
        clean = (numerator / denominator).clamp_min(0)
        return a, b, clean[ids] * transmission + back

    optimiser = torch.optim.LBFGS([raw_a, raw_b], max_iter=300, line_search_fn="strong_wolfe")

    def closure():
        optimiser.zero_grad()
        loss = (((model()[2] - y) / (y + 0.01)) ** 2).mean()
        loss.backward()
        return loss

    optimiser.step(closure)
    with torch.no_grad():
        a, b, fitted = model()
    from seathru.eval.track_slope import track_slope

    slope = track_slope(obs.track_ids[keep], obs.ranges[keep], fitted.numpy()).slope[0]
    return float(a), float(b), float(slope)


def _trained_water_part(run: Path, cameras, obs, windows) -> str | None:
    """The slope the trained water makes: its water applied to the restored colour."""
    model_path = run / "train" / "model.pt"
    if not model_path.is_file():
        return None
    from seathru.io.model import load_model
    from seathru.io.tracks import rendered_colours

    model = load_model(model_path, torch.device("cpu"))
    with torch.no_grad():
        rendered = rendered_colours(model, cameras, obs, windows)
        attn, bs, veiling = (v.double().numpy() for v in model.medium(torch.tensor(
            _ray_directions(cameras, obs), dtype=torch.float32)))
    z = obs.ranges[:, None] * cameras.scale
    restored = rendered["restored"].astype(np.float64)
    with_water = restored * np.exp(-attn * z) + veiling * (1 - np.exp(-bs * z))
    made = _slopes(obs, with_water) - _slopes(obs, restored)
    return (f"The trained water's part (its water applied to the restored colour at each "
            f"observation's range, per ray): {_fmt(made)} per unit (R, G, B), against the "
            f"input's {_fmt(_slopes(obs, windows.observed))}; the full render's slope "
            f"{_fmt(_slopes(obs, rendered['rgb'].astype(np.float64)))}, the restored render's "
            f"{_fmt(_slopes(obs, restored))}.")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, required=True,
                        help="the dataset's results folder (poses/ from COLMAP)")
    parser.add_argument("--veiling", default="1,1.5,2",
                        help="multiples of the open water's colour to hold the veiling light at")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    from seathru.io.cameras import read_cameras
    from seathru.io.tracks import SPARSE_DIR, track_observations, track_windows

    started = time.perf_counter()
    torch.set_num_threads(2)
    cameras = read_cameras(args.run / "poses" / "cameras.json")
    obs = track_observations(cameras, cameras.root / SPARSE_DIR)
    windows = track_windows(cameras, obs)
    windowed = windows.observed
    side = 0.02 * np.array([f.width for f in cameras.frames])[obs.frames]
    fixed = _box_means(cameras, obs, side)
    box9 = _box_means(cameras, obs, np.full(len(obs.rows), 9.0))
    lines = ["# Colour along a real dive's COLMAP tracks (`benchmarks/bench_reef_tracks.py`)",
             "", f"Run: `{args.run}`; {len(np.unique(obs.track_ids))} tracks, "
             f"{len(obs.rows)} observations, median range {np.median(obs.ranges):.2f} "
             "(COLMAP units). Slopes: change of log colour per unit of range, within tracks "
             "(R, G, B).", "",
             "| colour of an observation | slope |", "|---|---|",
             f"| its pixel | {_fmt(_slopes(obs, obs.observed))} |",
             f"| a window 2% of the width across, fixed in pixels | {_fmt(_slopes(obs, fixed))} |",
             f"| the evaluate step's window (the same patch of surface in every view) | "
             f"{_fmt(_slopes(obs, windowed))} |"]
    nearest = pd.Series(np.arange(len(obs.rows))).groupby(obs.track_ids).transform(
        lambda rows: rows.iloc[int(np.argmin(obs.ranges[rows.to_numpy()]))]).to_numpy()
    contrast = np.log(np.maximum(obs.observed[:, 1], 1e-3) / np.maximum(box9[:, 1], 1e-3))
    polarity = contrast[nearest]
    lines += ["", "By what the nearest view of the track shows at its pixel (green against a "
              "9-pixel box):", "", "| tracks | observations | at the pixel | over windows |",
              "|---|---|---|---|"]
    for name, keep in (("dark blob (> 5% below)", polarity < -0.05),
                       ("bright blob (> 5% above)", polarity > 0.05),
                       ("neither", np.abs(polarity) <= 0.05)):
        lines.append(f"| {name} | {int(keep.sum())} | {_fmt(_slopes(obs, obs.observed, keep))} "
                     f"| {_fmt(_slopes(obs, windowed, keep))} |")

    open_water, shares, distance = _open_water(cameras, obs)
    brightness = pd.Series(windowed[:, 1]).groupby(obs.track_ids).transform("median").to_numpy()
    thirds = np.quantile(brightness, [1 / 3, 2 / 3])
    lines += ["", f"The tracked surfaces' median colour over windows {_fmt(np.median(windowed, 0))}"
              f"; the open water's (training views) {_fmt(open_water)}. By the track's "
              "brightness (median green over windows):", "",
              "| tracks | median green | slope over windows |", "|---|---|---|"]
    for name, keep in (("darkest third", brightness < thirds[0]),
                       ("middle third", (brightness >= thirds[0]) & (brightness < thirds[1])),
                       ("brightest third", brightness >= thirds[1])):
        lines.append(f"| {name} | {np.median(windowed[keep, 1]):.3f} | "
                     f"{_fmt(_slopes(obs, windowed, keep))} |")

    ups = np.array([-np.asarray(f.c2w_array)[:3, 1] for f in cameras.frames])
    up = ups.mean(0)
    agreement = float(np.linalg.norm(up))
    elevation = np.degrees(np.arcsin(np.clip(_ray_directions(cameras, obs) @ (up / agreement),
                                             -1, 1)))
    cuts = np.quantile(elevation, [1 / 3, 2 / 3])
    lines += ["", f"By where the ray looks (degrees above the horizontal; the cameras' up axes "
              f"agree to {agreement:.2f}):", "", "| rays | elevation | slope over windows |",
              "|---|---|---|"]
    for name, keep in (("lowest third", elevation < cuts[0]),
                       ("middle third", (elevation >= cuts[0]) & (elevation < cuts[1])),
                       ("highest third", elevation >= cuts[1])):
        lines.append(f"| {name} | {np.min(elevation[keep]):.0f} to {np.max(elevation[keep]):.0f}"
                     f" | {_fmt(_slopes(obs, windowed, keep))} |")

    seen = np.isfinite(distance)
    heights = np.array([f.height for f in cameras.frames], np.float64)[obs.frames]
    lines += ["", "Log colour over windows against range, alone and beside one more term, all "
              "within tracks (observations in frames with open water: "
              f"{int(seen.sum())} of {len(seen)}); the term's own coefficient per unit of it:",
              "", "| fitted on | range slope | the term's coefficient |", "|---|---|---|",
              *_with_covariates(obs, windowed, {
                  "range and log(1 + pixels to the nearest open water in the image)":
                      np.log1p(np.where(seen, distance, 1e4)),
                  "range and the image row (share of the height)": obs.rows / heights,
                  "range and the ray's elevation (degrees)": elevation})]
    lines += ["", "Linear colour over windows, with one intercept per track: the slope alone and "
              "with one additive offset per frame; the offsets' correlation with the frame's "
              "open-water share and with its tracks' mean range:", "",
              "| channel | slope alone | with frame offsets | offsets vs open water | "
              "offsets vs range |", "|---|---|---|---|---|", *_offset_fit(obs, windowed, shares)]

    lines += ["", "The best water per channel with the veiling light held (one clean colour per "
              "track; over windows):", "",
              "| channel | veiling light | sigma_attn | sigma_bs | slope of the fit | input |",
              "|---|---|---|---|---|---|"]
    input_slopes = _slopes(obs, windowed)
    for channel in (1, 2):
        for multiple in (float(m) for m in args.veiling.split(",")):
            veiling = multiple * float(open_water[channel])
            a, b, slope = _held_veiling_fit(obs, windowed, channel, veiling)
            lines.append(f"| {'RGB'[channel]} | {veiling:.3f} ({multiple:g}x the open water) "
                         f"| {a:.4f} | {b:.4f} | {slope:.3f} | {input_slopes[channel]:.3f} |")
    trained = _trained_water_part(args.run, cameras, obs, windows)
    if trained:
        lines += ["", trained]
    lines += ["", f"Machine: {cpu_name()}; {time.strftime('%Y-%m-%d')}; "
              f"{time.perf_counter() - started:.0f} s in all."]
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
