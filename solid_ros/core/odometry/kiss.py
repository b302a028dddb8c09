"""KISS-ICP as an odometry source: clouds in, a pose per cloud out, when there is no odometry.

:class:`KissOdometry` implements :class:`~solid_ros.core.odometry.track.OdometrySource` over
KISS-ICP (Vizzo et al., RA-L 2023; PyPI ``kiss-icp``, imported only when this source is
built). Each cloud is registered with ``KissICP.register_frame`` exactly as KISS-ICP's own
pipeline does, so a cloud it registers gets KISS-ICP's pose unchanged. A max range or voxel of
0 is taken from the first cloud (:func:`~solid_ros.core.odometry.guard.derive_settings`).

A cloud KISS-ICP cannot register never raises and never moves the pose silently: the source
resets (a fresh KISS-ICP), counts the reset and starts a new odometry segment
(:attr:`OdomSample.segment`), with a one-line :attr:`OdomSample.reason` for the caller's log.
The new segment starts at the last accepted pose, a guess that no odometry supports. A cloud
cannot be registered when:

- it holds fewer than :data:`MIN_POINTS` finite points within the range gate (empty, NaN);
- its stamp is older than the last cloud's (a replay restarted, a clock reset);
- it is degenerate: its planar points leave a direction of horizontal translation (the
  sensor's x-y plane) unconstrained: a corridor, a single wall, ``kiss_min_constraint``;
- KISS-ICP raises or returns a non-finite pose;
- the registration jumps: the step from the last pose, or from the constant-velocity
  prediction, is longer than ``kiss_max_step_m`` (0: half the max range, beyond which two
  clouds share too little to register);
- it does not overlap the previous cloud where KISS-ICP put it: its overlap is below
  ``kiss_min_overlap`` times the run's typical overlap
  (:class:`~solid_ros.core.odometry.guard.OverlapGuard`: a jump in the input that KISS-ICP
  followed only part of the way, as it does: its correspondences reach a few metres).

A cloud that jumps or does not overlap when aligned from KISS-ICP's own guess is aligned again
from a time-scaled and a standstill guess (:mod:`solid_ros.core.odometry.kiss_step`); only when
none passes does the source reset, and a failed alignment never enters KISS-ICP's map. A cloud
kept from the standstill guess after a gap in time (the time-scaled guess was tried) gives a
pose but leaves KISS-ICP's motion as it was: along a road, whose structure repeats along the
motion, the standstill alignment passes the checks while the car drives on, and a motion taken
from it held the odometry still for 80 clouds (riv281 from cloud 110, 2.6 s after the last:
none of their steps tracked, plain KISS-ICP 50). At the usual spacing a standstill is taken
for one, motion included: a hand-held sensor stops turning (quickshack).
A degenerate or non-overlapping cloud is itself a good cloud: it becomes the first cloud of the
new segment. Clouds with too few points are dropped and the next one starts the segment.
Clouds that lose some points (NaN rows) are counted in :attr:`KissOdometry.input_counts`.
No covariance is given: KISS-ICP reports none, and the back end uses its per-metre model.
That model holds KISS-ICP's typical steps but not a runaway in a weak scene (hku1: steps
0.6-0.8 m against 0.1-0.2 m of the reference): the back end checks a scan-only odometry with
registered steps (``backend_step_registration``, :mod:`solid_ros.core.backend.posegraph`).
"""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import NodeConfig
from solid_ros.core.errors import SolidError
from solid_ros.core.odometry.guard import Frame, OverlapGuard, derive_settings, prepare
from solid_ros.core.odometry.kiss_step import Aligned, align, commit, guesses, prepared
from solid_ros.core.odometry.track import OdomSample, Points

__all__ = ['MIN_POINTS', 'KissOdometry', 'derive_settings', 'load_kiss_icp']

FloatArray = npt.NDArray[np.float64]

MIN_POINTS = 100  # finite points within the range gate a cloud needs to be registered


def load_kiss_icp() -> tuple[Any, Any, Any]:
    """Import KISS-ICP on first use: ``KissICP``, ``KISSConfig``, ``voxel_down_sample``.

    Raises:
        SolidError: kiss-icp, or small_gicp (the overlap check's neighbours,
            :mod:`solid_ros.core.odometry.guard`), is not installed (the message says how to
            install it).
    """
    try:
        from kiss_icp.config import KISSConfig  # type: ignore[import-untyped]
        from kiss_icp.kiss_icp import KissICP  # type: ignore[import-untyped]
        from kiss_icp.voxelization import voxel_down_sample  # type: ignore[import-untyped]
    except ImportError as err:
        raise SolidError("odometry_source 'kiss_icp' needs KISS-ICP: pip install kiss-icp "
                         "(or pip install 'solid_ros[kiss]')") from err
    try:
        import small_gicp  # noqa: F401
    except ImportError as err:  # at start, not as a reset on every cloud
        raise SolidError("odometry_source 'kiss_icp' needs small_gicp for its overlap "
                         'check: pip install small-gicp') from err
    return KissICP, KISSConfig, voxel_down_sample


