"""Procedural dive scene with exact (analytic) ray casting, and dive camera paths.

World frame: metres, z up. The seabed is the gently undulating height field ``z = h(x, y)``
(a sum of three sinusoids, amplitude a few centimetres; ``amplitude=0`` gives the flat plane
``z = base``), optionally on a reef slope that levels off at a crest (``Seabed.slope``; the
reef scene and its survey path are in ``seathru.sim.reef``). On it rest textured objects with
closed-form ray intersections: ellipsoids (spheres and half-buried rocks) and boxes, each
rotated about the vertical.

Ray casting returns the range ``t``: the Euclidean distance from the ray origin to the first
surface along the *unit* ray direction (``inf`` for a ray that meets nothing: open water).
Planes, ellipsoids and boxes are intersected in closed form. The undulating seabed is
intersected by Lipschitz-bounded sphere tracing (steps never overshoot the first root, because
``|grad h|`` is bounded) followed by Newton polishing, which reaches the root to ~1e-9 m: exact
for every practical purpose.

Clean radiance ``J`` (linear RGB) is Lambertian and view independent: texture albedo times
``ambient + diffuse * max(0, n . l) * visibility`` for one distant downwelling light ``l``
(hard shadows are cast by the objects). Lambertian shading keeps every surface point the same
colour in every view, which both SfM and the NeRF assume.

Textures: callers pass sRGB ``uint8`` images (the simulate step passes scikit-image sample images
shipped inside the package); any missing texture is replaced by procedural fractal noise.
Photographs tile with their mirror images (no seams). The seabed's local detail comes mostly
from a procedural, non-repeating 12 m cobble field (random Voronoi pebbles): a tiled photograph
alone repeats every few metres, which makes SIFT match the wrong places along a transect.
Textures are pre-filtered to at most ``MAX_TEXELS_PER_METRE``; with the default 2 x 2
supersampling that keeps aliasing low at 1-10 m ranges. Farther away (the survey's far slope,
20-50 m at grazing angles) the seabed texture aliases in the clean images; every water preset
but the clearest hides it.
This module does no file I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import cv2
import numpy as np

from seathru.radiometry.colour import srgb_to_linear

NO_HIT = -2
SEABED = -1
MAX_SEABED_RANGE_M = 1000.0  # a reef slope seen beyond this range counts as open water
MAX_TEXELS_PER_METRE = 200.0  # textures are pre-filtered to this density against aliasing


# --------------------------------------------------------------------------------------------
# Textures and noise
# --------------------------------------------------------------------------------------------

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


# --------------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------------

def _yaw_matrix(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Seabed:
    """Height field ``h(x, y) = base + ramp(u) + amplitude * (0.6 sin(k1 x + p1) cos(k2 y + p2)
    + 0.4 sin(k3 (x cos a + y sin a) + p3))`` with ``k = 2 pi / wavelength``.

    ``ramp`` is an optional reef slope: with ``u = x cos d + y sin d`` (``d`` =
    ``slope_direction``, the way up the slope), ``ramp(u) = slope * (crest - w * softplus((crest
    - u) / w))`` rises with gradient ``slope`` (rise per metre) below the crest line ``u = crest``
    and levels off into a flat reef top above it (``w`` = ``crest_width`` rounds the edge). Far
    down the slope the seabed keeps falling: a ray travelling down faster than the slope never
    meets it (open water). ``slope = 0`` (the default) is the gently undulating plain.
    """

    amplitude: float = 0.08
    base: float = 0.0
    wavelengths: tuple[float, float, float] = (4.0, 3.3, 2.7)
    phases: tuple[float, float, float] = (0.3, 1.1, 2.0)
    direction: float = 0.6  # radians, direction of the third wave
    slope: float = 0.0  # rise per metre of the reef slope (tan of its angle); 0: no slope
    slope_direction: float = math.pi / 2  # radians from +x: the way up the slope
    crest: float = 0.0  # metres along slope_direction where the slope levels off
    crest_width: float = 1.0  # metres, the rounding of the crest

    def _k(self) -> tuple[float, float, float]:
        return tuple(2.0 * math.pi / w for w in self.wavelengths)  # type: ignore[return-value]

    def _below_crest(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """``(crest - u) / crest_width``: how far below the crest line (x, y) lies."""
        cd, sd = math.cos(self.slope_direction), math.sin(self.slope_direction)
        return (self.crest - (x * cd + y * sd)) / self.crest_width

    def _ramp(self, below: np.ndarray) -> np.ndarray:
        return self.slope * (self.crest - self.crest_width * np.logaddexp(0.0, below))

    def top(self) -> float:
        """Upper bound of ``h``."""
        return self.base + self.slope * self.crest + abs(self.amplitude)

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        height = np.full(np.broadcast(x, y).shape, self.base)
        if self.slope != 0.0:
            height = height + self._ramp(self._below_crest(x, y))
        if self.amplitude == 0.0:
            return height
        k1, k2, k3 = self._k()
        p1, p2, p3 = self.phases
        ca, sa = math.cos(self.direction), math.sin(self.direction)
        return height + self.amplitude * (
            0.6 * np.sin(k1 * x + p1) * np.cos(k2 * y + p2)
            + 0.4 * np.sin(k3 * (x * ca + y * sa) + p3))

    def height_and_gradient(self, x: np.ndarray, y: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``h``, ``dh/dx``, ``dh/dy`` at (x, y)."""
        shape = np.broadcast(x, y).shape
        height, gx, gy = np.full(shape, self.base), np.zeros(shape), np.zeros(shape)
        if self.slope != 0.0:
            below = self._below_crest(x, y)
            rise = self.slope * 0.5 * (1.0 + np.tanh(0.5 * below))  # slope * sigmoid(below)
            height = height + self._ramp(below)
            gx = gx + rise * math.cos(self.slope_direction)
            gy = gy + rise * math.sin(self.slope_direction)
        if self.amplitude == 0.0:
            return height, gx, gy
        k1, k2, k3 = self._k()
        p1, p2, p3 = self.phases
        ca, sa = math.cos(self.direction), math.sin(self.direction)
        a, b, c = k1 * x + p1, k2 * y + p2, k3 * (x * ca + y * sa) + p3
        sin_a, cos_a, sin_b, cos_b = np.sin(a), np.cos(a), np.sin(b), np.cos(b)
        sin_c, cos_c = np.sin(c), np.cos(c)
        amp = self.amplitude
        height = height + amp * (0.6 * sin_a * cos_b + 0.4 * sin_c)
        wave3 = 0.4 * k3 * cos_c
        gx = gx + amp * (0.6 * k1 * cos_a * cos_b + wave3 * ca)
        gy = gy + amp * (-0.6 * k2 * sin_a * sin_b + wave3 * sa)
        return height, gx, gy

    def lipschitz(self) -> float:
        """Upper bound of ``|grad h|``."""
        k1, k2, k3 = self._k()
        return abs(self.amplitude) * (0.6 * math.hypot(k1, k2) + 0.4 * k3) + abs(self.slope)

    def _scan_for_root(self, rays: np.ndarray, tt: np.ndarray, ox, oy, oz, dx, dy, dz,
                       t_max: np.ndarray, step: float = 0.005, steps: int = 400) -> np.ndarray:
        """Of ``rays`` (indices) that have no root before ``tt``, those whose gap to the seabed
        turns negative within ``steps`` x ``step`` metres on; ``tt`` is set to that first root
        (bisection, to 1e-12 m). Returns the rays found."""
        def gap(index, t):
            return oz[index] + t * dz[index] - self.height(ox[index] + t * dx[index],
                                                           oy[index] + t * dy[index])

        hits = []
        for ray in rays:
            ahead = tt[ray] + step * np.arange(1, steps + 1)
            ahead = ahead[ahead <= t_max[ray]]
            below = np.flatnonzero(gap(np.full(ahead.size, ray), ahead) <= 0.0)
            if below.size == 0:
                continue
            high = ahead[below[0]]
            low = tt[ray] if below[0] == 0 else ahead[below[0] - 1]
            for _ in range(60):
                middle = 0.5 * (low + high)
                if gap(np.array([ray]), np.array([middle]))[0] > 0.0:
                    low = middle
                else:
                    high = middle
            tt[ray] = low
            hits.append(ray)
        return np.asarray(hits, dtype=np.int64)

    def intersect(self, origins: np.ndarray, dirs: np.ndarray, max_iterations: int = 2000
                  ) -> np.ndarray:
        """Range to the first seabed hit, (N,); ``inf`` where the ray never reaches it: it
        climbs away, runs down a reef slope faster than the slope falls, or would meet a reef
        slope only beyond :data:`MAX_SEABED_RANGE_M`. A ray still stepping after
        ``max_iterations`` steps (grazing the seabed near-tangentially) is scanned on for 2 m
        in 5 mm steps.

        ``origins`` (N, 3) or one shared origin (3,); rays must start above the seabed.
        """
        origins = np.broadcast_to(origins, dirs.shape)
        oz, dz = origins[:, 2], dirs[:, 2]
        t = np.full(dirs.shape[0], np.inf)
        if self.amplitude == 0.0 and self.slope == 0.0:
            down = np.flatnonzero(dz < -1e-9)
            t[down] = (self.base - oz[down]) / dz[down]
            return t
        top = self.top()
        horizontal = np.hypot(dirs[:, 0], dirs[:, 1])
        waves = self.lipschitz() - abs(self.slope)  # bound of the waves' gradient
        # How fast the gap to the seabed can close along a ray: -dz + (reef slope's rise along
        # the ray) + waves. The slope's rise is rise(u) (d . up) with rise(u) in [0, slope]
        # monotone along a ray, never larger ahead than where the ray is now: the current rise
        # bounds every later step (exact on the slope's straight parts, so those converge fast).
        cd, sd = math.cos(self.slope_direction), math.sin(self.slope_direction)
        up_slope = dirs[:, 0] * cd + dirs[:, 1] * sd
        fastest = waves * horizontal - dz + abs(self.slope) * np.maximum(up_slope, 0.0)
        if self.slope == 0.0:  # a plain: only rays going down can reach it
            rays = np.flatnonzero(dz < -1e-9)
        else:  # a slope can rise faster than a ray climbs; beyond the top nothing is hit
            rays = np.flatnonzero((fastest > 1e-9) & ((oz < top) | (dz < -1e-9)))
        ox, oy, oz = (np.ascontiguousarray(origins[rays, k]) for k in range(3))
        dx, dy, dz = (np.ascontiguousarray(dirs[rays, k]) for k in range(3))
        base_speed = waves * horizontal[rays] - dz
        up_slope = up_slope[rays]
        with np.errstate(divide="ignore"):
            to_top = (top - oz) / dz
        # Start where the ray crosses the level above every crest (rays going down) or at the
        # camera (rays starting below it); stop where a rising ray passes that level.
        tt = np.where(dz < 0.0, np.maximum(to_top, 0.0), 0.0)
        t_max = np.where(dz > 0.0, to_top, np.inf if self.slope == 0.0 else MAX_SEABED_RANGE_M)
        # From there conservative steps (the gap divided by the fastest the gap can close
        # along the rest of the ray) cannot skip the first root. A ray within 1 um of the
        # seabed has found it if it is closing in; if it is moving away (a near miss: grazing a
        # crest), it steps on by 1 mm.
        tolerance, escape = 1e-6, 1e-3
        found = np.zeros(rays.size, dtype=bool)
        active = np.arange(rays.size)
        for _ in range(max_iterations):
            ta = tt[active]
            px, py = ox[active] + ta * dx[active], oy[active] + ta * dy[active]
            gap = oz[active] + ta * dz[active] - self.height(px, py)
            speed = base_speed[active]
            if self.slope != 0.0:
                rise = self.slope * 0.5 * (1.0 + np.tanh(0.5 * self._below_crest(px, py)))
                speed = speed + rise * up_slope[active]
            near = np.flatnonzero(gap <= tolerance)
            closing_in = np.zeros(active.size, dtype=bool)
            if near.size:
                _, gx, gy = self.height_and_gradient(px[near], py[near])
                rate = dz[active[near]] - gx * dx[active[near]] - gy * dy[active[near]]
                closing_in[near] = rate < 0.0
                gap[near] = np.where(rate < 0.0, gap[near], escape)
            found[active[closing_in]] = True
            # Where even the fastest closing rate is not positive, the gap only grows: no hit.
            moving = (speed > 1e-12) & ~closing_in
            tt[active] = ta + np.where(moving, np.maximum(gap, 0.0)
                                       / np.where(moving, speed, 1.0), 0.0)
            active = active[moving & (tt[active] < t_max[active])]
            if active.size == 0:
                break
        if active.size:
            # Out of steps: a ray grazing the seabed near-tangentially, where the conservative
            # steps shrink with the gap. No root lies before tt, so scan on in short steps and
            # bisect the first sign change.
            found[self._scan_for_root(active, tt, ox, oy, oz, dx, dy, dz, t_max)] = True
        found = np.flatnonzero(found)
        # Newton polishing from just above the first root, until each ray has converged.
        active = found
        for _ in range(8):
            ta = tt[active]
            ax, ay, az = ox[active], oy[active], oz[active]
            bx, by, bz = dx[active], dy[active], dz[active]
            height, gx, gy = self.height_and_gradient(ax + ta * bx, ay + ta * by)
            gap_a = az + ta * bz - height
            slope = bz - gx * bx - gy * by
            tt[active] = ta + np.where(slope < -1e-6, -gap_a / np.minimum(slope, -1e-6), 0.0)
            active = active[np.abs(gap_a) > 1e-12]
            if active.size == 0:
                break
        t[rays[found]] = tt[found]
        return t

    def normal(self, points: np.ndarray) -> np.ndarray:
        _, gx, gy = self.height_and_gradient(points[:, 0], points[:, 1])
        n = np.stack([-gx, -gy, np.ones_like(gx)], axis=1)
        return n / np.linalg.norm(n, axis=1, keepdims=True)


