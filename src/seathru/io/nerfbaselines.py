"""The community's evaluation protocol (NerfBaselines, ``evaluate.protocol=nerfbaselines``):
predictions against the stored images, written in NerfBaselines' layout.

Folder ``results/<dataset>/evaluate/nerfbaselines/`` (replaced atomically)::

    color/<name>.png      the prediction, 8-bit, quantised as the protocol does
    gt-color/<name>.png   the ground truth: the stored image as the protocol reads it
    info.json             method, protocol and dataset metadata (NerfBaselines' info.json)
    results.json          NerfBaselines' results format (``nerfbaselines/io.py``,
                          ``serialize_evaluation_results``): ``metrics`` (means, 5 decimals),
                          ``metrics_raw`` (per image, base64 of float32 in name order),
                          ``metrics_sha256``, ``predictions_sha256``, ``ground_truth_sha256``,
                          ``evaluation_protocol``, ``nb_info``, render/evaluate dates and
                          versions; ours under ``seathru`` (per-image values, the ground truth's
                          source, deviations from the protocol)

The prediction is the render's full image (``render/test/<name>/full.tiff``) taken back to the
stored image's encoding and geometry (``seathru.io.stored_views``), then quantised; the metrics
are ``seathru.eval.protocols``. The held-out views must be the protocol's (every 8th of the
sorted stored names: ``poses.test_every=8``), rendered at full resolution.
"""

from __future__ import annotations

import base64
import hashlib
import logging
import struct
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from seathru import __version__
from seathru.errors import PipelineError
from seathru.eval import protocols
from seathru.io.atomic import atomic_dir, write_json
from seathru.io.cameras import CameraSet
from seathru.io.evaluation import read_render
from seathru.io.jsonfile import json_safe
from seathru.io.stored_views import (StoredView, frame_source_camera, ingest_folder_of,
                                     read_stored_codes, read_stored_views, render_to_stored,
                                     source_cameras)
from seathru.radiometry.stored_encoding import stored_values

log = logging.getLogger(__name__)

METHOD = "seathru-nerf (seathru-pipeline)"
PROTOCOL_DESCRIPTION = ("NerfBaselines 'default' protocol of the seathru-nerf dataset: every 8th "
                        "image of the sorted names held out, full resolution, prediction "
                        "quantised by truncation (clip(x*255).astype(uint8)), ground truth the "
                        "stored image; PSNR, SSIM (dm-pix), MAE, MSE, LPIPS")
SOURCES = ("nerfbaselines/datasets/seathru_nerf.py, nerfbaselines/evaluation.py "
           "(DefaultEvaluationProtocol), nerfbaselines/utils.py (convert_image_dtype, "
           "image_to_srgb), nerfbaselines/metrics.py, nerfbaselines/io.py")


def _now() -> str:
    return datetime.now(timezone.utc).replace(tzinfo=None).isoformat(timespec="seconds")


def check_protocol_split(cameras: CameraSet, views: dict[str, StoredView]) -> list[str]:
    """The held-out names, checked to be the protocol's (every 8th of the sorted file names).

    Raises:
        PipelineError: a frame without a stored image, or a test split that differs, naming
            the views and the setting to change.
    """
    missing = [f.name for f in cameras.frames if f.name not in views]
    if missing:
        raise PipelineError(f"{missing[:3]}: not in the ingest manifest; re-run 'ingest'")
    by_file = {views[f.name].file_name: f.name for f in cameras.frames}
    wanted = sorted(by_file[n] for n in protocols.held_out_names(list(by_file)))
    held = sorted(f.name for f in cameras.split("test"))
    if held != wanted:
        extra, lacking = sorted(set(held) - set(wanted)), sorted(set(wanted) - set(held))
        raise PipelineError(
            f"evaluate.protocol=nerfbaselines holds out every {protocols.HOLD_EVERY}th image of "
            f"the sorted names, but the camera file's test views differ (not held out by the "
            f"protocol: {extra[:4]}; missing: {lacking[:4]}); set poses.test_every="
            f"{protocols.HOLD_EVERY}")
    return held


def protocol_view(cameras: CameraSet, name: str, renders: Path, view: StoredView,
                  candidates: list) -> tuple[np.ndarray, np.ndarray]:
    """``(prediction, ground truth)`` of one held-out view, uint8 ``(H, W, 3)`` each."""
    frame = next(f for f in cameras.frames if f.name == name)
    full = read_render(renders, name, "full")
    if full.shape[:2] != (frame.height, frame.width):
        raise PipelineError(f"{renders}/test/{name}: rendered at {full.shape[1]}x"
                            f"{full.shape[0]}, the camera is {frame.width}x{frame.height}; "
                            "the protocol needs full resolution: render.downscale=1")
    camera = frame_source_camera(frame, view.size, candidates)
    stored = stored_values(full, view.gains, view.exposure_factor, view.encoding)
    prediction = protocols.quantise_truncate(render_to_stored(stored, frame, camera))
    truth = protocols.stored_codes_as_uint8(read_stored_codes(view))
    if truth.shape != prediction.shape:
        raise PipelineError(f"{view.path}: stored image of {truth.shape[1]}x{truth.shape[0]} "
                            f"pixels, prediction {prediction.shape[1]}x{prediction.shape[0]}; "
                            "the protocol needs full resolution")
    return prediction, truth


