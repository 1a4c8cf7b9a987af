"""PSNR / SSIM on held-out views; against the truth for simulated datasets.

Per held-out (test split) view, the render step's full-colour render ``test/<name>/full.tiff``
is compared with the view's linear image from the camera file, the way the NeRF papers do:
both clipped to [0, 1] and quantised to 8 bits, PSNR with data range 1, SSIM with an 11-tap
Gaussian window (sigma 1.5). Reported in linear space (the official SeaThru-NeRF evaluation) and
after sRGB encoding of the same linear values. LPIPS (AlexNet or VGG, v0.1) is computed on the
linear 8-bit images when ``--lpips-weights`` points at weights present on disk; otherwise the
column says ``unavailable`` (weights are never downloaded).

With ``--truth`` (a simulated dataset's ``simulate/truth`` folder):

- colour gain: the ingest step normalises exposure and white-balances, so the pipeline's linear
  values differ from the simulator's by one gain per channel. It is fitted once per dataset by
  least squares between the full renders and the truth images *with water* (pooled over the
  held-out views), and the same gain is applied to the restored renders before comparing them
  with the clean truth ``J`` (and to the fitted medium colour ``c_med``), over the pixels where
  ``J`` is defined (open-water pixels have none). The full render compared with the clean truth
  is reported too: the restoration should beat it;
- metric scale: camera centres of the evaluated camera file (normalised units) are aligned to
  the truth centres (metres) by a similarity (Umeyama); its scale converts predicted depths to
  metres (median absolute relative error and correlation against the truth range) and fitted
  coefficients to 1/m;
- water parameters: relative error per channel of sigma_attn, sigma_bs (1/m) and c_med.

Outputs in ``--out``: ``metrics.csv`` (one row per held-out view) and ``summary.json`` (means,
render speed from ``render_stats.json``, training time from ``train_log.csv``, fitted water
parameters against the truth, the medium selection).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from seathru.eval import metrics
from seathru.errors import PipelineError
from seathru.io.atomic import write_json, write_text
from seathru.io.cameras import CameraSet, read_cameras
from seathru.io.images import read_image

log = logging.getLogger(__name__)

UNAVAILABLE = "unavailable"
WATER_KEYS = ("sigma_attn", "sigma_bs", "c_med")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--renders", required=True, type=Path,
                        help="output folder of the render step")
    parser.add_argument("--cameras", required=True, type=Path,
                        help="cameras.json from the poses step (held-out views: split 'test')")
    parser.add_argument("--train-dir", required=True, type=Path,
                        help="output folder of the train step (water.json, train_log.csv, "
                             "selection.json)")
    parser.add_argument("--truth", type=Path, default=None,
                        help="simulated datasets: the simulate step's truth/ folder")
    parser.add_argument("--lpips-weights", type=Path, default=None,
                        help="LPIPS weights on disk: one .pth holding the trunk and the linear "
                             "layers, or a folder with the torchvision backbone (alexnet/vgg16) "
                             "and the lpips v0.1 linear layers; absent: LPIPS 'unavailable'")
    parser.add_argument("--dataset", default=None,
                        help="dataset id for the tables (default: the folder above --out)")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--threads", type=int, default=None, help="CPU threads for torch")


def run(args: argparse.Namespace) -> None:
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    dataset = args.dataset or _dataset_name(args.out)
    cameras = read_cameras(args.cameras)
    views = sorted(cameras.split("test"), key=lambda f: f.name)
    if not views:
        raise PipelineError(f"{args.cameras}: no frame has split 'test'; nothing to evaluate")
    if not args.renders.is_dir():
        raise PipelineError(f"{args.renders}: render folder not found; run the 'render' step")
    lpips_net, lpips_status = load_lpips(args.lpips_weights)

    rows = []
    for frame in views:
        full = _read_render(args.renders, frame.name, "full")
        target = _resize_to(read_image(cameras.image_path(frame)), full.shape[:2])
        row = {"dataset": dataset, "view": frame.name, **metrics.image_metrics(full, target)}
        row["lpips"] = UNAVAILABLE
        if lpips_net is not None:
            try:
                row["lpips"] = metrics.lpips_distance(lpips_net, metrics.quantise_8bit(full),
                                                      metrics.quantise_8bit(target))
            except ValueError as exc:
                log.warning("%s: LPIPS unavailable (%s)", frame.name, exc)
        rows.append(row)
        log.info("%s: PSNR %.2f dB, SSIM %.4f (linear)", frame.name, row["psnr_linear"],
                 row["ssim_linear"])

    truth_summary = None
    if args.truth is not None:
        truth_rows, truth_summary = evaluate_against_truth(args.truth, args.renders, cameras,
                                                          args.train_dir, [f.name for f in views])
        for row in rows:
            row.update(truth_rows[row["view"]])

    table = pd.DataFrame(rows)
    summary = build_summary(dataset, table, args.renders, args.train_dir, lpips_status,
                            truth_summary)
    args.out.mkdir(parents=True, exist_ok=True)
    write_text(args.out / "metrics.csv", table.to_csv(index=False, float_format="%.6g"))
    write_json(args.out / "summary.json", _json_safe(summary))
    log.info("%s: mean PSNR %.2f dB over %d views", dataset, table["psnr_linear"].mean(),
             len(table))


def _dataset_name(out: Path) -> str:
    out = Path(out).resolve()
    return out.parent.name if out.name == "evaluate" else out.name


def _read_render(renders: Path, view: str, name: str) -> np.ndarray:
    path = Path(renders) / "test" / view / f"{name}.tiff"
    if not path.is_file():
        raise PipelineError(f"{path}: render not found; re-run the 'render' step with the same "
                            "cameras.json")
    return read_image(path)


def _resize_to(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Area-resize an image to the render's (H, W) when the render was downscaled."""
    if image.shape[:2] == tuple(shape):
        return image
    return cv2.resize(image, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)


