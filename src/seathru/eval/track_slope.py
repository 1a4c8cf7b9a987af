"""Does colour depend on range? The pooled within-track slope of colour along SfM tracks.

A 3D point seen from several cameras (one COLMAP track) has one colour. Through water its
pixels darken with range (attenuation) and drift towards the veiling light (backscatter), so in
the input images log colour falls with range; once the water is removed (the restored render)
it should not depend on range at all. Pooling the tracks with a fixed effect each (every track
its own intercept, one common slope: the "within" least-squares estimator) compares each point
only with itself, so the points' different colours do not enter the slope.

    slope_c = sum_t sum_i (z_ti - mean_t z) (y_tic - mean_t y_c) / sum_t sum_i (z_ti - mean_t z)^2

with ``y = log(colour)`` (or the colour itself). The standard error is cluster-robust by track
(the observations of one point share its errors). :func:`slope_reduction` says how much of the
input's range dependence the restoration removed: ``1 - |restored| / |input|``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TrackSlope:
    """The pooled within-track slope per channel.

    Attributes:
        slope: (C,) change of (log) colour per unit of range.
        stderr: (C,) its cluster-robust (by track) standard error.
        tracks: tracks used (two or more observations at different ranges).
        observations: their observations.
    """

    slope: np.ndarray
    stderr: np.ndarray
    tracks: int
    observations: int


def track_slope(track_ids: np.ndarray, ranges: np.ndarray, colours: np.ndarray, *,
                log: bool = True, floor: float = 1e-3) -> TrackSlope:
    """The within-track least-squares slope of colour against range, per channel.

    Args:
        track_ids: (N,) integer id of the 3D point each observation belongs to.
        ranges: (N,) distance from the camera centre to the point.
        colours: (N, C) linear colour of the point's pixel in that view.
        log: fit log colour (a relative change per unit range, free of the points'
            brightness) rather than the colour itself.
        floor: with ``log``, colours are clipped below at ``floor`` (log of 0).

    Returns:
        the slope per channel, its standard error and how many tracks / observations it rests
        on (NaN slopes when no track has two observations at different ranges).

    Example::

        fit = track_slope(ids, ranges, rgb)      # fit.slope[2]: blue's slope
    """
    ids = np.asarray(track_ids)
    z = np.asarray(ranges, dtype=np.float64)
    values = np.asarray(colours, dtype=np.float64)
    if values.ndim == 1:
        values = values[:, None]
    if not (ids.shape == z.shape == values.shape[:1]):
        raise ValueError(f"track_ids {ids.shape}, ranges {z.shape} and colours {values.shape} "
                         f"disagree in length")
    y = np.log(np.maximum(values, floor)) if log else values
    _, index, counts = np.unique(ids, return_inverse=True, return_counts=True)
    tracks = counts.size
    mean_z = np.bincount(index, z, tracks) / np.maximum(counts, 1)
    centred_z = z - mean_z[index]
    spread = np.bincount(index, centred_z ** 2, tracks)
    used_tracks = (counts >= 2) & (spread > 1e-12 * np.maximum(mean_z ** 2, 1e-300))
    used = used_tracks[index]
    channels = y.shape[1]
    if not used.any():
        nan = np.full(channels, np.nan)
        return TrackSlope(nan, nan.copy(), 0, 0)
    mean_y = np.stack([np.bincount(index, y[:, c], tracks) for c in range(channels)], 1) \
        / np.maximum(counts, 1)[:, None]
    centred_y = y - mean_y[index]
    cz, cy, where = centred_z[used], centred_y[used], index[used]
    denominator = float(np.sum(cz ** 2))
    slope = (cz[:, None] * cy).sum(0) / denominator
    residual = cy - cz[:, None] * slope
    scores = np.stack([np.bincount(where, cz * residual[:, c], tracks) for c in
                       range(channels)], 1)
    n_tracks = int(used_tracks.sum())
    correction = n_tracks / max(n_tracks - 1, 1)
    stderr = np.sqrt(correction * (scores ** 2).sum(0)) / denominator
    return TrackSlope(slope, stderr, n_tracks, int(used.sum()))


@dataclass(frozen=True)
class SlopeBeside:
    """The within-track slope on range fitted together with one more term.

    Attributes:
        slope, stderr: (C,) the range slope and its cluster-robust standard error.
        coefficient, coefficient_stderr: (C,) the term's own, likewise.
        observations: observations used.
    """

    slope: np.ndarray
    stderr: np.ndarray
    coefficient: np.ndarray
    coefficient_stderr: np.ndarray
    observations: int


def slope_beside(track_ids: np.ndarray, ranges: np.ndarray, colours: np.ndarray,
                 term: np.ndarray, *, floor: float = 1e-3) -> SlopeBeside | None:
    """The within-track least-squares fit of log colour on range and ``term`` together.

    Both regressors are centred within each track, as in :func:`track_slope`; the standard
    errors are cluster-robust by track (sandwich). Observations with a non-finite term are left
    out. Used to ask whether the colour change with range is something else the views vary
    along: on d3_reef, the distance to the open water in the image.

    Args:
        track_ids, ranges: (N,) as for :func:`track_slope`.
        colours: (N, C) linear colour.
        term: (N,) the other regressor.

    Returns:
        the fit, or None when fewer than two tracks have two observations with a finite term,
        or the two regressors are collinear.

    Example::

        fit = slope_beside(ids, ranges, rgb, np.log1p(pixels_to_open_water))
    """
    keep = np.isfinite(np.asarray(term, dtype=np.float64))
    ids = np.asarray(track_ids)[keep]
    x = np.stack([np.asarray(ranges, dtype=np.float64)[keep],
                  np.asarray(term, dtype=np.float64)[keep]], 1)
    values = np.asarray(colours, dtype=np.float64)[keep]
    values = values[:, None] if values.ndim == 1 else values
    y = np.log(np.maximum(values, floor))
    _, index, counts = np.unique(ids, return_inverse=True, return_counts=True)
    used = counts[index] >= 2
    if int((counts >= 2).sum()) < 2:
        return None

    def centred(v: np.ndarray) -> np.ndarray:
        means = np.stack([np.bincount(index, v[:, k], counts.size) for k in range(v.shape[1])],
                         1) / counts[:, None]
        return (v - means[index])[used]

    cx, cy, where = centred(x), centred(y), index[used]
    gram = cx.T @ cx
    if np.linalg.cond(gram) > 1e12:
        return None
    inverse = np.linalg.inv(gram)
    beta = inverse @ cx.T @ cy                                   # (2, C)
    residual = cy - cx @ beta
    tracks = int(np.unique(where).size)
    correction = tracks / max(tracks - 1, 1)
    errors = np.zeros_like(beta)
    for c in range(cy.shape[1]):
        scores = np.stack([np.bincount(where, cx[:, k] * residual[:, c], counts.size)
                           for k in range(2)], 1)
        covariance = correction * inverse @ (scores.T @ scores) @ inverse
        errors[:, c] = np.sqrt(np.maximum(np.diag(covariance), 0.0))
    return SlopeBeside(beta[0], errors[0], beta[1], errors[1], int(used.sum()))


def slope_reduction(input_slope: np.ndarray, restored_slope: np.ndarray) -> np.ndarray:
    """``1 - |restored| / |input|`` per channel: 1 when the restoration removed every range
    dependence, 0 when it left it as it was, negative when it made it worse (NaN where the input
    has no slope)."""
    before = np.abs(np.asarray(input_slope, dtype=np.float64))
    after = np.abs(np.asarray(restored_slope, dtype=np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(before > 0, 1.0 - after / before, np.nan)


def slope_reduction_overall(input_slope: np.ndarray, restored_slope: np.ndarray) -> float:
    """``1 - sum|restored| / sum|input|`` over the channels (NaN where the input has no slope):
    the share of the input's range dependence a restoration removed, all channels together."""
    total = float(np.sum(np.abs(np.asarray(input_slope, dtype=np.float64))))
    after = float(np.sum(np.abs(np.asarray(restored_slope, dtype=np.float64))))
    return 1.0 - after / total if total > 0 else float("nan")


