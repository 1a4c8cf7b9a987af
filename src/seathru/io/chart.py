"""Colour-chart annotations and the chart measurement of the evaluate step.

Annotation (one small JSON file; ``evaluate.chart``, or ``colour_chart.json`` in the dataset's
folder)::

    {"format": "seathru-colour-chart/1",
     "chart": "macbeth-classic-24",        # a key of seathru.eval.colour_chart.CHARTS
     "image": "IMG_0042.jpg",              # the stored image (file name or stem)
     "image_size": [6000, 4000],           # optional: the size the corners refer to
     "corners": [[x, y], [x, y], [x, y], [x, y]],   # outer corners of the patch area
     "occluded": [2],                      # optional: 0-based patches hidden by something
     "note": "..."}

Corners follow ``seathru.eval.colour_chart`` (corner 0 beside patch 1; pixel (u, v) centred at
(u + 0.5, v + 0.5)) on the stored image as ingest oriented it. Without an annotation, OpenCV's
``mcc`` detector looks for a ColorChecker Classic 24 in the stored images (held-out views
first); that it found none is recorded.

The chart is measured on up to three images of its view (``seathru.io.stored_views``): the
stored photo (decoded to linear, no white balance: what the camera saw; not for RAW sources),
the ingest's linear image (white-balanced and exposure-normalised: what the model was trained
on) and the restored render (the scene without water). Patches marked occluded, and patches
clipped in the stored image (a sample at 98 % of the top code or more), are left out of all
three.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from seathru.errors import PipelineError
from seathru.eval import colour_chart
from seathru.io.cameras import CameraSet, Frame
from seathru.io.images import read_image
from seathru.io.jsonfile import read_json
from seathru.io.manifest import read_manifest
from seathru.io.renders import PHOTOS_DIR, RESTORED_PHOTO
from seathru.io.stored_views import (StoredView, ingest_folder_of, read_stored_codes,
                                     read_stored_views, source_cameras, stored_points_on_frame)
from seathru.radiometry import stored_encoding
from seathru.radiometry.colour import linear_to_srgb

log = logging.getLogger(__name__)

FORMAT = "seathru-colour-chart/1"
ANNOTATION_NAME = "colour_chart.json"
CLIPPED_LEVEL = 0.98
#: Long side the stored images are reduced to before chart detection.
DETECT_MAX_SIZE = 2000


def read_chart_annotation(path: str | Path) -> dict[str, Any]:
    """The annotation at ``path``, checked: chart type known, four corners, patch indices.

    Raises:
        PipelineError: naming the file and the field.
    """
    data = read_json(path, hint="write a colour-chart annotation (see seathru.io.chart)")
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise PipelineError(f"{path}: expected format {FORMAT!r}")
    if data.get("chart") not in colour_chart.CHARTS:
        raise PipelineError(f"{path}: chart {data.get('chart')!r} unknown; known: "
                            f"{', '.join(colour_chart.CHARTS)}")
    corners = np.asarray(data.get("corners", []), dtype=np.float64)
    if corners.shape != (4, 2) or not np.all(np.isfinite(corners)):
        raise PipelineError(f"{path}: corners must be four [x, y] pairs")
    spec = colour_chart.CHARTS[data["chart"]]
    occluded = [int(i) for i in data.get("occluded", [])]
    if any(not 0 <= i < spec.patches for i in occluded):
        raise PipelineError(f"{path}: occluded patches must be in 0..{spec.patches - 1}")
    if not isinstance(data.get("image"), str) or not data["image"]:
        raise PipelineError(f"{path}: 'image' must name the annotated image")
    size = data.get("image_size")
    return {**data, "corners": corners, "occluded": occluded,
            "image_size": None if size is None else (int(size[0]), int(size[1]))}


def find_annotation(given: Path | None, ingest: Path) -> Path | None:
    """``given``, or ``colour_chart.json`` in the dataset's folder (as given to ingest, its
    image subfolder or the folder above that)."""
    if given is not None:
        return given
    manifest = read_manifest(ingest / "manifest.json", strict=False)
    source = manifest.get("input", {}) if isinstance(manifest, dict) else {}
    for folder in (source.get("given"), source.get("folder")):
        if folder:
            for candidate in (Path(folder) / ANNOTATION_NAME,
                              Path(folder).parent / ANNOTATION_NAME):
                if candidate.is_file():
                    return candidate
    return None


def stored_linear(view: StoredView) -> np.ndarray:
    """The stored image decoded to linear values in [0, 1] (no white balance, no exposure)."""
    codes = read_stored_codes(view)
    values = codes.astype(np.float64) / (np.iinfo(codes.dtype).max
                                         if np.issubdtype(codes.dtype, np.integer) else 1.0)
    return stored_encoding.decode(values, view.encoding)


def detect_chart(views: dict[str, StoredView], order: list[str]) -> dict[str, Any] | None:
    """An annotation-like dict for the first view where ``mcc`` finds a ColorChecker, or None."""
    import cv2

    for name in order:
        view = views[name]
        image = linear_to_srgb(np.clip(stored_linear(view), 0.0, 1.0))
        factor = max(1.0, max(view.size) / DETECT_MAX_SIZE)
        if factor > 1:
            image = cv2.resize(image.astype(np.float32), (round(view.size[0] / factor),
                                                          round(view.size[1] / factor)),
                               interpolation=cv2.INTER_AREA)
        corners = colour_chart.detect_macbeth(image)
        if corners is not None:
            return {"chart": "macbeth-classic-24", "image": name, "corners": corners * factor,
                    "occluded": [], "image_size": view.size}
    return None


def _measure(image: np.ndarray, corners: np.ndarray, spec, use: np.ndarray) -> dict:
    means = colour_chart.patch_means(image, corners, spec.rows, spec.cols)
    return {**colour_chart.chart_errors(means, spec, use), "patch_means": means.tolist()}


def evaluate_colour_chart(cameras: CameraSet, renders: Path, annotation: Path | None,
                          detect: bool = True,
                          render_restored: Callable[[Frame], np.ndarray] | None = None
                          ) -> dict[str, Any]:
    """The chart's colour accuracy on its view: stored photo, ingest image, restored render.

    Args:
        annotation: the annotation file (:func:`find_annotation`), or None.
        detect: without an annotation, look for a ColorChecker with OpenCV's ``mcc``.
        render_restored: renders the restored image of a frame that the render step did not
            render (not held out); None: such a view is measured on its photos only.

    Returns:
        ``source`` (annotation file, ``mcc`` or ``none``), ``chart``, ``image``, ``excluded``
        patches and per image ``stored`` / ``ingest`` / ``restored`` / ``restored_photo`` (the
        render step's restored photograph of the view, where it wrote one) the measures of
        ``seathru.eval.colour_chart.chart_errors`` (or a ``reason`` it is absent).
    """
    ingest = ingest_folder_of(cameras)
    views = read_stored_views(ingest)
    if annotation is not None:
        found, source = read_chart_annotation(annotation), str(annotation)
    elif detect:
        held = sorted(f.name for f in cameras.split("test"))
        order = held + sorted(set(views) - set(held))
        found, source = detect_chart(views, order), "mcc"
        if found is None:
            log.info("colour chart: OpenCV mcc found no ColorChecker in %d images", len(order))
            return {"source": "none", "reason": f"no annotation; OpenCV mcc found no "
                                                f"ColorChecker Classic in {len(order)} images"}
    else:
        return {"source": "none", "reason": "no annotation and detection switched off"}
    name = Path(found["image"]).stem
    if name not in views:
        raise PipelineError(f"{source}: image {found['image']!r} is not an image of the dataset")
    view, spec = views[name], colour_chart.CHARTS[found["chart"]]
    size = found.get("image_size") or view.size
    corners = np.asarray(found["corners"]) * np.array([view.size[0] / size[0],
                                                       view.size[1] / size[1]])
    photo = stored_linear(view)
    use = np.ones(spec.patches, bool)
    use[found["occluded"]] = False
    samples = colour_chart.patch_samples(_stored_values_of(view, photo), corners, spec.rows,
                                         spec.cols)
    peaks = np.where(np.isfinite(samples), samples, 0.0).max(axis=(1, 2))
    clipped = [int(i) for i in np.flatnonzero(peaks >= CLIPPED_LEVEL)]
    use[clipped] = False
    result: dict[str, Any] = {"source": source, "chart": spec.name, "reference": spec.source,
                              "image": name, "occluded": found["occluded"], "clipped": clipped}
    if view.kind != "raw":
        result["stored"] = _measure(photo, corners, spec, use)
    linear = read_image(ingest / "linear" / f"{name}.tiff")
    scale = np.array([linear.shape[1] / view.size[0], linear.shape[0] / view.size[1]])
    result["ingest"] = _measure(linear, corners * scale, spec, use)
    result["restored"] = _restored(cameras, renders, name, view, corners, spec, use,
                                   render_restored)
    result["restored_photo"] = _restored_photo(cameras, renders, name, view, corners, spec, use)
    for image in ("stored", "ingest", "restored", "restored_photo"):
        part = result.get(image) or {}
        if "mean_delta_e00" in part:
            log.info("colour chart (%s): %s: mean dE00 %.2f, grey angular error %.2f deg",
                     name, image, part["mean_delta_e00"], part["mean_grey_angular_error_deg"])
    return result


def _stored_values_of(view: StoredView, photo: np.ndarray) -> np.ndarray:
    """The stored values in [0, 1] of a decoded photo (for the clipping test)."""
    return stored_encoding.encode(photo, view.encoding)


def _restored_photo(cameras, renders, name, view, corners, spec, use) -> dict:
    frame = next((f for f in cameras.frames if f.name == name), None)
    if frame is None:
        return {"reason": f"{name} has no camera (not registered by the poses step)"}
    for path in (Path(renders) / "test" / name / f"{RESTORED_PHOTO}.tiff",
                 Path(renders) / PHOTOS_DIR / f"{name}.tiff"):
        if path.is_file():
            return _measure_on_frame(read_image(path), frame, cameras, view, corners, spec, use)
    return {"reason": f"the render step restored no photograph of {name} "
                      "(render.photos.restore: all restores every view's)"}


def _restored(cameras, renders, name, view, corners, spec, use, render_restored) -> dict:
    frame = next((f for f in cameras.frames if f.name == name), None)
    if frame is None:
        return {"reason": f"{name} has no camera (not registered by the poses step)"}
    path = Path(renders) / "test" / name / "restored.tiff"
    if path.is_file():
        image = read_image(path)
    elif render_restored is not None:
        image = render_restored(frame)
    else:
        return {"reason": f"{name} is a training view and no model to render it"}
    return _measure_on_frame(image, frame, cameras, view, corners, spec, use)


def _measure_on_frame(image, frame, cameras, view, corners, spec, use) -> dict:
    """The chart measured on an image in the frame's (undistorted) geometry, at its size."""
    points = stored_points_on_frame(corners, view.size, frame, source_cameras(cameras))
    points *= np.array([image.shape[1] / frame.width, image.shape[0] / frame.height])
    return _measure(image, points, spec, use)
