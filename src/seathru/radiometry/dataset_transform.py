"""The dataset-level linear map of ingest: one exposure scale, one white balance for all views.

Every image ``i`` is mapped pixel-wise by ``((x * gains * factor_i) @ matrix_i.T) * post_gains``
(:func:`seathru.radiometry.linearise.apply_colour`). The parameters are estimated here from small
per-image summaries (EXIF exposure, as-shot gains, a pixel sample), so the full images never
need to be in memory at once. Pure numpy; no file I/O.

White balance methods: ``none``; ``camera`` = the dataset median of the as-shot multipliers;
``percentile`` = SeaThru-NeRF's recipe, each channel divided by its ``wb_percentile``-th
percentile over all sampled pixels. With ``colour='srgb'`` RAW images go through LibRaw's
camera-to-sRGB matrix after the camera white balance (the matrix expects white-balanced input)
and a percentile white balance is applied after the matrix (``post_gains``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from seathru.radiometry import linearise


@dataclass(frozen=True)
class ImageStatistics:
    """What the dataset estimate needs of one decoded image.

    ``samples``: ``(N, 3)`` linear pixels (unscaled, as decoded); ``camera_wb``: ``(3,)`` as-shot
    gains (green 1) or None; ``colour_matrix``: ``(3, 3)`` camera-to-sRGB or None; exposure
    fields None when unknown.
    """

    samples: np.ndarray
    exposure_time: float | None = None
    iso: float | None = None
    f_number: float | None = None
    camera_wb: np.ndarray | None = None
    colour_matrix: np.ndarray | None = None


@dataclass(frozen=True)
class DatasetTransform:
    """The estimated map; per-image arrays are in input order.

    ``factors``: ``(N,)`` exposure factors (1 where unknown or not normalised); ``exposure``:
    the normalisation (None when switched off); ``wb_gains``: ``(3,)`` white balance applied
    before the matrix; ``matrices``: per image ``(3, 3)`` or None; ``post_gains``: ``(3,)`` after
    the matrix or None; ``matching_scale``: global scale of the 8-bit matching copies;
    ``image_warnings``: per image, to append to its decoder warnings.
    """

    factors: np.ndarray
    exposure: linearise.ExposureNormalisation | None
    wb_method: str
    wb_gains: np.ndarray
    camera_gains: np.ndarray | None
    percentile_levels: np.ndarray | None
    post_gains: np.ndarray | None
    matrices: list[np.ndarray | None]
    colour_space: str
    matching_scale: float
    sampled_pixels: int
    warnings: list[str] = field(default_factory=list)
    image_warnings: list[list[str]] = field(default_factory=list)

    def image_gains(self, index: int) -> np.ndarray:
        """``(3,)`` gains of image ``index`` before the matrix: white balance x exposure."""
        return self.wb_gains * self.factors[index]

    @property
    def exposure_values(self) -> np.ndarray:
        """``(N,)`` exposure ``t * ISO / N^2`` per image, NaN where unknown or not normalised."""
        if self.exposure is None:
            return np.full(len(self.factors), np.nan)
        return self.exposure.exposure


def dataset_transform(images: Sequence[ImageStatistics], kind: str, wb: str = "percentile",
                      wb_percentile: float = 99.8, colour: str = "raw",
                      exposure_normalise: bool = True) -> DatasetTransform:
    """Exposure factors, white balance, colour matrices and matching exposure of a dataset.

    Args:
        images: one summary per image, in output order.
        kind: ``raw``, ``linear`` or ``srgb`` (the colour matrix applies to RAW only).
        wb: ``none``, ``camera`` or ``percentile``.
        wb_percentile: percentile each channel is divided by for ``percentile``.
        colour: ``raw`` (camera raw space) or ``srgb`` (LibRaw's matrix, RAW only).
        exposure_normalise: scale every image to the median exposure ``t * ISO / N^2``.

    Returns:
        the transform; ``image_gains(i)`` and ``matrices[i]`` and ``post_gains`` are the
        arguments of ``linearise.apply_colour`` for image ``i``.

    Raises:
        ValueError: a percentile white balance with a channel that is black everywhere.

    Example::

        stats = [ImageStatistics(samples=pixels, exposure_time=t) for pixels, t in views]
        transform = dataset_transform(stats, kind="linear", wb="none")
    """
    count = len(images)
    image_warnings: list[list[str]] = [[] for _ in range(count)]
    normalisation = None
    if exposure_normalise:
        normalisation = linearise.exposure_normalisation(
            [im.exposure_time for im in images], [im.iso for im in images],
            [im.f_number for im in images])
        for mine, warnings in zip(image_warnings, normalisation.warnings):
            mine.extend(warnings)
        factors = normalisation.factors
    else:
        factors = np.ones(count)

    warnings: list[str] = []
    use_matrix = colour == "srgb" and kind == "raw"
    camera = None
    if wb == "camera" or (use_matrix and wb == "percentile"):
        camera = linearise.dataset_camera_gains([im.camera_wb for im in images])
        if camera is None:
            warnings.append("no as-shot white balance in the files (only RAW files carry "
                            "one): camera white balance gains set to 1")
    gains_camera = camera if camera is not None else np.ones(3)

    matrices: list[np.ndarray | None] = [None] * count
    if use_matrix:
        for i, image in enumerate(images):
            if image.colour_matrix is None:
                image_warnings[i].append("LibRaw has no camera-to-sRGB matrix for this camera: "
                                         "left in camera raw colour")
            matrices[i] = image.colour_matrix

    def transformed(pre: np.ndarray, post: np.ndarray | None) -> np.ndarray:
        return np.concatenate([linearise.apply_colour(image.samples, pre * factors[i],
                                                      matrices[i], post)
                               for i, image in enumerate(images)])

    post_gains = None
    levels = None
    if wb == "percentile":
        if use_matrix:
            post_gains, levels = linearise.percentile_gains(transformed(gains_camera, None),
                                                            wb_percentile)
            gains = gains_camera
        else:
            gains, levels = linearise.percentile_gains(transformed(np.ones(3), None),
                                                       wb_percentile)
    else:
        gains = gains_camera if wb == "camera" else np.ones(3)

    samples = transformed(gains, post_gains)
    colour_space = "srgb-linear" if use_matrix else ("camera raw" if kind == "raw" else "as stored")
    return DatasetTransform(
        factors=factors, exposure=normalisation, wb_method=wb, wb_gains=gains,
        camera_gains=camera, percentile_levels=levels, post_gains=post_gains, matrices=matrices,
        colour_space=colour_space, matching_scale=linearise.matching_exposure(samples),
        sampled_pixels=int(samples.shape[0]), warnings=warnings, image_warnings=image_warnings)