def far_tracks(track_ids: np.ndarray, ranges: np.ndarray, share: float = 0.9) -> np.ndarray:
    """(N,) bool: the observations of the tracks whose median range lies above the ``share``
    quantile of all tracks' median ranges (the far tail; the rest are the near tracks).

    Far tracks spread most in range, so they weigh most in the pooled slope, and there the
    restoration divides by the smallest transmittance: a slope split into near and far tracks
    tells a restoration that fails everywhere from one that fails only in the far field.

    Args:
        track_ids, ranges: (N,) as for :func:`track_slope`.
        share: the quantile of the tracks' median ranges that separates near from far.

    Example::

        far = far_tracks(ids, ranges)
        near_fit = track_slope(ids[~far], ranges[~far], rgb[~far])
    """
    track_ids, ranges = np.asarray(track_ids), np.asarray(ranges, dtype=np.float64)
    if track_ids.shape != ranges.shape:
        raise ValueError(f"track_ids {track_ids.shape} and ranges {ranges.shape} disagree")
    if track_ids.size == 0:
        return np.zeros(0, bool)
    import pandas as pd

    median = pd.Series(ranges).groupby(track_ids).median()
    threshold = np.quantile(median.to_numpy(), share)
    return pd.Series(track_ids).map(median > threshold).to_numpy(bool)


