"""Textures of the simulated dive: photographs (sRGB ``uint8``) spread over metres, fractal
noise and a cobble field, sampled in metres.

Callers pass sRGB ``uint8`` images (the simulate step passes scikit-image sample images shipped
inside the package); any missing texture is replaced by procedural fractal noise
(:func:`procedural_texture_srgb`). Photographs tile with their mirror images (no seams). The
seabed's local detail comes mostly from a procedural, non-repeating 12 m cobble field (random
Voronoi pebbles, :func:`pebble_texture`): a tiled photograph alone repeats every few metres,
which makes SIFT match the wrong places along a transect. Textures are pre-filtered to at most
:data:`MAX_TEXELS_PER_METRE`; with the default 2 x 2 supersampling that keeps aliasing low at
1-10 m ranges. Farther away (the survey's far slope, 20-50 m at grazing angles) the seabed
texture aliases in the clean images; every water preset but the clearest hides it. No file I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from seathru.radiometry.colour import srgb_to_linear

MAX_TEXELS_PER_METRE = 200.0  # textures are pre-filtered to this density against aliasing


@dataclass(frozen=True)
class Texture:
    """A tiling albedo texture: ``image`` (h, w, 3) float32 linear in [0, 1], ``texel_m`` metres
    per texel."""

    image: np.ndarray
    texel_m: float


def texture_from_srgb(image: np.ndarray, width_m: float,
                      max_texels_per_m: float = MAX_TEXELS_PER_METRE,
                      mirror: bool = True) -> Texture:
    """An sRGB ``uint8`` image (h, w) or (h, w, 3) spread over ``width_m`` metres, linearised and
    downsampled (area filter) when it is denser than ``max_texels_per_m``.

    ``mirror`` tiles the image with its mirror images (period ``2 * width_m``) so a photograph
    repeats without visible seams.
    """
    rgb = np.asarray(image)
    if rgb.ndim == 2:
        rgb = np.repeat(rgb[..., None], 3, axis=2)
    rgb = rgb[..., :3]
    if rgb.dtype == np.uint8:
        rgb = rgb.astype(np.float32) / 255.0
    h, w = rgb.shape[:2]
    density = w / width_m
    if density > max_texels_per_m:
        new_w = max(8, int(round(width_m * max_texels_per_m)))
        new_h = max(8, int(round(h * new_w / w)))
        rgb = cv2.resize(rgb.astype(np.float32), (new_w, new_h), interpolation=cv2.INTER_AREA)
        w = new_w
    linear = np.asarray(srgb_to_linear(np.clip(rgb, 0.0, 1.0)), dtype=np.float32)
    if mirror:
        linear = np.concatenate([linear, linear[:, ::-1]], axis=1)
        linear = np.concatenate([linear, linear[::-1]], axis=0)
    return Texture(image=np.ascontiguousarray(linear), texel_m=width_m / w)


def fractal_noise_image(rng: np.random.Generator, size: int, channels: int = 1,
                        exponent: float = 1.6, lowest_cycles: float = 2.0) -> np.ndarray:
    """Periodic fractal noise, (size, size, channels) float32 in [0, 1]: white noise shaped in
    the Fourier domain to a ``1 / f**exponent`` amplitude spectrum (frequencies below
    ``lowest_cycles`` per image removed), so it tiles exactly and has detail at every scale."""
    freq = np.fft.fftfreq(size) * size
    radius = np.hypot(freq[:, None], freq[None, :])
    gain = np.where(radius >= lowest_cycles, np.maximum(radius, 1.0) ** -exponent, 0.0)
    out = np.empty((size, size, channels), np.float32)
    for c in range(channels):
        spectrum = np.fft.fft2(rng.normal(size=(size, size))) * gain
        noise = np.real(np.fft.ifft2(spectrum))
        out[..., c] = (noise - noise.min()) / max(float(np.ptp(noise)), 1e-12)
    return out


def procedural_texture_srgb(rng: np.random.Generator, size: int = 256, colour: bool = True
                            ) -> np.ndarray:
    """Fractal noise texture, (size, size, 3) ``uint8``, seamless when tiled."""
    noise = fractal_noise_image(rng, size, 3 if colour else 1, exponent=1.2)
    return np.round(np.broadcast_to(noise, (size, size, 3)) * 255.0).astype(np.uint8)


def pebble_texture(rng: np.random.Generator, size: int = 2048, spacing_px: float = 20.0
                   ) -> np.ndarray:
    """Non-repeating cobble field, (size, size, 3) float32 albedo factor with mean 1, seamless
    when tiled.

    Voronoi cells around random seeds are the pebbles, each with its own brightness and a slight
    tint, darkened towards its rim (the crevices). Unlike a tiled photograph it never repeats
    within its extent, so SIFT cannot match one tile to another.
    """
    count = int((size / spacing_px) ** 2)
    seeds = rng.integers(0, size, (count, 2))
    # Periodic Voronoi diagram: wrapped copies of the seeds in a margin around the image.
    margin = int(4 * spacing_px)
    shifted = [(seeds + np.array([dx, dy]) * size) for dx in (-1, 0, 1) for dy in (-1, 0, 1)]
    all_seeds = np.concatenate(shifted)
    seed_id = np.tile(np.arange(count), 9)
    inside = np.all((all_seeds >= -margin) & (all_seeds < size + margin), axis=1)
    all_seeds, seed_id = all_seeds[inside] + margin, seed_id[inside]
    field_ = np.ones((size + 2 * margin, size + 2 * margin), np.uint8)
    field_[all_seeds[:, 1], all_seeds[:, 0]] = 0
    dist, labels = cv2.distanceTransformWithLabels(field_, cv2.DIST_L2, 5,
                                                   labelType=cv2.DIST_LABEL_PIXEL)
    owner = np.zeros(int(labels.max()) + 1, np.int64)
    owner[labels[all_seeds[:, 1], all_seeds[:, 0]]] = seed_id
    pebble = owner[labels[margin:margin + size, margin:margin + size]]
    dist = dist[margin:margin + size, margin:margin + size]
    shade = rng.uniform(0.5, 1.3, count).astype(np.float32)
    tint = (1.0 + rng.normal(0.0, 0.06, (count, 3))).astype(np.float32)
    dome = np.clip(1.0 - 0.8 * (dist / (0.6 * spacing_px)) ** 2, 0.15, 1.0)
    texture = shade[pebble][..., None] * tint[pebble] * dome[..., None]
    return (texture / texture.mean()).astype(np.float32)


def sample_texture(texture: Texture, u_m: np.ndarray, v_m: np.ndarray) -> np.ndarray:
    """Bilinear, wrapping lookup at metric coordinates ``u_m`` (across) and ``v_m`` (down),
    shape (N,) each; returns (N, 3) float32."""
    n = u_m.shape[0]
    if n == 0:
        return np.zeros((0, 3), np.float32)
    h, w = texture.image.shape[:2]
    # Wrap in float64 first: cv2.remap takes float32 maps, which lose texel precision far away.
    x = np.mod(u_m / texture.texel_m - 0.5, w).astype(np.float32)
    y = np.mod(v_m / texture.texel_m - 0.5, h).astype(np.float32)
    cols = 1024
    rows = -(-n // cols)
    pad = rows * cols - n
    map_x = np.pad(x, (0, pad)).reshape(rows, cols)
    map_y = np.pad(y, (0, pad)).reshape(rows, cols)
    out = cv2.remap(texture.image, map_x, map_y, interpolation=cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_WRAP)
    return out.reshape(-1, 3)[:n]
