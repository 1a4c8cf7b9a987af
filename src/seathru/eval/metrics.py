"""Evaluation metrics: image quality, radiometric and metric alignment, depth and water errors.

Pure numpy / PyTorch, no file I/O. Images are ``(H, W, 3)`` arrays, depth maps ``(H, W)``.

Image metrics follow the NeRF papers' evaluation code (mip-NeRF / SeaThru-NeRF): images are
clipped to [0, 1] and quantised to 8 bits (``round(x * 255) / 255``) before comparison; PSNR is
``-10 log10(MSE)`` with data range 1; SSIM uses an 11-tap Gaussian window with sigma 1.5, the
population covariance and K1 = 0.01, K2 = 0.03, averaged over the pixels where the window fits
inside the image (a "valid" convolution) and over the colour channels. scikit-image's
``structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
data_range=1)`` computes exactly that (its reflect-padded filter is cropped by the window radius),
so it is used here rather than a hand-written copy.

LPIPS (Zhang et al. 2018) is implemented as a small torch module that loads its weights from a
state dict supplied by the caller (the ``lpips`` package is not a dependency and nothing is ever
downloaded); see :func:`lpips_from_state_dict`.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from skimage.metrics import structural_similarity

from seathru.radiometry.colour import linear_to_srgb

SSIM_SIGMA = 1.5
SSIM_TRUNCATE = 3.5  # scipy's truncation: radius int(3.5 * 1.5 + 0.5) = 5, an 11-tap window
SSIM_RADIUS = int(SSIM_TRUNCATE * SSIM_SIGMA + 0.5)


# --------------------------------------------------------------------------------- image metrics

def quantise_8bit(image: np.ndarray) -> np.ndarray:
    """Clip to [0, 1] and quantise to 8-bit levels, as the official evaluation does. float64."""
    return np.round(np.clip(np.asarray(image, dtype=np.float64), 0.0, 1.0) * 255.0) / 255.0


def _valid_mask(valid, shape) -> np.ndarray | None:
    if valid is None:
        return None
    valid = np.asarray(valid, dtype=bool)
    if valid.shape != tuple(shape[:2]):
        raise ValueError(f"mask shape {valid.shape} does not match image shape {shape}")
    return valid


def psnr(prediction: np.ndarray, target: np.ndarray, data_range: float = 1.0,
         valid: np.ndarray | None = None) -> float:
    """Peak signal-to-noise ratio in dB over all pixels and channels (inf for identical images).

    ``valid``: optional ``(H, W)`` boolean mask; the mean squared error is then taken over the
    valid pixels only.
    """
    prediction = np.asarray(prediction, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if prediction.shape != target.shape:
        raise ValueError(f"shape mismatch: {prediction.shape} vs {target.shape}")
    valid = _valid_mask(valid, prediction.shape)
    error = (prediction - target) ** 2
    mse = float(np.mean(error if valid is None else error[valid]))
    if mse == 0.0:
        return float("inf")
    return float(10.0 * np.log10(data_range ** 2 / mse))


def ssim(prediction: np.ndarray, target: np.ndarray, data_range: float = 1.0,
         valid: np.ndarray | None = None) -> float:
    """Structural similarity with the NeRF papers' settings (see module docstring).

    ``prediction`` and ``target``: ``(H, W)`` or ``(H, W, C)`` with ``H, W >= 11``. ``valid``:
    optional ``(H, W)`` mask; the SSIM map is then averaged over the valid window centres only
    (pixels outside it must still hold finite values: they enter the windows of their
    neighbours).
    """
    prediction = np.asarray(prediction, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if prediction.shape != target.shape:
        raise ValueError(f"shape mismatch: {prediction.shape} vs {target.shape}")
    valid = _valid_mask(valid, prediction.shape)
    result = structural_similarity(
        prediction, target, gaussian_weights=True, sigma=SSIM_SIGMA, truncate=SSIM_TRUNCATE,
        use_sample_covariance=False, data_range=data_range,
        channel_axis=-1 if prediction.ndim == 3 else None, full=valid is not None)
    if valid is None:
        return float(result)
    ssim_map = result[1]
    pad = SSIM_RADIUS
    inner = ssim_map[pad:-pad, pad:-pad]
    keep = valid[pad:-pad, pad:-pad]
    if not keep.any():
        return float("nan")
    return float(inner[keep].mean())


def image_metrics(prediction: np.ndarray, target: np.ndarray,
                  valid: np.ndarray | None = None) -> dict[str, float]:
    """PSNR and SSIM of two linear images, in linear space and after sRGB encoding.

    Linear: the official SeaThru-NeRF evaluation (images as stored, 8-bit quantised). sRGB: the
    same linear values encoded with the sRGB transfer curve, then quantised; no exposure change,
    so it measures the same images in a perceptually more uniform space.
    ``valid``: optional ``(H, W)`` mask of the pixels to score (e.g. where a simulated clean
    image is defined); non-finite values outside it are replaced by 0 in both images.
    """
    prediction = np.asarray(prediction, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if valid is not None:
        valid = _valid_mask(valid, prediction.shape)
        outside = ~valid[..., None] if prediction.ndim == 3 else ~valid
        prediction = np.where(outside, 0.0, prediction)
        target = np.where(outside, 0.0, target)
    pred_lin, target_lin = quantise_8bit(prediction), quantise_8bit(target)
    pred_srgb = quantise_8bit(linear_to_srgb(prediction))
    target_srgb = quantise_8bit(linear_to_srgb(target))
    return {"psnr_linear": psnr(pred_lin, target_lin, valid=valid),
            "ssim_linear": ssim(pred_lin, target_lin, valid=valid),
            "psnr_srgb": psnr(pred_srgb, target_srgb, valid=valid),
            "ssim_srgb": ssim(pred_srgb, target_srgb, valid=valid)}


# ------------------------------------------------------------------------------- colour gain fit

def channel_gain_sums(prediction: np.ndarray, target: np.ndarray,
                      valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel sums (sum p*t, sum p*p) for a least-squares gain; add them over views to pool.

    ``prediction``, ``target``: ``(..., 3)``; ``valid``: boolean ``(...)`` or None.
    """
    p = np.asarray(prediction, dtype=np.float64).reshape(-1, prediction.shape[-1])
    t = np.asarray(target, dtype=np.float64).reshape(-1, target.shape[-1])
    keep = np.all(np.isfinite(p), axis=1) & np.all(np.isfinite(t), axis=1)
    if valid is not None:
        keep &= np.asarray(valid, dtype=bool).reshape(-1)
    p, t = p[keep], t[keep]
    return (p * t).sum(axis=0), (p * p).sum(axis=0)