def colour_slope_summary(track_ids: np.ndarray, ranges: np.ndarray, observed: np.ndarray,
                         restored: np.ndarray, rendered: np.ndarray | None = None, *,
                         log: bool = True, floor: float = 1e-3) -> dict:
    """The input's and the restoration's slopes on the same observations, and the reduction.

    A model whose full render (with water) does not follow the input's slope removes it from
    the restored render too, water or not: ``rendered`` tells a restoration that removed the
    water from a reconstruction that never held the range dependence.

    Args:
        track_ids, ranges: (N,) as for :func:`track_slope`.
        observed: (N, 3) input (underwater) colours; restored: (N, 3) restored colours.
        rendered: (N, 3) optional full renders (with water) at the same pixels.
        log, floor: as for :func:`track_slope`.

    Returns:
        ``{"input": {...}, "restored": {...}, "reduction": [3], "reduction_overall"}``; a
        slope record holds ``slope``, ``stderr`` (lists per channel), ``tracks``,
        ``observations``. ``reduction_overall`` is ``1 - sum|restored| / sum|input|`` over
        the channels. With ``rendered``, also ``"rendered"`` (its slope record) and
        ``"reproduced"`` (per channel, rendered slope / input slope: 1 when the full render
        changes with range as the input does).

    Example::

        summary = colour_slope_summary(ids, ranges, rgb_in, restored, rendered=rgb_out)
        summary["reduction_overall"], summary["reproduced"]
    """
    before = track_slope(track_ids, ranges, observed, log=log, floor=floor)
    after = track_slope(track_ids, ranges, restored, log=log, floor=floor)
    summary = {"log_colour": log,
               "input": _record(before), "restored": _record(after),
               "reduction": slope_reduction(before.slope, after.slope).tolist(),
               "reduction_overall": slope_reduction_overall(before.slope, after.slope)}
    if rendered is not None:
        full = track_slope(track_ids, ranges, rendered, log=log, floor=floor)
        with np.errstate(divide="ignore", invalid="ignore"):
            reproduced = np.where(before.slope != 0, full.slope / before.slope, np.nan)
        summary["rendered"] = _record(full)
        summary["reproduced"] = reproduced.tolist()
    return summary


def _record(fit: TrackSlope) -> dict:
    return {"slope": fit.slope.tolist(), "stderr": fit.stderr.tolist(), "tracks": fit.tracks,
            "observations": fit.observations}