# ---------------------------------------------------------------------------------------- LPIPS

def load_lpips(path: Path | None):
    """(network, status): the LPIPS network when weights exist at ``path``, else (None, reason).

    A path that does not exist means the weights are not installed on this machine: LPIPS is
    reported unavailable. Files that exist but do not hold LPIPS weights are an error.
    """
    if path is None:
        return None, f"{UNAVAILABLE}: no --lpips-weights given"
    path = Path(path)
    if not path.exists():
        log.warning("LPIPS weights %s not found: LPIPS unavailable", path)
        return None, f"{UNAVAILABLE}: {path} not found"
    import torch

    files = sorted(p for p in path.iterdir() if p.suffix in (".pth", ".pt")) if path.is_dir() \
        else [path]
    state = {}
    for file in files:
        try:
            loaded = torch.load(file, map_location="cpu", weights_only=True)
        except Exception as exc:
            raise PipelineError(f"{file}: cannot be read as a torch state dict ({exc})") from None
        if isinstance(loaded, dict):
            state.update(loaded)
    try:
        network = metrics.lpips_from_state_dict(state)
    except ValueError as exc:
        raise PipelineError(f"--lpips-weights {path}: {exc}") from None
    return network, f"available ({network.net_name}, {path})"


# ---------------------------------------------------------------------------------------- truth

def _truth_centres(truth_cameras: CameraSet, names: list[str]) -> np.ndarray:
    frames = {f.name: f for f in truth_cameras.frames}
    centre = np.asarray(truth_cameras.centre, dtype=np.float64)
    return np.stack([frames[n].c2w_array[:3, 3] / truth_cameras.scale + centre for n in names])


