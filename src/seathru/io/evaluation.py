"""Files of the evaluate step and the inputs only it reads.

- ``evaluate/summary.json`` (format ``seathru-evaluation/1``): a
  :class:`seathru.eval.summary.EvaluationSummary` with a ``format`` key first; written by the
  evaluate step, read by the report;
- ``evaluate/metrics.csv``: one row per held-out view (:class:`seathru.eval.summary.ViewMetrics`),
  columns ``VIEW_COLUMNS`` then, for simulated datasets, ``TRUTH_COLUMNS``; ``lpips`` holds a
  number or ``unavailable``;
- :func:`truth_evaluation`: the simulated datasets' comparison with the simulator's truth
  (``seathru.eval.truth``), reading one view at a time;
- inputs: the render step's held-out renders ``test/<view>/<name>.tiff``, the simulator's truth
  images ``truth/<kind>/<view>.tiff``, camera centres of a camera file, ``train/train_log.csv``
  (written by the train step) as a table, and LPIPS weights (torch state dicts on disk, never
  downloaded).
"""

from __future__ import annotations

import dataclasses
import os
import types
import typing
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from seathru.errors import PipelineError
from seathru.eval import summary as dataset_summary
from seathru.eval import truth as truth_eval
from seathru.eval.summary import (VIEW_COLUMNS, EvaluationSummary, TruthSummary, ViewMetrics,
                                  metrics_table)
from seathru.io.atomic import write_json, write_text
from seathru.io.cameras import CameraSet, read_cameras
from seathru.io.images import read_image, read_mask
from seathru.io.jsonfile import json_safe, read_json
from seathru.io.renders import RESTORED_PHOTO, RESTORED_REPROJECTED, RESTORED_SUPPORT
from seathru.io.stored_views import (source_cameras, stored_image_on_frame,
                                     undistort_interpolation)
from seathru.io.water import WaterReport, read_truth_water
from seathru.radiometry.linearise import resize_area

EVALUATION_FORMAT = "seathru-evaluation/1"


# ------------------------------------------------------------------------------ summary.json