@dataclass(frozen=True)
class Ellipsoid:
    """Ellipsoid (sphere when the radii are equal) rotated by ``yaw`` about the vertical."""

    name: str
    centre: tuple[float, float, float]
    radii: tuple[float, float, float]
    yaw: float = 0.0
    texture: str = "rock"
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def to_local(self, points: np.ndarray) -> np.ndarray:
        return (points - np.asarray(self.centre)) @ _yaw_matrix(self.yaw)

    def bounding_radius(self) -> float:
        return max(self.radii)

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Range (N,) along unit ``dirs`` (N, 3) from ``origins`` (N, 3) or (3,); inf = miss."""
        radii = np.asarray(self.radii)
        o = self.to_local(origins) / radii
        d = (dirs @ _yaw_matrix(self.yaw)) / radii
        a = np.einsum("ij,ij->i", d, d)
        b = 2.0 * (d @ o if o.ndim == 1 else np.einsum("ij,ij->i", o, d))
        c = (o @ o if o.ndim == 1 else np.einsum("ij,ij->i", o, o)) - 1.0
        disc = b * b - 4.0 * a * c
        t = np.full(dirs.shape[0], np.inf)
        ok = disc >= 0.0
        sq = np.sqrt(np.where(ok, disc, 0.0))
        # Numerically stable roots (no cancellation when b is large).
        q = -0.5 * (b + np.copysign(sq, b))
        with np.errstate(divide="ignore", invalid="ignore"):
            r1, r2 = q / a, c / q
        near = np.minimum(r1, r2)
        far = np.maximum(r1, r2)
        first = np.where(near > 1e-9, near, far)
        hit = ok & (first > 1e-9)
        t[hit] = first[hit]
        return t

    def normal(self, points: np.ndarray) -> np.ndarray:
        radii = np.asarray(self.radii)
        local = self.to_local(points) / (radii * radii)
        n = local @ _yaw_matrix(self.yaw).T
        return n / np.linalg.norm(n, axis=1, keepdims=True)


@dataclass(frozen=True)
class Box:
    """Box with half extents ``half_size`` rotated by ``yaw`` about the vertical."""

    name: str
    centre: tuple[float, float, float]
    half_size: tuple[float, float, float]
    yaw: float = 0.0
    texture: str = "crate"
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def to_local(self, points: np.ndarray) -> np.ndarray:
        return (points - np.asarray(self.centre)) @ _yaw_matrix(self.yaw)

    def bounding_radius(self) -> float:
        return float(np.linalg.norm(self.half_size))

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Range (N,) along unit ``dirs`` (N, 3) from ``origins`` (N, 3) or (3,); inf = miss."""
        half = np.asarray(self.half_size)
        o = self.to_local(origins)
        d = dirs @ _yaw_matrix(self.yaw)
        d = np.where(np.abs(d) < 1e-12, 1e-12, d)
        t1 = (-half - o) / d
        t2 = (half - o) / d
        t_enter = np.max(np.minimum(t1, t2), axis=1)
        t_exit = np.min(np.maximum(t1, t2), axis=1)
        t = np.full(dirs.shape[0], np.inf)
        hit = (t_exit >= t_enter) & (t_enter > 1e-9)
        t[hit] = t_enter[hit]
        return t

    def normal(self, points: np.ndarray) -> np.ndarray:
        local = self.to_local(points) / np.asarray(self.half_size)
        axis = np.argmax(np.abs(local), axis=1)
        n_local = np.zeros_like(local)
        n_local[np.arange(local.shape[0]), axis] = np.sign(local[np.arange(local.shape[0]), axis])
        return n_local @ _yaw_matrix(self.yaw).T