#: A spread of the frames' colour offsets (root mean square against the median frame, log red
#: or blue against green) above this is a colour cast that changes from frame to frame: 0.009
#: (red) on the simulated survey's camera JPEGs, 0.05 on its orbit, 0.12-0.18 on simulated dives
#: white-balanced frame by frame, 0.03 / 0.06 (R/G, B/G) on d3_reef, where training on its
#: photographs brought to one cast improved neither the held-out PSNR nor the slope reduction
#: (benchmarks/results/frame_colour.md, camera_jpeg.md).
FRAME_COLOUR_SPREAD = 0.08
#: Patterns of offsets that the range term explains all but this share of do not count towards
#: whether the cast varies (:attr:`FrameColour.range_free_spread`): 0.7-1% on the simulated
#: transects, 5% on the surveys, 60% on d3_reef, 89% and more on the orbits.
FRAME_COLOUR_RANGE_LIKE = 0.02


@dataclass(frozen=True)
class FrameColour:
    """Each frame's colour offset along the tracks, beyond what the points and their ranges
    explain.

    Attributes:
        frames: (F,) the frame ids with an offset (at least ``min_observations`` each).
        offsets: (F, 2) log red / green and log blue / green of each frame against the median
            frame.
        spread: (2,) root mean square of the offsets against the median frame, per ratio (a
            camera's white balance may move a few frames far and leave the rest alike, which
            a median absolute deviation would miss).
        noise: (2,) the median frame's standard error of its offset (robust residual spread /
            sqrt of its observations): what the spread would be from noise alone.
        range_free_spread: (2,) the spread of the offsets without their parts along the
            range-like patterns (``range_like`` of :func:`frame_colour_offsets`): what decides
            whether the cast varies.
        range_like: (2,) how many patterns of offsets were range-like.
        least_unexplained: (2,) the smallest share of a pattern of offsets the range term
            leaves unexplained: 1 where the frames' casts and the ranges are independent, near
            0 where the camera moves towards what it saw (0.7-1% on the simulated transects,
            5% on the surveys, 60% on d3_reef, 89% and more on the orbits): there a cast
            drifting along the path and the water's change with range look alike, and the
            offsets along that pattern rest on the range term's shape.
    """

    frames: np.ndarray
    offsets: np.ndarray
    spread: np.ndarray
    noise: np.ndarray
    range_free_spread: np.ndarray
    range_like: np.ndarray
    least_unexplained: np.ndarray

    @property
    def varies(self) -> bool:
        """Whether the colour cast changes from frame to frame: the range-free spread above
        :data:`FRAME_COLOUR_SPREAD` (and three times the noise)."""
        return bool(np.max(self.range_free_spread)
                    > max(FRAME_COLOUR_SPREAD, 3 * float(np.max(self.noise))))


#: Unknowns of the range term in frame_colour_offsets' equations, before the offsets.
RANGE_TERMS = 4


def range_columns(relative: np.ndarray, level: np.ndarray) -> np.ndarray:
    """The range term of :func:`frame_colour_offsets` (N, :data:`RANGE_TERMS`): range over the
    median and its square, each alone and in proportion to the track's own ratio."""
    return np.stack([relative, relative ** 2, level * relative, level * relative ** 2], axis=1)


