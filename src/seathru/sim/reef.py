"""A reef slope with open water above it, and the ``survey`` camera path along it.

The scene: the seabed rises towards +y as a reef slope (``REEF_SLOPE_DEG``) up to a rounded crest
(``REEF_CREST_M`` from the origin), beyond which the reef top is flat. A wall of tall coral heads
stands on the crest and rises into the open water; smaller heads, the demo's textured balls and
boxes and a slender head beside the diver's track are scattered over the slope.

The path (:func:`survey_path`): a diver swims along the slope's contour, downslope of the crest
and about a metre above the seabed, looking obliquely up and across the slope. The seabed and
the objects fill the lower part of every frame, at ranges from about half a metre (a slender
head beside the start of the track) to 20-50 m (the slope far ahead, seen at a grazing angle
just below the crest line); above the crest line the rays meet nothing: open water to infinity,
4-40 % of each frame. Looking up the slope bounds every seabed range (every ray of the frame
points at least ~5 deg up the slope, so it meets the crest within ~50 m), so there is no far
floor and no edge to the world. The diver sways, bobs and looks around a little: without
rotation self-calibrating SfM confuses the focal length (and then mirrors the reconstruction).

Pure numpy, no file I/O.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from seathru.sim.camera_paths import look_at
from seathru.sim.scene import Scene, scene_textures
from seathru.sim.shapes import Box, Ellipsoid, SceneObject, Seabed

REEF_SLOPE_DEG = 25.0
REEF_CREST_M = 3.0     # crest line: y = 3 m, about 1.4 m above the seabed at the origin
SURVEY_DOWNSLOPE_M = 4.5  # the diver's track: this far downslope of the crest (y = -1.5 m)
CORAL_TEXTURES = ("coral", "algae", "rock", "gravel")


def reef_seabed(amplitude: float) -> Seabed:
    """The reef slope, rising towards +y, with waves of ``amplitude`` m on it."""
    return Seabed(amplitude=amplitude, slope=math.tan(math.radians(REEF_SLOPE_DEG)),
                  slope_direction=math.pi / 2, crest=REEF_CREST_M, crest_width=0.8)


def reef_objects(seabed: Seabed) -> list[SceneObject]:
    """The demo's textured balls and boxes on the slope, a wall of tall coral heads along the
    crest, smaller heads over the slope and a slender head beside the survey track (a fixed
    layout)."""

    def seated(x: float, y: float, radii: tuple[float, float, float]
               ) -> tuple[float, float, float]:
        # Sunk by a third of the height and by the drop of the slope under the object, so its
        # downslope side rests on the seabed.
        ground = float(seabed.height(np.array(x), np.array(y)))
        return (x, y, ground + 0.35 * radii[2] - 0.5 * seabed.slope * max(radii[:2]))

    deg = math.pi / 180.0
    objects: list[SceneObject] = [
        Ellipsoid("ball_coffee", seated(0.0, 0.4, (0.45,) * 3), (0.45,) * 3, 0.0, "coffee"),
        Ellipsoid("ball_astronaut", seated(2.3, 1.1, (0.35,) * 3), (0.35,) * 3, 30 * deg,
                  "astronaut"),
        Ellipsoid("ball_coral", seated(-2.1, 0.1, (0.3,) * 3), (0.3,) * 3, 0.0, "coral"),
        Box("crate", seated(-3.9, 1.3, (0.45, 0.3, 0.5)), (0.45, 0.3, 0.5), 25 * deg, "cat"),
        Box("block", seated(4.3, 0.3, (0.3, 0.3, 0.4)), (0.3, 0.3, 0.4), -15 * deg, "rocket"),
    ]
    rng = np.random.default_rng(2024)

    def tint() -> tuple[float, float, float]:
        return tuple(float(v) for v in rng.uniform(0.7, 1.2, 3))  # type: ignore[return-value]

    # The wall: tall heads along the crest, standing out against the open water.
    for i, x in enumerate(np.arange(-10.0, 10.01, 1.25)):
        radii = (rng.uniform(0.35, 0.6), rng.uniform(0.35, 0.6), rng.uniform(0.6, 1.2))
        y = REEF_CREST_M + rng.uniform(-0.6, 0.4)
        objects.append(Ellipsoid(f"head_{i + 1}", seated(float(x + rng.uniform(-0.3, 0.3)), y,
                                                         radii), radii, rng.uniform(0, math.pi),
                                 CORAL_TEXTURES[i % 4], tint()))
    # Smaller heads over the slope, clear of the objects placed so far.
    keep_clear = [(o.centre[0], o.centre[1], 0.6 + max(o.radii if isinstance(o, Ellipsoid)
                                                       else o.half_size[:2])) for o in objects]
    count = 0
    while count < 40:
        x, y = rng.uniform(-7.0, 7.0), rng.uniform(-0.9, 2.4)
        if any(math.hypot(x - cx, y - cy) < r for cx, cy, r in keep_clear):
            continue
        r = rng.uniform(0.15, 0.4)
        radii = (r, r * rng.uniform(0.7, 1.0), r * rng.uniform(0.6, 1.3))
        keep_clear.append((x, y, r + 0.4))
        objects.append(Ellipsoid(f"coral_{count + 1}", seated(x, y, radii), radii,
                                 rng.uniform(0, math.pi), CORAL_TEXTURES[count % 4], tint()))
        count += 1
    # One slender head just upslope of the start of the track, rising to the diver's height:
    # the nearest surface of the dive (~0.5 m) as the diver swims past it. (More of them hide
    # too much of the frames for SfM.)
    radii = (0.2, 0.16, 0.8)
    objects.append(Ellipsoid("pillar", seated(-1.2, REEF_CREST_M - SURVEY_DOWNSLOPE_M + 0.6,
                                              radii), radii, 0.4, "rock", tint()))
    return objects


def build_reef_scene(textures_srgb: Mapping[str, np.ndarray] | None = None, seed: int = 0,
                     seabed_amplitude: float = 0.08) -> Scene:
    """The reef-slope scene (see the module docstring); textures as
    :func:`seathru.sim.scene.build_dive_scene`.

    Example::

        scene = build_reef_scene({}, seed=0)
        poses = survey_path(scene, 24, np.random.default_rng(0))
    """
    seabed = reef_seabed(seabed_amplitude)
    objects = reef_objects(seabed)
    return Scene(seabed=seabed, objects=objects,
                 textures=scene_textures(textures_srgb, objects, seed),
                 target=(0.0, REEF_CREST_M - SURVEY_DOWNSLOPE_M, 0.0))


def survey_path(scene: Scene, views: int, rng: np.random.Generator, length: float = 3.5,
                downslope: float = SURVEY_DOWNSLOPE_M, height: float = 1.2,
                yaw_deg: float = 48.0, pitch_deg: float = -3.0, sway: float = 0.25,
                bob: float = 0.15, look_around_deg: tuple[float, float] = (10.0, 6.0)
                ) -> np.ndarray:
    """Diver swimming ``length`` m along the contour of ``scene``'s reef slope (centred on
    ``scene.target``), ``downslope`` m below the crest line and ``height`` m above the seabed
    (bobbing +-``bob`` m, swaying +-``sway`` m across the slope), looking ``yaw_deg`` up the
    slope from the swimming direction and ``pitch_deg`` above the horizon, and looking around a
    little (yaw, pitch +-``look_around_deg``) so that self-calibrating SfM sees the focal
    length. Returns (views, 4, 4) camera-to-world, OpenCV axes.
    """
    seabed = scene.seabed
    up_slope = np.array([math.cos(seabed.slope_direction), math.sin(seabed.slope_direction)])
    along = np.array([up_slope[1], -up_slope[0]])  # the contour, up-slope on the left
    heading = math.atan2(along[1], along[0])
    start = float(np.asarray(scene.target[:2]) @ along) - 0.5 * length
    look_yaw, look_pitch = (math.radians(v) for v in look_around_deg)
    poses = []
    for i in range(views):
        frac = i / max(views - 1, 1)
        across = seabed.crest - downslope + sway * math.sin(2.0 * math.pi * frac) \
            + rng.normal(0.0, 0.02)
        x, y = (start + frac * length) * along + across * up_slope
        ground = float(seabed.height(np.array(x), np.array(y)))
        z = ground + height + bob * math.sin(3.0 * math.pi * frac) + rng.normal(0.0, 0.02)
        yaw = heading + math.radians(yaw_deg) + look_yaw * math.sin(2.0 * math.pi * frac + 0.5) \
            + rng.normal(0.0, 0.02)
        pitch = math.radians(pitch_deg) + look_pitch * math.cos(3.0 * math.pi * frac) \
            + rng.normal(0.0, 0.02)
        forward = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw),
                            math.sin(pitch)])
        poses.append(look_at((x, y, z), np.array([x, y, z]) + forward,
                             roll=rng.normal(0.0, math.radians(2.0))))
    return np.stack(poses)