SceneObject = Ellipsoid | Box


# --------------------------------------------------------------------------------------------
# Scene
# --------------------------------------------------------------------------------------------

@dataclass
class Scene:
    """Seabed, objects, textures and light. ``target`` is the point orbits circle around (the
    centre of a survey)."""

    seabed: Seabed
    objects: list[SceneObject]
    textures: dict[str, Texture]
    light_dir: np.ndarray = field(default_factory=lambda: _unit([0.35, 0.25, 1.0]))
    ambient: float = 0.25
    diffuse: float = 0.9
    seabed_tint: tuple[float, float, float] = (0.62, 0.54, 0.42)
    target: tuple[float, float, float] = (0.0, 0.0, 0.2)

    def describe(self) -> dict:
        """JSON-ready description of the geometry (for ``truth/scene.json``)."""
        objects = []
        for obj in self.objects:
            entry = {"name": obj.name, "type": type(obj).__name__.lower(),
                     "centre": list(obj.centre), "yaw_rad": obj.yaw, "texture": obj.texture}
            if isinstance(obj, Ellipsoid):
                entry["radii"] = list(obj.radii)
            else:
                entry["half_size"] = list(obj.half_size)
            objects.append(entry)
        seabed = self.seabed
        return {"units": "metres, z up",
                "seabed": {"formula": "z = base + ramp(u) + amplitude * (0.6 sin(k1 x + p1) "
                                      "cos(k2 y + p2) + 0.4 sin(k3 (x cos a + y sin a) + p3)), "
                                      "k = 2 pi / wavelength; ramp(u) = slope * (crest - "
                                      "crest_width * ln(1 + exp((crest - u) / crest_width))), "
                                      "u = x cos d + y sin d (ramp = 0 when slope = 0)",
                           "amplitude": seabed.amplitude, "base": seabed.base,
                           "wavelengths": list(seabed.wavelengths),
                           "phases": list(seabed.phases), "a": seabed.direction,
                           "slope": seabed.slope, "d": seabed.slope_direction,
                           "crest": seabed.crest, "crest_width": seabed.crest_width},
                "objects": objects,
                "light": {"direction_to_light": self.light_dir.tolist(), "ambient": self.ambient,
                          "diffuse": self.diffuse},
                "orbit_target": list(self.target)}