def gain_from_sums(cross: np.ndarray, power: np.ndarray) -> np.ndarray:
    """The gain g minimising sum (g p - t)^2 per channel; 1 where the prediction is all zero."""
    cross, power = np.asarray(cross, dtype=np.float64), np.asarray(power, dtype=np.float64)
    return np.where(power > 0, cross / np.where(power > 0, power, 1.0), 1.0)


def fit_channel_gain(prediction: np.ndarray, target: np.ndarray,
                     valid: np.ndarray | None = None) -> np.ndarray:
    """Least-squares per-channel gain ``g`` (shape ``(C,)``) with ``g * prediction ~ target``.

    Used to undo the radiometric scale between the pipeline's normalised, white-balanced linear
    images and a simulator's ground truth: fitted on the full render against the truth image
    with water, then applied unchanged to the restored render and the medium colour.
    """
    return gain_from_sums(*channel_gain_sums(prediction, target, valid))


# ------------------------------------------------------------------------------- metric scale

def metric_scale(centres_normalised: np.ndarray, centres_truth: np.ndarray) -> dict[str, float]:
    """Truth units (metres) per normalised scene unit, from corresponding camera centres.

    ``centres_normalised``: ``(N, 3)`` camera centres of the evaluated camera file (normalised
    units); ``centres_truth``: ``(N, 3)`` the same cameras' true centres. A similarity alignment
    (Umeyama, ``seathru.geometry.poses.umeyama``) absorbs any rotation, translation and scale the
    pose estimation introduced (COLMAP's arbitrary frame); its scale converts normalised
    distances (depths) to metres and normalised coefficients (1/unit) to 1/m by division.
    Returns ``scale``, the alignment's RMS residual in truth units and that residual relative to
    the truth trajectory's extent.
    """
    from seathru.geometry.poses import umeyama

    centres_normalised = np.asarray(centres_normalised, dtype=np.float64)
    centres_truth = np.asarray(centres_truth, dtype=np.float64)
    alignment = umeyama(centres_normalised, centres_truth)
    residual = np.linalg.norm(alignment.apply(centres_normalised) - centres_truth, axis=1)
    rms = float(np.sqrt(np.mean(residual ** 2)))
    extent = float(np.max(np.linalg.norm(centres_truth[:, None] - centres_truth[None], axis=-1)))
    return {"scale": float(alignment.scale), "rms_residual": rms,
            "relative_residual": rms / extent if extent > 0 else float("nan")}


