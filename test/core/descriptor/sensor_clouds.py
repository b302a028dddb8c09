"""Synthetic clouds of known sensors for the sensor measurement tests (numpy only)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


def cloud(elevation_deg: FloatArray, azimuth_deg: FloatArray, ranges: FloatArray) -> FloatArray:
    """Points at these elevations, azimuths (degrees) and 3-D ranges, (N, 3)."""
    el, az = np.radians(elevation_deg), np.radians(azimuth_deg)
    return np.stack([ranges * np.cos(el) * np.cos(az), ranges * np.cos(el) * np.sin(az),
                     ranges * np.sin(el)], axis=1)


def spinning(seed: int, rings: int = 16, down: float = -15.0, up: float = 15.0,
             per_ring: int = 900, far: float = 60.0, blocked_deg: float = 0.0) -> FloatArray:
    """A spinning multi-ring sensor's cloud; ``blocked_deg`` of its front returns nothing."""
    rng = np.random.default_rng(seed)
    el = np.repeat(np.linspace(down, up, rings), per_ring)
    az = np.tile(np.linspace(-180.0, 180.0, per_ring, endpoint=False), rings)
    keep = np.abs(az) >= 0.5 * blocked_deg
    return cloud(el[keep], az[keep], rng.uniform(2.0, far, int(keep.sum())))


def rosette(seed: int, width: float = 70.0, centre: float = 0.0, down: float = -38.6,
            up: float = 38.6, count: int = 10_000, near: float = 1.0,
            far: float = 40.0) -> FloatArray:
    """A non-repetitive sector sensor's cloud (elevations spread, no rings)."""
    rng = np.random.default_rng(seed)
    el = rng.uniform(down, up, count)
    az = centre + rng.uniform(-0.5 * width, 0.5 * width, count)
    return cloud(el, az, rng.uniform(near, far, count))