def _unit(v: Sequence[float]) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


# name -> (width in metres over which the image is spread, contrast gain about the mean).
# Object textures are also scaled to a mean albedo of OBJECT_MEAN_ALBEDO. Water eats contrast,
# so the gains keep enough local detail for SIFT after the backscatter veil.
TEXTURE_LAYOUT = {
    "seabed_a": (3.0, 1.6),   # gravel
    "seabed_b": (4.5, 1.6),   # moon (rocky craters)
    "algae": (1.2, 1.6),      # grass
    "rock": (0.8, 2.0),       # moon
    "gravel": (1.0, 1.5),     # gravel
    "coffee": (1.0, 1.3),
    "astronaut": (1.0, 1.2),
    "coral": (0.5, 1.6),      # retina (orange-red)
    "cat": (0.7, 1.6),        # chelsea
    "rocket": (1.0, 1.3),
}
OBJECT_MEAN_ALBEDO = 0.3


def default_objects(seabed: Seabed) -> list[SceneObject]:
    """The demo layout: three balls, two boxes, seven half-buried rocks and twenty pebbles in a
    ~9 x 5 m patch."""

    def on_ground(x: float, y: float, lift: float) -> tuple[float, float, float]:
        return (x, y, float(seabed.height(np.array(x), np.array(y))) + lift)

    deg = math.pi / 180.0
    return [
        Ellipsoid("ball_coffee", on_ground(0.0, 0.0, 0.40), (0.45, 0.45, 0.45), 0.0, "coffee"),
        Ellipsoid("ball_astronaut", on_ground(1.3, -0.9, 0.27), (0.32,) * 3, 30 * deg,
                  "astronaut"),
        Ellipsoid("ball_coral", on_ground(-1.1, -1.0, 0.22), (0.28,) * 3, 0.0, "coral"),
        Box("crate", on_ground(-1.0, 1.0, 0.22), (0.45, 0.30, 0.25), 25 * deg, "cat"),
        Box("block", on_ground(2.6, 0.8, 0.16), (0.30, 0.30, 0.20), -15 * deg, "rocket"),
        Ellipsoid("rock_1", on_ground(1.1, 1.2, 0.05), (0.50, 0.35, 0.30), 40 * deg, "algae",
                  (0.75, 0.95, 0.6)),
        Ellipsoid("rock_2", on_ground(-2.4, 0.3, 0.0), (0.60, 0.45, 0.35), -20 * deg, "rock",
                  (0.9, 0.85, 0.8)),
        Ellipsoid("rock_3", on_ground(2.8, -0.9, 0.02), (0.40, 0.30, 0.25), 70 * deg, "gravel",
                  (0.8, 0.75, 0.65)),
        Ellipsoid("rock_4", on_ground(-3.2, -0.8, 0.0), (0.45, 0.50, 0.30), 10 * deg, "algae",
                  (0.7, 0.9, 0.55)),
        Ellipsoid("rock_5", on_ground(0.3, -2.0, 0.0), (0.55, 0.35, 0.28), -35 * deg, "rock",
                  (0.85, 0.8, 0.75)),
        Ellipsoid("rock_6", on_ground(3.9, 0.1, 0.0), (0.50, 0.40, 0.32), 55 * deg, "gravel",
                  (0.85, 0.8, 0.7)),
        Ellipsoid("rock_7", on_ground(-3.9, 1.0, 0.02), (0.40, 0.35, 0.30), 0.0, "rock",
                  (0.8, 0.8, 0.85)),
    ] + _pebbles(seabed)


