"""Rigid-body helpers of the core: quaternions, rotation matrices, pose vectors, yaw.

Poses are 4x4 homogeneous matrices T_world_sensor (sensor coordinates to world) or the vector
``(x, y, z, qx, qy, qz, qw)``; quaternions are ``(x, y, z, w)``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.errors import PoseError, SolidError

__all__ = ['invert_rigid', 'matrix_to_quaternion', 'matrix_to_vector', 'pose_to_vector',
           'quaternion_to_matrix', 'relative_yaw', 'rot_z', 'rotation_deg', 'rpy_matrix',
           'vector_to_matrix', 'yaw_of']

FloatArray = npt.NDArray[np.float64]


def quaternion_to_matrix(x: float, y: float, z: float, w: float) -> FloatArray:
    """Rotation matrix of a quaternion (normalised first).

    Raises:
        PoseError: the quaternion has zero length.
    """
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not n > 1e-12:
        raise PoseError('quaternion has zero length')
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quaternion(rotation: npt.ArrayLike) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w) of a rotation matrix, with w >= 0."""
    r = np.asarray(rotation, dtype=np.float64)
    # Shepperd's method: pivot on the largest diagonal term for stability.
    k = np.array([
        [r[0, 0] - r[1, 1] - r[2, 2], r[1, 0] + r[0, 1], r[2, 0] + r[0, 2], r[2, 1] - r[1, 2]],
        [r[1, 0] + r[0, 1], r[1, 1] - r[0, 0] - r[2, 2], r[2, 1] + r[1, 2], r[0, 2] - r[2, 0]],
        [r[2, 0] + r[0, 2], r[2, 1] + r[1, 2], r[2, 2] - r[0, 0] - r[1, 1], r[1, 0] - r[0, 1]],
        [r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1], r[0, 0] + r[1, 1] + r[2, 2]],
    ]) / 3.0
    vals, vecs = np.linalg.eigh(k)
    q = vecs[:, int(np.argmax(vals))]
    if q[3] < 0:
        q = -q
    return float(q[0]), float(q[1]), float(q[2]), float(q[3])


def rpy_matrix(roll: float, pitch: float, yaw: float) -> FloatArray:
    """Rotation ``Rz(yaw) Ry(pitch) Rx(roll)`` (radians; ROS fixed-axis roll, pitch, yaw)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    out: FloatArray = rot_z(yaw) @ ry @ rx
    return out


def matrix_to_vector(T: npt.ArrayLike) -> FloatArray:
    """``(x, y, z, qx, qy, qz, qw)`` of a 4x4 or 3x4 transform (w >= 0)."""
    arr = np.asarray(T, dtype=np.float64)
    return np.concatenate([arr[:3, 3], matrix_to_quaternion(arr[:3, :3])])


def vector_to_matrix(vector: npt.ArrayLike) -> FloatArray:
    """4x4 transform of ``(x, y, z, qx, qy, qz, qw)`` (the inverse of
    :func:`matrix_to_vector`)."""
    v = np.asarray(vector, dtype=np.float64).reshape(7)
    out = np.eye(4)
    out[:3, :3] = quaternion_to_matrix(*(float(x) for x in v[3:]))
    out[:3, 3] = v[:3]
    return out


def rot_z(yaw: float) -> FloatArray:
    """Rotation matrix of ``yaw`` radians CCW about +z."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def yaw_of(rotation: npt.ArrayLike) -> float:
    """Heading (rotation about +z) of a rotation matrix, radians in (-pi, pi]."""
    r = np.asarray(rotation, dtype=np.float64)
    return math.atan2(float(r[1, 0]), float(r[0, 0]))


def relative_yaw(pose_query: npt.ArrayLike, pose_candidate: npt.ArrayLike) -> float:
    """Ground-truth yaw in the detector's convention p_candidate = Rz(yaw) p_query.

    It is the z-rotation of R_candidate^T R_query, which for planar motion equals
    yaw(query) - yaw(candidate).
    """
    rq = np.asarray(pose_query, dtype=np.float64)[:3, :3]
    rc = np.asarray(pose_candidate, dtype=np.float64)[:3, :3]
    return yaw_of(rc.T @ rq)


def pose_to_vector(pose: Any) -> npt.NDArray[np.float64]:
    """Normalise a pose to ``(x, y, z, qx, qy, qz, qw)``.

    Args:
        pose: a 4x4 or 3x4 homogeneous matrix, or 7 values ``x y z qx qy qz qw``.

    Raises:
        SolidError: the pose has another shape, non-finite values or a zero quaternion.
    """
    arr = np.asarray(pose, dtype=np.float64)
    if arr.shape in ((4, 4), (3, 4)):
        if not np.all(np.isfinite(arr)):
            raise SolidError('pose matrix holds NaN or infinite values')
        if not np.linalg.det(arr[:3, :3]) > 0.0:
            raise SolidError('pose rotation is not a rotation matrix: non-positive '
                             f'determinant {arr[:3, :3].tolist()}')
        return matrix_to_vector(arr)
    arr = arr.ravel()
    if arr.shape != (7,):
        raise SolidError(f'pose must be a 4x4 or 3x4 matrix or 7 values (x y z qx qy qz qw), '
                         f'got shape {np.shape(pose)}')
    norm = float(np.linalg.norm(arr[3:]))
    if not np.all(np.isfinite(arr)) or norm == 0.0:
        raise SolidError(f'pose has non-finite values or a zero quaternion: {arr.tolist()}')
    return np.concatenate([arr[:3], arr[3:] / norm])


def rotation_deg(q1: npt.NDArray[np.float64], q2: npt.NDArray[np.float64]) -> float:
    """Angle of the relative rotation between two unit quaternions, degrees."""
    c = min(abs(float(q1 @ q2)), 1.0)
    return math.degrees(2.0 * math.acos(c))


def angle_deg(T: npt.ArrayLike) -> float:
    """Rotation angle of a 4x4 (or 3x3) transform's rotation, degrees in [0, 180]."""
    R = np.asarray(T, dtype=np.float64)[:3, :3]
    return math.degrees(math.acos(min(max((float(np.trace(R)) - 1.0) / 2.0, -1.0), 1.0)))


def invert_rigid(T: FloatArray) -> FloatArray:
    """Inverses of rigid 4x4 transforms (any leading dimensions), by transposing rotations."""
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ T[..., :3, 3, None])[..., 0]
    out[..., 3, 3] = 1.0
    return out
