"""The poses step's COLMAP tracks as colour observations: input and restored colour of every
3D point in every view that sees it, and their range (``seathru.eval.track_slope``).

Reads the COLMAP model the poses step keeps in ``poses/sparse`` (source units; its images are
named ``<frame>.png``; posed datasets read from a source have none). Each 3D point is projected
with the camera file's own (undistorted, normalised) cameras into the views of its track, so
its pixel is that of the pipeline's linear image ``images/<frame>.tiff``; the range is the
distance from the camera centre to the point, in source units. For the colour slopes an
observation's colour is the mean over a window around that pixel that spans the same patch of
the surface in every view (:func:`window_samples`); its restored colour is rendered with the
trained model through the window's samples for every view of the track (the render step writes
restored images of the held-out views only, and few points are seen in two of those).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from seathru.errors import PipelineError
from seathru.geometry.poses import pixel_of_points
from seathru.io import renders as renders_io
from seathru.io.cameras import CameraSet
from seathru.io.colmap import read_model
from seathru.io.images import read_image, read_mask
from seathru.io.stored_views import one_white_balance
from seathru.radiometry.glare import GlareCorrection

log = logging.getLogger(__name__)
#: A track's colour in a view is the mean over a square window this share of the image's width
#: across at the track's median range, scaled by (median range / range) so that every view of
#: the track averages the same patch of its surface (:func:`window_samples`).
TRACK_WINDOW = 0.02
#: The window is sampled on a grid of this many points a side: the same points in the input
#: image, the renders and the restored photograph.
WINDOW_GRID = 5

SPARSE_DIR = "sparse"
MIN_TRACKS = 20     # fewer tracks: no slope is reported


@dataclass
class TrackObservations:
    """Observations of 3D points, one row each (N rows)."""

    track_ids: np.ndarray   # (N,) COLMAP point3D id
    frames: np.ndarray      # (N,) index into ``names``
    names: list[str]        # frame names
    rows: np.ndarray        # (N,) pixel row in the frame's image
    cols: np.ndarray        # (N,) pixel column
    ranges: np.ndarray      # (N,) camera centre to point, source units
    observed: np.ndarray    # (N, 3) input linear colour at the pixel
    held_out: np.ndarray    # (N,) bool: the frame's split is 'test'
    points: np.ndarray | None = None   # (N, 3) the 3D point, the camera file's normalised units


def track_observations(cameras: CameraSet, model_dir: Path, max_points: int = 20000,
                       seed: int = 0) -> TrackObservations:
    """Every observation of the COLMAP model's 3D points in the camera file's frames.

    Observations that project outside the image, behind the camera, onto a masked-out pixel
    or onto a non-finite pixel are left out; at most ``max_points`` points (a random draw).

    Raises:
        PipelineError: the model cannot be read (names the folder).
    """
    model = read_model(model_dir)
    frames = {f.name: i for i, f in enumerate(cameras.frames)}
    image_frame = {image_id: frames.get(Path(image.name).stem, -1)
                   for image_id, image in model.images.items()}
    point_ids, xyz, frame_index = [], [], []
    for point_id, point in model.points3D.items():
        for element in point.track.elements:
            index = image_frame.get(element.image_id, -1)
            if index >= 0:
                point_ids.append(point_id)
                xyz.append(point.xyz)
                frame_index.append(index)
    point_ids, frame_index = np.asarray(point_ids, np.int64), np.asarray(frame_index, np.int64)
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    unique = np.unique(point_ids)
    if unique.size > max_points:
        keep = np.isin(point_ids, np.random.default_rng(seed).choice(unique, max_points,
                                                                     replace=False))
        point_ids, frame_index, xyz = point_ids[keep], frame_index[keep], xyz[keep]
    normalised = (xyz - np.asarray(cameras.centre, np.float64)) * cameras.scale
    rows = np.full(len(xyz), -1, np.int64)
    cols = rows.copy()
    ranges = np.full(len(xyz), np.nan)
    observed = np.full((len(xyz), 3), np.nan)
    for index, frame in enumerate(cameras.frames):
        here = np.flatnonzero(frame_index == index)
        if here.size == 0:
            continue
        row, col, camera, inside = pixel_of_points(frame.c2w_array, frame.fx, frame.fy,
                                                   frame.cx, frame.cy, frame.width,
                                                   frame.height, normalised[here])
        image = read_image(cameras.image_path(frame))[..., :3]
        mask_path = cameras.mask_path(frame)
        mask = read_mask(mask_path) if mask_path is not None and mask_path.is_file() else None
        good = here[inside]
        r, c = row[inside].astype(np.int64), col[inside].astype(np.int64)
        valid = np.isfinite(image[r, c]).all(-1)
        if mask is not None:
            valid &= (mask[..., 0] if mask.ndim == 3 else mask)[r, c] > 0
        good, r, c = good[valid], r[valid], c[valid]
        rows[good], cols[good] = r, c
        ranges[good] = np.linalg.norm(camera[inside][valid], axis=1) / cameras.scale
        observed[good] = image[r, c]
    found = rows >= 0
    held_out = np.array([f.split == "test" for f in cameras.frames])[frame_index]
    return TrackObservations(point_ids[found], frame_index[found],
                             [f.name for f in cameras.frames], rows[found], cols[found],
                             ranges[found], observed[found], held_out[found],
                             normalised[found])


def window_samples(cameras: CameraSet, obs: TrackObservations, window: float = TRACK_WINDOW,
                   grid: int = WINDOW_GRID) -> np.ndarray:
    """Where each observation's colour is sampled: a ``grid`` x ``grid`` grid over a square
    window around its pixel, ``window`` of the frame's width across at the track's median
    range and scaled by (median range / range), so that it spans the same patch of the surface
    in every view of the track.

    Why a window and not the pixel: the tracks' pixels are feature points, blobs and corners.
    Seen near, the pixel resolves the blob; seen far, it averages the blob with what surrounds
    it, so a dark blob brightens with range and a bright one darkens, whatever the water
    (measured on d3_reef: docs/water.md, "The tracks' colour over windows"). The same points
    sample the input, the renders and the restored photographs, so all are averaged alike.

    Args:
        cameras: the camera file the observations' pixels refer to.
        obs: (N) observations (:func:`track_observations`).
        window: the window's side as a share of the frame's width, at the track's median range.
        grid: sample points a side.

    Returns:
        (N, grid * grid, 2) sample points (x, y) in the frame's pixel coordinates (pixel
        (u, v) centred at (u + 0.5, v + 0.5)), inside the image.

    Example::

        points = window_samples(cameras, obs)      # (N, 25, 2)
    """
    import pandas as pd

    median = pd.Series(obs.ranges).groupby(obs.track_ids).transform("median").to_numpy()
    widths = np.array([f.width for f in cameras.frames], np.float64)[obs.frames]
    heights = np.array([f.height for f in cameras.frames], np.float64)[obs.frames]
    side = window * widths * median / np.maximum(obs.ranges, 1e-12)
    steps = (np.arange(grid) + 0.5) / grid - 0.5
    dx, dy = np.meshgrid(steps, steps)
    x = obs.cols[:, None] + 0.5 + side[:, None] * dx.ravel()[None]
    y = obs.rows[:, None] + 0.5 + side[:, None] * dy.ravel()[None]
    x = np.clip(x, 0.5, widths[:, None] - 0.5)
    y = np.clip(y, 0.5, heights[:, None] - 0.5)
    return np.stack([x, y], -1)


def _sample(image: np.ndarray, points: np.ndarray, scale_x: float = 1.0,
            scale_y: float = 1.0) -> np.ndarray:
    """(n, S, C) the image (H, W, C) at points (n, S, 2), bilinear, the points given in pixel
    coordinates of a frame ``1 / scale`` the image's size."""
    from scipy.ndimage import map_coordinates

    rows = (points[..., 1] * scale_y - 0.5).ravel()
    cols = (points[..., 0] * scale_x - 0.5).ravel()
    values = np.stack([map_coordinates(image[..., c], [rows, cols], order=1, mode="nearest")
                       for c in range(image.shape[-1])], -1)
    return values.reshape(*points.shape[:2], image.shape[-1])