def _pebbles(seabed: Seabed, count: int = 20) -> list[SceneObject]:
    """Small stones and shells scattered between the big objects (a fixed layout)."""
    rng = np.random.default_rng(1234)
    keep_clear = [(0.0, 0.0, 0.8), (1.3, -0.9, 0.6), (-1.1, -1.0, 0.5), (-1.0, 1.0, 0.8),
                  (2.6, 0.8, 0.6), (1.1, 1.2, 0.7), (-2.4, 0.3, 0.8), (2.8, -0.9, 0.6),
                  (-3.2, -0.8, 0.7), (0.3, -2.0, 0.7), (3.9, 0.1, 0.7), (-3.9, 1.0, 0.6)]
    textures = ("gravel", "coral", "rock", "algae")
    pebbles: list[SceneObject] = []
    while len(pebbles) < count:
        x, y = rng.uniform(-4.5, 4.5), rng.uniform(-2.5, 2.5)
        if any(math.hypot(x - cx, y - cy) < r for cx, cy, r in keep_clear):
            continue
        keep_clear.append((x, y, 0.35))
        rx = rng.uniform(0.07, 0.16)
        radii = (rx, rx * rng.uniform(0.6, 1.0), rx * rng.uniform(0.4, 0.7))
        z = float(seabed.height(np.array(x), np.array(y))) + 0.2 * radii[2]
        tint = tuple(float(v) for v in rng.uniform(0.7, 1.2, 3))
        pebbles.append(Ellipsoid(f"pebble_{len(pebbles) + 1}", (x, y, z), radii,
                                 rng.uniform(0.0, math.pi), textures[len(pebbles) % 4], tint))
    return pebbles


def build_dive_scene(textures_srgb: Mapping[str, np.ndarray] | None = None, seed: int = 0,
                     seabed: Seabed | None = None, objects: Sequence[SceneObject] | None = None
                     ) -> Scene:
    """The demo scene. ``textures_srgb`` maps texture names of :data:`TEXTURE_LAYOUT` to sRGB
    ``uint8`` images; missing ones (and unknown names used by ``objects``) get fractal noise
    seeded by ``seed``. ``objects=None`` gives :func:`default_objects`."""
    seabed = Seabed() if seabed is None else seabed
    objects = default_objects(seabed) if objects is None else list(objects)
    return Scene(seabed=seabed, objects=objects,
                 textures=scene_textures(textures_srgb, objects, seed))


def scene_textures(textures_srgb: Mapping[str, np.ndarray] | None, objects: Sequence[SceneObject],
                   seed: int) -> dict[str, Texture]:
    """Every texture of :data:`TEXTURE_LAYOUT` and of ``objects``, from ``textures_srgb`` (sRGB
    ``uint8`` images by name) or, where missing, fractal noise seeded by ``seed``; plus the
    seabed's procedural cobbles and low-frequency variation."""
    rng = np.random.default_rng(seed)
    textures_srgb = dict(textures_srgb or {})
    names = set(TEXTURE_LAYOUT) | {o.texture for o in objects}
    textures = {}
    for name in sorted(names):
        image = textures_srgb.get(name)
        if image is None:
            image = procedural_texture_srgb(rng, colour=name not in ("seabed_a", "seabed_b"))
        width_m, contrast = TEXTURE_LAYOUT.get(name, (1.0, 1.0))
        texture = texture_from_srgb(image, width_m)
        mean = texture.image.mean(axis=(0, 1))
        albedo = mean + contrast * (texture.image - mean)
        if not name.startswith("seabed"):
            albedo *= OBJECT_MEAN_ALBEDO / max(float(mean.mean()), 1e-3)
        textures[name] = Texture(np.clip(albedo, 0.0, 1.0).astype(np.float32), texture.texel_m)
    textures["seabed_pebbles"] = Texture(pebble_texture(rng), texel_m=12.0 / 2048)
    # Low-frequency fractal noise breaks up the tiling of the seabed textures.
    for name, width_m in (("seabed_mix", 12.0), ("seabed_patches", 30.0)):
        textures[name] = Texture(
            image=np.repeat(fractal_noise_image(rng, 128, exponent=2.0), 3, axis=2),
            texel_m=width_m / 128)
    return textures


