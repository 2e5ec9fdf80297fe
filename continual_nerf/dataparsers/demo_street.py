"""The demo street: a vehicle with three cameras drives down a street between facades (the paper's automotive
setting, like a Waymo segment's front cameras). Each stretch of road is seen during its own time span only; the
front, front-left and front-right cameras (45 degrees apart) see it at every instant."""

from __future__ import annotations

import colorsys
from typing import List, Tuple

import numpy as np

from continual_nerf.dataparsers.demo_scene import (
    Crate,
    Scene,
    checker,
    hue_along,
    look_matrices,
    with_object_moved,
    with_wall_repainted,
)

STREET_MIN = np.array([-40.0, -6.0, 0.0])
STREET_MAX = np.array([40.0, 6.0, 12.0])
"""The street between its facades (y = +-6 m), up to the sky at 12 m."""
LONG_STREET_LENGTH = 400.0
"""Length of the `long-street` scene, metres: five times the street, new facades all the way."""
CAMERA_HEIGHT = 1.8
"""Height of the rig's cameras above the road, metres."""
CAMERA_YAWS = (0.0, 45.0, -45.0)
"""Front, front-left and front-right cameras: yaw from the driving direction, degrees (positive: to the left)."""
CAMERA_PITCH = -4.0
"""Every camera looks this many degrees down."""


def street(rng: np.random.Generator, length: float = STREET_MAX[0] - STREET_MIN[0]) -> Scene:
    """Facades with windows whose colour drifts along the street, a road with lane marks, parked cars, posts and
    bays that stand out from the facades; `length` metres long."""
    lo, hi = street_bounds(length)
    return Scene(
        lo=lo,
        hi=hi,
        crates=_street_objects(rng, lo[0], hi[0]),
        surface=lambda points, axis, positive: _street_colour(points, axis, positive, lo[0], hi[0]),
    )


def street_bounds(length: float) -> Tuple[np.ndarray, np.ndarray]:
    """The corners of a street `length` metres long, centred on the origin."""
    lo, hi = STREET_MIN.copy(), STREET_MAX.copy()
    lo[0], hi[0] = -length / 2, length / 2
    return lo, hi


def _street_colour(points: np.ndarray, axis: np.ndarray, positive: np.ndarray, start: float, end: float) -> np.ndarray:
    """Facades (y walls), road (floor), sky (ceiling) and the street's two ends."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    colour = np.empty_like(points)
    facade = axis == 1
    window = windows(points)
    bands = 0.8 + 0.2 * checker(x, z, 1.25)
    walls = hue_along(x + 3.0 * positive, start, end, 0.45, 0.9) * bands[:, None]
    glass = np.array([0.15, 0.2, 0.3]) + 0.1 * np.sin(x / 3.0)[:, None]
    colour[facade] = np.where(window[:, None], glass, walls)[facade]
    road = (axis == 2) & ~positive
    asphalt = 0.3 + 0.08 * checker(x, y, 2.0)
    kerb = np.abs(y) > 4.5
    dash = (np.abs(y) < 0.1) & ((x % 3.0) < 1.5)
    grey = np.where(dash, 0.9, np.where(kerb, 0.55 + 0.1 * checker(x, y, 0.6), asphalt))
    colour[road] = (grey[:, None] * np.array([1.0, 1.0, 0.97]))[road]
    sky = (axis == 2) & positive
    colour[sky] = (np.array([0.55, 0.7, 0.95]) + 0.05 * np.sin(x / 7.0)[:, None])[sky]
    ends = axis == 0
    colour[ends] = (
        np.where(positive[ends, None], [[0.2, 0.3, 0.8]], [[0.8, 0.3, 0.2]])
        * (0.7 + 0.3 * checker(y, z, 1.0))[ends, None]
    )
    return colour


def windows(points: np.ndarray) -> np.ndarray:
    """Which of the facades' points (N, 3) are windows."""
    x, z = points[:, 0], points[:, 2]
    return ((x % 2.5) > 0.6) & ((x % 2.5) < 1.9) & ((z % 3.0) > 0.9) & ((z % 3.0) < 2.4) & (z > 2.5)