# ------------------------------------------------------------------------------- depth and water

def depth_errors(predicted: np.ndarray, truth: np.ndarray,
                 valid: np.ndarray | None = None) -> dict[str, float]:
    """Errors of a metric depth map against the truth, over valid pixels (truth finite and > 0).

    Returns median and mean absolute relative error ``|p - t| / t``, RMSE (truth units) and the
    Pearson correlation of ``p`` and ``t``; NaN everywhere when fewer than 2 pixels are valid.
    """
    p = np.asarray(predicted, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    keep = np.isfinite(p) & np.isfinite(t) & (t > 0)
    if valid is not None:
        keep &= np.asarray(valid, dtype=bool)
    p, t = p[keep], t[keep]
    if p.size < 2:
        nan = float("nan")
        return {"depth_median_abs_rel": nan, "depth_mean_abs_rel": nan, "depth_rmse": nan,
                "depth_corr": nan}
    rel = np.abs(p - t) / t
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = float(np.corrcoef(p, t)[0, 1]) if p.std() > 0 and t.std() > 0 else float("nan")
    return {"depth_median_abs_rel": float(np.median(rel)), "depth_mean_abs_rel": float(rel.mean()),
            "depth_rmse": float(np.sqrt(np.mean((p - t) ** 2))), "depth_corr": corr}


def relative_error(fitted, truth) -> np.ndarray:
    """Per-element ``|fitted - truth| / |truth|`` (NaN where the truth is 0)."""
    fitted = np.asarray(fitted, dtype=np.float64)
    truth = np.asarray(truth, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(truth != 0, np.abs(fitted - truth) / np.abs(truth), np.nan)


# ---------------------------------------------------------------------------------------- LPIPS

# Feature trunks as (torchvision ``features`` index, layer) lists; LPIPS taps the ReLU outputs
# closing each of the five slices (Zhang et al. 2018, ``lpips/pretrained_networks.py``).
_TRUNKS = {
    "alex": {"convs": {0: (3, 64, 11, 4, 2), 3: (64, 192, 5, 1, 2), 6: (192, 384, 3, 1, 1),
                       8: (384, 256, 3, 1, 1), 10: (256, 256, 3, 1, 1)},
             "pools": (2, 5), "slice_ends": (2, 5, 8, 10, 12)},
    "vgg": {"convs": {0: (3, 64, 3, 1, 1), 2: (64, 64, 3, 1, 1), 5: (64, 128, 3, 1, 1),
                      7: (128, 128, 3, 1, 1), 10: (128, 256, 3, 1, 1), 12: (256, 256, 3, 1, 1),
                      14: (256, 256, 3, 1, 1), 17: (256, 512, 3, 1, 1), 19: (512, 512, 3, 1, 1),
                      21: (512, 512, 3, 1, 1), 24: (512, 512, 3, 1, 1), 26: (512, 512, 3, 1, 1),
                      28: (512, 512, 3, 1, 1)},
            "pools": (4, 9, 16, 23), "slice_ends": (4, 9, 16, 23, 30)},
}
_LPIPS_SHIFT = (-0.030, -0.088, -0.188)
_LPIPS_SCALE = (0.458, 0.448, 0.450)
LPIPS_MIN_SIZE = 32


def _normalise_lpips_keys(state: Mapping) -> tuple[dict, dict]:
    """Split a state dict into trunk weights keyed by torchvision ``features`` index and the five
    linear-layer weights, accepting the layouts of ``lpips.LPIPS().state_dict()``
    (``net.sliceK.I.weight``, ``linK.model.1.weight``), torchvision (``features.I.weight``) and
    the lpips package's ``weights/v0.1/<net>.pth`` (``linK.model.1.weight``)."""
    trunk, lins = {}, {}
    for key, value in state.items():
        parts = key.split(".")
        if parts[0] == "net" and len(parts) == 4 and parts[1].startswith("slice"):
            trunk[f"{parts[2]}.{parts[3]}"] = value
        elif parts[0] == "features" and len(parts) == 3:
            trunk[f"{parts[1]}.{parts[2]}"] = value
        elif parts[0].startswith("lin") and parts[0][3:].isdigit() and parts[-1] == "weight":
            lins[int(parts[0][3:])] = value
    return trunk, lins


def lpips_from_state_dict(state: Mapping):
    """Build an LPIPS v0.1 network (AlexNet or VGG16 trunk, detected from the weights).

    ``state``: a mapping of tensors holding the trunk (``features.*`` or ``net.slice*``) and the
    five linear layers (``lin0`` .. ``lin4``); merge the torchvision backbone file and the lpips
    ``v0.1/<net>.pth`` file into one mapping when they come separately. Raises ``ValueError``
    when weights are missing or do not fit either trunk. Returns a ``torch.nn.Module`` in eval
    mode whose ``forward(a, b)`` takes ``(N, 3, H, W)`` tensors in [0, 1] and returns ``(N,)``.
    """
    import torch
    from torch import nn

    trunk_state, lins = _normalise_lpips_keys(state)
    if sorted(lins) != [0, 1, 2, 3, 4]:
        raise ValueError(f"LPIPS weights need linear layers lin0..lin4, found {sorted(lins)}")
    widths = [int(lins[i].shape[1]) for i in range(5)]
    net_name = {(64, 192, 384, 256, 256): "alex",
                (64, 128, 256, 512, 512): "vgg"}.get(tuple(widths))
    if net_name is None:
        raise ValueError(f"LPIPS linear layer widths {widths} match neither AlexNet nor VGG16")
    spec = _TRUNKS[net_name]

    layers: list[nn.Module] = []
    for index in range(spec["slice_ends"][-1]):
        if index in spec["convs"]:
            c_in, c_out, kernel, stride, pad = spec["convs"][index]
            layers.append(nn.Conv2d(c_in, c_out, kernel, stride=stride, padding=pad))
        elif index in spec["pools"]:
            layers.append(nn.MaxPool2d(kernel_size=3 if net_name == "alex" else 2,
                                       stride=2))
        else:
            layers.append(nn.ReLU(inplace=False))
    features = nn.Sequential(*layers)
    missing = [f"{i}.{w}" for i in spec["convs"] for w in ("weight", "bias")
               if f"{i}.{w}" not in trunk_state]
    if missing:
        raise ValueError(f"LPIPS {net_name} trunk weights missing: {missing[:4]}"
                         f"{' ...' if len(missing) > 4 else ''} (supply the torchvision "
                         f"{'alexnet' if net_name == 'alex' else 'vgg16'} backbone weights)")
    features.load_state_dict({k: torch.as_tensor(v) for k, v in trunk_state.items()
                              if int(k.split('.')[0]) < len(layers)})

    class _LPIPS(nn.Module):
        def __init__(self):
            super().__init__()
            self.net_name = net_name
            self.features = features
            self.slice_ends = spec["slice_ends"]
            self.lins = nn.ParameterList(
                [nn.Parameter(torch.as_tensor(lins[i]).reshape(1, -1, 1, 1).float(),
                              requires_grad=False) for i in range(5)])
            self.register_buffer("shift", torch.tensor(_LPIPS_SHIFT).reshape(1, 3, 1, 1))
            self.register_buffer("scale", torch.tensor(_LPIPS_SCALE).reshape(1, 3, 1, 1))

        def _taps(self, x):
            taps, start = [], 0
            for end in self.slice_ends:
                for layer in self.features[start:end]:
                    x = layer(x)
                taps.append(x)
                start = end
            return taps

        def forward(self, a, b):
            a = ((2.0 * a - 1.0) - self.shift) / self.scale
            b = ((2.0 * b - 1.0) - self.shift) / self.scale
            total = 0.0
            for fa, fb, weight in zip(self._taps(a), self._taps(b), self.lins):
                fa = fa / (torch.sqrt((fa ** 2).sum(dim=1, keepdim=True)) + 1e-10)
                fb = fb / (torch.sqrt((fb ** 2).sum(dim=1, keepdim=True)) + 1e-10)
                total = total + ((fa - fb) ** 2 * weight).sum(dim=1).mean(dim=(1, 2))
            return total

    return _LPIPS().eval()


def lpips_distance(network, prediction: np.ndarray, target: np.ndarray) -> float:
    """LPIPS between two ``(H, W, 3)`` images in [0, 1] (clipped) with a network from
    :func:`lpips_from_state_dict`. Raises ``ValueError`` for images under LPIPS_MIN_SIZE pixels
    on a side (the trunk's pooling leaves nothing to compare)."""
    import torch

    if min(np.shape(prediction)[:2]) < LPIPS_MIN_SIZE:
        raise ValueError(f"image of {np.shape(prediction)[1]}x{np.shape(prediction)[0]} pixels "
                         f"is too small for LPIPS (needs {LPIPS_MIN_SIZE} on each side)")

    def to_tensor(image):
        image = np.clip(np.asarray(image, dtype=np.float32), 0.0, 1.0)
        return torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1)))[None]

    with torch.no_grad():
        return float(network(to_tensor(prediction), to_tensor(target))[0])