def _window_mean(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(n, C) the mean of values (n, S, C) over the valid (n, S) samples."""
    weights = valid.astype(np.float64)
    return (values * weights[..., None]).sum(1) / np.maximum(weights.sum(1), 1.0)[:, None]


@dataclass
class TrackWindows:
    """Each observation's window (:func:`track_windows`), N observations of S samples."""

    points: np.ndarray     # (N, S, 2) sample points, the frame's pixel coordinates
    valid: np.ndarray      # (N, S) bool: the sample lies on valid input pixels
    observed: np.ndarray   # (N, 3) input linear colour, the mean over the valid samples
    # (N,) pixels from the observation to the nearest open water in its input image
    # (seathru.radiometry.open_water), inf in a frame that shows none; None unless asked for
    open_water_distance: np.ndarray | None = None


def track_windows(cameras: CameraSet, obs: TrackObservations, window: float = TRACK_WINDOW,
                  grid: int = WINDOW_GRID, open_water: bool = False) -> TrackWindows:
    """The observations' windows (:func:`window_samples`) and the input's colour over each;
    with ``open_water``, also each observation's distance to the open water in its image.

    A sample counts where the input image is finite and inside the frame's mask at all four
    pixels it interpolates (undistortion leaves invalid borders); the renders and restored
    photographs are averaged over the same samples. An observation none of whose samples
    count keeps them all (its own pixel is valid: :func:`track_observations`).

    Example::

        windows = track_windows(cameras, obs)
        fit = track_slope(obs.track_ids, obs.ranges, windows.observed)
    """
    from scipy.ndimage import distance_transform_edt

    from seathru.radiometry.open_water import open_water_mask

    points = window_samples(cameras, obs, window, grid)
    valid = np.ones(points.shape[:2], bool)
    values = np.zeros((*points.shape[:2], 3))
    distance = np.full(len(obs.rows), np.inf)
    for index, frame in enumerate(cameras.frames):
        here = np.flatnonzero(obs.frames == index)
        if here.size == 0:
            continue
        image = np.asarray(read_image(cameras.image_path(frame))[..., :3], np.float64)
        good = np.isfinite(image).all(-1)
        mask_path = cameras.mask_path(frame)
        if mask_path is not None and mask_path.is_file():
            mask = read_mask(mask_path)
            good &= mask[..., 0] if mask.ndim == 3 else mask
        values[here] = _sample(np.nan_to_num(image), points[here])
        valid[here] = _sample(good[..., None].astype(np.float64), points[here])[..., 0] > 0.999
        water = open_water_mask(np.nan_to_num(image), valid=good) if open_water else None
        if water is not None and water.any():
            distance[here] = distance_transform_edt(~water)[obs.rows[here], obs.cols[here]]
    valid[~valid.any(1)] = True
    return TrackWindows(points, valid, _window_mean(values, valid),
                        distance if open_water else None)


def observation_rays(cameras: CameraSet, obs: TrackObservations,
                     points: np.ndarray | None = None):
    """The ray through each observation's pixel centre (as ``seathru.nerf.rays.camera_rays_np``),
    or through each of its sample ``points`` (N, S, 2) (:func:`window_samples`), one frame at a
    time.

    Yields:
        ``(rows, origins, directions, near, far)``: ``rows`` (n,) indices into ``obs``;
        origins and directions (n * S, 3) float32 tensors in the camera file's frame, S rays of
        each observation in a row (S = 1 without ``points``); near and far (n * S,) float32
        tensors, the frame's bounds.
    """
    import torch

    if points is None:
        points = np.stack([obs.cols + 0.5, obs.rows + 0.5], -1)[:, None].astype(np.float64)
    for index, frame in enumerate(cameras.frames):
        here = np.flatnonzero(obs.frames == index)
        if here.size == 0:
            continue
        c2w = frame.c2w_array
        where = points[here].reshape(-1, 2)
        camera = np.stack([(where[:, 0] - frame.cx) / frame.fx,
                           (where[:, 1] - frame.cy) / frame.fy,
                           np.ones(len(where))], axis=-1)
        directions = camera @ c2w[:3, :3].T
        directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
        origins = np.broadcast_to(c2w[:3, 3], directions.shape)
        yield (here, torch.from_numpy(origins.astype(np.float32)),
               torch.from_numpy(directions.astype(np.float32)),
               torch.full((len(where),), float(frame.near)),
               torch.full((len(where),), float(frame.far)))


def rendered_colours(model, cameras: CameraSet, obs: TrackObservations,
                     windows: TrackWindows | None = None, chunk: int = 8192
                     ) -> dict[str, np.ndarray]:
    """The model's colours at each observation: ``{"restored": (N, 3), "rgb": (N, 3)}``, the
    restored (water removed) and the full (with water) render, at its pixel or, with
    ``windows`` (:func:`track_windows`), the mean over the rays through its valid samples."""
    from seathru.nerf.inference import render_rays

    points = None if windows is None else windows.points
    colours = {key: np.zeros((len(obs.rows), 3), np.float32) for key in ("restored", "rgb")}
    for here, origins, directions, near, far in observation_rays(cameras, obs, points):
        rendered = render_rays(model, origins, directions, near, far, chunk)
        for key, values in colours.items():
            samples = rendered[key].numpy().reshape(here.size, -1, 3)
            values[here] = samples.mean(1) if windows is None else _window_mean(
                samples, windows.valid[here])
    return colours


def opacity_in_front(model, cameras: CameraSet, obs: TrackObservations, share: float = 0.8,
                     chunk: int = 8192) -> np.ndarray:
    """(N,) object opacity the model gathers on each observation's ray before ``share`` of the
    range of its COLMAP point: fog or floaters in front of the surface.

    The restored view renders the object field alone, so whatever the object field holds in
    front of a surface is part of the restored colour (fog that stands in for water the medium
    misses shows as colour that grows with range).
    """
    import torch

    from seathru.nerf.inference import render_rays

    opacity = np.zeros(len(obs.rows), np.float32)
    for here, origins, directions, near, _ in observation_rays(cameras, obs):
        before = torch.from_numpy((share * obs.ranges[here] * cameras.scale).astype(np.float32))
        opacity[here] = render_rays(model, origins, directions, near,
                                    torch.maximum(before, near * 1.001), chunk)["opacity"].numpy()
    return opacity


def restored_photo_colours(renders: Path, cameras: CameraSet, obs: TrackObservations,
                           windows: TrackWindows | None = None
                           ) -> tuple[np.ndarray, np.ndarray] | None:
    """The input images and the render step's restored photographs (``photos/<view>.tiff``)
    over each observation's window: ``(input, restored)``, each (N, 3), the means over the
    valid samples of ``windows`` (:func:`track_windows`, the default), scaled to the
    photograph's size. None unless every frame with an observation has one
    (``render.photos.restore`` other than ``all``).
    """
    windows = track_windows(cameras, obs) if windows is None else windows
    restored = np.zeros((len(obs.rows), 3))
    for index, frame in enumerate(cameras.frames):
        here = np.flatnonzero(obs.frames == index)
        if here.size == 0:
            continue
        path = Path(renders) / renders_io.PHOTOS_DIR / f"{frame.name}.tiff"
        if not path.is_file():
            return None
        photo = np.nan_to_num(np.asarray(read_image(path)[..., :3], np.float64))
        samples = _sample(photo, windows.points[here], photo.shape[1] / frame.width,
                          photo.shape[0] / frame.height)
        restored[here] = _window_mean(samples, windows.valid[here])
    return windows.observed, restored


def track_colour_slope(cameras: CameraSet, model_path: Path, threads: int | None = None,
                       min_tracks: int = MIN_TRACKS, renders: Path | None = None
                       ) -> dict | None:
    """``summary.json``'s ``track_colour_slope``: the within-track slope of log colour against
    range in the input images, in the restored renders and in the full renders (with water),
    per channel, and its reduction, each colour the mean over the observation's window
    (:func:`window_samples`: the same samples in every image), and ``frame_colour``: each
    frame's colour offset beyond what the points and their ranges explain
    (``seathru.eval.track_slope.frame_colour_offsets``: a camera's auto white balance); with
    the render step's
    restored photographs in ``renders`` (:func:`restored_photo_colours`), each part also holds
    ``"photographs"``: the same summary of the input images and the restored photographs
    (``seathru.eval.track_slope.colour_slope_summary``). Over all views of the tracks, over
    the held-out views alone where at least ``min_tracks`` tracks have two held-out
    observations (else that part is ``{"source": "none", "reason": ...}``), and over all views
    of the nearest 90% of the tracks and of the farthest 10% (``near_tracks``, ``far_tracks``;
    ``seathru.eval.track_slope.far_tracks``). None without a
    COLMAP model next to the camera file; ``{"source": "none", "reason": ...}`` without a
    trained model.
    """
    from seathru.eval.track_slope import colour_slope_summary, far_tracks, frame_colour_offsets

    model_dir = (cameras.root or Path(".")) / SPARSE_DIR
    if not model_dir.is_dir():
        return None
    if not Path(model_path).is_file():
        return {"source": "none", "reason": f"{model_path}: no trained model"}
    obs = track_observations(cameras, model_dir)
    windows = track_windows(cameras, obs, open_water=True)
    observed = windows.observed
    photo = None if renders is None else restored_photo_colours(renders, cameras, obs, windows)
    result: dict = {"source": str(model_dir), "range_units": "source units (COLMAP's)",
                    "restored_from": "the trained model, rendered through every sample of "
                                     "each observation's window",
                    "window": {"share_of_width": TRACK_WINDOW, "grid": WINDOW_GRID,
                               "at": "the track's median range, scaled by median range / "
                                     "range (the same patch of surface in every view)"}}
    far = far_tracks(obs.track_ids, obs.ranges)
    parts = {"all_views": np.ones(len(obs.rows), bool), "held_out_views": obs.held_out,
             "near_tracks": ~far, "far_tracks": far}
    rendered = None
    for name, keep in parts.items():
        ids, counts = np.unique(obs.track_ids[keep], return_counts=True)
        enough = int((counts >= 2).sum())
        if enough < min_tracks:
            result[name] = {"source": "none", "reason": f"{enough} tracks have two or more "
                                                        f"observations (need {min_tracks})"}
            continue
        if rendered is None:
            from seathru.io.model import load_model
            from seathru.nerf.device import select_device

            try:
                model = load_model(model_path, select_device("auto", threads))
            except PipelineError as exc:
                return {"source": "none", "reason": str(exc)}
            rendered = rendered_colours(model, cameras, obs, windows)
        result[name] = colour_slope_summary(obs.track_ids[keep], obs.ranges[keep],
                                            observed[keep], rendered["restored"][keep],
                                            rendered["rgb"][keep])
        if photo is not None:
            result[name]["photographs"] = colour_slope_summary(
                obs.track_ids[keep], obs.ranges[keep], photo[0][keep], photo[1][keep])
    if rendered is not None and "reduction" in result.get("all_views", {}):
        restorations = {"restored": rendered["restored"]}
        if photo is not None:
            restorations["photographs"] = photo[1]
        beside = _near_open_water(obs, windows, restorations)
        if beside is not None:
            result["all_views"]["near_open_water"] = beside
    cast = frame_colour_offsets(obs.track_ids, obs.frames, obs.ranges, observed)
    if cast is not None:
        result["frame_colour"] = _frame_colour_record(cast, obs.names,
                                                      one_white_balance(cameras))
    headline = result.get("all_views", {})
    if "reduction" in headline:
        log.info("track colour slope (log colour per unit range, R G B): input %s, full render "
                 "%s, restored %s, reduction %s", _fmt(headline["input"]["slope"]),
                 _fmt(headline["rendered"]["slope"]), _fmt(headline["restored"]["slope"]),
                 _fmt(headline["reduction"]))
    return result


def _near_open_water(obs: TrackObservations, windows: TrackWindows,
                     restorations: dict[str, np.ndarray] | None = None) -> dict | None:
    """``track_colour_slope``'s ``near_open_water``: the input's log colour over windows fitted
    within tracks on range together with log(1 + pixels to the nearest open water in the image)
    (``seathru.eval.track_slope.slope_beside``). A negative ``coefficient`` says the same
    surface is brighter where its image shows it next to the open water (veiling glare in the
    housing's port or in-camera tone mapping; docs/water.md), which the water model does not
    explain. Each of ``restorations`` ((N, 3) colours by name: the restored render, the
    restored photographs) is fitted the same way, with the share of the input's range slope
    (beside the term) it removed. None without open water in the frames."""
    from seathru.eval.track_slope import slope_beside, slope_reduction, slope_reduction_overall

    distance = windows.open_water_distance
    if distance is None or not np.isfinite(distance).any():
        return None
    term = np.log1p(distance)
    fit = slope_beside(obs.track_ids, obs.ranges, windows.observed, term)
    if fit is None:
        return None
    part = {"term": "log(1 + pixels from the observation to the nearest open water in its image)",
            "slope": fit.slope.tolist(), "stderr": fit.stderr.tolist(),
            "coefficient": fit.coefficient.tolist(),
            "coefficient_stderr": fit.coefficient_stderr.tolist(),
            "observations": fit.observations}
    for name, colours in (restorations or {}).items():
        restored = slope_beside(obs.track_ids, obs.ranges, colours, term)
        if restored is None:
            continue
        part[name] = {"slope": restored.slope.tolist(), "stderr": restored.stderr.tolist(),
                      "coefficient": restored.coefficient.tolist(),
                      "reduction": slope_reduction(fit.slope, restored.slope).tolist(),
                      "reduction_overall": slope_reduction_overall(fit.slope, restored.slope)}
    return part


def _fmt(values) -> str:
    return " ".join(f"{v:.3g}" for v in values)


def input_colour_change(cameras: CameraSet, max_points: int = 5000,
                        near_open_water: bool = False) -> dict | None:
    """How the input colour of the training views changes with range along COLMAP tracks
    (each observation's colour the mean over its window, :func:`window_samples`): evidence of
    water for the medium decision that does not depend on the model.

    With ``near_open_water``, also how it changes with the distance to the open water in the
    image, fitted beside range (``seathru.radiometry.glare``; the fit a
    ``GlareCorrection`` is made from: :func:`glare_correction`).

    Returns:
        ``{"tracks", "observations", "median_range", "slope", "stderr", "t",
        "change_over_median_range"}`` (per channel, log colour; the change is
        ``slope * median range``), with ``near_open_water`` (:func:`_glare_fit`) where asked
        for and the frames show open water, and ``frame_colour``: each training frame's colour
        cast beyond what the points and their ranges explain
        (``seathru.eval.track_slope.frame_colour_offsets``; :func:`frame_colour_gains`); None
        without a COLMAP model beside the camera file or with fewer than :data:`MIN_TRACKS`
        tracks.
    """
    from seathru.eval.track_slope import frame_colour_offsets, track_slope

    model_dir = (cameras.root or Path(".")) / SPARSE_DIR
    if not model_dir.is_dir():
        return None
    try:
        obs = track_observations(cameras, model_dir, max_points=max_points)
    except PipelineError as exc:
        log.warning("no track evidence: %s", exc)
        return None
    train = ~obs.held_out
    windows = track_windows(cameras, obs, open_water=near_open_water)
    fit = track_slope(obs.track_ids[train], obs.ranges[train], windows.observed[train])
    if fit.tracks < MIN_TRACKS:
        return None
    median = float(np.median(obs.ranges[train]))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(fit.stderr > 0, fit.slope / fit.stderr, 0.0)
    result = {"tracks": int(fit.tracks), "observations": int(fit.observations),
              "median_range": median, "slope": fit.slope.tolist(),
              "stderr": fit.stderr.tolist(), "t": t.tolist(),
              "change_over_median_range": (fit.slope * median).tolist()}
    glare = _glare_fit(cameras, obs, windows, train) if near_open_water else None
    if glare is not None:
        result["near_open_water"] = glare
    cast = frame_colour_offsets(obs.track_ids[train], obs.frames[train], obs.ranges[train],
                                windows.observed[train])
    if cast is not None:
        result["frame_colour"] = _frame_colour_record(cast, obs.names,
                                                      one_white_balance(cameras))
    return result


def _frame_colour_record(cast, names: list[str], one_balance: bool) -> dict:
    """A ``seathru.eval.track_slope.FrameColour`` as JSON, offsets by frame name; with
    ``one_balance`` (``seathru.io.stored_views.one_white_balance``) it never varies: what it
    found is the water's change with range that the range term missed, not a cast."""
    from seathru.eval.track_slope import FRAME_COLOUR_SPREAD

    return {"ratios": ["log red / green", "log blue / green"], "spread": cast.spread.tolist(),
            "noise": cast.noise.tolist(), "varies": cast.varies and not one_balance,
            "one_white_balance": one_balance,
            "threshold": FRAME_COLOUR_SPREAD,
            "range_free_spread": cast.range_free_spread.tolist(),
            "least_unexplained": cast.least_unexplained.tolist(),
            "offsets": {names[int(f)]: o.tolist() for f, o in zip(cast.frames, cast.offsets)}}


def frame_colour_gains(track_change: dict | None) -> dict[str, list[float]] | None:
    """Per frame name, the gains (R, G, B) that bring its colour cast to the median frame's,
    from :func:`input_colour_change`'s ``frame_colour`` where the casts vary; else None."""
    cast = (track_change or {}).get("frame_colour")
    if not cast or not cast.get("varies"):
        return None
    return {name: [math.exp(-red), 1.0, math.exp(-blue)]
            for name, (red, blue) in cast["offsets"].items()}


def _glare_fit(cameras: CameraSet, obs: TrackObservations, windows: TrackWindows,
               use: np.ndarray) -> dict | None:
    """The observations ``use`` (N,) fitted within tracks on range and the log of their
    distance to the open water in the image (share of the width), clipped to its 5-95th
    percentile (``seathru.eval.track_slope.slope_beside``); observations in frames without
    open water count at the far end. None where no frame shows open water."""
    from seathru.eval.track_slope import slope_beside
    from seathru.radiometry.glare import brighter_near_open_water

    pixels = windows.open_water_distance
    if pixels is None or not np.isfinite(pixels[use]).any():
        return None
    widths = np.array([f.width for f in cameras.frames], np.float64)[obs.frames]
    share = (pixels / widths)[use]
    near, reference, far = np.percentile(share[np.isfinite(share)], [5, 50, 95])
    if not 0 < near < far:
        return None
    term = np.log(np.clip(np.where(np.isfinite(share), share, far), near, far))
    fit = slope_beside(obs.track_ids[use], obs.ranges[use], windows.observed[use], term)
    if fit is None:
        return None
    return {"term": "log of the distance to the nearest open water in the image (share of "
                    "the width), clipped to its 5-95th percentile",
            "slope": fit.slope.tolist(), "stderr": fit.stderr.tolist(),
            "coefficient": fit.coefficient.tolist(),
            "coefficient_stderr": fit.coefficient_stderr.tolist(),
            "observations": fit.observations, "near": float(near),
            "reference": float(reference), "far": float(far),
            "brighter": brighter_near_open_water(fit.coefficient, fit.coefficient_stderr)}


def glare_correction(track_change: dict | None) -> GlareCorrection | None:
    """The ``seathru.radiometry.glare.GlareCorrection`` of :func:`input_colour_change`'s
    ``near_open_water`` fit where it finds the photographs brighter next to the open water
    (its ``brighter``), with the channels' mean coefficient; else None."""
    fit = (track_change or {}).get("near_open_water")
    if not fit or not fit.get("brighter"):
        return None
    return GlareCorrection(float(np.mean(fit["coefficient"])), fit["near"], fit["reference"],
                           fit["far"])


def training_depth_observations(cameras: CameraSet, max_points: int = 20000,
                                min_views: int = 3) -> TrackObservations | None:
    """The observations of COLMAP points in the training views, for depth supervision
    (``train.loss.sparse_depth_weight``): points seen by at least ``min_views`` training views
    (a longer track is triangulated more reliably); None without a COLMAP model beside the
    camera file or without such points."""
    model_dir = (cameras.root or Path(".")) / SPARSE_DIR
    if not model_dir.is_dir():
        return None
    obs = track_observations(cameras, model_dir, max_points=max_points)
    train = ~obs.held_out
    ids, counts = np.unique(obs.track_ids[train], return_counts=True)
    keep = train & np.isin(obs.track_ids, ids[counts >= min_views])
    if not keep.any():
        return None
    return TrackObservations(obs.track_ids[keep], obs.frames[keep], obs.names, obs.rows[keep],
                             obs.cols[keep], obs.ranges[keep], obs.observed[keep],
                             obs.held_out[keep], obs.points[keep])