def _write_png(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
        raise PipelineError(f"{path}: cannot be written")


def encode_values(values: list[float]) -> str:
    """NerfBaselines' ``metrics_raw`` encoding: base64 of the values packed as float32."""
    return base64.b64encode(b"".join(struct.pack("f", v) for v in values)).decode("ascii")


def metrics_sha256(lists: dict[str, list[float]]) -> str:
    """NerfBaselines' ``metrics_sha256`` (``get_metrics_hash``): per metric in name order, its
    lower-case name, its sorted values encoded as :func:`encode_values`, a newline."""
    sha = hashlib.sha256()
    for name in sorted(lists):
        sha.update(name.lower().encode("utf8"))
        sha.update(encode_values(sorted(lists[name])).encode("ascii"))
        sha.update(b"\n")
    return sha.hexdigest()


def files_sha256(folder: Path, names: list[str]) -> str:
    """sha256 of the files' bytes in name order (NerfBaselines' ``get_predictions_sha``)."""
    sha = hashlib.sha256()
    for name in sorted(names):
        sha.update((folder / name).read_bytes())
    return sha.hexdigest()


def evaluate_nerfbaselines(cameras: CameraSet, renders: Path, out: Path, dataset: str,
                           lpips_network=None, training: dict | None = None) -> dict[str, Any]:
    """Run the protocol on the held-out views and write ``out`` (see the module docstring).

    Args:
        lpips_network: ``seathru.eval.summary.lpips_network``'s network, or None (no LPIPS).
        training: ``{"steps": ..., "time_s": ...}`` of the train step, for info.json.

    Returns:
        the summary's part: protocol, means, per-view values, the folder.
    """
    views = read_stored_views(ingest_folder_of(cameras))
    held = check_protocol_split(cameras, views)
    candidates = source_cameras(cameras)
    per_view: dict[str, dict[str, float]] = {}
    lpips_key = "lpips" if getattr(lpips_network, "net_name", "alex") == "alex" else "lpips_vgg"
    kinds = sorted({views[n].kind for n in held})
    with atomic_dir(out) as tmp:
        for name in held:
            prediction, truth = protocol_view(cameras, name, renders, views[name], candidates)
            _write_png(tmp / "color" / f"{name}.png", prediction)
            _write_png(tmp / "gt-color" / f"{name}.png", truth)
            values = protocols.view_protocol_metrics(prediction, truth, lpips_network)
            if "lpips" in values:
                values[lpips_key] = values.pop("lpips")
            per_view[name] = values
            log.info("%s (nerfbaselines): PSNR %.2f dB, SSIM %.4f", name, values["psnr"],
                     values["ssim"])
        lists = protocols.protocol_lists(per_view[n] for n in held)
        means = protocols.protocol_means(per_view[n] for n in held)
        files = [f"{n}.png" for n in held]
        metadata = {"id": dataset, "name": dataset, "color_space": "srgb",
                    "evaluation_protocol": protocols.PROTOCOL_NAME,
                    "ground_truth": _ground_truth_note(kinds)}
        info = {"method": METHOD, "seathru_version": __version__,
                "num_iterations": (training or {}).get("steps"),
                "total_train_time": (training or {}).get("time_s"), "datetime": _now(),
                "dataset_metadata": metadata, "evaluation_protocol": protocols.PROTOCOL_NAME,
                "protocol": PROTOCOL_DESCRIPTION, "protocol_source": SOURCES,
                "render_version": f"seathru-pipeline {__version__}",
                "render_datetime": _now(), "render_dataset_metadata": metadata}
        write_json(tmp / "info.json", json_safe(info))
        nb_info = {k: v for k, v in info.items() if not k.startswith("render_")}
        results = {
            "render_datetime": info["render_datetime"], "render_version": info["render_version"],
            "render_dataset_metadata": metadata, "nb_info": nb_info,
            "evaluate_datetime": _now(), "evaluate_version": f"seathru-pipeline {__version__}",
            "metrics": {k: round(v, 5) for k, v in means.items()},
            "metrics_raw": {k: encode_values(v) for k, v in lists.items()},
            "metrics_sha256": metrics_sha256(lists),
            "predictions_sha256": files_sha256(tmp / "color", files),
            "ground_truth_sha256": files_sha256(tmp / "gt-color", files),
            "evaluation_protocol": protocols.PROTOCOL_NAME,
            "seathru": {"images": files, "per_image": per_view,
                        "ground_truth": metadata["ground_truth"],
                        "lpips": "computed" if lpips_network is not None else "unavailable"}}
        write_json(tmp / "results.json", json_safe(results))
    return {"protocol": "nerfbaselines", "folder": str(out), "views": len(held),
            "means": means, "ground_truth": metadata["ground_truth"]}


def _ground_truth_note(kinds: list[str]) -> str:
    notes = {"srgb": "the stored 8-bit sRGB files as they are",
             "linear": "the stored linear files as they are (16-bit: top byte, as PIL reads "
                       "them)",
             "raw": "RAW source: the ingest's white-balanced linear image, as an images_wb/ "
                    "file would store it"}
    return "; ".join(notes[k] for k in kinds)

