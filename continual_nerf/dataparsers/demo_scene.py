"""Procedural textured scenes and an exact ray caster for them (numpy only): the demo room and the demo street.

Room: one camera walks along a corridor-room's long axis looking at one side wall, so consecutive tasks see
overlapping, and distant tasks disjoint, parts of the scene: the setting in which a NeRF trained task by task
forgets. Street: a vehicle drives down a street between facades with three cameras (front, front-left,
front-right), so each stretch of road is seen during its own time span only, by several cameras at each instant.
Poses are exact; colours come from analytic textures.
"""

from __future__ import annotations

import colorsys
import dataclasses
from dataclasses import dataclass
from typing import Callable, List, Optional

import numpy as np

ROOM_MIN = np.array([-10.0, -2.5, 0.0])
ROOM_MAX = np.array([10.0, 2.5, 3.0])
EYE_HEIGHT = 1.5
ROOMS = 4
"""Rooms in a row in the `rooms` scene, each as long as the room, joined by doorways the camera walks through."""
DOOR_Y = (-1.7, -0.1)
"""The doorways' extent across the rooms (the camera walks at y = -0.9 +- 0.3) and their height, metres."""
DOOR_HEIGHT = 2.2
WALL_THICKNESS = 0.2


@dataclass(frozen=True)
class Crate:
    """An axis-aligned box standing on the floor."""

    lo: np.ndarray
    hi: np.ndarray
    rgb: np.ndarray


SurfaceColour = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
"""Colour of a scene's bounding box seen from inside, at hit points (N, 3), given the axis hit and its side."""
SurfaceMask = Callable[[np.ndarray], np.ndarray]
"""Which hit points (N, 3) of a surface are of one kind (the street's windows)."""


@dataclass(frozen=True)
class Scene:
    """A box seen from inside (walls, floor, ceiling or sky) with boxes standing in it."""

    lo: np.ndarray
    """Lower corner of the bounding box, metres."""
    hi: np.ndarray
    """Upper corner of the bounding box, metres."""
    crates: List[Crate]
    """Boxes inside the scene."""
    surface: SurfaceColour
    """Texture of the bounding box's inside."""


def room(rng: np.random.Generator) -> Scene:
    """The corridor-room: textured walls whose colour drifts along the room, crates along both long walls."""
    return Scene(lo=ROOM_MIN, hi=ROOM_MAX, crates=make_crates(rng), surface=room_colour(ROOM_MIN[0], ROOM_MAX[0]))


def rooms(rng: np.random.Generator) -> Scene:
    """ROOMS corridor-rooms in a row, joined by doorways: the walls' colour drifts over all of them, so no two rooms
    look alike, and each room has its own crates."""
    length = ROOM_MAX[0] - ROOM_MIN[0]
    hi = ROOM_MAX + np.array([(ROOMS - 1) * length, 0.0, 0.0])
    crates = [crate for i in range(ROOMS) for crate in make_crates(rng, start=ROOM_MIN[0] + i * length)]
    for i in range(1, ROOMS):
        crates += _partition(ROOM_MIN[0] + i * length)
    return Scene(lo=ROOM_MIN, hi=hi, crates=crates, surface=room_colour(ROOM_MIN[0], hi[0]))


def _partition(x: float) -> List[Crate]:
    """A wall across the rooms at `x` with a doorway: two wall pieces beside it and a lintel above it."""
    grey = np.array([0.82, 0.8, 0.76])
    lo_x, hi_x = x - WALL_THICKNESS / 2, x + WALL_THICKNESS / 2
    pieces = [
        ((lo_x, ROOM_MIN[1], 0.0), (hi_x, DOOR_Y[0], ROOM_MAX[2])),
        ((lo_x, DOOR_Y[1], 0.0), (hi_x, ROOM_MAX[1], ROOM_MAX[2])),
        ((lo_x, DOOR_Y[0], DOOR_HEIGHT), (hi_x, DOOR_Y[1], ROOM_MAX[2])),
    ]
    return [Crate(lo=np.array(lo), hi=np.array(hi), rgb=grey) for lo, hi in pieces]


