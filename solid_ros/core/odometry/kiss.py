"""KISS-ICP as an odometry source: clouds in, a pose per cloud out, when there is no odometry.

:class:`KissOdometry` implements :class:`~solid_ros.core.odometry.track.OdometrySource` over
KISS-ICP (Vizzo et al., RA-L 2023; PyPI ``kiss-icp``, imported only when this source is
built). Each cloud is registered with ``KissICP.register_frame`` exactly as KISS-ICP's own
pipeline does, so a cloud it registers gets KISS-ICP's pose unchanged.

A cloud KISS-ICP cannot register never raises and never moves the pose silently: the source
resets (a fresh KISS-ICP), counts the reset and starts a new odometry segment
(:attr:`OdomSample.segment`), with a one-line :attr:`OdomSample.reason` for the caller's log.
The new segment starts at the last accepted pose, a guess that no odometry supports. A cloud
cannot be registered when:

- it holds fewer than :data:`MIN_POINTS` finite points within the range gate (empty, NaN);
- it is degenerate: its planar points leave a direction of horizontal translation (the
  sensor's x-y plane) unconstrained: a corridor, a single wall, ``kiss_min_constraint``;
- KISS-ICP raises or returns a non-finite pose;
- the registration jumps: the step from the last pose, or from the constant-velocity
  prediction, is longer than ``kiss_max_step_m``;
- it does not overlap the previous cloud where KISS-ICP put it: fewer than
  ``kiss_min_overlap`` of its structure points lie within two voxels of the previous cloud
  (a jump in the input that KISS-ICP followed only part of the way, as it does: its
  correspondences reach a few metres).

A degenerate or non-overlapping cloud is itself a good cloud: it becomes the first cloud of the
new segment. Clouds with too few points are dropped and the next one starts the segment.
No covariance is given: KISS-ICP reports none, and the back end uses its per-metre model.
That model holds KISS-ICP's typical steps but not a runaway in a weak scene (hku1: steps
0.6-0.8 m against 0.1-0.2 m of the reference): the back end checks a scan-only odometry with
registered steps (``backend_step_registration``, :mod:`solid_ros.core.backend.posegraph`).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import NodeConfig
from solid_ros.core.errors import SolidError
from solid_ros.core.odometry.track import OdomSample, Points

__all__ = ['MIN_POINTS', 'KissOdometry', 'load_kiss_icp']

FloatArray = npt.NDArray[np.float64]

MIN_POINTS = 100  # finite points within the range gate a cloud needs to be registered
_NEIGHBOURS = 10  # points per normal estimate
_PLANAR = 3.0  # a point is planar when its 2nd covariance eigenvalue is this times the 1st
_STRUCTURE_MAX_NZ = 0.7  # |n_z| below this: a wall, pole or trunk rather than the ground
_MIN_STRUCTURE = 20  # fewer structure points than this: the overlap test is skipped


def load_kiss_icp() -> tuple[Any, Any, Any]:
    """Import KISS-ICP on first use: ``KissICP``, ``KISSConfig``, ``voxel_down_sample``.

    Raises:
        SolidError: kiss-icp is not installed (the message says how to install it).
    """
    try:
        from kiss_icp.config import KISSConfig  # type: ignore[import-untyped]
        from kiss_icp.kiss_icp import KissICP  # type: ignore[import-untyped]
        from kiss_icp.voxelization import voxel_down_sample  # type: ignore[import-untyped]
    except ImportError as err:
        raise SolidError("odometry_source 'kiss_icp' needs KISS-ICP: pip install kiss-icp "
                         "(or pip install 'solid_ros[kiss]')") from err
    return KissICP, KISSConfig, voxel_down_sample


@dataclass(frozen=True)
class _Frame:
    """What the checks keep of a cloud: its voxelised points, their normals and a kd-tree."""

    points: FloatArray  # (M, 3) in the cloud's sensor frame
    structure: npt.NDArray[np.bool_]
    constraint: float
    tree: Any


class KissOdometry:
    """KISS-ICP odometry behind :class:`~solid_ros.core.odometry.track.OdometrySource`.

    Args:
        config: node settings (``kiss_*``); defaults when None.

    Raises:
        SolidError: kiss-icp is not installed.

    Attributes:
        name: 'kiss_icp'.
        segment: the current odometry segment (0 until the first reset).
        resets: resets so far (segments started after the first).
        reset_counts: clouds that could not be registered, by kind: 'points', 'degenerate',
            'failed', 'jump', 'overlap' (a bad cloud while the new segment has no cloud yet
            is counted but starts no further segment), and 'requested' (:meth:`reset`).
        registered: clouds registered.
    """

    name = 'kiss_icp'

    def __init__(self, config: NodeConfig | None = None) -> None:
        self.config = config if config is not None else NodeConfig()
        self._KissICP, self._KISSConfig, self._voxel_down_sample = load_kiss_icp()
        self.segment = 0
        self.resets = 0
        self.registered = 0
        self.reset_counts: Counter[str] = Counter()
        self._origin: FloatArray = np.eye(4)  # odom <- this segment's KISS-ICP frame
        self._pose: FloatArray = np.eye(4)  # last accepted pose, odom frame
        self._kiss: Any = None  # None: the segment has no cloud yet
        self._prev: _Frame | None = None
        self._pending: str | None = None  # reset reason for the next sample

    def _new_kiss(self) -> Any:
        c = self.config
        kc = self._KISSConfig()
        kc.data.max_range = c.kiss_max_range
        kc.data.min_range = c.kiss_min_range
        kc.data.deskew = c.kiss_deskew
        kc.mapping.voxel_size = c.kiss_voxel_size
        return self._KissICP(kc)

    def pose_for(self, stamp_ns: int, points: Points | None = None,
                 point_times: npt.ArrayLike | None = None) -> OdomSample | None:
        """Register ``points`` and return the sensor pose in the odometry frame.

        Args:
            stamp_ns: the cloud's stamp.
            points: (N, 3+) x, y, z in the sensor frame (None: no cloud, no pose).
            point_times: per-point times normalised to [0, 1] over the sweep, used by
                ``kiss_deskew`` (without them KISS-ICP does not deskew).

        Returns:
            The pose, with ``reason`` set when the cloud could not be registered (its pose is
            then the last one, in a new ``segment``), or None without a cloud.
        """
        if points is None:
            return None
        frame = _finite_xyz(points)
        gated = _in_range(frame, self.config.kiss_min_range, self.config.kiss_max_range)
        if gated < MIN_POINTS:
            self._reset('points', f'{gated} finite points within '
                        f'({self.config.kiss_min_range:g}, {self.config.kiss_max_range:g}) m, '
                        f'needs {MIN_POINTS}')
            return self._sample(stamp_ns)
        times = np.zeros(0) if point_times is None else np.ravel(
            np.asarray(point_times, dtype=np.float64))
        if len(times) != len(frame):
            times = np.zeros(0)  # a time per finite point or none
        check = self._prepare(frame)
        if self._kiss is not None and check.constraint < self.config.kiss_min_constraint:
            self._reset('degenerate', f'degenerate cloud: translation constraint '
                        f'{check.constraint:.4f} < {self.config.kiss_min_constraint:g} '
                        '(a corridor or a single wall)')
        why = self._register(frame, times, check)
        if why is not None:
            self._reset(*why)
            if why[0] != 'failed':
                self._register(frame, times, check)  # a good cloud: first of the new segment
        return self._sample(stamp_ns)

    def _register(self, frame: FloatArray, times: FloatArray,
                  check: _Frame) -> tuple[str, str] | None:
        """Register one cloud; on success keep it, else return (kind, reason)."""
        fresh = self._kiss is None
        kiss = self._new_kiss() if fresh else self._kiss
        before = np.array(kiss.last_pose, dtype=np.float64)
        predicted = before @ np.asarray(kiss.last_delta, dtype=np.float64)
        try:
            kiss.register_frame(frame, times)
            new = np.array(kiss.last_pose, dtype=np.float64)
        except Exception as err:  # the binding may raise anything
            return 'failed', f'KISS-ICP failed: {" ".join(str(err).split())[:160]}'
        if new.shape != (4, 4) or not np.all(np.isfinite(new)):
            return 'failed', 'KISS-ICP returned a non-finite pose'
        if not fresh:
            step = np.linalg.inv(before) @ new
            jump = max(float(np.linalg.norm(step[:3, 3])),
                       float(np.linalg.norm((np.linalg.inv(predicted) @ new)[:3, 3])))
            if jump > self.config.kiss_max_step_m:
                return 'jump', (f'registration jumped {jump:.2f} m '
                                f'(> kiss_max_step_m {self.config.kiss_max_step_m:g})')
            overlap = self._overlap(check, step)
            if overlap < self.config.kiss_min_overlap:
                return 'overlap', (f'cloud does not overlap the previous one where KISS-ICP '
                                   f'put it: {overlap:.2f} of its structure within '
                                   f'{2 * self.config.kiss_voxel_size:g} m '
                                   f'(< kiss_min_overlap {self.config.kiss_min_overlap:g})')
        self._kiss, self._prev = kiss, check
        self._pose = self._origin @ new
        self.registered += 1
        return None

    def _prepare(self, frame: FloatArray) -> _Frame:
        """Voxelise as KISS-ICP does for registration, then normals, structure, constraint."""
        from scipy.spatial import cKDTree

        r = np.linalg.norm(frame, axis=1)
        gated = frame[(r > self.config.kiss_min_range) & (r < self.config.kiss_max_range)]
        pts = np.asarray(self._voxel_down_sample(gated, 1.5 * self.config.kiss_voxel_size),
                         dtype=np.float64).reshape(-1, 3)
        tree = cKDTree(pts)
        k = min(_NEIGHBOURS, len(pts))
        _, idx = tree.query(pts, k=k)
        nb = pts[np.asarray(idx).reshape(len(pts), k)]
        centred = nb - nb.mean(axis=1, keepdims=True)
        w, v = np.linalg.eigh(np.einsum('nki,nkj->nij', centred, centred))
        normals = v[:, :, 0]
        planar = normals[w[:, 1] > _PLANAR * np.maximum(w[:, 0], 1e-12)]
        # Horizontal only: without ground (a tilted or high sensor) z rests on KISS-ICP's
        # motion prediction, but the structure still fixes the position (x, y).
        xy = planar[:, :2]
        info = xy.T @ xy / max(len(pts), 1)
        return _Frame(pts, np.abs(normals[:, 2]) < _STRUCTURE_MAX_NZ,
                      float(np.linalg.eigvalsh(info)[0]), tree)

    def _overlap(self, check: _Frame, step: FloatArray) -> float:
        """Fraction of the cloud's structure points within two voxels of the previous cloud,
        mapped by KISS-ICP's step (``p_prev = step p``); 1.0 when too little structure."""
        prev = self._prev
        struct = check.points[check.structure]
        if prev is None or len(struct) < _MIN_STRUCTURE:
            return 1.0
        dist, _ = prev.tree.query(struct @ step[:3, :3].T + step[:3, 3])
        return float(np.mean(np.asarray(dist) < 2.0 * self.config.kiss_voxel_size))

    def reset(self, reason: str = 'requested') -> None:
        """Start a new segment on the next cloud (a caller's reset: a time jump, a relocalised
        robot); the next sample carries ``reason``."""
        self._reset('requested', reason)

    def _reset(self, kind: str, reason: str) -> None:
        """Forget KISS-ICP's state and start a new segment at the last pose (unless the
        current segment has no cloud yet)."""
        self.reset_counts[kind] += 1
        if self._kiss is None:
            note = f'odometry segment {self.segment} still has no cloud: {reason}'
        else:
            self._kiss, self._prev = None, None
            self._origin = self._pose.copy()
            self.segment += 1
            self.resets += 1
            note = f'odometry reset, segment {self.segment} starts: {reason}'
        self._pending = note if self._pending is None else f'{self._pending}; {note}'

    def _sample(self, stamp_ns: int) -> OdomSample:
        reason, self._pending = self._pending, None
        return OdomSample(int(stamp_ns), self._pose.copy(), None, self.segment, reason)


def _finite_xyz(points: Points) -> FloatArray:
    """(N, 3) float64 C-contiguous x, y, z of the finite rows (none for a malformed array)."""
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] < 3 or not np.issubdtype(p.dtype, np.number):
        return np.zeros((0, 3))
    xyz = p[:, :3].astype(np.float64)
    return np.ascontiguousarray(xyz[np.all(np.isfinite(xyz), axis=1)])


def _in_range(points: FloatArray, low: float, high: float) -> int:
    r = np.linalg.norm(points, axis=1)
    return int(np.count_nonzero((r > low) & (r < high)))
