"""Pose files and messages: KITTI 3x4 and TUM files, times files, Odometry messages.

Every pose is a 4x4 homogeneous matrix T_world_sensor (maps sensor coordinates to world).
Stamps are integer nanoseconds; text stamps are parsed digit by digit so that a stamp written
as ``1577836980.0991046`` becomes exactly ``1577836980099104600`` ns (no float rounding).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.database.atomic import write_atomic
from solid_ros.core.errors import PoseError
from solid_ros.core.geometry import matrix_to_vector, vector_to_matrix

__all__ = [
    'PoseError', 'PoseTrack', 'format_stamp_ns', 'load_reference', 'odometry_to_pose',
    'parse_stamp_ns', 'read_kitti_poses', 'read_times', 'read_tum_poses', 'write_kitti_poses',
    'write_tum_poses',
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

# Largest |R^T R - I| entry of a KITTI rotation: files print about 6 digits (1e-6 seen), so
# 1e-3 only refuses what is not a rotation (zero, scaled, sheared or reflected matrices).
_ORTHO_TOL = 1e-3


@dataclass(frozen=True)
class PoseTrack:
    """Reference poses, optionally stamped.

    Attributes:
        poses: (N, 4, 4) T_world_sensor.
        stamps_ns: (N,) int64 stamps, or None when poses pair with scans by order.
        source: where they came from (file name or topic), for messages and reports.
    """

    poses: FloatArray
    stamps_ns: IntArray | None
    source: str

    def __len__(self) -> int:
        return int(self.poses.shape[0])

    @property
    def positions(self) -> FloatArray:
        """(N, 3) translations."""
        return self.poses[:, :3, 3]


def parse_stamp_ns(text: str) -> int:
    """Parse a stamp in seconds (``'12.5'``, ``'1.2e3'``) as integer nanoseconds.

    Raises:
        ValueError: the text is not a finite number.
    """
    s = text.strip()
    if not s or any(c in s for c in 'eE') or s.lower() in ('nan', 'inf', '-inf', '+inf'):
        value = float(s)  # raises on garbage; exponent forms are rare, float is fine there
        if not math.isfinite(value):
            raise ValueError(f'stamp {text!r} is not finite')
        return round(value * 1e9)
    sign = -1 if s.startswith('-') else 1
    s = s.lstrip('+-')
    whole, _, frac = s.partition('.')
    if not (whole or frac) or not (whole.isdigit() or whole == '') or not (
            frac.isdigit() or frac == ''):
        raise ValueError(f'stamp {text!r} is not a number')
    frac9 = (frac + '000000000')[:9]
    ns = int(whole or '0') * 1_000_000_000 + int(frac9)
    if len(frac) > 9 and frac[9] >= '5':
        ns += 1
    return sign * ns


def format_stamp_ns(stamp_ns: int) -> str:
    """A stamp as exact decimal seconds with nine digits (the inverse of
    :func:`parse_stamp_ns`)."""
    ns = int(stamp_ns)
    sign = '-' if ns < 0 else ''
    sec, frac = divmod(abs(ns), 1_000_000_000)
    return f'{sign}{sec}.{frac:09d}'


def _checked_poses(poses: npt.ArrayLike, path: str | Path) -> FloatArray:
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[1:] not in ((4, 4), (3, 4)) or not np.all(np.isfinite(arr)):
        raise PoseError(f'{path}: expected finite (N, 4, 4) poses, got shape {arr.shape}')
    return arr


def write_tum_poses(path: str | Path, stamps_ns: npt.ArrayLike, poses: npt.ArrayLike) -> Path:
    """Write a TUM trajectory, ``stamp tx ty tz qx qy qz qw`` per line (stamps exact to the
    nanosecond), atomically; :func:`read_tum_poses` reads it back.

    Raises:
        PoseError: poses that are not finite (N, 4, 4), or as many stamps as poses.
        SolidError: the file cannot be written.
    """
    arr = _checked_poses(poses, path)
    stamps = np.asarray(stamps_ns, dtype=np.int64).ravel()
    if len(stamps) != len(arr):
        raise PoseError(f'{path}: {len(arr)} poses but {len(stamps)} stamps')
    lines = [format_stamp_ns(int(s)) + ' ' + ' '.join(f'{v:.10g}' for v in matrix_to_vector(T))
             for s, T in zip(stamps, arr)]
    text = ''.join(line + '\n' for line in lines).encode()
    return write_atomic(path, lambda f: f.write(text))


def write_kitti_poses(path: str | Path, poses: npt.ArrayLike) -> Path:
    """Write KITTI poses, the row-major 3x4 ``[R | t]`` per line, atomically;
    :func:`read_kitti_poses` reads it back.

    Raises:
        PoseError: poses that are not finite (N, 4, 4).
        SolidError: the file cannot be written.
    """
    arr = _checked_poses(poses, path)
    lines = [' '.join(f'{v:.10g}' for v in T[:3, :4].ravel()) for T in arr]
    text = ''.join(line + '\n' for line in lines).encode()
    return write_atomic(path, lambda f: f.write(text))


def _rows(path: str | Path, what: str) -> list[list[str]]:
    try:
        text = Path(path).read_text(encoding='utf-8')
    except (OSError, UnicodeDecodeError) as err:
        reason = getattr(err, 'strerror', None) or str(err)
        raise PoseError(f'cannot read {what} file {path}: {reason}') from err
    rows = []
    for line in text.splitlines():
        line = line.split('#', 1)[0].strip()
        if line:
            rows.append(line.replace(',', ' ').split())
    if not rows:
        raise PoseError(f'{what} file {path} is empty')
    return rows


def _floats(row: list[str], path: str | Path, lineno: int, count: int) -> list[float]:
    if len(row) != count:
        raise PoseError(f'{path}:{lineno}: expected {count} numbers, got {len(row)}')
    try:
        vals = [float(v) for v in row]
    except ValueError as err:
        raise PoseError(f'{path}:{lineno}: not a number ({err})') from err
    if not all(math.isfinite(v) for v in vals):
        raise PoseError(f'{path}:{lineno}: non-finite value')
    return vals


def read_kitti_poses(path: str | Path) -> FloatArray:
    """Read a KITTI pose file: one row-major 3x4 [R | t] per line.

    Returns:
        (N, 4, 4) poses.

    Raises:
        PoseError: unreadable file, wrong column count, non-numeric value or a 3x3 part that
            is not a rotation matrix (line named).
    """
    rows = _rows(path, 'poses')
    out = np.zeros((len(rows), 4, 4))
    out[:, 3, 3] = 1.0
    for i, row in enumerate(rows):
        out[i, :3, :] = np.reshape(_floats(row, path, i + 1, 12), (3, 4))
        rot = out[i, :3, :3]
        if not (np.abs(rot.T @ rot - np.eye(3)).max() <= _ORTHO_TOL
                and np.linalg.det(rot) > 0.0):
            raise PoseError(f'{path}:{i + 1}: the 3x3 part is not a rotation matrix '
                            f'(rows {rot.round(6).tolist()})')
    return out


def _check_increasing(stamps: IntArray, path: str | Path, what: str) -> None:
    """Refuse stamps that repeat or go back: pairing by stamp would pick arbitrary poses."""
    bad = np.flatnonzero(np.diff(stamps) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        word = 'repeats' if stamps[i] == stamps[i - 1] else 'is before'
        raise PoseError(f'{path}:{i + 1}: {what} stamp {stamps[i] / 1e9:.9f} {word} the '
                        f'previous one ({stamps[i - 1] / 1e9:.9f}); stamps must increase')


def read_tum_poses(path: str | Path) -> tuple[IntArray, FloatArray]:
    """Read a TUM trajectory: ``stamp tx ty tz qx qy qz qw`` per line.

    Returns:
        (stamps_ns (N,), poses (N, 4, 4)).

    Raises:
        PoseError: unreadable file, malformed line, or stamps that repeat or go back (line
            named).
    """
    rows = _rows(path, 'poses')
    stamps = np.zeros(len(rows), dtype=np.int64)
    poses = np.zeros((len(rows), 4, 4))
    for i, row in enumerate(rows):
        vals = _floats(row, path, i + 1, 8)
        stamps[i] = parse_stamp_ns(row[0])
        try:
            poses[i] = vector_to_matrix(vals[1:8])
        except PoseError as err:
            raise PoseError(f'{path}:{i + 1}: {err}') from err
    _check_increasing(stamps, path, 'pose')
    return stamps, poses


def read_times(path: str | Path) -> IntArray:
    """Read a times file (one stamp in seconds per line, KITTI ``times.txt`` style).

    Raises:
        PoseError: unreadable file, a line that is not one number, or stamps that repeat
            or go back (line named).
    """
    rows = _rows(path, 'times')
    out = np.zeros(len(rows), dtype=np.int64)
    for i, row in enumerate(rows):
        if len(row) != 1:
            raise PoseError(f'{path}:{i + 1}: expected one stamp, got {len(row)} values')
        try:
            out[i] = parse_stamp_ns(row[0])
        except ValueError as err:
            raise PoseError(f'{path}:{i + 1}: {err}') from err
    _check_increasing(out, path, 'the')
    return out


def load_reference(poses_path: str | Path, times_path: str | Path | None = None) -> PoseTrack:
    """Load reference poses, detecting KITTI (12 columns) or TUM (8 columns) format.

    Args:
        poses_path: KITTI or TUM file.
        times_path: stamps for a KITTI file (one per pose). Without it KITTI poses pair with
            scans by order. Not allowed with TUM files, which carry their own stamps.

    Raises:
        PoseError: unreadable files, unknown format, or pose/stamp counts that differ.
    """
    first = _rows(poses_path, 'poses')[0]
    if len(first) == 8:
        if times_path is not None:
            raise PoseError(f'{poses_path} is a TUM file with its own stamps; drop --times')
        stamps, poses = read_tum_poses(poses_path)
        return PoseTrack(poses, stamps, str(poses_path))
    if len(first) != 12:
        raise PoseError(f'{poses_path}: {len(first)} columns; expected 12 (KITTI 3x4) or 8 '
                        '(TUM: stamp tx ty tz qx qy qz qw)')
    poses = read_kitti_poses(poses_path)
    if times_path is None:
        return PoseTrack(poses, None, str(poses_path))
    times = read_times(times_path)
    if len(times) != len(poses):
        raise PoseError(f'{poses_path} has {len(poses)} poses but {times_path} has '
                        f'{len(times)} stamps')
    return PoseTrack(poses, times, str(poses_path))


def odometry_to_pose(msg: Any) -> FloatArray:
    """Return T_world_sensor of a nav_msgs/Odometry (rclpy or rosbags message).

    Raises:
        PoseError: the message has no pose.pose or a zero-length quaternion.
    """
    try:
        p = msg.pose.pose.position
        q = msg.pose.pose.orientation
        vals = [float(v) for v in (p.x, p.y, p.z, q.x, q.y, q.z, q.w)]
    except (AttributeError, TypeError, ValueError) as err:
        raise PoseError(f'not an Odometry message: {err}') from err
    return vector_to_matrix(vals)