def make_crates(rng: np.random.Generator, count: int = 14, start: float = ROOM_MIN[0]) -> list[Crate]:
    """Crates spread along both long walls of the room that starts at x = `start`, each with its own colour."""
    crates = []
    length = ROOM_MAX[0] - ROOM_MIN[0]
    for i, x in enumerate(np.linspace(start + 1.0, start + length - 1.0, count)):
        side = 1.0 if i % 2 == 0 else -1.0
        size = rng.uniform([0.4, 0.4, 0.4], [0.9, 0.8, 1.6])
        y_wall = ROOM_MAX[1] if side > 0 else ROOM_MIN[1]
        y_centre = y_wall - side * (size[1] / 2 + rng.uniform(0.05, 0.6))
        lo = np.array([x + rng.uniform(-0.4, 0.4) - size[0] / 2, y_centre - size[1] / 2, 0.0])
        hue = rng.uniform(0.0, 1.0)
        crates.append(Crate(lo=lo, hi=lo + size, rgb=np.array(colorsys.hsv_to_rgb(hue, 0.7, 0.9))))
    return crates


def camera_path(num_frames: int, rng: np.random.Generator, num_rooms: int = 1) -> np.ndarray:
    """Camera-to-world matrices (num_frames, 3, 4), OpenGL convention, in capture order: a walk along `num_rooms`
    rooms in a row, forward only, looking at the left wall and swaying as in one room."""
    t = np.linspace(0.0, 1.0, num_frames)
    x = ROOM_MIN[0] + 1.5 + t * (num_rooms * (ROOM_MAX[0] - ROOM_MIN[0]) - 3.0)
    phase = rng.uniform(0, 2 * np.pi, size=3)
    y = -0.9 + 0.3 * np.sin(2 * np.pi * 2 * num_rooms * t + phase[0])
    z = EYE_HEIGHT + 0.15 * np.sin(2 * np.pi * 3 * num_rooms * t + phase[1])
    yaw = np.pi / 2 + np.deg2rad(30.0) * np.sin(2 * np.pi * 4 * num_rooms * t + phase[2])
    pitch = np.deg2rad(-12.0 + 6.0 * np.sin(2 * np.pi * 5 * num_rooms * t))
    return look_matrices(np.stack([x, y, z], axis=-1), yaw, pitch)


def look_matrices(positions: np.ndarray, yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """Camera-to-world matrices (N, 3, 4), OpenGL convention, of cameras at `positions` looking along yaw (from +x
    towards +y) and pitch (up from the horizon), radians, with no roll (z is up)."""
    forward = np.stack([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)], axis=-1)
    right = np.cross(forward, np.array([0.0, 0.0, 1.0]))
    right /= np.linalg.norm(right, axis=-1, keepdims=True)
    up = np.cross(right, forward)
    return np.stack([right, up, -forward, positions], axis=-1)


def checker(u: np.ndarray, v: np.ndarray, period: float) -> np.ndarray:
    return ((np.floor(u / period) + np.floor(v / period)) % 2).astype(np.float64)


def hue_along(x: np.ndarray, start: float, end: float, saturation: float, value: float) -> np.ndarray:
    """Colour that drifts with the position x from start to end, so tasks differ in colour too."""
    return hsv_to_rgb((x - start) / (end - start) * 0.85, saturation, value)


def hsv_to_rgb(hue: np.ndarray, saturation: float, value: float) -> np.ndarray:
    """colorsys.hsv_to_rgb over an array of hues (..., 3): the same arithmetic, so the same colours to the last bit."""
    scaled = hue * 6.0
    sector = np.floor(scaled)  # colorsys truncates; the hues here are never negative
    f = scaled - sector
    p = np.full_like(hue, value * (1.0 - saturation))
    q = value * (1.0 - saturation * f)
    t = value * (1.0 - saturation * (1.0 - f))
    v = np.full_like(hue, value)
    table = np.stack([(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)])  # (6, 3, ...)
    index = (sector.astype(np.int64) % 6)[None, None]
    return np.moveaxis(np.take_along_axis(table, np.broadcast_to(index, (1, 3, *hue.shape)), axis=0)[0], 0, -1)


def room_colour(start: float, end: float) -> SurfaceColour:
    """The texture of rooms from x = `start` to `end`, its colour drifting along them."""
    return lambda points, axis, positive: _room_colour(points, axis, positive, start, end)


