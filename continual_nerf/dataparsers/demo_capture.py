"""What a real capture adds to the demo's exact renders: exposure and white balance that change along the capture,
cameras of a rig that respond to colour differently, poses that are slightly wrong, and a depth sensor's flaws.

Each effect draws from its own random stream (seeded by the scene's seed and the effect), so an effect that is off
draws nothing and the scene, its path and the other effects stay as they are.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

EXPOSURE_STREAM, RESPONSE_STREAM, POSE_STREAM, DEPTH_STREAM = 1, 2, 3, 4
"""Random streams of the effects: numpy.random.default_rng([seed, stream])."""
EDGE_JUMP = 0.05
"""Relative depth difference between neighbouring pixels from which a depth sensor sees a discontinuity."""
TINT_SHARE = 1 / 3
"""White balance changes by this share of the exposure strength per channel."""
DRIFT_SHARE = 1 / 5
"""Within a segment, exposure drifts smoothly by up to this share of the exposure strength."""
GAMMA_SHARE = 1 / 2
"""A camera's gamma departs from 1 by up to this share of the response strength."""
NOISE_CYCLES = (0.5, 3.0)
"""Smooth pose errors are sums of sinusoids of this many cycles per capture (like drift or latency)."""
PoseNoiseKind = Literal["smooth", "independent"]


def effect_rng(seed: int, stream: int) -> np.random.Generator:
    return np.random.default_rng([seed, stream])


def exposure_gains(num_instants: int, segments: int, strength: float, rng: np.random.Generator) -> np.ndarray:
    """(num_instants, 3) per-channel gains: per segment of the capture an exposure level in [1 - strength,
    1 + strength] and a white-balance tint, times a smooth drift along the capture."""
    segment = np.zeros(num_instants, dtype=int)
    for index, span in enumerate(np.array_split(np.arange(num_instants), segments)):
        segment[span] = index
    level = rng.uniform(1 - strength, 1 + strength, size=segments)
    tint = rng.uniform(1 - TINT_SHARE * strength, 1 + TINT_SHARE * strength, size=(segments, 3))
    along = np.linspace(0.0, 1.0, num_instants)
    drift = 1 + DRIFT_SHARE * strength * np.sin(np.pi * segments * along + rng.uniform(0, 2 * np.pi))
    return level[segment, None] * tint[segment] * drift[:, None]


@dataclass(frozen=True)
class CameraResponse:
    """How one camera turns scene colour into pixel values: value = gain * colour ** gamma, per channel."""

    gain: np.ndarray
    """(3,) per-channel gain."""
    gamma: float
    """Exponent applied before the gain."""


NEUTRAL = CameraResponse(gain=np.ones(3), gamma=1.0)
"""A camera that records colour as it is."""


def camera_responses(num_cameras: int, strength: float, rng: np.random.Generator) -> list[CameraResponse]:
    """A response per camera: gains within 1 +- strength per channel, gamma within 1 +- strength / 2."""
    return [
        CameraResponse(
            gain=rng.uniform(1 - strength, 1 + strength, size=3),
            gamma=float(rng.uniform(1 - GAMMA_SHARE * strength, 1 + GAMMA_SHARE * strength)),
        )
        for _ in range(num_cameras)
    ]


def captured(image: np.ndarray, gain: np.ndarray, response: CameraResponse) -> np.ndarray:
    """The uint8 image a camera with `response` records of the exact `image` (uint8) at exposure `gain` (3,)."""
    colour = image.astype(np.float64) / 255
    value = gain * response.gain * colour**response.gamma
    return np.round(np.clip(value, 0.0, 1.0) * 255).astype(np.uint8)


def unit_rms(curves: np.ndarray) -> np.ndarray:
    """`curves` (num_instants, dims) scaled to a root mean square norm of 1 over the instants."""
    return curves / np.sqrt((curves**2).sum(axis=-1).mean())


def smooth_curves(num_instants: int, dims: int, rng: np.random.Generator) -> np.ndarray:
    """(num_instants, dims) sums of three sinusoids along the capture, scaled to a root mean square norm of 1."""
    along = np.linspace(0.0, 1.0, num_instants)[:, None, None]
    cycles = rng.uniform(*NOISE_CYCLES, size=(1, dims, 3))
    phases = rng.uniform(0, 2 * np.pi, size=(1, dims, 3))
    return unit_rms(np.sin(2 * np.pi * cycles * along + phases).sum(axis=-1))


def independent_curves(num_instants: int, dims: int, rng: np.random.Generator) -> np.ndarray:
    """(num_instants, dims) independent normal draws per instant, scaled to a root mean square norm of 1."""
    return unit_rms(rng.normal(size=(num_instants, dims)))


def trajectory_length(positions: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(positions, axis=0), axis=-1).sum())