def cast_rays(scene: Scene, origins: np.ndarray, dirs: np.ndarray, include_seabed: bool = True,
              candidates: Sequence[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """First hit of each ray. ``origins`` (N, 3) or one shared origin (3,), unit ``dirs``
    (N, 3), float64. ``candidates`` optionally lists, per object, the indices of the rays that
    may hit it (a superset, from a coarse culling pass); otherwise every ray is culled against
    every object's bounding sphere.

    Returns ``(t, index)``: range (N,) (``inf`` for no hit) and the hit surface (N,) int:
    the object's index in ``scene.objects``, :data:`SEABED` or :data:`NO_HIT`.
    """
    n = dirs.shape[0]
    shared = origins.ndim == 1
    index = np.full(n, NO_HIT, dtype=np.int64)
    if include_seabed:
        t_best = scene.seabed.intersect(origins, dirs)
        index[np.isfinite(t_best)] = SEABED
    else:
        t_best = np.full(n, np.inf)
    for i, obj in enumerate(scene.objects):
        if candidates is not None:
            near = candidates[i]
        else:
            radius = obj.bounding_radius()
            to_centre = np.asarray(obj.centre) - origins
            if shared:
                along = dirs @ to_centre
                dist2 = to_centre @ to_centre - along * along
            else:
                along = np.einsum("ij,ij->i", dirs, to_centre)
                dist2 = np.einsum("ij,ij->i", to_centre, to_centre) - along * along
            near = np.flatnonzero((dist2 <= radius * radius) & (along > -radius))
        if near.size == 0:
            continue
        t = obj.intersect(origins if shared else origins[near], dirs[near])
        closer = t < t_best[near]
        t_best[near[closer]] = t[closer]
        index[near[closer]] = i
    return t_best, index


def _points_in_discs(points: np.ndarray, discs: Sequence[tuple[float, float, float]],
                     cell: float = 0.25) -> list[np.ndarray]:
    """For each disc (x, y, radius), the indices of the 2-D ``points`` (N, 2) in the grid cells
    its bounding box touches: a cheap superset of the points inside it."""
    ij = np.floor(points / cell).astype(np.int64)
    low = ij.min(axis=0)
    high = ij.max(axis=0) - low
    ij -= low
    key = ij[:, 0] * (high[1] + 1) + ij[:, 1]
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    result = []
    for x, y, r in discs:
        i0, i1 = (int(math.floor((v / cell))) - int(low[0]) for v in (x - r, x + r))
        j0, j1 = (int(math.floor((v / cell))) - int(low[1]) for v in (y - r, y + r))
        i0, i1 = max(i0, 0), min(i1, int(high[0]))
        j0, j1 = max(j0, 0), min(j1, int(high[1]))
        if i0 > i1 or j0 > j1:
            result.append(np.zeros(0, np.int64))
            continue
        rows = np.arange(i0, i1 + 1) * (high[1] + 1)
        starts = np.searchsorted(sorted_key, rows + j0, side="left")
        ends = np.searchsorted(sorted_key, rows + j1, side="right")
        result.append(np.concatenate([order[s:e] for s, e in zip(starts, ends)]))
    return result


def _shadow_candidates(scene: Scene, points: np.ndarray) -> list[np.ndarray]:
    """Per object, the points whose ray towards the (distant) light may pass through it.

    Every shadow ray has direction l; sliding each point along l to height 0 gives a 2-D
    point q. A ray within R of the object's centre c crosses height c_z within
    R (1 + |l_xy| / l_z) horizontally of c, i.e. q lies in a disc around c_xy - l_xy c_z / l_z.
    """
    light = scene.light_dir
    slope = light[:2] / light[2]
    q = points[:, :2] - points[:, 2:3] * slope
    spread = 1.0 + float(np.linalg.norm(slope))
    discs = [(obj.centre[0] - slope[0] * obj.centre[2], obj.centre[1] - slope[1] * obj.centre[2],
              obj.bounding_radius() * spread) for obj in scene.objects]
    return _points_in_discs(q, discs)


def _view_candidates(scene: Scene, origin: np.ndarray, dirs: np.ndarray, tile: int = 8
                     ) -> list[np.ndarray]:
    """Per object, the rays of a view (``dirs`` (H, W, S, 3), one ``origin``) that may hit it,
    flat indices into ``dirs.reshape(-1, 3)``: the rays of every tile of tile x tile pixels
    whose cone of directions overlaps the object's bounding cone."""
    h, w, s, _ = dirs.shape
    th, tw = -(-h // tile), -(-w // tile)
    flat_index = np.arange(h * w * s).reshape(h, w, s)
    pad = ((0, th * tile - h), (0, tw * tile - w), (0, 0))
    # Pad edge tiles with copies of edge rays (for their cones) marked -1 (not real rays).
    tiles_dirs = np.pad(dirs, pad + ((0, 0),), mode="edge").reshape(th, tile, tw, tile, s, 3)
    tiles_dirs = tiles_dirs.transpose(0, 2, 1, 3, 4, 5).reshape(th * tw, -1, 3)
    tiles_index = np.pad(flat_index, pad, constant_values=-1).reshape(th, tile, tw, tile, s)
    tiles_index = tiles_index.transpose(0, 2, 1, 3, 4).reshape(th * tw, -1)
    axis = tiles_dirs.sum(axis=1)
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    spread = np.arccos(np.clip(np.einsum("tkj,tj->tk", tiles_dirs, axis).min(axis=1), -1, 1))
    result = []
    for obj in scene.objects:
        to_centre = np.asarray(obj.centre) - origin
        distance = float(np.linalg.norm(to_centre))
        radius = obj.bounding_radius()
        if distance <= radius:
            result.append(np.arange(h * w * s))
            continue
        half_angle = math.asin(radius / distance)
        angle = np.arccos(np.clip(axis @ (to_centre / distance), -1.0, 1.0))
        hit_tiles = np.flatnonzero(angle <= half_angle + spread + 1e-9)
        rays = tiles_index[hit_tiles].ravel()
        result.append(rays[rays >= 0])
    return result


def _triplanar(texture: Texture, local: np.ndarray, normal_local: np.ndarray) -> np.ndarray:
    """Triplanar mapping in object coordinates: blend of the three axis projections weighted by
    ``|n|^4``. Opposite faces are offset by half a tile so they do not show mirror images."""
    weights = np.abs(normal_local) ** 4
    weights /= weights.sum(axis=1, keepdims=True)
    h, w = texture.image.shape[:2]
    shift_u, shift_v = 0.5 * w * texture.texel_m, 0.37 * h * texture.texel_m
    result = np.zeros((local.shape[0], 3), np.float32)
    for axis, (a, b) in enumerate(((1, 2), (0, 2), (0, 1))):
        use = weights[:, axis] > 1e-3
        if not np.any(use):
            continue
        back = normal_local[use, axis] < 0
        u = local[use, a] + back * shift_u
        v = -local[use, b] + back * shift_v
        result[use] += weights[use, axis, None] * sample_texture(texture, u, v)
    return result


def _seabed_albedo(scene: Scene, points: np.ndarray) -> np.ndarray:
    x, y = points[:, 0], points[:, 1]
    ca, sa = math.cos(0.52), math.sin(0.52)
    fine = sample_texture(scene.textures["seabed_a"], x, -y)
    coarse = sample_texture(scene.textures["seabed_b"], ca * x - sa * y + 1.7, -(sa * x + ca * y))
    pebbles = sample_texture(scene.textures["seabed_pebbles"], x, y)
    mix = sample_texture(scene.textures["seabed_mix"], x, y)[:, :1]
    mix = np.clip((mix - 0.3) * 2.5, 0.0, 1.0)
    # The non-repeating cobbles carry most of the local detail everywhere (stronger where
    # ``mix`` is high); the tiled photographs add finer grain and sandy variation.
    detail = pebbles ** (0.6 + 0.6 * mix) \
        * (0.6 + 0.4 * fine / max(float(scene.textures["seabed_a"].image.mean()), 1e-3)) \
        * (0.8 + 0.2 * coarse / max(float(scene.textures["seabed_b"].image.mean()), 1e-3))
    patches = 0.65 + 0.7 * sample_texture(scene.textures["seabed_patches"], y, x)[:, :1]
    return np.clip(np.asarray(scene.seabed_tint) * detail * patches * 0.8, 0.0, 1.0)


def _object_albedo(scene: Scene, obj: SceneObject, points: np.ndarray,
                   normals: np.ndarray) -> np.ndarray:
    local = obj.to_local(points)
    normal_local = normals @ _yaw_matrix(obj.yaw)
    albedo = _triplanar(scene.textures[obj.texture], local, normal_local)
    return np.clip(albedo * np.asarray(obj.tint), 0.0, 1.0)


def shade(scene: Scene, origins: np.ndarray, dirs: np.ndarray, t: np.ndarray,
          index: np.ndarray) -> np.ndarray:
    """Clean linear radiance J (N, 3) of the hits from :func:`cast_rays` (same ``origins``,
    ``dirs``); NaN where no hit."""
    radiance = np.full((dirs.shape[0], 3), np.nan)
    hit = index != NO_HIT
    points = (origins if origins.ndim == 1 else origins[hit]) + t[hit, None] * dirs[hit]
    idx = index[hit]
    normals = np.zeros_like(points)
    albedo = np.zeros_like(points)
    order = np.argsort(idx, kind="stable")
    bounds = np.searchsorted(idx[order], np.arange(SEABED, len(scene.objects) + 1))
    for i in range(SEABED, len(scene.objects)):
        sel = order[bounds[i - SEABED]:bounds[i - SEABED + 1]]
        if sel.size == 0:
            continue
        if i == SEABED:
            normals[sel] = scene.seabed.normal(points[sel])
            albedo[sel] = _seabed_albedo(scene, points[sel])
        else:
            obj = scene.objects[i]
            normals[sel] = obj.normal(points[sel])
            albedo[sel] = _object_albedo(scene, obj, points[sel], normals[sel])
    cosine = np.clip(normals @ scene.light_dir, 0.0, None)
    lit = cosine > 0.0
    visible = np.zeros(points.shape[0])
    if np.any(lit) and scene.objects:
        shadow_origins = points[lit] + 1e-5 * normals[lit]
        shadow_dirs = np.broadcast_to(scene.light_dir, shadow_origins.shape)
        t_shadow, _ = cast_rays(scene, shadow_origins, np.ascontiguousarray(shadow_dirs),
                                include_seabed=False,
                                candidates=_shadow_candidates(scene, shadow_origins))
        visible[lit] = np.isinf(t_shadow)
    elif np.any(lit):
        visible[lit] = 1.0
    irradiance = scene.ambient + scene.diffuse * cosine * visible
    radiance[hit] = albedo * irradiance[:, None]
    return radiance


def render_view(scene: Scene, origin: np.ndarray, dirs: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """Clean image and range of one view.

    ``origin`` (3,) camera centre, ``dirs`` (H, W, S, 3) unit ray directions, S subsamples per
    pixel. Returns ``clean`` (H, W, 3) float32 (mean radiance of the subsamples) and ``range``
    (H, W) float32 (mean range of the subsamples, metres). A pixel where any subsample sees
    open water (no surface) is an open-water pixel: range ``+inf`` and clean radiance 0 (there
    is no surface to restore).
    """
    h, w, s, _ = dirs.shape
    flat = np.ascontiguousarray(dirs.reshape(-1, 3), dtype=np.float64)
    origin = np.asarray(origin, np.float64)
    t, index = cast_rays(scene, origin, flat, candidates=_view_candidates(scene, origin, dirs))
    radiance = shade(scene, origin, flat, t, index)
    t = np.where(index == NO_HIT, np.inf, t)
    rng_m = t.reshape(h, w, s).mean(axis=2)
    clean = np.where(np.isfinite(rng_m)[..., None], radiance.reshape(h, w, s, 3).mean(axis=2),
                     0.0)
    return clean.astype(np.float32), rng_m.astype(np.float32)


# --------------------------------------------------------------------------------------------
# Camera paths
# --------------------------------------------------------------------------------------------

def look_at(eye: Sequence[float], target: Sequence[float], roll: float = 0.0) -> np.ndarray:
    """Camera-to-world (4, 4), OpenCV axes (x right, y down, z forward), world z up."""
    eye = np.asarray(eye, np.float64)
    forward = _unit(np.asarray(target, np.float64) - eye)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-9:  # looking straight up or down: any right vector will do
        right = np.array([1.0, 0.0, 0.0]) - forward[0] * forward
    right = right / np.linalg.norm(right)
    down = np.cross(forward, right)
    c, s = math.cos(roll), math.sin(roll)
    right, down = c * right + s * down, -s * right + c * down
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, eye
    return c2w


def orbit_path(scene: Scene, views: int, rng: np.random.Generator, radius: float = 2.5,
               height: float = 2.2, height_variation: float = 0.2) -> np.ndarray:
    """Diver circling ``scene.target`` once at ``radius`` m, ``height`` m above the seabed
    (varying by +-``height_variation``), looking at the target with small aim and roll jitter.
    Returns (views, 4, 4) camera-to-world."""
    target = np.asarray(scene.target)
    poses = []
    for i in range(views):
        angle = 2.0 * math.pi * i / views + rng.uniform(-0.03, 0.03)
        x = target[0] + radius * math.cos(angle)
        y = target[1] + radius * math.sin(angle)
        ground = float(scene.seabed.height(np.array(x), np.array(y)))
        z = ground + height + height_variation * math.sin(2.0 * angle + 0.4)
        aim = target + rng.normal(0.0, 0.05, 3)
        poses.append(look_at((x, y, z), aim, roll=rng.normal(0.0, math.radians(2.0))))
    return np.stack(poses)


def transect_path(scene: Scene, views: int, rng: np.random.Generator, length: float = 6.0,
                  height: float = 1.6, pitch_deg: float = 45.0) -> np.ndarray:
    """Diver swimming along +x at ``height`` m above the seabed (bobbing +-0.1 m), camera
    pitched ``pitch_deg`` below the horizon; the footprint centre sweeps ``length`` m across the
    scene centre with a slow lateral sway, while the diver looks around a little (yaw +-6 deg,
    pitch +-4 deg): pure forward motion over a plane would leave the focal length ambiguous to
    self-calibrating SfM. Returns (views, 4, 4) camera-to-world."""
    reach = height / math.tan(math.radians(pitch_deg))
    poses = []
    for i in range(views):
        frac = i / max(views - 1, 1)
        look_x = scene.target[0] - 0.5 * length + frac * length
        x = look_x - reach
        y = scene.target[1] + 0.3 * math.sin(2.0 * math.pi * frac) + rng.normal(0.0, 0.02)
        ground = float(scene.seabed.height(np.array(x), np.array(y)))
        z = ground + height + 0.1 * math.sin(3.0 * math.pi * frac) + rng.normal(0.0, 0.02)
        yaw = math.radians(6.0) * math.sin(2.0 * math.pi * frac) + rng.normal(0.0, 0.02)
        pitch = math.radians(pitch_deg + 4.0 * math.cos(3.0 * math.pi * frac)) + rng.normal(
            0.0, 0.02)
        forward = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw),
                            -math.sin(pitch)])
        poses.append(look_at((x, y, z), np.array([x, y, z]) + forward,
                             roll=rng.normal(0.0, math.radians(2.0))))
    return np.stack(poses)