def evaluate_against_truth(truth_dir: Path, renders: Path, cameras: CameraSet, train_dir: Path,
                           views: list[str]) -> tuple[dict[str, dict], dict]:
    """Per-view truth metrics (keyed by view) and the dataset's truth summary."""
    truth_dir = Path(truth_dir)
    truth_cameras = read_cameras(truth_dir / "cameras.json")
    truth_names = {f.name for f in truth_cameras.frames}
    missing = [v for v in views if v not in truth_names]
    if missing:
        raise PipelineError(f"{truth_dir / 'cameras.json'}: no truth for held-out views "
                            f"{missing[:3]}; the camera file and the simulation do not match")

    # Metric scale from every camera both files know.
    shared = sorted(f.name for f in cameras.frames if f.name in truth_names)
    frames = {f.name: f for f in cameras.frames}
    if len(shared) >= 3:
        scale = metrics.metric_scale(np.stack([frames[n].c2w_array[:3, 3] for n in shared]),
                                     _truth_centres(truth_cameras, shared))
        scale["method"] = f"similarity alignment of {len(shared)} camera centres"
    else:  # too few cameras to align: trust that the source units are the truth's
        scale = {"scale": 1.0 / cameras.scale, "rms_residual": float("nan"),
                 "relative_residual": float("nan"),
                 "method": "camera-file normalisation only (fewer than 3 shared cameras)"}
    metres_per_unit = scale["scale"]

    def truth_image(kind: str, view: str, shape) -> np.ndarray:
        path = truth_dir / kind / f"{view}.tiff"
        if not path.is_file():
            raise PipelineError(f"{path}: truth image not found; re-run the 'simulate' step")
        return _resize_to(read_image(path), shape)

    # Pass 1: one colour gain per dataset, full render against the truth with water.
    cross, power = np.zeros(3), np.zeros(3)
    for view in views:
        full = _read_render(renders, view, "full")
        c, p = metrics.channel_gain_sums(full, truth_image("water", view, full.shape[:2]))
        cross, power = cross + c, power + p
    gain = metrics.gain_from_sums(cross, power)

    # Pass 2: restored against clean, full against clean (baseline), depth.
    rows = {}
    for view in views:
        full = _read_render(renders, view, "full")
        restored = _read_render(renders, view, "restored")
        depth = _read_render(renders, view, "depth")
        shape = full.shape[:2]
        clean, water = truth_image("clean", view, shape), truth_image("water", view, shape)
        truth_depth = truth_image("depth", view, shape)
        # the clean image is undefined (NaN) where a pixel sees open water: not scored
        defined = np.all(np.isfinite(clean), axis=-1)
        restored_m = metrics.image_metrics(gain * restored, clean, valid=defined)
        baseline = metrics.image_metrics(gain * full, clean, valid=defined)
        fit = metrics.image_metrics(gain * full, water)
        depth_m = metrics.depth_errors(depth * metres_per_unit, truth_depth)
        rows[view] = {
            "restored_psnr_linear": restored_m["psnr_linear"],
            "restored_ssim_linear": restored_m["ssim_linear"],
            "restored_psnr_srgb": restored_m["psnr_srgb"],
            "restored_ssim_srgb": restored_m["ssim_srgb"],
            "full_vs_clean_psnr_linear": baseline["psnr_linear"],
            "full_vs_clean_ssim_linear": baseline["ssim_linear"],
            "full_vs_water_psnr_linear": fit["psnr_linear"],
            "depth_median_abs_rel": depth_m["depth_median_abs_rel"],
            "depth_corr": depth_m["depth_corr"],
            "depth_rmse_m": depth_m["depth_rmse"],
        }

    truth_water = json.loads((truth_dir / "water.json").read_text()) \
        if (truth_dir / "water.json").is_file() else None
    if truth_water is None:
        raise PipelineError(f"{truth_dir / 'water.json'}: truth water parameters not found; "
                            "re-run the 'simulate' step")
    fitted = fitted_water_normalised(Path(train_dir), cameras)
    water = compare_water(fitted, truth_water, metres_per_unit, gain)
    summary = {"colour_gain": gain.tolist(),
               "colour_gain_note": "per-channel least-squares gain fitted between the full "
                                   "renders and the truth images with water (held-out views "
                                   "pooled), applied to restored renders and c_med",
               "metric_scale": scale, "water": water}
    return rows, summary