def _room_colour(points: np.ndarray, axis: np.ndarray, positive: np.ndarray, start: float, end: float) -> np.ndarray:
    """Texture of the room's walls, floor and ceiling at hit points."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    colour = np.empty_like(points)
    side = axis == 1
    base = hue_along(x, start, end, 0.55, 0.95)
    stripes = 0.75 + 0.25 * np.sin(2 * np.pi * x / 0.37) * np.sin(2 * np.pi * z / 0.29)
    tiles = 0.65 + 0.35 * checker(x, z, 0.5)
    colour[side] = base[side] * (tiles * stripes)[side, None]
    floor = (axis == 2) & ~positive
    floor_base = hue_along(start + end - x, start, end, 0.35, 0.8)
    colour[floor] = floor_base[floor] * (0.55 + 0.45 * checker(x, y, 0.8))[floor, None]
    ceiling = (axis == 2) & positive
    colour[ceiling] = (0.8 + 0.15 * np.sin(2 * np.pi * x / 2.0))[ceiling, None] * np.array([0.95, 0.93, 0.88])
    ends = axis == 0
    colour[ends] = (
        np.where(positive[ends, None], [[0.2, 0.3, 0.8]], [[0.8, 0.3, 0.2]])
        * (0.7 + 0.3 * checker(y, z, 0.4))[ends, None]
    )
    return colour


def _intersect_box_inside(
    origins: np.ndarray, dirs: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distance to a box's inside, the axis of the wall hit and whether it is the max side."""
    with np.errstate(divide="ignore"):
        t_axis = np.where(dirs > 0, (hi - origins) / dirs, (lo - origins) / dirs)
    t_axis = np.where(dirs == 0, np.inf, t_axis)
    axis = np.argmin(t_axis, axis=-1)
    rows = np.arange(len(axis))
    return t_axis[rows, axis], axis, dirs[rows, axis] > 0


def _intersect_crate(origins: np.ndarray, dirs: np.ndarray, crate: Crate) -> tuple[np.ndarray, np.ndarray]:
    """Entry distance (inf when missed) and the axis of the face hit."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (crate.lo - origins) / dirs
        t2 = (crate.hi - origins) / dirs
    t_near_axes = np.nan_to_num(np.minimum(t1, t2), nan=-np.inf)
    t_far = np.nan_to_num(np.maximum(t1, t2), nan=np.inf).min(axis=-1)
    t_near = t_near_axes.max(axis=-1)
    hit = (t_near < t_far) & (t_near > 1e-4)
    return np.where(hit, t_near, np.inf), np.argmax(t_near_axes, axis=-1)


def cast_rays(origins: np.ndarray, dirs: np.ndarray, scene: Scene) -> np.ndarray:
    """RGB in [0, 1] seen along each ray (N, 3)."""
    t, axis, positive = _intersect_box_inside(origins, dirs, scene.lo, scene.hi)
    colour = scene.surface(origins + t[:, None] * dirs, axis, positive)
    shade = np.array([0.85, 1.0, 0.75])[axis]
    for crate in scene.crates:
        t_crate, crate_axis = _intersect_crate(origins, dirs, crate)
        nearer = t_crate < t
        if not nearer.any():
            continue
        t = np.where(nearer, t_crate, t)
        points = origins[nearer] + t_crate[nearer, None] * dirs[nearer]
        rel = (points - crate.lo) / (crate.hi - crate.lo)
        edge = np.minimum(rel, 1 - rel)
        edge[np.arange(len(edge)), crate_axis[nearer]] = 1.0
        border = np.where(edge.min(axis=-1) < 0.08, 0.45, 1.0)
        colour[nearer] = crate.rgb * border[:, None]
        shade[nearer] = np.array([0.8, 0.95, 1.0])[crate_axis[nearer]]
    return np.clip(colour * shade[:, None], 0.0, 1.0)


def hit_distances(origins: np.ndarray, dirs: np.ndarray, scene: Scene) -> np.ndarray:
    """Distance along each unit ray (N,) to the surface cast_rays colours it with."""
    t, _, _ = _intersect_box_inside(origins, dirs, scene.lo, scene.hi)
    for crate in scene.crates:
        t = np.minimum(t, _intersect_crate(origins, dirs, crate)[0])
    return t


def camera_rays(
    c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float, u: np.ndarray, v: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Origins and unit world directions of the rays through image points (u, v), (N, 3) each, and the length of
    each direction in camera coordinates before it was made a unit (its z component is -1)."""
    dirs_cam = np.stack([(u - cx) / fx, -(v - cy) / fy, -np.ones_like(u)], axis=-1).reshape(-1, 3)
    lengths = np.linalg.norm(dirs_cam, axis=-1)
    dirs = dirs_cam @ c2w[:, :3].T / lengths[:, None]
    return np.broadcast_to(c2w[:, 3], dirs.shape), dirs, lengths