MOVE_DISTANCE = 4.5
"""How far the street's moved car goes along the kerb, metres: half the spacing of the parked cars."""
REPAINTED_LENGTH = 12.0
"""Length of the street's repainted stretch of facade, metres."""
CAR_Y = 3.8
"""Distance of the parked cars' centres from the street's middle, metres."""


def with_car_moved(scene: Scene) -> Scene:
    """`scene` with the parked car on the left kerb (+y) nearest the middle of the street moved along it."""
    cars = [i for i, c in enumerate(scene.crates) if abs((c.lo[1] + c.hi[1]) / 2 - CAR_Y) < 1e-6]
    return with_object_moved(scene, MOVE_DISTANCE, cars)


def with_facade_repainted(scene: Scene) -> Scene:
    """`scene` with a stretch of the left (+y) facade, about the middle of the street, painted over (not its
    windows)."""
    return with_wall_repainted(scene, REPAINTED_LENGTH, keep=windows)


def _street_objects(rng: np.random.Generator, start: float, end: float) -> List[Crate]:
    """Parked cars along both kerbs, posts on the pavements and bays standing out from the facades."""
    objects = []
    for side in (1.0, -1.0):
        for x in np.arange(start + 4.0, end - 4.0, 9.0) + rng.uniform(-2.0, 2.0):
            size = np.array([rng.uniform(3.6, 4.6), 1.8, rng.uniform(1.3, 1.7)])
            objects.append(_box(x, side * 3.8, size, colorsys.hsv_to_rgb(rng.uniform(), 0.6, 0.85)))
        for x in np.arange(start + 8.0, end - 6.0, 12.0) + rng.uniform(-3.0, 3.0):
            objects.append(_box(x, side * 5.3, np.array([0.3, 0.3, 4.5]), (0.25, 0.25, 0.28)))
        for x in np.arange(start + 10.0, end - 10.0, 16.0) + rng.uniform(-4.0, 4.0):
            size = np.array([rng.uniform(3.0, 6.0), 0.8, rng.uniform(6.0, 11.0)])
            objects.append(_box(x, side * 5.6, size, colorsys.hsv_to_rgb(rng.uniform(), 0.3, 0.75)))
    return objects


def _box(x: float, y: float, size: np.ndarray, rgb: Tuple[float, float, float]) -> Crate:
    lo = np.array([x - size[0] / 2, y - size[1] / 2, 0.0])
    return Crate(lo=lo, hi=lo + size, rgb=np.array(rgb))


def rig_path(
    num_instants: int, rng: np.random.Generator, length: float = STREET_MAX[0] - STREET_MIN[0]
) -> Tuple[np.ndarray, np.ndarray]:
    """Camera-to-world matrices (3 * num_instants, 3, 4) of the rig driving down a street `length` metres long, OpenGL
    convention, in capture order (front, front-left, front-right at each instant), and the instant of each image."""
    t = np.linspace(0.0, 1.0, num_instants)
    phase = rng.uniform(0, 2 * np.pi, size=2)
    laps = length / (STREET_MAX[0] - STREET_MIN[0])  # the same weave per metre on a longer street
    lo, hi = street_bounds(length)
    x = lo[0] + 8.0 + t * (hi[0] - lo[0] - 16.0)  # the street's ends stay ahead and behind
    y = -1.8 + 0.25 * np.sin(2 * np.pi * 1.5 * laps * t + phase[0])
    heading = 0.04 * np.sin(2 * np.pi * 2 * laps * t + phase[1])
    positions = np.stack([x, y, np.full_like(x, CAMERA_HEIGHT)], axis=-1)
    cameras = [
        look_matrices(positions, heading + np.deg2rad(yaw), np.full_like(x, np.deg2rad(CAMERA_PITCH)))
        for yaw in CAMERA_YAWS
    ]
    poses = np.stack(cameras, axis=1).reshape(-1, 3, 4)
    return poses, np.repeat(np.arange(num_instants), len(CAMERA_YAWS))