def noisy_poses(
    poses: np.ndarray,
    instants: np.ndarray,
    degrees: float,
    translation: float,
    rng: np.random.Generator,
    kind: PoseNoiseKind = "smooth",
) -> np.ndarray:
    """`poses` (N, 3, 4) with an error per capture instant (a rig's cameras share it), smooth along the capture or
    drawn anew at every instant (`kind`): a rotation of root mean square angle `degrees` about the camera centre and a
    shift of root mean square length `translation` times the trajectory's length."""
    num_instants = int(instants.max()) + 1
    first_of_instant = np.unique(instants, return_index=True)[1]
    length = trajectory_length(poses[first_of_instant, :, 3])
    curves = smooth_curves if kind == "smooth" else independent_curves
    rotations = rotation_matrices(np.deg2rad(degrees) * curves(num_instants, 3, rng))
    shifts = translation * length * curves(num_instants, 3, rng)
    noisy = poses.copy()
    noisy[:, :, :3] = rotations[instants] @ poses[:, :, :3]
    noisy[:, :, 3] += shifts[instants]
    return noisy


def rotation_matrices(rotation_vectors: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations about the axes of (N, 3) vectors by their lengths (radians): Rodrigues' formula."""
    angle = np.linalg.norm(rotation_vectors, axis=-1)[:, None, None]
    x, y, z = (rotation_vectors / np.maximum(angle[:, :, 0], 1e-12)).T
    zero = np.zeros_like(x)
    cross = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=-1).reshape(-1, 3, 3)
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def pose_errors(estimated: np.ndarray, true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pose of (N, 3, 4) camera-to-world matrices: the rotation error (degrees) and the distance between the
    camera centres."""
    relative = np.swapaxes(true[:, :, :3], 1, 2) @ estimated[:, :, :3]
    cosine = np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    return np.rad2deg(np.arccos(cosine)), np.linalg.norm(estimated[:, :, 3] - true[:, :, 3], axis=-1)


@dataclass(frozen=True)
class DepthSensor:
    """The flaws of a structured-light or time-of-flight depth sensor (Kinect, Structure Sensor); none by default."""

    noise: float = 0.0
    """Standard deviation (metres) of the depth error at 1 m; it grows with the square of the depth."""
    max_range: float = math.inf
    """Metres beyond which the sensor measures nothing."""
    edge_holes: int = 0
    """Pixels on either side of a depth discontinuity the sensor measures nothing at."""
    dropout: float = 0.0
    """Share of pixels it measures nothing at, at random."""

    @property
    def exact(self) -> bool:
        return self == DepthSensor()

    def name(self) -> str:
        """What sets this sensor apart, for the folder of its depth maps ("" for an exact one)."""
        parts = {"noise": self.noise, "range": self.max_range, "edges": self.edge_holes, "dropout": self.dropout}
        default = {"noise": 0.0, "range": math.inf, "edges": 0, "dropout": 0.0}
        return "_".join(f"{key}{value:g}" for key, value in parts.items() if value != default[key])


def discontinuities(depth: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels whose depth differs from a 4-neighbour's by more than EDGE_JUMP of the nearer one."""
    across = np.abs(np.diff(depth, axis=1)) > EDGE_JUMP * np.minimum(depth[:, :-1], depth[:, 1:])
    down = np.abs(np.diff(depth, axis=0)) > EDGE_JUMP * np.minimum(depth[:-1], depth[1:])
    edges = np.zeros(depth.shape, dtype=bool)
    edges[:, :-1] |= across
    edges[:, 1:] |= across
    edges[:-1] |= down
    edges[1:] |= down
    return edges


def dilated(mask: np.ndarray, pixels: int) -> np.ndarray:
    """`mask` grown by `pixels` in every direction (a square neighbourhood)."""
    height, width = mask.shape
    for _ in range(pixels):
        padded = np.pad(mask, 1)
        mask = np.logical_or.reduce([padded[dy : dy + height, dx : dx + width] for dy in range(3) for dx in range(3)])
    return mask


def sensed_depth(depth: np.ndarray, sensor: DepthSensor, rng: np.random.Generator) -> np.ndarray:
    """The depth map (H, W, metres; 0: no measurement) `sensor` records of the exact z-depth `depth`."""
    holes = depth > sensor.max_range
    if sensor.edge_holes > 0:
        holes |= dilated(discontinuities(depth), sensor.edge_holes - 1)
    if sensor.dropout > 0:
        holes |= rng.random(depth.shape) < sensor.dropout
    noisy = depth + sensor.noise * depth**2 * rng.standard_normal(depth.shape) if sensor.noise > 0 else depth
    return np.where(holes | (noisy <= 0), 0.0, noisy).astype(np.float32)