def render_view(
    c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float, width: int, height: int, scene: Scene
) -> np.ndarray:
    """Render one view as uint8 (height, width, 3), 2x2 supersampled against aliasing."""
    samples = 2
    offsets = (np.arange(samples) + 0.5) / samples
    u = (np.arange(width)[:, None] + offsets[None, :]).ravel()
    v = (np.arange(height)[:, None] + offsets[None, :]).ravel()
    origins, dirs, _ = camera_rays(c2w, fx, fy, cx, cy, *np.meshgrid(u, v))
    rgb = cast_rays(origins, dirs, scene).reshape(height, samples, width, samples, 3).mean(axis=(1, 3))
    return np.round(rgb * 255).astype(np.uint8)


def render_depth(
    c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float, width: int, height: int, scene: Scene
) -> np.ndarray:
    """Exact z-depth (distance along the optical axis, metres) of one view at its pixel centres, (height, width)
    float32: what a perfect depth sensor registered to the colour camera records (one sample per pixel, never a mix
    of a foreground and a background depth)."""
    origins, dirs, lengths = camera_rays(
        c2w, fx, fy, cx, cy, *np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    )
    return (hit_distances(origins, dirs, scene) / lengths).reshape(height, width).astype(np.float32)


MOVE_DISTANCE = 1.5
"""How far the room's moved crate goes along the room, metres: half the spacing of the crates on its wall."""
PAINT = np.array([0.85, 0.32, 0.38])
"""The colour a repainted stretch of wall gets."""
REPAINTED_LENGTH = 3.0
"""Length of the room's repainted stretch of wall, metres."""


def viewed_crates(scene: Scene) -> List[int]:
    """The crates against the wall the camera looks at (+y), partition walls aside."""
    return [
        index
        for index, crate in enumerate(scene.crates)
        if (crate.lo[1] + crate.hi[1]) / 2 > 0 and crate.hi[1] < scene.hi[1] - 1e-6
    ]


def with_object_moved(scene: Scene, distance: float = MOVE_DISTANCE, candidates: Optional[List[int]] = None) -> Scene:
    """`scene` with the object nearest the middle of its length (among `candidates`, the crates against the viewed
    wall by default) moved `distance` metres along it."""
    chosen = viewed_crates(scene) if candidates is None else candidates
    middle = (scene.lo[0] + scene.hi[0]) / 2
    index = min(chosen, key=lambda i: abs((scene.crates[i].lo[0] + scene.crates[i].hi[0]) / 2 - middle))
    crate = scene.crates[index]
    shift = np.array([distance, 0.0, 0.0])
    moved = Crate(lo=crate.lo + shift, hi=crate.hi + shift, rgb=crate.rgb)
    return dataclasses.replace(scene, crates=[moved if i == index else c for i, c in enumerate(scene.crates)])


def with_wall_repainted(scene: Scene, length: float = REPAINTED_LENGTH, keep: Optional[SurfaceMask] = None) -> Scene:
    """`scene` with a stretch of the viewed (+y) wall, `length` metres about the middle of its length, painted over
    (its tiles stay: paint shows them), except where `keep` says (the street's windows)."""
    middle = (scene.lo[0] + scene.hi[0]) / 2
    surface = scene.surface

    def repainted(points: np.ndarray, axis: np.ndarray, positive: np.ndarray) -> np.ndarray:
        colour = surface(points, axis, positive)
        x, z = points[:, 0], points[:, 2]
        painted = (axis == 1) & positive & (np.abs(x - middle) < length / 2)
        if keep is not None:
            painted &= ~keep(points)
        colour[painted] = (PAINT * (0.8 + 0.2 * checker(x, z, 0.5))[:, None])[painted]
        return colour

    return dataclasses.replace(scene, surface=repainted)
