"""Whether a camera JPEG's chroma subsampling biases the colours the water is read from.

A diagnostic, not a test. For a simulated dive (``SIMULATED`` = a simulate step's folder), each
view is developed from its DNG as the simulator develops its camera JPEG
(``seathru.sim.sensor.develop_jpeg``), rounded to 8 bits, and encoded three ways at the
simulator's quality: 4:2:0 (cameras' usual), 4:4:4, and 4:2:0 with the colour detail restored
from the luma after decoding (each 2 x 2 block's colour fitted as a linear function of its luma
over 5 x 5 blocks, applied at full resolution, the guided-filter way). Against the 8-bit image
before encoding, in linear values: each pixel's mean absolute error per channel, and the linear
mean over 8 x 8-pixel blocks as a ratio, by the block's true range. Usage::

    python benchmarks/bench_jpeg_chroma.py results/demo/simulate [--views 12] \\
        [--out benchmarks/results/jpeg_chroma.md]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from machine import cpu_name

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from seathru.io.images import JPEG_SAMPLING_FACTORS, read_image  # noqa: E402
from seathru.io.truth import JPEG_QUALITY  # noqa: E402
from seathru.radiometry.colour import srgb_to_linear  # noqa: E402
from seathru.sim import sensor  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "jpeg_chroma.md"
RANGE_BINS_M = (0.0, 1.5, 2.5, 4.0, 6.0, 10.0, np.inf)
BLOCK = 8


def encoded(image8: np.ndarray, chroma: str) -> np.ndarray:
    """``image8`` (H, W, 3) uint8 RGB through a JPEG at ``chroma`` sampling, decoded, in [0, 1]."""
    ok, data = cv2.imencode(".jpg", cv2.cvtColor(image8, cv2.COLOR_RGB2BGR),
                            [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY,
                             cv2.IMWRITE_JPEG_SAMPLING_FACTOR, JPEG_SAMPLING_FACTORS[chroma]])
    assert ok
    return cv2.cvtColor(cv2.imdecode(data, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB) / 255.0


def colour_from_luma(decoded: np.ndarray, radius: int = 2, eps: float = 1e-4) -> np.ndarray:
    """Chroma detail restored from the luma: per 2 x 2 block a local linear model of Cb and Cr
    on Y (fitted over ``2 radius + 1`` blocks each way), applied to the full-resolution luma."""
    ycc = cv2.cvtColor(decoded.astype(np.float32), cv2.COLOR_RGB2YCrCb).astype(np.float64)
    h, w = (ycc.shape[0] // 2) * 2, (ycc.shape[1] // 2) * 2
    y = ycc[:h, :w, 0]

    def blocks(a: np.ndarray) -> np.ndarray:
        return a[:h, :w].reshape(h // 2, 2, w // 2, 2).mean((1, 3))

    def box(a: np.ndarray) -> np.ndarray:
        return cv2.blur(a, (2 * radius + 1, 2 * radius + 1), borderType=cv2.BORDER_REFLECT)

    y_low = blocks(y)
    mean_y, var_y = box(y_low), box(y_low * y_low) - box(y_low) ** 2
    out = ycc.copy()
    for channel in (1, 2):
        c_low = blocks(ycc[..., channel])
        slope = (box(y_low * c_low) - mean_y * box(c_low)) / (var_y + eps)
        offset = box(c_low) - slope * mean_y
        out[:h, :w, channel] = (cv2.resize(slope, (w, h), interpolation=cv2.INTER_LINEAR) * y
                                + cv2.resize(offset, (w, h), interpolation=cv2.INTER_LINEAR))
    return np.clip(cv2.cvtColor(out.astype(np.float32), cv2.COLOR_YCrCb2RGB), 0.0, 1.0)


def block_means(image: np.ndarray) -> np.ndarray:
    h, w = (image.shape[0] // BLOCK) * BLOCK, (image.shape[1] // BLOCK) * BLOCK
    return image[:h, :w].reshape(h // BLOCK, BLOCK, w // BLOCK, BLOCK, -1).mean((1, 3))


def main() -> None:
    import rawpy

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("simulated", type=Path)
    parser.add_argument("--views", type=int, default=12)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    recorded = json.loads((args.simulated / "truth" / "sensor.json").read_text())
    config = sensor.SensorConfig(black_level=recorded["black_level"],
                                 white_level=recorded["white_level"])
    kinds = ("4:2:0", "4:4:4", "4:2:0, colour from luma")
    pixel_errors = {k: [] for k in kinds}
    ratios = {k: [[] for _ in RANGE_BINS_M[:-1]] for k in kinds}
    raws = sorted((args.simulated / "raw").glob("*.dng"))[:args.views]
    for path in raws:
        with rawpy.imread(str(path)) as raw:
            mosaic = raw.raw_image_visible.copy()
        image8 = np.round(np.clip(sensor.develop_jpeg(mosaic, config), 0, 1) * 255).astype(
            np.uint8)
        reference = srgb_to_linear(image8 / 255.0)
        depth = read_image(args.simulated / "truth" / "depth" / f"{path.stem}.tiff")
        depth = depth[..., 0] if depth.ndim == 3 else depth
        decoded = {"4:2:0": encoded(image8, "4:2:0"), "4:4:4": encoded(image8, "4:4:4")}
        decoded["4:2:0, colour from luma"] = colour_from_luma(decoded["4:2:0"])
        surface = np.isfinite(depth)
        reference_blocks = block_means(reference)
        block_depth = block_means(depth[..., None])[..., 0]
        for kind, image in decoded.items():
            linear = srgb_to_linear(image)
            pixel_errors[kind].append(np.abs(linear - reference)[surface].mean(0))
            ratio = block_means(linear) / np.maximum(reference_blocks, 1e-6) - 1.0
            for i, (low, high) in enumerate(zip(RANGE_BINS_M[:-1], RANGE_BINS_M[1:])):
                chosen = np.isfinite(block_depth) & (block_depth >= low) & (block_depth < high)
                ratios[kind][i].append(ratio[chosen])
    lines = ["# Chroma subsampling and the colours the water is read from "
             "(`benchmarks/bench_jpeg_chroma.py`)", "",
             f"Device: {cpu_name()}. `{args.simulated}`, {len(raws)} views, JPEG quality "
             f"{JPEG_QUALITY}; against the 8-bit image before encoding, in linear values.", "",
             "| encoding | mean absolute error per pixel (R, G, B; 1e-3) |", "|---|---|"]
    for kind in kinds:
        error = np.mean(pixel_errors[kind], axis=0) * 1e3
        lines.append(f"| {kind} | {', '.join(f'{v:.1f}' for v in error)} |")
    lines += ["", f"Median ratio of the {BLOCK} x {BLOCK}-block linear means to the reference's, "
              "minus 1, in % (R, G, B), by the block's true range:", "",
              "| range (m) | blocks | " + " | ".join(kinds) + " |", "|---" * (2 + len(kinds)) + "|"]
    for i, (low, high) in enumerate(zip(RANGE_BINS_M[:-1], RANGE_BINS_M[1:])):
        count = sum(len(r) for r in ratios[kinds[0]][i])
        if not count:
            continue
        cells = []
        for kind in kinds:
            values = np.concatenate(ratios[kind][i])
            cells.append(", ".join(f"{100 * v:+.2f}" for v in np.median(values, axis=0)))
        label = f"{low:g}-{high:g}" if np.isfinite(high) else f"{low:g}+"
        lines.append(f"| {label} | {count} | " + " | ".join(cells) + " |")
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
