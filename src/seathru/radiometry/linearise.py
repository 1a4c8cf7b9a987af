"""Pure functions of the ingest step: from decoded camera values to one linear radiometric scale.

Arrays: colour images are ``(H, W, 3)`` float, masks ``(H, W)`` bool (True = valid unless the
name says otherwise), raw mosaics ``(H, W)`` integer with a matching ``(H, W)`` CFA colour-index
map (0 R, 1 G, 2 B, 3 second G, LibRaw's convention). No file I/O here.

Orientation uses LibRaw's ``flip`` code (0 none, 3 180 deg, 5 90 deg CCW, 6 90 deg CW; bit 4 =
transpose, bit 2 = flip rows, bit 1 = flip columns), so RAW and JPEG/TIFF inputs share one path.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import cv2
import numpy as np

from seathru.radiometry.colour import linear_to_srgb

#: Smallest plausible raw payload, in bits per sensor pixel. Lossless raw needs ~8-16 bits and
#: the most aggressive lossy raws (Kodak DC50 KDC, ~1.9) stay well above this; a stripped or
#: truncated file with the header of a multi-megapixel image is around 0.01-0.05.
MIN_RAW_BITS_PER_PIXEL = 0.25

#: A raw mosaic whose most common value covers more of the unsaturated samples than this is
#: not a photograph (LibRaw fills missing data with zeros or repeats when the payload is gone).
MAX_RAW_MODE_FRACTION = 0.95

#: Linear grey level the matching copies put the dataset median at (18 % grey, sRGB ~0.46).
MATCHING_TARGET_MEDIAN = 0.18


# --- orientation ----------------------------------------------------------------------------

_EXIF_TO_FLIP = {1: 0, 2: 1, 3: 3, 4: 2, 5: 4, 6: 6, 7: 7, 8: 5}


def exif_orientation_to_flip(orientation: int | None) -> int:
    """EXIF Orientation (1-8) to LibRaw's flip code (dcraw's ``"50132467"[o % 8]``); 0 if
    unknown."""
    return _EXIF_TO_FLIP.get(int(orientation), 0) if orientation else 0


def orient(image: np.ndarray, flip: int) -> np.ndarray:
    """Apply LibRaw flip code ``flip`` to ``(H, W)`` or ``(H, W, C)``; same as LibRaw's output.

    Equals ``rawpy.postprocess(user_flip=flip)`` applied to the ``user_flip=0`` output (checked
    in tests/test_ingest.py): rows flipped for bit 2, columns for bit 1, then transposed for bit 4.
    """
    if flip & 2:
        image = image[::-1]
    if flip & 1:
        image = image[:, ::-1]
    if flip & 4:
        image = np.swapaxes(image, 0, 1)
    return np.ascontiguousarray(image)


# --- exposure normalisation -----------------------------------------------------------------

EXPOSURE_FIELDS = ("exposure_time", "iso", "f_number")


@dataclass(frozen=True)
class ExposureNormalisation:
    """Per-image factors that bring every image to the dataset's median exposure.

    ``exposure[i] = t * ISO / N^2`` over the fields in ``fields_used`` (NaN when unknown);
    ``factors[i] = reference / exposure[i]`` (1 where unknown); ``reference`` = median exposure.
    """

    factors: np.ndarray
    exposure: np.ndarray
    reference: float | None
    fields_used: tuple[str, ...]
    unknown: np.ndarray
    warnings: list[list[str]] = field(default_factory=list)


def _valid_positive(value) -> bool:
    return value is not None and math.isfinite(float(value)) and float(value) > 0.0


def exposure_normalisation(exposure_time: Sequence[float | None], iso: Sequence[float | None],
                           f_number: Sequence[float | None]) -> ExposureNormalisation:
    """Factors ``k_i = median_j(E_j) / E_i`` with ``E = t * ISO / N^2``.

    A field that no image carries is treated as constant across the dataset (left out of E);
    an image that lacks a field other images carry cannot be placed on the common scale and
    gets ``k = 1`` plus a warning (its value is then as-shot, relative to the median image).
    """
    columns = {"exposure_time": list(exposure_time), "iso": list(iso), "f_number": list(f_number)}
    count = len(columns["exposure_time"])
    if any(len(values) != count for values in columns.values()):
        raise ValueError("exposure_time, iso and f_number must have one entry per image")
    used = tuple(name for name in EXPOSURE_FIELDS
                 if any(_valid_positive(v) for v in columns[name]))
    exposure = np.full(count, np.nan)
    warnings: list[list[str]] = [[] for _ in range(count)]
    unknown = np.ones(count, dtype=bool)
    for i in range(count):
        missing = [name for name in used if not _valid_positive(columns[name][i])]
        if not used:
            warnings[i].append("no exposure metadata (exposure time, ISO, f-number) in the "
                               "dataset; exposure factor 1")
        elif missing:
            warnings[i].append(f"missing {', '.join(missing)} while other images have it; "
                               "exposure factor 1 (not normalised)")
        else:
            value = 1.0
            if "exposure_time" in used:
                value *= float(columns["exposure_time"][i])
            if "iso" in used:
                value *= float(columns["iso"][i])
            if "f_number" in used:
                value /= float(columns["f_number"][i]) ** 2
            exposure[i] = value
            unknown[i] = False
    known = exposure[~unknown]
    reference = float(np.median(known)) if known.size else None
    factors = np.ones(count)
    if reference is not None:
        factors[~unknown] = reference / known
    return ExposureNormalisation(factors=factors, exposure=exposure, reference=reference,
                                 fields_used=used, unknown=unknown, warnings=warnings)


# --- white balance --------------------------------------------------------------------------

def camera_wb_gains(camera_whitebalance: Sequence[float]) -> np.ndarray | None:
    """As-shot multipliers ``[R, G, B, G2]`` (rawpy ``camera_whitebalance``) as RGB gains with
    green = 1; None when the camera recorded none (zeros, NaN)."""
    values = np.asarray(camera_whitebalance, dtype=np.float64)
    if values.size < 3 or not np.all(np.isfinite(values[:3])) or np.any(values[:3] <= 0):
        return None
    return values[:3] / values[1]


def dataset_camera_gains(per_image: Sequence[np.ndarray | None]) -> np.ndarray | None:
    """One set of as-shot gains for the whole dataset: the per-channel median over images.

    A per-image white balance would give the same surface different colours in different
    views (cameras on auto WB drift between shots), which a radiance field cannot fit.
    """
    known = [g for g in per_image if g is not None]
    if not known:
        return None
    gains = np.median(np.stack(known), axis=0)
    return gains / gains[1]


def percentile_gains(samples: np.ndarray,
                     percentile: float = 99.8) -> tuple[np.ndarray, np.ndarray]:
    """SeaThru-NeRF white balance: divide each channel by its ``percentile`` over the dataset.

    ``samples``: ``(N, 3)`` linear pixels pooled from all images. Returns ``(gains, levels)``
    with ``gains = 1 / levels``.
    """
    samples = np.asarray(samples, dtype=np.float64).reshape(-1, 3)
    if samples.shape[0] == 0:
        raise ValueError("no pixels to compute percentile white balance from")
    levels = np.percentile(samples, percentile, axis=0)
    if np.any(~np.isfinite(levels)) or np.any(levels <= 0):
        raise ValueError(f"the {percentile}th percentile is not positive in every channel "
                         f"({levels.tolist()}): the images are black in some channel")
    return 1.0 / levels, levels


def apply_colour(image: np.ndarray, gains: np.ndarray, matrix: np.ndarray | None = None,
                 post_gains: np.ndarray | None = None) -> np.ndarray:
    """``((image * gains) @ matrix.T) * post_gains``, float32; the per-pixel linear map of ingest.

    ``gains`` and ``post_gains``: ``(3,)``; ``matrix``: ``(3, 3)`` camera-to-output colour, or
    None for identity (raw colour space).
    """
    out = image.astype(np.float32, copy=True)
    out *= np.asarray(gains, dtype=np.float32)
    if matrix is not None:
        out = out @ np.asarray(matrix, dtype=np.float32).T
    if post_gains is not None:
        out *= np.asarray(post_gains, dtype=np.float32)
    return out


def usable_colour_matrix(matrix: np.ndarray | None) -> np.ndarray | None:
    """LibRaw's camera-to-sRGB matrix (``rawpy.color_matrix[:, :3]``) if it is a real one.

    LibRaw leaves it zero for cameras it has no colour data for (e.g. Kodak DC50); its rows
    sum to 1 otherwise (white-balanced neutral stays neutral).
    """
    if matrix is None:
        return None
    matrix = np.asarray(matrix, dtype=np.float64)[:3, :3]
    if not np.all(np.isfinite(matrix)) or not np.allclose(matrix.sum(axis=1), 1.0, atol=0.05):
        return None
    return matrix


# --- validity masks -------------------------------------------------------------------------

def raw_clipping(raw: np.ndarray, colors: np.ndarray, white_per_channel: Sequence[float],
                 saturation_threshold: float = 0.98) -> tuple[np.ndarray, np.ndarray]:
    """Saturated and black-clipped sites of a raw mosaic, ``(H, W)`` bool each.

    Saturated: at or above ``saturation_threshold`` x the channel's white level. Black-clipped:
    raw value 0, the ADC floor (before the black offset is subtracted: values between 0 and the
    black level are read noise and still carry signal on average).
    """
    white = np.asarray(white_per_channel, dtype=np.float64)
    limits = (saturation_threshold * white)[colors]
    saturated = raw >= limits
    black = raw <= 0
    return saturated, black


def block_any(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """2x2 blocks of ``mask`` reduced with OR to ``shape`` (LibRaw half_size output:
    ceil(H/2) x ceil(W/2))."""
    height, width = mask.shape
    padded = np.zeros((2 * shape[0], 2 * shape[1]), dtype=bool)
    h, w = min(height, padded.shape[0]), min(width, padded.shape[1])
    padded[:h, :w] = mask[:h, :w]
    return padded.reshape(shape[0], 2, shape[1], 2).any(axis=(1, 3))


def encoded_clipping(codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Saturated / black-clipped pixels of an integer image ``(H, W, 3)``: any channel at the
    top code (255 or 65535) / every channel at 0. Float images have no clipping codes: only
    non-finite.

    One channel at 0 is not masked: under water the red of open water and of far surfaces
    is 0 in an 8-bit photograph (measured: 20-30% of every d3_reef frame), and masking those
    pixels leaves the open water out of training altogether. A code of 0 there still says the
    value is below half a step, which the renderer can match."""
    if np.issubdtype(codes.dtype, np.integer):
        top = np.iinfo(codes.dtype).max
        return (codes >= top).any(axis=-1), (codes <= 0).all(axis=-1)
    return (~np.isfinite(codes)).any(axis=-1), np.zeros(codes.shape[:2], dtype=bool)


