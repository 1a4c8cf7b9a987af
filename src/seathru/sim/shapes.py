"""The simulated dive's surfaces, each with a closed-form or exact ray intersection: the seabed
(a height field, optionally a reef slope) and the objects on it (ellipsoids and boxes), each
rotated about the vertical.

World frame: metres, z up. The seabed is the gently undulating height field ``z = h(x, y)``
(a sum of three sinusoids, amplitude a few centimetres; ``amplitude=0`` gives the flat plane
``z = base``), optionally on a reef slope that levels off at a crest (``Seabed.slope``; the
reef scene and its survey path are in ``seathru.sim.reef``). Planes, ellipsoids and boxes are
intersected in closed form. The undulating seabed is intersected by Lipschitz-bounded sphere
tracing (steps never overshoot the first root, because ``|grad h|`` is bounded) followed by
Newton polishing, which reaches the root to ~1e-9 m: exact for every practical purpose.
``intersect`` returns the range along *unit* ray directions, ``inf`` for a miss. No file I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MAX_SEABED_RANGE_M = 1000.0  # a reef slope seen beyond this range counts as open water


def yaw_matrix(yaw: float) -> np.ndarray:
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
        return (points - np.asarray(self.centre)) @ yaw_matrix(self.yaw)

    def bounding_radius(self) -> float:
        return max(self.radii)

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Range (N,) along unit ``dirs`` (N, 3) from ``origins`` (N, 3) or (3,); inf = miss."""
        radii = np.asarray(self.radii)
        o = self.to_local(origins) / radii
        d = (dirs @ yaw_matrix(self.yaw)) / radii
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
        n = local @ yaw_matrix(self.yaw).T
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
        return (points - np.asarray(self.centre)) @ yaw_matrix(self.yaw)

    def bounding_radius(self) -> float:
        return float(np.linalg.norm(self.half_size))

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Range (N,) along unit ``dirs`` (N, 3) from ``origins`` (N, 3) or (3,); inf = miss."""
        half = np.asarray(self.half_size)
        o = self.to_local(origins)
        d = dirs @ yaw_matrix(self.yaw)
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
        return n_local @ yaw_matrix(self.yaw).T


SceneObject = Ellipsoid | Box