def frame_colour_offsets(track_ids: np.ndarray, frames: np.ndarray, ranges: np.ndarray,
                         colours: np.ndarray, *, floor: float = 1e-3, min_observations: int = 10,
                         iterations: int = 6, huber: float = 1.345,
                         range_like: float = FRAME_COLOUR_RANGE_LIKE) -> FrameColour | None:
    """Per-frame offsets of the colour ratios (log R/G, log B/G) along tracks: a camera's
    automatic white balance, which sets each frame's gains from what the frame shows.

    Water changes a point's colour with its range, and the same for every frame, so each
    observation's ratio is fitted as its track's own ratio, a smooth change with range
    (``range / median`` and its square: attenuation and the backscatter's bend, each also in
    proportion to the track's own ratio, without its frames' offsets: a point moves towards
    the water's colour the faster the further it lies from it) and its frame's offset. Solved
    exactly (weighted least squares within tracks; the normal equations have one unknown per
    frame), with Huber weights (``huber`` robust standard deviations) so that a few points
    placed or matched badly do not move it; the offsets are taken against the median frame.
    The ratios leave out what a frame's exposure changes in all channels alike.

    Whether the cast varies is decided without the patterns of offsets that the range term
    explains all but ``range_like`` of (:func:`_range_free`): where the camera moves towards
    what it saw, a drift along the path changes each track's colour as its range does, and the
    range term's misfit of the water fills it with a cast no camera made (0.094 in red on a
    turbid transect's plain JPEGs, none with the range-like pattern left out). The offsets
    themselves keep that pattern: where the rest shows a camera's cast, its drift along the
    path is as likely to be the camera's (a transect's JPEGs white-balanced frame by frame:
    red found within 0.006 with it, 0.062 without; benchmarks/results/frame_colour.md).

    Args:
        track_ids, ranges: (N,) as for :func:`track_slope`.
        frames: (N,) the frame each observation lies in (any integer ids).
        colours: (N, 3) linear colour of the observations, R G B.
        floor: colours are clipped below at ``floor`` (log of 0).
        min_observations: frames with fewer observations get no offset.
        iterations: rounds of reweighting (and of the tracks' own ratios).
        huber: the Huber threshold, in robust standard deviations of the residuals.
        range_like: patterns of offsets the range term leaves less of unexplained do not
            count towards whether the cast varies (0: every pattern counts).

    Returns:
        :class:`FrameColour`, or None with fewer than two frames of ``min_observations``.

    Example::

        cast = frame_colour_offsets(ids, frame_of, ranges, rgb)
        cast.varies, cast.spread    # e.g. True, [0.13, 0.04]
    """
    from scipy import sparse

    frames = np.asarray(frames)
    frame_ids, frame_index = np.unique(frames, return_inverse=True)
    counts = np.bincount(frame_index, minlength=len(frame_ids))
    kept = np.flatnonzero(counts >= min_observations)
    if len(kept) < 2:
        return None
    used = counts[frame_index] >= min_observations
    column = np.full(len(frame_ids), -1)
    column[kept] = np.arange(len(kept))
    columns = column[frame_index[used]]
    logs = np.log(np.clip(np.asarray(colours, np.float64)[used], floor, None))
    ratios = np.stack([logs[:, 0] - logs[:, 1], logs[:, 2] - logs[:, 1]], axis=1)
    _, track = np.unique(np.asarray(track_ids)[used], return_inverse=True)
    per_track = np.bincount(track).astype(np.float64)
    rows, count = np.arange(len(track)), len(kept)

    def centred(values: np.ndarray) -> np.ndarray:
        sums = np.zeros((len(per_track), values.shape[1]))
        np.add.at(sums, track, values)
        return values - (sums / per_track[:, None])[track]

    relative = np.asarray(ranges, np.float64)[used] / np.median(ranges)
    one_hot = sparse.csr_matrix((np.ones(len(rows)), (rows, columns)), shape=(len(rows), count))
    mean_of_track = sparse.csr_matrix((1.0 / per_track[track], (track, rows)))
    in_track = sparse.csr_matrix((np.ones(len(rows)), (rows, track)))
    # unknowns: the range term's coefficients, then one offset per frame
    offset_columns = one_hot - in_track @ (mean_of_track @ one_hot)
    target = centred(ratios)
    own = ratios - target                  # each observation's track's mean ratios
    offsets, residual = np.zeros((count, 2)), np.zeros_like(target)
    free, counted, least = np.zeros((count, 2)), np.zeros(2, int), np.ones(2)
    for ratio in range(2):
        intrinsic = own[:, ratio]
        weights = np.ones(len(rows))
        for _ in range(iterations):
            level = intrinsic - np.median(intrinsic)
            design = sparse.hstack([
                centred(range_columns(relative, level)),
                offset_columns]).tocsr()
            solution = _weighted_solve(design, target[:, ratio], weights)
            residual[:, ratio] = target[:, ratio] - design @ solution
            weights = _huber_weights(residual[:, ratio], huber)
            # the track's own ratio without its frames' offsets
            shifted = ratios[:, ratio] - solution[RANGE_TERMS + columns]
            intrinsic = shifted - centred(shifted[:, None])[:, 0]
        offsets[:, ratio] = solution[RANGE_TERMS:]
        normal = (design.T @ sparse.diags(weights) @ design).toarray()
        free[:, ratio], counted[ratio], least[ratio] = _range_free(
            normal, offsets[:, ratio], range_like)
    offsets -= np.median(offsets, axis=0)
    free -= np.median(free, axis=0)
    spread = np.sqrt(np.mean(offsets ** 2, axis=0))
    noise = np.median([1.4826 * np.median(np.abs(residual[columns == k]), axis=0)
                       / np.sqrt(counts[kept[k]]) for k in range(count)], axis=0)
    return FrameColour(frame_ids[kept], offsets, spread, noise,
                       np.sqrt(np.mean(free ** 2, axis=0)), counted, least)


