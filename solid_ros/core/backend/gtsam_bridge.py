"""The one place where poses and covariances cross into gtsam, and where gtsam is imported.

gtsam (PyPI ``gtsam`` 4.3) is imported only when a back end is built (:func:`require_gtsam`),
like small_gicp for verification, so the detector runs without it. Measurements go in as a 4x4
``T`` and a ROS-order covariance (doc/conventions.md) and come back the same way:
:func:`to_gtsam` and :func:`from_gtsam` are each other's inverse (tested by a round trip);
the block order is swapped by :func:`solid_ros.core.backend.noise.swap_blocks` alone.
"""

from __future__ import annotations

from types import ModuleType
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.backend.noise import swap_blocks
from solid_ros.core.errors import BackendError

if TYPE_CHECKING:
    import gtsam

__all__ = ['GTSAM_ERRORS', 'from_gtsam', 'pose3', 'pose_matrix', 'require_gtsam', 'robust',
           'to_gtsam']

FloatArray = npt.NDArray[np.float64]
# What gtsam raises from C++ (an indeterminant system is a RuntimeError subclass).
GTSAM_ERRORS: tuple[type[BaseException], ...] = (RuntimeError, ValueError, IndexError)


def require_gtsam() -> ModuleType:
    """Import gtsam, or say how to install it.

    Raises:
        BackendError: gtsam is not installed (the message gives ``pip install gtsam``).
    """
    try:
        import gtsam
    except ImportError as err:
        raise BackendError('the back end (backend: true) needs gtsam: pip install gtsam '
                           f'(PyPI gtsam 4.3; import failed: {err})') from err
    return gtsam


def pose3(T: npt.ArrayLike) -> gtsam.Pose3:
    """A 4x4 transform as a gtsam ``Pose3`` (the rotation re-orthonormalised)."""
    import gtsam

    m = np.asarray(T, dtype=np.float64)
    u, _, vt = np.linalg.svd(m[:3, :3])
    rot = u @ np.diag([1.0, 1.0, float(np.linalg.det(u @ vt))]) @ vt
    return gtsam.Pose3(gtsam.Rot3(rot), np.asarray(m[:3, 3], dtype=np.float64))


def pose_matrix(p: gtsam.Pose3) -> FloatArray:
    """A ``Pose3`` as a 4x4 transform."""
    out: FloatArray = np.asarray(p.matrix(), dtype=np.float64)
    return out


def to_gtsam(T: npt.ArrayLike, cov_ros: npt.ArrayLike) -> tuple[gtsam.Pose3,
                                                               gtsam.noiseModel.Gaussian]:
    """A measured pose and its ROS-order covariance (right perturbation ``T exp(delta)``) as
    gtsam's measurement and Gaussian noise model (rotation first)."""
    import gtsam

    return pose3(T), gtsam.noiseModel.Gaussian.Covariance(swap_blocks(cov_ros))


def from_gtsam(p: gtsam.Pose3, noise: gtsam.noiseModel.Gaussian) -> tuple[FloatArray, FloatArray]:
    """The inverse of :func:`to_gtsam`: 4x4 ``T`` and the ROS-order covariance."""
    return pose_matrix(p), swap_blocks(np.asarray(noise.covariance(), dtype=np.float64))


def robust(noise: gtsam.noiseModel.Base, kernel: str, width: float) -> Any:
    """``noise`` under the robust kernel ``'huber'``, ``'cauchy'`` or ``'none'`` (as is); the
    width is in sigmas of ``noise``."""
    import gtsam

    est = gtsam.noiseModel.mEstimator
    if kernel == 'huber':
        return gtsam.noiseModel.Robust.Create(est.Huber.Create(width), noise)
    if kernel == 'cauchy':
        return gtsam.noiseModel.Robust.Create(est.Cauchy.Create(width), noise)
    return noise
