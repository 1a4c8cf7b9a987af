"""Procedural dive scene: the seabed and objects (``seathru.sim.shapes``) with their textures
(``seathru.sim.textures``) and one light, exact ray casting through all of them, and shading.

Ray casting returns the range ``t``: the Euclidean distance from the ray origin to the first
surface along the *unit* ray direction (``inf`` for a ray that meets nothing: open water).

Clean radiance ``J`` (linear RGB) is Lambertian and view independent: texture albedo times
``ambient + diffuse * max(0, n . l) * visibility`` for one distant downwelling light ``l``
(hard shadows are cast by the objects). Lambertian shading keeps every surface point the same
colour in every view, which both SfM and the NeRF assume. The camera paths are in
``seathru.sim.camera_paths`` and ``seathru.sim.reef``. This module does no file I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from seathru.sim.shapes import Box, Ellipsoid, SceneObject, Seabed, yaw_matrix
from seathru.sim.textures import (Texture, fractal_noise_image, pebble_texture,
                                  procedural_texture_srgb, sample_texture, texture_from_srgb)

NO_HIT = -2
SEABED = -1


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
    normal_local = normals @ yaw_matrix(obj.yaw)
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


def render_subsamples(scene: Scene, origin: np.ndarray, dirs: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Clean radiance and range of every subsample of one view, before the pixel averages them.

    ``origin`` (3,) camera centre, ``dirs`` (H, W, S, 3) unit ray directions, S subsamples per
    pixel. Returns ``radiance`` (H, W, S, 3) float64 (0 where a subsample sees open water) and
    ``range`` (H, W, S) float64 (metres; ``+inf`` = open water), for the water to act on
    each ray at its own range (``seathru.sim.dive.subsampled_water_image``).
    """
    h, w, s, _ = dirs.shape
    flat = np.ascontiguousarray(dirs.reshape(-1, 3), dtype=np.float64)
    origin = np.asarray(origin, np.float64)
    t, index = cast_rays(scene, origin, flat, candidates=_view_candidates(scene, origin, dirs))
    radiance = shade(scene, origin, flat, t, index)
    t = np.where(index == NO_HIT, np.inf, t)
    return radiance.reshape(h, w, s, 3), t.reshape(h, w, s)


def pixel_means(radiance: np.ndarray, range_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The clean image and range map of subsamples from :func:`render_subsamples`: ``clean``
    (H, W, 3) float32, the mean radiance of the subsamples, and ``range`` (H, W) float32, their
    mean range. A pixel where any subsample sees open water (no surface) is an open-water pixel:
    range ``+inf`` and clean radiance 0 (there is no surface to restore)."""
    rng_m = range_m.mean(axis=2)
    clean = np.where(np.isfinite(rng_m)[..., None], radiance.mean(axis=2), 0.0)
    return clean.astype(np.float32), rng_m.astype(np.float32)


def render_view(scene: Scene, origin: np.ndarray, dirs: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """Clean image and range of one view: :func:`pixel_means` of :func:`render_subsamples`.

    ``origin`` (3,) camera centre, ``dirs`` (H, W, S, 3) unit ray directions. Returns ``clean``
    (H, W, 3) float32 and ``range`` (H, W) float32 (metres, ``+inf`` = open water).
    """
    return pixel_means(*render_subsamples(scene, origin, dirs))
