"""A random 360-degree place for the detector's tests: each seed another place."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ['place']


def place(seed: int, n: int = 6000) -> npt.NDArray[np.float64]:
    """A random 360-degree scene: walls of boxes at 5-60 m, ground and clutter."""
    rng = np.random.default_rng(seed)
    az = rng.uniform(0, 2 * np.pi, n)
    r = rng.choice(rng.uniform(5, 60, 12), n) + rng.normal(0, 0.5, n)
    z = rng.uniform(-1.7, 3.0, n)
    return np.stack([r * np.cos(az), r * np.sin(az), z], axis=1)