def fitted_water_normalised(train_dir: Path, cameras: CameraSet) -> dict | None:
    """The trained model's water parameters from ``water.json``: sigmas per normalised unit.

    Accepts a ``normalised`` section, ``<key>_normalised`` keys, or per-source-unit values (then
    divided by the camera file's scale). Returns None when the file is absent.
    """
    path = Path(train_dir) / "water.json"
    if not path.is_file():
        log.warning("%s not found: water parameters not evaluated", path)
        return None
    data = json.loads(path.read_text())
    section = data.get("normalised") or data.get("normalized")
    if isinstance(section, dict) and all(k in section for k in ("sigma_attn", "sigma_bs")):
        values = {k: section[k] for k in ("sigma_attn", "sigma_bs")}
    elif all(f"{k}_normalised" in data for k in ("sigma_attn", "sigma_bs")):
        values = {k: data[f"{k}_normalised"] for k in ("sigma_attn", "sigma_bs")}
    else:
        source = data.get("source_units") or data.get("per_source_unit") or data
        if not all(k in source for k in ("sigma_attn", "sigma_bs")):
            raise PipelineError(f"{path}: no sigma_attn / sigma_bs found; re-run the 'train' step")
        values = {k: (np.asarray(source[k], dtype=np.float64) / cameras.scale).tolist()
                  for k in ("sigma_attn", "sigma_bs")}
    c_med = (section or {}).get("c_med", data.get("c_med"))
    values["c_med"] = c_med
    return {k: None if v is None else [float(x) for x in np.ravel(v)] for k, v in values.items()}


def compare_water(fitted: dict | None, truth: dict, metres_per_unit: float,
                  gain: np.ndarray) -> dict:
    """Fitted (converted to 1/m and to the truth's colour scale) against the truth, per channel."""
    result = {"truth": {k: [float(x) for x in truth[k]] for k in WATER_KEYS if k in truth},
              "fitted": None, "relative_error": None}
    if fitted is None:
        return result
    converted = {}
    for key in ("sigma_attn", "sigma_bs"):
        if fitted.get(key) is not None:
            converted[key] = (np.asarray(fitted[key]) / metres_per_unit).tolist()
    if fitted.get("c_med") is not None:
        converted["c_med"] = (np.asarray(fitted["c_med"]) * gain).tolist()
    result["fitted"] = converted
    result["relative_error"] = {k: metrics.relative_error(converted[k], truth[k]).tolist()
                                for k in converted if k in truth}
    return result


# -------------------------------------------------------------------------------------- summary

def _read_json(path: Path) -> dict | None:
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError:
        return None
    except json.JSONDecodeError as exc:
        raise PipelineError(f"{path}: not valid JSON ({exc})") from None


def training_summary(train_dir: Path) -> dict | None:
    """Training time and last logged losses from ``train_log.csv`` (None when absent)."""
    path = Path(train_dir) / "train_log.csv"
    if not path.is_file():
        return None
    log_table = pd.read_csv(path)
    if log_table.empty or "wall_time_s" not in log_table:
        return None
    last = log_table.iloc[-1]
    test_psnr = log_table["test_psnr"].dropna() if "test_psnr" in log_table else pd.Series([])
    return {"time_s": float(log_table["wall_time_s"].max()),
            "steps": int(last["step"]) if "step" in log_table else None,
            "final_loss": float(last["loss"]) if "loss" in log_table else None,
            "final_test_psnr": float(test_psnr.iloc[-1]) if len(test_psnr) else None}


def build_summary(dataset: str, table: pd.DataFrame, renders: Path, train_dir: Path,
                  lpips_status: str, truth: dict | None) -> dict:
    numeric = table.drop(columns=["dataset", "view"]).apply(pd.to_numeric, errors="coerce")
    means = {column: float(numeric[column].mean()) for column in numeric.columns
             if numeric[column].notna().any()}
    if "lpips" not in means:
        means["lpips"] = UNAVAILABLE
    render_stats = _read_json(Path(renders) / "render_stats.json") or {}
    water = _read_json(Path(train_dir) / "water.json")
    return {
        "format": "seathru-evaluation/1",
        "dataset": dataset,
        "views": len(table),
        "means": means,
        "lpips": lpips_status,
        "render": {"fps": render_stats.get("fps"),
                   "seconds_per_frame": render_stats.get("seconds_per_frame"),
                   "resolution": render_stats.get("resolution"),
                   "device": (render_stats.get("settings") or {}).get("device")},
        "training": training_summary(train_dir),
        "water_fitted": water,
        "medium_selection": _read_json(Path(train_dir) / "selection.json"),
        "truth": truth,
    }


def _json_safe(value):
    """NaN and infinities become null (JSON has no such numbers)."""
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.ndarray):
        return _json_safe(value.tolist())
    return value