def _to_json(value: Any) -> Any:
    if dataclasses.is_dataclass(value):
        return {f.name: _to_json(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {k: _to_json(v) for k, v in value.items()}
    return json_safe(value)


_PLAIN = {float: (int, float), int: (int,), str: (str,), dict: (dict,), list: (list,)}


def _from_json(tp: Any, value: Any, where: str, source: str) -> Any:
    """``value`` checked against the annotation ``tp``; dataclasses built recursively."""
    origin = typing.get_origin(tp)
    options = typing.get_args(tp) if origin in (typing.Union, types.UnionType) else (tp,)
    if value is None:
        if type(None) in options:
            return None
        raise PipelineError(f"{source}: {where} must not be null")
    for option in options:
        base = typing.get_origin(option) or option
        if dataclasses.is_dataclass(option):
            if not isinstance(value, dict):
                raise PipelineError(f"{source}: {where} must be an object")
            hints = typing.get_type_hints(option)
            missing = [f.name for f in dataclasses.fields(option) if f.name not in value
                       and f.default is dataclasses.MISSING
                       and f.default_factory is dataclasses.MISSING]
            if missing:
                raise PipelineError(f"{source}: {where}.{missing[0]} is missing")
            known = {f.name for f in dataclasses.fields(option)}
            return option(**{k: _from_json(hints[k], v, f"{where}.{k}", source)
                             for k, v in value.items() if k in known})
        if base in _PLAIN and isinstance(value, _PLAIN[base]) and not isinstance(value, bool):
            return float(value) if base is float else value
    raise PipelineError(f"{source}: {where} has the wrong type ({value!r:.60})")


def write_summary(path: str | os.PathLike, summary: EvaluationSummary) -> None:
    """Write ``summary.json`` atomically (NaN and infinities as null)."""
    write_json(path, {"format": EVALUATION_FORMAT, **_to_json(summary)})


def read_summary(path: str | os.PathLike) -> EvaluationSummary:
    """Read ``summary.json``.

    Raises:
        PipelineError: naming the file when it is missing, not JSON, of another format or
        malformed.
    """
    data = read_json(path, hint="run the 'evaluate' step")
    if not isinstance(data, dict) or data.get("format") != EVALUATION_FORMAT:
        found = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise PipelineError(f"{path}: expected format {EVALUATION_FORMAT!r}, found {found!r}; "
                            "re-run the 'evaluate' step")
    if data.get("water_fitted") is not None:
        WaterReport.from_dict(data["water_fitted"], f"{path} (water_fitted)")
    fields = {k: v for k, v in data.items() if k != "format"}
    return _from_json(EvaluationSummary, fields, "summary", str(path))


# ------------------------------------------------------------------------------- metrics.csv

def write_metrics(path: str | os.PathLike, rows: list[ViewMetrics] | pd.DataFrame) -> None:
    """Write ``metrics.csv`` atomically."""
    table = rows if isinstance(rows, pd.DataFrame) else metrics_table(rows)
    write_text(path, table.to_csv(index=False, float_format="%.6g"))


def read_metrics(path: str | os.PathLike) -> pd.DataFrame:
    """Read ``metrics.csv`` (``view`` as text).

    Raises:
        PipelineError: naming the file when it is missing, unreadable or lacks a column.
    """
    try:
        table = pd.read_csv(path, dtype={"dataset": str, "view": str})
    except FileNotFoundError:
        raise PipelineError(f"{path}: file not found; run the 'evaluate' step") from None
    except (pd.errors.ParserError, pd.errors.EmptyDataError) as exc:
        raise PipelineError(f"{path}: cannot be read as a table ({exc})") from None
    missing = [c for c in VIEW_COLUMNS if c not in table.columns]
    if missing:
        raise PipelineError(f"{path}: missing columns {missing}; re-run the 'evaluate' step")
    return table


# ------------------------------------------------------------------------ inputs of evaluation

def read_render(renders: str | os.PathLike, view: str, name: str) -> np.ndarray:
    """A held-out render (``full``, ``restored``, ``depth``, ...) of the render step."""
    path = Path(renders) / "test" / view / f"{name}.tiff"
    if not path.is_file():
        raise PipelineError(f"{path}: render not found; re-run the 'render' step with the same "
                            "cameras.json")
    return read_image(path)


def view_support(renders: str | os.PathLike, view: str) -> dict[str, float]:
    """A held-out view's support columns (``unseen_surface_share``) from its renders, or {}
    where the render step wrote no ``restored_support`` (``render.photos.restore none``)."""
    folder = Path(renders) / "test" / view
    support, opacity = folder / f"{RESTORED_SUPPORT}.tiff", folder / "opacity.tiff"
    if not (support.is_file() and opacity.is_file()):
        return {}
    share = dataset_summary.unseen_surface_share(_plane(read_image(support)),
                                                 _plane(read_image(opacity)))
    return {} if share is None else {"unseen_surface_share": share}


def _plane(image: np.ndarray) -> np.ndarray:
    return image[..., 0] if image.ndim == 3 else image


def camera_centres(cameras: CameraSet, *, source_units: bool = False) -> dict[str, np.ndarray]:
    """Camera centres ``(3,)`` by frame name: in the file's normalised units, or with
    ``source_units`` in the units of the source reconstruction (``c / scale + centre``; metres
    for the simulator's truth cameras)."""
    centre = np.asarray(cameras.centre, dtype=np.float64)
    return {f.name: f.c2w_array[:3, 3] / cameras.scale + centre if source_units
            else f.c2w_array[:3, 3] for f in cameras.frames}


def read_truth_image(truth_dir: str | os.PathLike, kind: str, view: str) -> np.ndarray:
    """A simulated view's truth (``clean``, ``water`` or ``depth``) from the simulate step."""
    path = Path(truth_dir) / kind / f"{view}.tiff"
    if not path.is_file():
        raise PipelineError(f"{path}: truth image not found; re-run the 'simulate' step")
    return read_image(path)


def read_train_log(path: str | os.PathLike) -> pd.DataFrame | None:
    """The train step's ``train_log.csv`` as a table; None when it does not exist."""
    if not Path(path).is_file():
        return None
    try:
        return pd.read_csv(path)
    except (pd.errors.ParserError, pd.errors.EmptyDataError) as exc:
        raise PipelineError(f"{path}: cannot be read as a table ({exc})") from None


def read_lpips_weights(path: str | os.PathLike) -> dict | None:
    """The merged state dict of the LPIPS weights at ``path``; None when ``path`` does not exist.

    ``path``: one ``.pth`` file, or a folder whose ``.pth`` / ``.pt`` files are merged (the
    torchvision backbone and the lpips v0.1 linear layers).

    Raises:
        PipelineError: naming a file that exists but is not a torch state dict.
    """
    path = Path(path)
    if not path.exists():
        return None
    import torch

    files = sorted(p for p in path.iterdir() if p.suffix in (".pth", ".pt")) \
        if path.is_dir() else [path]
    state: dict = {}
    for file in files:
        try:
            loaded = torch.load(file, map_location="cpu", weights_only=True)
        except Exception as exc:
            raise PipelineError(f"{file}: cannot be read as a torch state dict ({exc})") from None
        if isinstance(loaded, dict):
            state.update(loaded)
    return state


def load_lpips(path: str | os.PathLike | None):
    """``(network or None, status text)`` of ``seathru.eval.summary.lpips_network`` for the
    weights at ``path`` (None: not configured).

    Raises:
        PipelineError: naming ``--lpips-weights`` when the weights do not fit the network.
    """
    weights = None if path is None else read_lpips_weights(path)
    try:
        return dataset_summary.lpips_network(weights, path)
    except ValueError as exc:
        raise PipelineError(f"--lpips-weights {path}: {exc}") from None


# ----------------------------------------------------------------- against the simulator's truth

def resized_like(image: np.ndarray, like: np.ndarray) -> np.ndarray:
    """``image`` area-resized to ``like``'s size (renders may be downscaled)."""
    return resize_area(image, (like.shape[1], like.shape[0]))


def truth_on_frames(cameras: CameraSet) -> Callable[[np.ndarray, str], np.ndarray]:
    """``(image, view) -> image`` that puts a simulator's truth image of ``view`` onto that
    frame's camera the way the poses step put the training images there
    (``stored_views.stored_image_on_frame``: the source camera's undistortion, then the frame's
    size). Colour images (three channels or more) are resampled as the training images were;
    anything else (depth, coverage) bilinearly."""
    frames, candidates = {f.name: f for f in cameras.frames}, source_cameras(cameras)
    colour_interpolation = undistort_interpolation(cameras)

    def on_frame(image: np.ndarray, view: str) -> np.ndarray:
        colour = image.ndim == 3 and image.shape[2] >= 3
        return stored_image_on_frame(image, frames[view], candidates,
                                     colour_interpolation if colour else "linear")

    return on_frame


def _images_and_water_truth(cameras: CameraSet, truth_dir: Path,
                            on_frame: Callable[[np.ndarray, str], np.ndarray]
                            ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """``(image, truth with water)`` of every frame, one at a time, on the frame's camera; the
    image NaN where its mask marks it invalid (clipped)."""
    for frame in cameras.frames:
        image = read_image(cameras.image_path(frame))[..., :3].astype(np.float32)
        mask_path = cameras.mask_path(frame)
        if mask_path is not None and mask_path.is_file():
            image[~read_mask(mask_path)] = np.nan
        water = on_frame(read_truth_image(truth_dir, "water", frame.name), frame.name)
        yield image, water[..., :3]


def _training_coverage(truth_dir: Path, truth_cameras: CameraSet, cameras: CameraSet
                       ) -> Callable[[str], np.ndarray] | None:
    """``view -> (H, W) float32`` on the simulator's camera: 1 where two or more of the
    evaluated camera file's training views see the pixel's true surface
    (``seathru.eval.truth.training_view_coverage``, true cameras and ranges); None where the
    simulation lacks a training view."""
    frames = {f.name: f for f in truth_cameras.frames}
    training = [f.name for f in cameras.frames if f.split != "test"]
    if not training or any(name not in frames for name in training):
        return None

    def truth_range(name: str) -> np.ndarray:
        depth = read_truth_image(truth_dir, "depth", name)
        depth = depth[..., 0] if depth.ndim == 3 else depth
        return depth.astype(np.float64) * truth_cameras.scale   # metres -> the file's units

    ranges = {name: truth_range(name) for name in training}

    def coverage(view: str) -> np.ndarray:
        counts = truth_eval.training_view_coverage(
            frames[view], truth_range(view), ((frames[n], ranges[n]) for n in training))
        return (counts >= 2).astype(np.float32)

    return coverage


def _supported(support: np.ndarray) -> np.ndarray:
    """The pixels the training photographs back (``seathru.nerf.reproject.SUPPORTED``)."""
    from seathru.nerf.reproject import SUPPORTED

    return np.nan_to_num(_plane(support)) >= SUPPORTED


def truth_evaluation(truth_dir: Path, renders: Path, cameras: CameraSet, rows: list[dict],
                     water: WaterReport | None) -> TruthSummary:
    """Add the truth columns to ``rows`` (one per held-out view, ``view`` keyed); return the
    summary's truth part: colour gain, metric scale, water against the truth.

    The truth images are in the simulator's cameras, the renders in the poses step's
    undistorted ones: each truth image goes through the undistortion the training images went
    through (``stored_views.stored_image_on_frame``). On the demo, whose COLMAP camera has a
    small radial term, an area resize alone had cost the restored view 0.6 dB and the full
    render 0.9 dB against the truth.

    Raises:
        PipelineError: the camera file and the simulation do not match (views without truth).
    """
    truth_dir, renders = Path(truth_dir), Path(renders)
    truth_cameras = read_cameras(truth_dir / "cameras.json")
    truth_centres = camera_centres(truth_cameras, source_units=True)
    views = [row["view"] for row in rows]
    missing = [view for view in views if view not in truth_centres]
    if missing:
        raise PipelineError(f"{truth_dir / 'cameras.json'}: no truth for held-out views "
                            f"{missing[:3]}; the camera file and the simulation do not match")
    scale = truth_eval.camera_metric_scale(camera_centres(cameras), truth_centres, cameras.scale)

    on_frame = truth_on_frames(cameras)

    def truth(kind: str, view: str, like: np.ndarray) -> np.ndarray:
        return resized_like(on_frame(read_truth_image(truth_dir, kind, view), view), like)

    gain = truth_eval.pooled_gain(_images_and_water_truth(cameras, truth_dir, on_frame))
    coverage = _training_coverage(truth_dir, truth_cameras, cameras)
    for row in rows:
        view = row["view"]
        full = read_render(renders, view, "full")
        covered = None
        if coverage is not None:
            covered = resized_like(on_frame(coverage(view), view), full) > 0.5
        photo = Path(renders) / "test" / view / f"{RESTORED_PHOTO}.tiff"
        reprojected = Path(renders) / "test" / view / f"{RESTORED_REPROJECTED}.tiff"
        support = Path(renders) / "test" / view / f"{RESTORED_SUPPORT}.tiff"
        row.update(truth_eval.view_truth_metrics(
            full=full, restored=read_render(renders, view, "restored"),
            depth=read_render(renders, view, "depth"), clean=truth("clean", view, full),
            water=truth("water", view, full), truth_depth=truth("depth", view, full),
            gain=gain, metres_per_unit=scale.scale, covered=covered,
            restored_photo=read_image(photo) if photo.is_file() else None,
            reprojected=read_image(reprojected) if reprojected.is_file() else None,
            supported=_supported(read_image(support)) if support.is_file() else None))
    fitted = None if water is None else water.normalised.as_dict()
    uncertainty = None if water is None else water.uncertainty
    comparison = truth_eval.compare_water(
        fitted, read_truth_water(truth_dir / "water.json").as_dict(), scale.scale, gain,
        halfwidth=uncertainty["halfwidth95"] if uncertainty else None,
        determined=uncertainty["determined"] if uncertainty else None)
    return truth_eval.truth_summary(gain, scale, comparison)
