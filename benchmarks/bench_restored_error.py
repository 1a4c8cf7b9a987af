"""What the restored view's error is made of, on a finished workflow run of a simulated dive.

For each held-out view the simulator's own image with water is restored by the fitted water
(``train/water.json``) three ways, and each is scored against the clean truth like the evaluate
step scores the restored render (same undistortion onto the frame, same colour gain):

- with the true range: what the water alone allows;
- with the model's rendered depth (``render/test/<view>/depth.tiff``): what the model's
  geometry allows;
- the model's own restored render (``restored_psnr_linear`` of ``metrics.csv``).

Per range band (true range) the restored red against the clean red (mean ratio) and the model's
depth against the true range (median ratio) show where the error sits; per coverage (how many
training views see the pixel's true surface, ``seathru.eval.truth.training_view_coverage``:
none, one, two or more) the same for the surfaces no reconstruction or a single view pins.
Writes ``benchmarks/results/restored_error.md``.

    python benchmarks/bench_restored_error.py --results results/demo
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from machine import cpu_name

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
OUT = REPO / "benchmarks" / "results" / "restored_error.md"
BANDS = ((0.0, 1.5), (1.5, 3.0), (3.0, 5.0), (5.0, 8.0), (8.0, np.inf))


def restore(water_image: np.ndarray, ranges: np.ndarray, sigma_attn, sigma_bs, c_med
            ) -> np.ndarray:
    """The clean image of a global water: ``(I - c_med (1 - exp(-sigma_bs z))) exp(sigma_attn z)``."""
    z = ranges[..., None]
    return (water_image - np.asarray(c_med) * (1.0 - np.exp(-np.asarray(sigma_bs) * z))) \
        * np.exp(np.asarray(sigma_attn) * z)


def main() -> None:
    from seathru.eval import metrics
    from seathru.eval import truth as truth_eval
    from seathru.io.cameras import read_cameras
    from seathru.io.evaluation import (_images_and_water_truth, camera_centres, read_render,
                                       read_truth_image, resized_like, truth_on_frames)
    from seathru.io.water import read_water

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", type=Path, required=True,
                        help="a simulated dataset's results folder (results/<dataset>)")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    root = args.results
    truth_dir = root / "simulate" / "truth"
    cameras = read_cameras(root / "poses" / "cameras.json")
    on_frame = truth_on_frames(cameras)
    gain = truth_eval.pooled_gain(_images_and_water_truth(cameras, truth_dir, on_frame))
    scale = truth_eval.camera_metric_scale(
        camera_centres(cameras), camera_centres(read_cameras(truth_dir / "cameras.json"),
                                                source_units=True), cameras.scale).scale
    water = read_water(root / "train" / "water.json").normalised.as_dict()
    fitted = (np.asarray(water["sigma_attn"]) / scale, np.asarray(water["sigma_bs"]) / scale,
              gain * np.asarray(water["c_med"]))

    def psnr(image: np.ndarray, clean: np.ndarray, valid: np.ndarray) -> float:
        return metrics.image_metrics(image, clean, valid=valid)["psnr_linear"]

    truth_cameras = read_cameras(truth_dir / "cameras.json")
    true_frames = {f.name: f for f in truth_cameras.frames}

    def true_range_of(name: str) -> np.ndarray:
        depth = read_truth_image(truth_dir, "depth", name)
        return (depth[..., 0] if depth.ndim == 3 else depth).astype(np.float64)

    training = [(true_frames[f.name], true_range_of(f.name)) for f in cameras.frames
                if f.split != "test" and f.name in true_frames]
    rows, bands, coverage = [], [], []
    for frame in cameras.split("test"):
        view = frame.name
        full = read_render(root / "render", view, "full")

        def truth(kind: str) -> np.ndarray:
            image = resized_like(on_frame(read_truth_image(truth_dir, kind, view), view), full)
            return image[..., 0] if kind == "depth" and image.ndim == 3 else image

        clean, water_image, true_range = truth("clean"), truth("water")[..., :3], truth("depth")
        depth = read_render(root / "render", view, "depth")
        depth = (depth[..., 0] if depth.ndim == 3 else depth) * scale
        restored = gain * read_render(root / "render", view, "restored")
        valid = np.all(np.isfinite(clean), -1) & np.isfinite(true_range) & (true_range > 0)
        by_truth = restore(water_image, np.where(valid, true_range, 0.0), *fitted)
        by_model = restore(water_image, depth, *fitted)
        rows.append((view, psnr(by_truth, clean, valid), psnr(by_model, clean, valid),
                     psnr(restored, clean, valid)))
        opacity = read_render(root / "render", view, "opacity")
        opacity = opacity[..., 0] if opacity.ndim == 3 else opacity
        squared = ((restored - clean) ** 2).sum(-1)
        total = float(squared[valid].sum())
        for low, high in BANDS:
            band = valid & (true_range >= low) & (true_range < high)
            if band.sum() < 50:
                continue
            red = lambda image: float(image[..., 0][band].mean() / clean[..., 0][band].mean())  # noqa: E731
            bands.append((view, f"{low:g}-{high:g} m", float(band.mean()), red(restored),
                          red(by_model), float(np.median(depth[band] / true_range[band])),
                          float(squared[band].sum() / total), float(np.median(opacity[band]))))
        counts = truth_eval.training_view_coverage(true_frames[view], true_range_of(view),
                                                   training).astype(np.float32)
        counts = np.round(resized_like(on_frame(counts, view), full[..., 0]))
        counts = counts[..., 0] if counts.ndim == 3 else counts
        for name, seen in (("none", counts == 0), ("one", counts == 1), ("two or more", counts >= 2)):
            part = valid & seen
            if part.sum() < 50:
                continue
            coverage.append((view, name, float(part.sum() / valid.sum()),
                             psnr(restored, clean, part), psnr(by_model, clean, part),
                             psnr(by_truth, clean, part),
                             float(np.median(depth[part] / true_range[part])),
                             float(squared[part].sum() / total)))

    lines = [
        "# What the restored view's error is made of (`benchmarks/bench_restored_error.py`)", "",
        f"Run `{root}`: the fitted water per metre sigma_attn "
        f"{', '.join(f'{v:.3f}' for v in fitted[0])}, sigma_bs "
        f"{', '.join(f'{v:.3f}' for v in fitted[1])}. The simulator's image with water restored "
        "by that water with the true range and with the model's rendered depth, and the model's "
        "own restored render, each against the clean truth (PSNR linear, pixels with a "
        "surface).", "",
        "| view | true range | model's depth | model's restored render |", "|---|---|---|---|",
        *(f"| {v} | {a:.2f} | {b:.2f} | {c:.2f} |" for v, a, b, c in rows), "",
        "Per range band (true range): share of the view's pixels, red of the restored render and "
        "of the restoration by the model's depth against the clean red (ratio of means), the "
        "model's depth against the true range (median ratio), the band's share of the view's "
        "squared error of the restored render, and the render's object opacity (median).", "",
        "| view | band | share | red, restored render | red, by the model's depth | depth ratio "
        "| share of the restored error | opacity |",
        "|---|---|---|---|---|---|---|---|",
        *(f"| {v} | {b} | {s:.2f} | {r:.3f} | {m:.3f} | {d:.3f} | {e:.2f} | {o:.2f} |"
          for v, b, s, r, m, d, e, o in bands), "",
        "Per coverage (how many training views see the pixel's true surface, true cameras): "
        "share of the view's surface pixels, PSNR of the restored render, of the restoration "
        "by the model's depth and by the true range, the model's depth against the true range "
        "(median ratio), and the share of the view's squared error of the restored render.", "",
        "| view | seen by | share | restored render | by the model's depth | by the true range "
        "| depth ratio | share of the restored error |",
        "|---|---|---|---|---|---|---|---|",
        *(f"| {v} | {n} | {s:.2f} | {r:.2f} | {m:.2f} | {t:.2f} | {d:.3f} | {e:.2f} |"
          for v, n, s, r, m, t, d, e in coverage), "",
        f"Machine: {cpu_name()}; {time.strftime('%Y-%m-%d')}.",
    ]
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
