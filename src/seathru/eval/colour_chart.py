"""Colour accuracy on a colour chart: CIEDE2000 against published values, grey angular error.

A chart is located by the four outer corners of its patch area (annotated, or found by OpenCV's
``mcc`` detector): corner 0 is the corner beside patch 1, corner 1 the end of patch 1's row,
corner 2 the opposite corner, corner 3 the end of patch 1's column; points are pixel
coordinates with pixel (u, v) centred at (u + 0.5, v + 0.5). Each patch is measured as the mean
of a grid of bilinear samples over the inner ``inner`` fraction of its cell (away from the gaps
and edges).

Measures (underwater colour literature: Akkaynak & Treibitz, Sea-thru, CVPR 2019; Berman et al.,
TPAMI 2020):

- CIEDE2000 (``skimage.color.deltaE_ciede2000``) between each patch and its reference, after a
  single exposure scale: one scalar ``s`` minimising ``sum ||s m - r||^2`` over the neutral
  patches in linear RGB (``m`` measured, ``r`` reference). One scale, not one per channel: a
  remaining colour cast (what a restoration should remove) stays in the error;
- the mean angular error of the neutral patches: the angle between each patch's linear RGB and
  the grey axis (1, 1, 1), in degrees; independent of exposure.

Images are linear RGB, taken as linear sRGB (D65); Lab is CIE L*a*b* D50 (the reference's
illuminant) after a Bradford adaptation from D65. Pure numpy / OpenCV; no file I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from skimage.color import deltaE_ciede2000, lab2xyz, xyz2lab, xyz_tristimulus_values

from seathru.radiometry.colour import srgb_to_linear

#: ColorChecker Classic 24, CIE L*a*b* (D50, 2 deg), for charts made after November 2014, as
#: published by X-Rite (the same data: colour-science's "ColorChecker24 - After November 2014").
#: Row-major from patch 1 (dark skin) to 24 (black); the neutral row is 19-24.
MACBETH_2014_LAB = np.array([
    [37.54, 14.37, 14.92], [64.66, 19.27, 17.50], [49.32, -3.82, -22.54],
    [43.46, -12.74, 22.72], [54.94, 9.61, -24.79], [70.48, -32.26, -0.37],
    [62.73, 35.83, 56.50], [39.43, 10.75, -45.17], [50.57, 48.64, 16.67],
    [30.10, 22.54, -20.87], [71.77, -24.13, 58.19], [71.51, 18.24, 67.37],
    [28.37, 15.42, -49.80], [54.38, -39.72, 32.27], [42.43, 51.05, 28.62],
    [81.80, 2.67, 80.41], [50.63, 51.28, -14.12], [49.57, -29.71, -28.32],
    [95.19, -1.03, 2.93], [81.29, -0.57, 0.44], [66.89, -0.75, -0.06],
    [50.76, -0.13, 0.14], [35.63, -0.46, -0.48], [20.64, 0.07, -0.46]])

# IEC 61966-2-1 linear sRGB -> XYZ (D65), and the Bradford cone response matrix.
SRGB_TO_XYZ = np.array([[0.4124564, 0.3575761, 0.1804375],
                        [0.2126729, 0.7151522, 0.0721750],
                        [0.0193339, 0.1191920, 0.9503041]])
BRADFORD = np.array([[0.8951, 0.2664, -0.1614],
                     [-0.7502, 1.7135, 0.0367],
                     [0.0389, -0.0685, 1.0296]])
# the whites scikit-image's Lab uses, so that the adapted white is exactly L* 100, a* = b* = 0
WHITE_D65 = np.asarray(xyz_tristimulus_values(illuminant="D65", observer="2"), np.float64)
WHITE_D50 = np.asarray(xyz_tristimulus_values(illuminant="D50", observer="2"), np.float64)


@dataclass(frozen=True)
class ChartSpec:
    """A chart's layout and reference values.

    ``reference_lab``: ``(rows * cols, 3)`` L*a*b* D50, row-major from patch 1; ``neutral``:
    indices of the grey patches; ``source``: where the values come from.
    """

    name: str
    rows: int
    cols: int
    reference_lab: np.ndarray
    neutral: tuple[int, ...]
    source: str

    @property
    def patches(self) -> int:
        return self.rows * self.cols


CHARTS: dict[str, ChartSpec] = {
    "macbeth-classic-24": ChartSpec(
        "macbeth-classic-24", 4, 6, MACBETH_2014_LAB, tuple(range(18, 24)),
        "X-Rite ColorChecker Classic, L*a*b* D50, charts made after November 2014"),
    "neutral-row-6": ChartSpec(
        "neutral-row-6", 1, 6, MACBETH_2014_LAB[18:24], tuple(range(6)),
        "a row of six neutral patches, white to black, of a chart without published values "
        "(e.g. a DGK Color Tools card): nominal references = the ColorChecker Classic's "
        "neutral row (X-Rite, after November 2014)"),
}


def _adaptation(source_white: np.ndarray, target_white: np.ndarray) -> np.ndarray:
    """Bradford chromatic adaptation matrix (XYZ to XYZ)."""
    cones = np.diag((BRADFORD @ target_white) / (BRADFORD @ source_white))
    return np.linalg.inv(BRADFORD) @ cones @ BRADFORD


def linear_srgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """Linear sRGB ``(..., 3)`` to CIE L*a*b* D50 (Bradford-adapted from D65)."""
    xyz = np.asarray(rgb, dtype=np.float64) @ SRGB_TO_XYZ.T
    xyz_d50 = xyz @ _adaptation(WHITE_D65, WHITE_D50).T
    return xyz2lab(xyz_d50, illuminant="D50", observer="2")


def lab_to_linear_srgb(lab: np.ndarray) -> np.ndarray:
    """CIE L*a*b* D50 ``(..., 3)`` to linear sRGB (D65), the inverse of
    :func:`linear_srgb_to_lab`; not clipped."""
    xyz_d50 = lab2xyz(np.asarray(lab, dtype=np.float64), illuminant="D50", observer="2")
    xyz = xyz_d50 @ _adaptation(WHITE_D50, WHITE_D65).T
    return xyz @ np.linalg.inv(SRGB_TO_XYZ).T


def patch_samples(image: np.ndarray, corners: np.ndarray, rows: int, cols: int,
                  inner: float = 0.4, grid: int = 5) -> np.ndarray:
    """Bilinear samples of each patch, ``(rows * cols, grid * grid, C)``, row-major.

    Args:
        image: ``(H, W, C)`` float.
        corners: ``(4, 2)`` outer corners of the patch area (module docstring for the order
            and pixel convention).
        inner: side of the sampled square as a fraction of a cell.
        grid: samples per side of that square.
    """
    corners = np.asarray(corners, dtype=np.float32).reshape(4, 2)
    unit = np.array([[0, 0], [cols, 0], [cols, rows], [0, rows]], dtype=np.float32)
    homography = cv2.getPerspectiveTransform(unit, corners).astype(np.float64)
    offsets = 0.5 + inner * (np.arange(grid) + 0.5 - grid / 2) / grid
    du, dv = np.meshgrid(offsets, offsets)
    cells = [(c + du.ravel(), r + dv.ravel()) for r in range(rows) for c in range(cols)]
    u = np.concatenate([c[0] for c in cells])
    v = np.concatenate([c[1] for c in cells])
    points = homography @ np.stack([u, v, np.ones_like(u)])
    px, py = points[0] / points[2] - 0.5, points[1] / points[2] - 0.5  # cv2: integer centres
    image = np.ascontiguousarray(image, dtype=np.float32)
    samples = cv2.remap(image, px.astype(np.float32)[None], py.astype(np.float32)[None],
                        interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                        borderValue=np.nan)
    return samples.reshape(rows * cols, grid * grid, -1)


def patch_means(image: np.ndarray, corners: np.ndarray, rows: int, cols: int,
                inner: float = 0.4, grid: int = 5) -> np.ndarray:
    """Mean of each patch's samples (:func:`patch_samples`), ``(rows * cols, C)``; NaN for a
    patch outside the image."""
    samples = patch_samples(image, corners, rows, cols, inner, grid)
    valid = np.isfinite(samples)
    counts = valid.sum(axis=1)
    sums = np.where(valid, samples, 0.0).sum(axis=1)
    return np.divide(sums, counts, out=np.full(sums.shape, np.nan), where=counts > 0)


def grey_angular_error_deg(rgb: np.ndarray) -> np.ndarray:
    """Angle between each RGB ``(..., 3)`` and the grey axis (1, 1, 1), degrees."""
    rgb = np.asarray(rgb, dtype=np.float64)
    norm = np.linalg.norm(rgb, axis=-1) * np.sqrt(3.0)
    cos = np.divide(rgb.sum(axis=-1), norm, out=np.full(norm.shape, np.nan), where=norm > 0)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def chart_exposure_scale(measured: np.ndarray, reference: np.ndarray) -> float:
    """The scalar ``s`` minimising ``sum ||s m - r||^2`` over the rows of ``(N, 3)`` arrays."""
    m, r = np.asarray(measured, np.float64), np.asarray(reference, np.float64)
    power = float(np.sum(m * m))
    if power <= 0:
        raise ValueError("the neutral patches are black: no exposure scale")
    return float(np.sum(m * r) / power)


def chart_errors(measured: np.ndarray, spec: ChartSpec,
                 use: np.ndarray | None = None) -> dict:
    """CIEDE2000 and grey angular error of measured patches.

    Args:
        measured: ``(spec.patches, 3)`` linear RGB patch means.
        spec: the chart.
        use: ``(spec.patches,)`` bool, patches to score (others: clipped, occluded); all when
            None.

    Returns:
        ``delta_e00`` (per patch, None where not used), ``mean_delta_e00``, ``max_delta_e00``,
        ``grey_angular_error_deg`` (per neutral patch), ``mean_grey_angular_error_deg``,
        ``exposure_scale``, ``patches_used``; means are NaN when nothing is usable.

    Example::

        >>> spec = CHARTS["macbeth-classic-24"]
        >>> exact = lab_to_linear_srgb(spec.reference_lab)
        >>> round(chart_errors(0.5 * exact, spec)["mean_delta_e00"], 6)
        0.0
    """
    measured = np.asarray(measured, dtype=np.float64).reshape(spec.patches, 3)
    use = np.ones(spec.patches, bool) if use is None else np.asarray(use, bool).copy()
    use &= np.all(np.isfinite(measured), axis=1)
    neutral = np.array([i for i in spec.neutral if use[i]], dtype=int)
    reference = lab_to_linear_srgb(spec.reference_lab)
    scale = chart_exposure_scale(measured[neutral], reference[neutral]) if len(neutral) else np.nan
    delta = np.full(spec.patches, np.nan)
    if len(neutral) and np.isfinite(scale):
        lab = linear_srgb_to_lab(scale * measured[use])
        delta[use] = deltaE_ciede2000(spec.reference_lab[use], lab)
    angles = grey_angular_error_deg(measured[list(spec.neutral)])
    angles[~use[list(spec.neutral)]] = np.nan

    def mean(values):
        finite = values[np.isfinite(values)]
        return float(finite.mean()) if finite.size else float("nan")

    return {"delta_e00": [None if not np.isfinite(d) else float(d) for d in delta],
            "mean_delta_e00": mean(delta),
            "max_delta_e00": float(np.nanmax(delta)) if np.isfinite(delta).any() else np.nan,
            "grey_angular_error_deg": [None if not np.isfinite(a) else float(a) for a in angles],
            "mean_grey_angular_error_deg": mean(angles), "exposure_scale": float(scale),
            "patches_used": int(np.isfinite(delta).sum() if len(neutral) else 0)}


def implausible_chart(image_linear: np.ndarray, corners: np.ndarray,
                     spec: ChartSpec) -> str | None:
    """Why ``corners`` cannot be a chart of ``spec`` in ``image_linear`` ``(H, W, 3)``, or None.

    Checks: a convex quadrilateral inside the image, patches at least 3 pixels on a side, and
    neutral patches that get darker from the first to the last, the first at least twice as
    bright as the last (a detector's false positive on texture rarely has both).
    """
    corners = np.asarray(corners, dtype=np.float64).reshape(4, 2)
    height, width = image_linear.shape[:2]
    if np.any(corners < -1) or np.any(corners[:, 0] > width + 1) or \
            np.any(corners[:, 1] > height + 1):
        return "corners outside the image"
    edges = np.roll(corners, -1, axis=0) - corners
    turns = edges[:, 0] * np.roll(edges, -1, axis=0)[:, 1] - \
        edges[:, 1] * np.roll(edges, -1, axis=0)[:, 0]
    if not (np.all(turns > 0) or np.all(turns < 0)):
        return "not a convex quadrilateral"
    sides = np.linalg.norm(edges, axis=1)
    if min(sides[0], sides[2]) / spec.cols < 3 or min(sides[1], sides[3]) / spec.rows < 3:
        return "patches smaller than 3 pixels"
    means = patch_means(image_linear, corners, spec.rows, spec.cols)
    luminance = means[list(spec.neutral)] @ SRGB_TO_XYZ[1]
    if not np.all(np.diff(luminance) < 0) or not luminance[0] >= 2 * max(luminance[-1], 1e-6):
        return "the neutral patches do not go from light to dark"
    return None


def detect_macbeth(image_srgb: np.ndarray) -> np.ndarray | None:
    """Corners ``(4, 2)`` (module convention) of a ColorChecker Classic 24 found by OpenCV's
    ``mcc`` detector (opencv-contrib, no neural network) in an sRGB image ``(H, W, 3)``
    (uint8, or float in [0, 1]); None when it finds none or only an implausible one
    (:func:`implausible_chart`)."""
    image = np.asarray(image_srgb)
    if image.dtype != np.uint8:
        image = np.clip(np.nan_to_num(image) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    detector = cv2.mcc.CCheckerDetector.create()
    detector.setColorChartType(cv2.mcc.MCC24)
    detector.setUseDnnModel(False)
    if not detector.process(cv2.cvtColor(image, cv2.COLOR_RGB2BGR), 1):
        return None
    box = np.asarray(detector.getBestColorChecker().getBox(), dtype=np.float64).reshape(4, 2)
    corners = box + 0.5  # OpenCV puts pixel centres at integers
    linear = srgb_to_linear(image.astype(np.float64) / 255.0)
    if implausible_chart(linear, corners, CHARTS["macbeth-classic-24"]) is not None:
        return None
    return corners