class KissOdometry:
    """KISS-ICP odometry behind :class:`~solid_ros.core.odometry.track.OdometrySource`.

    Args:
        config: node settings (``kiss_*``); defaults when None.
        segment: the first segment's number (a source that continues another one, as
            :class:`~solid_ros.core.odometry.kiss_process.KissProcess` after a restart).
        pose: where the first segment starts in the odometry frame (identity when None).

    Raises:
        SolidError: kiss-icp is not installed.

    Attributes:
        name: 'kiss_icp'.
        takes_point_times: True: :meth:`pose_for` takes per-point times (deskew).
        config: the settings in use (max range and voxel derived from the first cloud when
            they are 0).
        segment: the current odometry segment (0 until the first reset).
        resets: resets so far (segments started after the first).
        reset_counts: clouds that could not be registered, by kind: 'points', 'stamp',
            'degenerate', 'failed', 'jump', 'overlap' (a bad cloud while the new segment has
            no cloud yet is counted but starts no further segment), and 'requested'
            (:meth:`reset`).
        input_counts: clouds that lost points: 'nan' (rows with a non-finite coordinate).
        recovered: clouds whose registration from KISS-ICP's guess failed the checks and that
            registered from another guess instead, by guess ('time-scaled', 'standstill').
        registered: clouds registered.
        deskewed: clouds that came with per-point times while ``kiss_deskew`` is on.
    """

    name = 'kiss_icp'
    takes_point_times = True  # pose_for deskews with per-point times

    def __init__(self, config: NodeConfig | None = None, *, segment: int = 0,
                 pose: FloatArray | None = None) -> None:
        self.config = config if config is not None else NodeConfig()
        self._KissICP, self._KISSConfig, self._voxel_down_sample = load_kiss_icp()
        self.segment = int(segment)
        self.resets = 0
        self.registered = 0
        self.deskewed = 0
        self.reset_counts: Counter[str] = Counter()
        self.input_counts: Counter[str] = Counter()
        start = np.eye(4) if pose is None else np.array(pose, dtype=np.float64)
        self._origin: FloatArray = start.copy()  # odom <- this segment's KISS-ICP frame
        self._pose: FloatArray = start  # last accepted pose, odom frame
        self._kiss: Any = None  # None: the segment has no cloud yet
        self._prev: Frame | None = None
        self._guard: OverlapGuard | None = None
        self._stamp: int | None = None
        self._stamps: tuple[int | None, int | None] = (None, None)  # segment's last two
        self.recovered: Counter[str] = Counter()
        self._pending: str | None = None  # reset reason for the next sample

    def _new_kiss(self) -> Any:
        c = self.config
        kc = self._KISSConfig()
        kc.data.max_range = c.kiss_max_range
        kc.data.min_range = c.kiss_min_range
        kc.data.deskew = c.kiss_deskew
        kc.mapping.voxel_size = c.kiss_voxel_size
        return self._KissICP(kc)

    @property
    def max_step_m(self) -> float:
        """Longest registration step not taken as a jump, metres."""
        c = self.config
        return c.kiss_max_step_m if c.kiss_max_step_m > 0 else c.kiss_max_range / 2.0

    @property
    def typical_overlap(self) -> float | None:
        """The run's median overlap of consecutive clouds (None: not measured yet)."""
        return None if self._guard is None else self._guard.typical

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
        frame, keep = _finite_xyz(points)
        if len(keep) and not keep.all():
            self.input_counts['nan'] += 1
        if self._guard is None:
            self._settle(frame)
        c = self.config
        ranges = _norms(frame)
        in_gate = (ranges > c.kiss_min_range) & (ranges < c.kiss_max_range)
        gated = int(np.count_nonzero(in_gate))
        if gated < MIN_POINTS:
            self._reset('points', f'{gated} finite points within ({c.kiss_min_range:g}, '
                        f'{c.kiss_max_range:g}) m, needs {MIN_POINTS}')
            return self._sample(stamp_ns)
        if self._stamp is not None and stamp_ns < self._stamp:
            self._reset('stamp', f'cloud stamp {(self._stamp - stamp_ns) * 1e-9:.3f} s older '
                        'than the last one')
        self._stamp = int(stamp_ns)
        times = np.zeros(0) if point_times is None else np.ravel(
            np.asarray(point_times, dtype=np.float64))
        times = times[keep] if len(times) == len(keep) else np.zeros(0)
        if len(times) and c.kiss_deskew:
            self.deskewed += 1
        check = self._prepare(frame[in_gate])
        if self._kiss is not None and check.constraint < c.kiss_min_constraint:
            self._reset('degenerate', f'degenerate cloud: translation constraint '
                        f'{check.constraint:.4f} < {c.kiss_min_constraint:g} '
                        '(a corridor or a single wall)')
        why = self._register(frame, times, check)
        if why is not None:
            self._reset(*why)
            if why[0] != 'failed':
                self._register(frame, times, check)  # a good cloud: first of the new segment
        return self._sample(stamp_ns)

    def _settle(self, frame: FloatArray) -> None:
        """Derive the settings left to the data from the first cloud with finite points."""
        if len(frame) == 0:
            return
        self.config = derive_settings(self.config, [frame])
        self._guard = OverlapGuard(self.config.kiss_min_overlap,
                                   2.0 * self.config.kiss_voxel_size)

    def _register(self, frame: FloatArray, times: FloatArray,
                  check: Frame) -> tuple[str, str] | None:
        """Register one cloud; on success keep it, else return (kind, reason).

        It is aligned from KISS-ICP's guess; when that fails the checks, from the other
        guesses (:func:`~solid_ros.core.odometry.kiss_step.guesses`) before giving up.
        """
        fresh = self._kiss is None
        kiss = self._new_kiss() if fresh else self._kiss
        first: tuple[str, str] | None = None
        try:
            source, map_points = prepared(kiss, frame, times)
            tried = guesses(kiss, None if fresh else self._ratio())
            # After a gap in time no guess bridged, a standstill pose is no motion.
            gap = any(label == 'time-scaled' for label, _ in tried)
            for label, guess in tried:
                step = align(kiss, source, map_points, guess)
                if step.pose.shape != (4, 4) or not np.all(np.isfinite(step.pose)):
                    return 'failed', 'KISS-ICP returned a non-finite pose'
                why, overlap = (None, None) if fresh else self._check(kiss, step, check)
                if why is None:
                    commit(kiss, step, not (gap and label == 'standstill'))
                    kept = label
                    break
                first = first or why
            else:
                return first
        except Exception as err:  # the binding may raise anything
            return 'failed', f'KISS-ICP failed: {" ".join(str(err).split())[:160]}'
        if first is not None:
            self.recovered[kept] += 1
        if overlap is not None and self._guard is not None:
            self._guard.accept(overlap)
        self._kiss, self._prev = kiss, check
        self._pose = self._origin @ step.pose
        self._stamps = (self._stamps[1], self._stamp)
        self.registered += 1
        return None

    def _ratio(self) -> float | None:
        """Time since the segment's last cloud over the time between its two before."""
        older, last = self._stamps
        if older is None or last is None or self._stamp is None or last <= older:
            return None
        return (self._stamp - last) / (last - older)

    def _check(self, kiss: Any, step: Aligned,
               check: Frame) -> tuple[tuple[str, str] | None, float | None]:
        """(kind, reason) when the aligned cloud jumps or does not overlap, and its overlap."""
        if self._prev is None or self._guard is None:
            return None, None
        last = np.asarray(kiss.last_pose, dtype=np.float64)
        move = np.linalg.inv(last) @ step.pose
        jump = max(float(np.linalg.norm(move[:3, 3])),
                   float(np.linalg.norm((np.linalg.inv(step.guess) @ step.pose)[:3, 3])))
        if jump > self.max_step_m:
            return ('jump', f'registration jumped {jump:.2f} m (> {self.max_step_m:g} m)'), None
        overlap = self._guard.overlap(check, self._prev, move)
        if self._guard.fails(overlap):
            return ('overlap', f'cloud does not overlap the previous one where KISS-ICP put '
                    f'it: {overlap:.2f} of its structure within {self._guard.reach:g} m, below '
                    f"{self._guard.bar:.2f} ({self._guard.ratio:g} x the run's "
                    f'{self._guard.typical:.2f})'), overlap
        return None, overlap

    def _prepare(self, gated: FloatArray) -> Frame:
        """Voxelise the points within the range gate as KISS-ICP does for registration, then
        normals, structure, constraint."""
        voxel = 1.5 * self.config.kiss_voxel_size
        return prepare(np.asarray(self._voxel_down_sample(gated, voxel), dtype=np.float64))

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
            self._kiss, self._prev, self._stamps = None, None, (None, None)
            self._origin = self._pose.copy()
            self.segment += 1
            self.resets += 1
            note = f'odometry reset, segment {self.segment} starts: {reason}'
        self._pending = note if self._pending is None else f'{self._pending}; {note}'

    def _sample(self, stamp_ns: int) -> OdomSample:
        reason, self._pending = self._pending, None
        return OdomSample(int(stamp_ns), self._pose.copy(), None, self.segment, reason)


def _finite_xyz(points: Points) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
    """(N, 3) float64 C-contiguous x, y, z of the finite rows, and which rows those are (none
    for a malformed array).

    Column by column and without the masked copy when every row is finite: a row-wise
    ``np.all(..., axis=1)`` and the copy took 6.6 ms of a 121k-point cloud.
    """
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] < 3 or not np.issubdtype(p.dtype, np.number):
        return np.zeros((0, 3)), np.zeros(0, dtype=bool)
    xyz = np.array(p[:, :3], dtype=np.float64, order='C')
    finite = np.isfinite(xyz)
    keep = finite[:, 0] & finite[:, 1] & finite[:, 2]
    return (xyz if keep.all() else xyz[keep]), keep


def _norms(points: FloatArray) -> FloatArray:
    """Each row's length, as ``np.linalg.norm(points, axis=1)`` sums it (x, then y, then z),
    without its row-wise reduction (3.7 ms of a 121k-point cloud, computed twice before)."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    out: FloatArray = np.sqrt(x * x + y * y + z * z)
    return out