def dilate_invalid(invalid: np.ndarray, radius: int = 1) -> np.ndarray:
    """Grow an invalid-pixel mask by ``radius`` pixels (3x3 for 1): demosaicing and JPEG chroma
    subsampling spread a clipped sample into its neighbours."""
    if radius <= 0 or not invalid.any():
        return invalid.copy()
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), dtype=np.uint8)
    return cv2.dilate(invalid.astype(np.uint8), kernel).astype(bool)


# --- resizing -------------------------------------------------------------------------------

def fit_size(width: int, height: int, max_size: int | None) -> tuple[int, int]:
    """``(width, height)`` scaled down so the long edge is at most ``max_size`` (0/None: as is)."""
    if not max_size or max(width, height) <= max_size:
        return width, height
    scale = max_size / max(width, height)
    return max(1, round(width * scale)), max(1, round(height * scale))


def llff_downscaled_size(width: int, height: int, factor: int) -> tuple[int, int]:
    """LLFF ``images_N`` size: each side divided by N and rounded, at least 1 pixel.

    Not the render size (``seathru.nerf.rays``), which floors.

    Example::

        >>> llff_downscaled_size(1001, 750, 4)
        (250, 188)
    """
    return max(1, round(width / factor)), max(1, round(height / factor))


def resize_area(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Area-average resample to ``size = (width, height)`` (OpenCV INTER_AREA): each output pixel
    is the mean radiance of the input pixels it covers, so linear values stay linear."""
    if (image.shape[1], image.shape[0]) == tuple(size):
        return image.copy()
    return cv2.resize(np.ascontiguousarray(image, dtype=np.float32), size,
                      interpolation=cv2.INTER_AREA)


def block_average(image: np.ndarray, factor: int) -> np.ndarray:
    """Means of ``factor`` x ``factor`` pixel blocks (a partial last row or column dropped):
    an image at the resolution the train step renders its snapshots at.

    Args:
        image: ``(H, W)`` or ``(H, W, C)``; a block holding a non-finite value (open water's
            infinite range) averages to a non-finite value.
        factor: the downscale, >= 1.

    Returns:
        ``(H // factor, W // factor[, C])`` float64.

    Example::

        block_average(np.arange(16.0).reshape(4, 4), 2)   # [[2.5, 4.5], [10.5, 12.5]]
    """
    image = np.asarray(image, dtype=np.float64)
    if factor == 1:
        return image
    height, width = image.shape[0] // factor, image.shape[1] // factor
    cropped = image[:height * factor, :width * factor]
    blocks = cropped.reshape(height, factor, width, factor, *image.shape[2:])
    with np.errstate(invalid="ignore"):
        return blocks.mean(axis=(1, 3))


def resize_mask(valid: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize a validity mask: an output pixel is valid only if every input pixel under it is."""
    if (valid.shape[1], valid.shape[0]) == tuple(size):
        return valid.copy()
    return resize_area(valid.astype(np.float32), size) >= 1.0 - 1e-4


# --- statistics and display -----------------------------------------------------------------

def sample_pixels(image: np.ndarray, max_pixels: int) -> np.ndarray:
    """Deterministic, spatially uniform subsample of at most ``max_pixels`` pixels ``(N, 3)``:
    a regular grid with the same stride in x and y (bounded memory for dataset statistics)."""
    height, width = image.shape[:2]
    stride = max(1, math.ceil(math.sqrt(height * width / max(1, max_pixels))))
    return np.ascontiguousarray(image[::stride, ::stride].reshape(-1, image.shape[-1]),
                                dtype=np.float32)


def matching_exposure(samples: np.ndarray, target: float = MATCHING_TARGET_MEDIAN) -> float:
    """One global scale that puts the median channel-mean of ``samples`` ``(N, 3)`` at
    ``target``."""
    level = float(np.median(np.asarray(samples, dtype=np.float64).mean(axis=-1))) if len(
        samples) else 0.0
    return target / level if level > 0 and math.isfinite(level) else 1.0


def matching_image(linear: np.ndarray, scale: float) -> np.ndarray:
    """sRGB-encoded values in [0, 1] for feature matching: ``srgb(clip(scale * linear))``."""
    return linear_to_srgb(np.clip(linear * np.float32(scale), 0.0, 1.0)).astype(np.float32)


def matching_grey(image: np.ndarray, clahe_clip: float | None = None,
                  clahe_tiles: int = 8) -> np.ndarray:
    """The 8-bit grey copy SIFT runs on, contrast-equalised (CLAHE) for murky water.

    COLMAP turns colour into grey before SIFT anyway, so the equalisation runs on grey.

    Args:
        image: ``(H, W)`` or ``(H, W, C)`` in OpenCV's BGR(A) channel order (as ``cv2.imread``
            gives it): uint8, uint16 (top 8 bits kept) or float in [0, 1].
        clahe_clip: CLAHE clip limit; None for no equalisation.
        clahe_tiles: CLAHE tiles per side.

    Returns:
        ``(H, W)`` uint8.
    """
    if image.dtype == np.uint16:
        image = (image // 257).astype(np.uint8)
    elif image.dtype != np.uint8:
        image = np.round(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8)
    if image.ndim == 3:
        image = cv2.cvtColor(np.ascontiguousarray(image[..., :3]), cv2.COLOR_BGR2GRAY)
    if clahe_clip is not None:
        image = cv2.createCLAHE(clipLimit=clahe_clip,
                                tileGridSize=(clahe_tiles, clahe_tiles)).apply(image)
    return image


# --- sanity of decoded data -----------------------------------------------------------------

def invalid_raw_reason(raw: np.ndarray, file_bytes: int, raw_width: int, raw_height: int,
                       saturated: np.ndarray | None = None) -> str | None:
    """Why a decoded raw mosaic cannot be a photograph, or None if it looks like one.

    LibRaw decodes some stripped or truncated files without an error (it fills missing data with
    zeros or repeats): a file far too small for its pixel count, an empty mosaic or one where a
    single value covers nearly all unsaturated samples is rejected.
    """
    if raw_width <= 0 or raw_height <= 0 or raw.size == 0:
        return f"raw image dimensions are {raw_width}x{raw_height}: no image data"
    bits = 8.0 * file_bytes / (raw_width * raw_height)
    if bits < MIN_RAW_BITS_PER_PIXEL:
        return (f"file holds {file_bytes} bytes, {bits:.3f} bits per pixel for a "
                f"{raw_width}x{raw_height} sensor (at least {MIN_RAW_BITS_PER_PIXEL} expected): "
                "image data missing (stripped or truncated file)")
    values = raw[~saturated] if saturated is not None else raw.ravel()
    if values.size == 0:
        return None  # fully saturated frame: real, and the mask will say so
    counts = np.bincount(values.ravel().astype(np.int64)) if np.issubdtype(
        values.dtype, np.integer) else np.unique(values, return_counts=True)[1]
    mode_fraction = counts.max() / values.size
    if mode_fraction > MAX_RAW_MODE_FRACTION:
        return (f"{100 * mode_fraction:.1f}% of the raw samples share one value: the image data "
                "is missing or corrupt")
    return None


def invalid_image_reason(image: np.ndarray) -> str | None:
    """Why a decoded image ``(H, W, C)`` is unusable (empty, non-finite, constant), or None."""
    if image.size == 0 or image.shape[0] == 0 or image.shape[1] == 0:
        return "decoded image is empty"
    finite = np.isfinite(image)
    if not finite.any():
        return "decoded image has no finite values"
    values = image[finite]
    if values.min() == values.max():
        return f"decoded image is constant (every value {float(values.min()):g}): no image data"
    return None