def _range_free(normal: np.ndarray, offsets: np.ndarray, range_like: float
                ) -> tuple[np.ndarray, int, float]:
    """``offsets`` (F,) without their parts along the patterns the range term explains all but
    ``range_like`` of; those patterns' count; the least share unexplained.

    ``normal``: the weighted normal matrix of the design, the :data:`RANGE_TERMS` range
    columns first. A pattern's share unexplained is its generalised eigenvalue of the offsets'
    Schur complement (what the range columns cannot fit) against their own block, over the
    offsets that sum to zero (the rows fix them only up to a common shift); projected out
    along the block's metric, so that the fit's other offsets keep their values.
    """
    from scipy.linalg import eigh

    terms, count = RANGE_TERMS, len(offsets)
    if count < 3:
        return offsets, 0, 1.0
    own = normal[terms:, terms:]
    cross = normal[:terms, terms:]
    explained = cross.T @ np.linalg.pinv(normal[:terms, :terms]) @ cross
    sums_to_zero = np.linalg.qr(np.c_[np.ones(count), np.eye(count)[:, :-1]])[0][:, 1:]
    metric = sums_to_zero.T @ own @ sums_to_zero
    metric += 1e-9 * max(float(np.trace(metric)) / count, 1e-12) * np.eye(count - 1)
    shares, vectors = eigh(sums_to_zero.T @ (own - explained) @ sums_to_zero, metric)
    low = shares < range_like
    patterns = sums_to_zero @ vectors[:, low]         # own-orthonormal
    return (offsets - patterns @ (patterns.T @ own @ offsets), int(low.sum()),
            float(shares.min()))


def _weighted_solve(design, target: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The weighted least-squares solution, the offsets summing to zero (the rows, within
    tracks, fix them only up to a common shift)."""
    from scipy import sparse

    normal = (design.T @ sparse.diags(weights) @ design).toarray()
    gauge = np.zeros(normal.shape[0])
    gauge[RANGE_TERMS:] = 1.0
    normal += max(float(np.trace(normal)) / len(gauge), 1e-12) * np.outer(gauge, gauge)
    return np.linalg.lstsq(normal, design.T @ (weights * target), rcond=None)[0]


def _huber_weights(residual: np.ndarray, threshold: float) -> np.ndarray:
    """Huber's weights of ``residual`` at ``threshold`` robust standard deviations."""
    scale = max(1.4826 * float(np.median(np.abs(residual))), 1e-9)
    return np.minimum(1.0, threshold * scale / np.maximum(np.abs(residual), 1e-12))
