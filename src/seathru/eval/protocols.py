"""The community's evaluation protocol for the SeaThru-NeRF dataset (NerfBaselines), in numpy.

What NerfBaselines does (read in the nerfbaselines/nerfbaselines repository):

- split, ``nerfbaselines/datasets/seathru_nerf.py`` (``_select_indices_llff``, ``llffhold=8``):
  images in sorted path order, those at index 0, 8, 16, ... are held out for testing; full
  resolution (no ``downscale_loaded_factor``), images from ``images_wb/``;
- protocol ``default`` (``nerfbaselines/evaluation.py``, ``DefaultEvaluationProtocol``): the
  ground truth is the stored image as PIL reads it (``np.array(image, dtype=np.uint8)``, colour
  space ``srgb``, i.e. left as stored; ``nerfbaselines/datasets/_common.py``), the prediction is
  quantised with ``image_to_srgb(pred, np.uint8)`` whose ``convert_image_dtype`` is
  ``np.clip(image * 255.0, 0, 255).astype(np.uint8)`` (truncation, not rounding;
  ``nerfbaselines/utils.py``); both go back to float32 by ``/ 255``;
- metrics (``nerfbaselines/metrics.py``): ``psnr = -10 log10(mse)`` on images clipped to
  [0, 1]; ``ssim = dmpix_ssim`` (dm-pix: 11-tap Gaussian, sigma 1.5, k1 0.01, k2 0.03, "valid"
  filtering, mean over pixels and channels) - what ``seathru.eval.metrics.ssim`` computes
  (tests/test_protocols.py checks it against a dm-pix transcription); ``mae``, ``mse``;
  ``lpips`` (AlexNet) where weights are available;
- per-dataset values are the means over the test views (``accumulate_metrics``).

Images are ``(H, W, 3)``; quantised ones ``uint8``.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from seathru.eval import metrics

#: NerfBaselines' ``llffhold`` for the SeaThru-NeRF dataset.
HOLD_EVERY = 8
#: NerfBaselines' name of the protocol (``info.json`` / ``results.json``).
PROTOCOL_NAME = "default"
#: The metrics NerfBaselines' default protocol writes, in its order (lpips when available).
METRIC_NAMES = ("psnr", "ssim", "mae", "mse", "lpips")


def held_out_names(names: Sequence[str], hold_every: int = HOLD_EVERY) -> list[str]:
    """The protocol's test images: index 0, ``hold_every``, ... of the sorted ``names``.

    ``names`` are the stored file names (NerfBaselines sorts the image paths).

    Example::

        >>> held_out_names([f"{i:02d}.png" for i in range(10)], 8)
        ['00.png', '08.png']
    """
    if hold_every < 1:
        raise ValueError(f"hold_every must be >= 1, got {hold_every}")
    return [name for i, name in enumerate(sorted(names)) if i % hold_every == 0]


def quantise_truncate(image: np.ndarray) -> np.ndarray:
    """A float image as NerfBaselines quantises it: ``clip(x * 255, 0, 255)`` truncated to uint8.

    uint8 input is returned unchanged; NaN counts as 0.
    """
    image = np.asarray(image)
    if image.dtype == np.uint8:
        return image
    values = np.nan_to_num(np.asarray(image, dtype=np.float64) * 255.0, nan=0.0)
    return np.clip(values, 0.0, 255.0).astype(np.uint8)


def stored_codes_as_uint8(codes: np.ndarray) -> np.ndarray:
    """A stored image's codes as the protocol's uint8 ground truth.

    8-bit codes as they are; 16-bit codes keep their top byte (PIL opens a 16-bit RGB PNG as
    8-bit RGB through its ``RGB;16B`` unpacker, which takes the most significant byte); float
    values are quantised by :func:`quantise_truncate`.
    """
    codes = np.asarray(codes)
    if codes.dtype == np.uint8:
        return codes
    if codes.dtype == np.uint16:
        return (codes >> 8).astype(np.uint8)
    return quantise_truncate(codes)


def view_protocol_metrics(prediction: np.ndarray, truth: np.ndarray,
                          lpips_network=None) -> dict[str, float]:
    """The protocol's metrics of one test view.

    Args:
        prediction, truth: ``(H, W, 3)`` uint8 (quantised as the protocol does).
        lpips_network: from ``seathru.eval.summary.lpips_network``, or None (no ``lpips``).

    Returns:
        ``psnr`` (dB; inf for identical images), ``ssim``, ``mae``, ``mse`` and, with a
        network, ``lpips``.
    """
    prediction, truth = np.asarray(prediction), np.asarray(truth)
    if prediction.dtype != np.uint8 or truth.dtype != np.uint8:
        raise ValueError("the protocol compares uint8 images; quantise them first")
    if prediction.shape != truth.shape:
        raise ValueError(f"prediction {prediction.shape} and ground truth {truth.shape} differ "
                         "in size")
    pred = prediction.astype(np.float64) / 255.0
    gt = truth.astype(np.float64) / 255.0
    out = {"psnr": metrics.psnr(pred, gt), "ssim": metrics.ssim(pred, gt),
           "mae": float(np.mean(np.abs(pred - gt))), "mse": float(np.mean((pred - gt) ** 2))}
    if lpips_network is not None:
        out["lpips"] = metrics.lpips_distance(lpips_network, pred, gt)
    return out


def protocol_means(per_view: Iterable[Mapping[str, float]]) -> dict[str, float]:
    """Mean of every metric over the views (NerfBaselines' ``accumulate_metrics``)."""
    lists = protocol_lists(per_view)
    return {name: float(np.mean(values)) for name, values in lists.items()}


def protocol_lists(per_view: Iterable[Mapping[str, float]]) -> dict[str, list[float]]:
    """Per metric, its values over the views in order (``metrics_lists`` of NerfBaselines)."""
    lists: dict[str, list[float]] = {}
    for view in per_view:
        for name, value in view.items():
            lists.setdefault(name, []).append(float(value))
    return lists
