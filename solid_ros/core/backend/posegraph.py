"""Back end: a pose graph (gtsam iSAM2) that turns published loops into corrected poses.

One call per keyframe, :meth:`PoseGraph.update` with the detector's :class:`ScanResult` and
the keyframe's odometry sample, adds the keyframe's variable ``X_i = T_map_sensor``, the
odometry step from the previous keyframe (noise: :mod:`solid_ros.core.backend.noise`), and the
keyframe's loops, runs an iSAM2 step (``backend_extra_iterations`` more after loops) and
returns a :class:`BackendState`: the corrected pose, the correction ``T_map_odom`` and the
marginal covariance of the pose.

Loops. A loop ``T`` from query ``q`` to match ``m`` of this session is a between factor
``X_m^-1 X_q = T`` under the robust kernel ``backend_loop_kernel``; to a keyframe of a loaded
map (fixed pose ``P_m`` in the map frame) it is a unary factor ``X_q = P_m T``. Each loop is
first judged against the current estimate (:mod:`solid_ros.core.backend.gate`): its Mahalanobis
distance with the loop's covariance plus the relative marginal covariance of its two keyframes
(iSAM2's joint marginal). Within ``backend_loop_gate`` sigmas it is added; beyond
``backend_loop_refuse`` refused; in between it waits until a loop of another keyframe agrees
with it. Where loops already tie the map the relative covariance is small and a false loop
lies far beyond the refusal; after a long loop-free drive it holds the odometry's drift, so a
true first loop passes (or waits one keyframe).

Registered steps. With ``backend_step_registration`` on, the detector registers each keyframe
to the previous one (:attr:`ScanResult.step`); the result is a second between factor beside
the odometry step, least squares with its covariance and the loop floors. The odometry
steps then take the loop kernel (Huber): where the two agree both count, where they disagree
by many sigmas the clouds win. A scan-only odometry that ran away in a weak scene (KISS-ICP
on hku1: steps 0.6-0.8 m against 0.1-0.2 m) is pulled back. Where the step's registration
failed a test (a hard scene for the odometry too: hku1's keyframe 62, whose KISS-ICP step is
1.2 m off) the odometry step alone links the keyframes, robust and with
:func:`~solid_ros.core.backend.noise.unchecked_covariance` (as uncertain as it is long), so a
loop that contradicts it is not refused by the gate. Not across a segment break.

Segments (:mod:`solid_ros.core.backend.segments`). An odometry step longer than
``backend_segment_jump_m`` (a jump, a reset) gets no odometry factor: the keyframe starts a new
segment whose first pose has a weak prior at the pose that keeps map->odom where it was. The
first loop between two parts no loop has tied yet is not gated: it moves the part that is not
fixed rigidly onto the other (a ``'tie'`` event) and the graph is rebuilt there.

Loaded map. Its keyframe poses are fixed. The session starts with map = odom; the first loop
to a loaded keyframe moves the whole session into the map's frame at once (map->odom jumps,
an ``'anchor'`` event), later ones refine it through the gate.

Failures of gtsam are caught and the graph rebuilt (:mod:`solid_ros.core.backend.solver`); bad
odometry covariances fall back to the model with a throttled ``'odom_covariance'`` warning.
Nothing here logs: events come back in the state for the caller to log.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.backend.gate import Candidate, LoopJudge, loop_sigmas, relative
from solid_ros.core.backend.gtsam_bridge import GTSAM_ERRORS
from solid_ros.core.backend.noise import (
    floored,
    loop_covariance,
    odometry_step_noise,
    rotation_angle,
    swap_blocks,
    unchecked_covariance,
)
from solid_ros.core.backend.segments import MAP, Segments, move_rigidly, tie_move
from solid_ros.core.backend.solver import FactorRecord, GraphSolver
from solid_ros.core.config import SolidConfig
from solid_ros.core.geometry import pose_to_vector, vector_to_matrix
from solid_ros.core.odometry.track import OdomSample
from solid_ros.core.results import (
    BackendEvent,
    BackendState,
    Keyframe,
    LoopCandidate,
    LoopOutcome,
    ScanResult,
    loop_name,
)

__all__ = ['PoseGraph', 'key_of']

FloatArray = npt.NDArray[np.float64]
_ANCHOR_SIGMAS = (1e-3, 1e-3)  # metres, radians: the session's first pose (map = odom)
_WEAK_SIGMAS = (100.0, 1.0)  # a new segment's first pose, a re-anchored session
_WARN_PERIOD_NS = 10 * 10**9
_KEY_BASE = ord('x') << 56  # gtsam.symbol('x', index)


def key_of(index: int) -> int:
    """gtsam key of this session's keyframe ``index`` (``gtsam.symbol('x', index)``)."""
    return _KEY_BASE | int(index)


@dataclass
class _Kf:
    index: int
    stamp_ns: int
    odom: FloatArray
    covariance: Any
    segment: int
    odom_segment: int = 0  # the odometry source's segment (it resets when it loses track)


class _Rows:
    """Append-only arrays of the keyframes' indices, stamps and odometry poses (doubling)."""

    def __init__(self) -> None:
        self._n = 0
        self._indices = np.zeros(0, dtype=np.int64)
        self._stamps = np.zeros(0, dtype=np.int64)
        self._odom = np.zeros((0, 4, 4))

    def append(self, index: int, stamp_ns: int, odom: FloatArray) -> None:
        if self._n == len(self._indices):
            size = max(64, 2 * self._n)
            self._indices = np.resize(self._indices, size)
            self._stamps = np.resize(self._stamps, size)
            self._odom = np.resize(self._odom, (size, 4, 4))
        self._indices[self._n], self._stamps[self._n] = index, stamp_ns
        self._odom[self._n] = odom
        self._n += 1

    def arrays(self) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], FloatArray]:
        """Copies of the rows so far."""
        n = self._n
        return self._indices[:n].copy(), self._stamps[:n].copy(), self._odom[:n].copy()


def _sigma_cov(sigmas: tuple[float, float]) -> FloatArray:
    return floored(np.zeros((6, 6)), *sigmas)


class PoseGraph:
    """The pose graph of this session's keyframes (see the module docstring).

    Args:
        config: settings (``session_id`` and the ``backend_*`` ones).
        prior_map: fixed map-frame poses of a loaded map's keyframes, by ``(session, index)``
            (4x4 or ``x y z qx qy qz qw``), e.g. from
            :func:`solid_ros.core.database.persistence.read_map_poses`.

    Raises:
        BackendError: gtsam is not installed.
    """

    def __init__(self, config: SolidConfig,
                 prior_map: Mapping[tuple[int, int], Any] | None = None) -> None:
        self.config = config
        self._prior = {(int(s), int(i)): vector_to_matrix(pose_to_vector(p))
                       for (s, i), p in (prior_map or {}).items()}
        self._placed: tuple[npt.NDArray[np.int64], FloatArray] | None = None
        # Loop outcomes so far (LoopOutcome reasons), and 'confirmed' / 'unconfirmed' for
        # pending loops taken or dropped later.
        self.counts: Counter[str] = Counter()
        self.reset()

    def reset(self) -> None:
        """Forget this session's keyframes (after the detector was reset); the loaded map
        stays."""
        cfg = self.config
        self._solver = GraphSolver(cfg.backend_loop_kernel, cfg.backend_loop_kernel_width)
        self._kfs: dict[int, _Kf] = {}
        # The keyframes' indices, stamps and odometry poses as arrays, in order (the hint of
        # every keyframe takes them all: listing them object by object grew to 28 ms a
        # keyframe at 3,000 keyframes).
        self._rows = _Rows()
        self._last: _Kf | None = None
        self._segs = Segments()
        self._segment = -1
        self._correction: FloatArray = np.eye(4)
        self._warned: dict[str, tuple[int, int]] = {}
        self._judge = LoopJudge()
        self.loops: list[LoopCandidate] = []  # accepted loops, in order
        self.steps = 0  # registered steps added beside the odometry

    @property
    def anchored(self) -> bool:
        """Whether the session has been placed in the loaded map's frame."""
        return self._segs.anchored

    @property
    def rebuilds(self) -> int:
        """Times the graph was rebuilt after a gtsam failure."""
        return self._solver.rebuilds

    def correction(self) -> FloatArray:
        """``T_map_odom`` at the newest keyframe (identity before any)."""
        out: FloatArray = self._correction.copy()
        return out

    def update(self, result: ScanResult, odom: OdomSample | None = None) -> BackendState:
        """Add one scan's keyframe and loops (see the module docstring).

        Args:
            result: what the detector returned for the scan (gated-out scans change nothing).
            odom: the keyframe's odometry sample (pose and covariance); without it the pose
                the detector got (``result.pose``) is used with the noise model.

        Bad input (no pose, a repeated index, an unusable covariance) and gtsam failures
        come back as events; call from one thread.

        Raises:
            BackendError: gtsam failed and not even the graph before this keyframe's new
                factors could be solved again (never seen in the tests and benches).
        """
        t0 = time.perf_counter()
        events: list[BackendEvent] = []
        T = _odom_pose(result, odom)
        index = result.query_index
        if not result.keyframe or index < 0:
            return self._state(result, None, (), events, t0)
        if T is None:
            self._warn(events, 'no_pose', result.stamp_ns, f'keyframe {index} has no odometry '
                       'pose: it stays out of the pose graph and its loops are skipped')
            return self._state(result, None, self._skip(result.loops, 'no_pose'), events, t0)
        if self._last is not None and index <= self._last.index:
            events.append(BackendEvent('ignored', f'keyframe {index} is not after keyframe '
                                       f'{self._last.index}: ignored (reset the back end with '
                                       'the detector)'))
            return self._state(result, None, self._skip(result.loops, 'no_pose'), events, t0)
        kf = self._add_keyframe(index, result.stamp_ns, T, odom, events, result.step)
        outcomes = self._add_loops(kf, result.loops, events)
        return self._state(result, kf, outcomes, events, t0)

    def _add_keyframe(self, index: int, stamp_ns: int, T: FloatArray, odom: OdomSample | None,
                      events: list[BackendEvent], registered: LoopCandidate | None = None
                      ) -> _Kf:
        cfg = self.config
        cov = None if odom is None else odom.covariance
        prev = self._last
        key = key_of(index)
        if prev is None:
            self._segment = self._segs.new()
            init = T.copy()
            rec = FactorRecord('anchor', (key,), init, _sigma_cov(_ANCHOR_SIGMAS))
        else:
            step = np.asarray(np.linalg.solve(prev.odom, T), dtype=np.float64)
            init = self._correction @ T
            jump = float(np.linalg.norm(step[:3, 3]))
            reset = odom is not None and odom.segment != prev.odom_segment
            if reset or jump > cfg.backend_segment_jump_m:
                self._segment = self._segs.new()
                rec = FactorRecord('prior', (key,), init, _sigma_cov(_WEAK_SIGMAS))
                why = (f'the odometry reset ({odom.reason or "new odometry segment"})'
                       if reset and odom is not None else f'odometry jumped {jump:.1f} m')
                events.append(BackendEvent('segment', f'{why} between keyframes {prev.index} '
                                           f'and {index}: new graph segment {self._segment}'))
            else:
                noise = odometry_step_noise(step, prev.covariance, cov, cfg)
                if noise.bad:
                    self._warn(events, 'odom_covariance', stamp_ns, 'odometry covariance is '
                               'not usable (NaN, negative or not positive definite): the '
                               'noise model is used instead')
                rec = FactorRecord('odom', (key_of(prev.index), key), step, noise.covariance)
        recs = [rec]
        if rec.kind == 'odom' and cfg.backend_step_registration == 'on':
            # A scan-only odometry: robust, so that registered steps and loops outvote a step
            # that ran away; one the clouds could not check is as uncertain as it is long.
            rec.robust = True
            if registered is not None and prev is not None:
                recs += self._step_record(prev, key, registered)
            if len(recs) == 1:
                rec.covariance = unchecked_covariance(rec.measured, rec.covariance)
            elif prev is not None:
                # Start from the registered step: one iSAM2 step from the odometry's guess
                # weighs a runaway odometry step fully (the kernel sees no residual there).
                init = self._solver.values[key_of(prev.index)] @ recs[1].measured
        kf = _Kf(index, stamp_ns, T, cov, self._segment, 0 if odom is None else odom.segment)
        self._note_rebuild(self._solver.add(recs, {key: init}), events)
        self._kfs[index] = kf
        self._rows.append(index, stamp_ns, T)
        self._last = kf
        return kf

    def _step_record(self, prev: _Kf, key: int, registered: LoopCandidate
                     ) -> list[FactorRecord]:
        """The registered step to the previous keyframe as a factor (none when it is to
        another keyframe or its covariance is not usable)."""
        cov = loop_covariance(registered.covariance, self.config)
        if (cov is None or registered.match_index != prev.index
                or registered.match_session != self.config.session_id):
            return []
        self.steps += 1
        return [FactorRecord('step', (key_of(prev.index), key), registered.matrix(), cov)]

    def _add_loops(self, kf: _Kf, loops: Sequence[LoopCandidate],
                   events: list[BackendEvent]) -> tuple[LoopOutcome, ...]:
        cfg, judge = self.config, self._judge
        outcomes: list[LoopOutcome] = []
        taken: list[Candidate] = []
        for loop in loops:
            rec, reason = self._loop_record(kf, loop)
            if rec is None:
                outcomes.append(LoopOutcome(loop, reason))
            elif (tie := tie_move(self._segs, self._solver, kf.segment, None
                                  if rec.kind == 'map_loop'
                                  else self._kfs[loop.match_index].segment, rec)) is not None:
                outcomes.append(self._tie(kf, loop, rec, *tie, events))
            else:
                c = Candidate(rec, loop, loop_sigmas(self._solver, rec), kf.index)
                outcomes.append(LoopOutcome(loop, judge.judge(self._solver, cfg, c, taken,
                                                              events), c.sigmas))
        later = {id(c.loop) for c in judge.untangle(self._solver, cfg, taken)}
        failed = self._take(taken, events) if taken else set()
        if taken:
            again = judge.regate(self._solver, cfg, events)
            if again:
                self.counts.update(failed=len(self._take(again, events)))
        self.counts.update(unconfirmed=judge.expire(kf.index, events),
                           confirmed=sum(e.kind == 'confirmed' for e in events))
        self.counts += Counter()  # drop zero counts
        outcomes = [LoopOutcome(o.loop, 'failed' if id(o.loop) in failed else 'pending',
                                o.sigmas) if id(o.loop) in failed | later else o
                    for o in outcomes]
        for o in outcomes:
            self.counts[o.reason] += 1
        return tuple(outcomes)

    def _take(self, taken: list[Candidate], events: list[BackendEvent]) -> set[int]:
        """Add accepted loops to the graph (``backend_extra_iterations`` more steps).

        Returns:
            ``id()`` of the loops gtsam could not solve with (dropped again).
        """
        err = self._solver.add([c.rec for c in taken], {}, self.config.backend_extra_iterations)
        self._note_rebuild(err, events)
        failed = set()
        for c in taken:
            if c.rec.dropped:
                failed.add(id(c.loop))
            else:
                self.loops.append(c.loop)
        return failed

    def _loop_record(self, kf: _Kf, loop: LoopCandidate) -> tuple[FactorRecord | None, str]:
        """The factor of a loop, or None and why there is none."""
        cov = loop_covariance(loop.covariance, self.config)
        if cov is None:
            return None, 'no_covariance'
        T = loop.matrix()
        if loop.match_session == self.config.session_id:
            if loop.match_index not in self._kfs:
                return None, 'unknown_keyframe'
            return FactorRecord('loop', (key_of(loop.match_index), key_of(kf.index)), T, cov,
                                robust=True), 'added'
        fixed = self._prior.get((loop.match_session, loop.match_index))
        if fixed is None:
            return None, 'unknown_session'
        return FactorRecord('map_loop', (key_of(kf.index),), fixed @ T, cov, robust=True), 'added'

    def _tie(self, kf: _Kf, loop: LoopCandidate, rec: FactorRecord, moved: set[int],
             move: FloatArray, events: list[BackendEvent]) -> LoopOutcome:
        """Place untied segments with a loop (the first loop to a loaded map moves the whole
        session into the map's frame), then tie them."""
        first_anchor = rec.kind == 'map_loop' and not self._segs.anchored
        keys = {key_of(k.index) for k in self._kfs.values() if k.segment in moved}
        if not move_rigidly(self._solver, keys, move, rec,
                            _sigma_cov(_WEAK_SIGMAS) if first_anchor else None):
            return LoopOutcome(loop, 'failed')
        if rec.kind == 'map_loop':
            self._segs.anchored = True
        self._segs.join(kf.segment, MAP if rec.kind == 'map_loop'
                        else self._kfs[loop.match_index].segment)
        self.loops.append(loop)
        what = 'relocalised in the loaded map' if first_anchor else (
            f'segment(s) {", ".join(map(str, sorted(moved)))} placed')
        events.append(BackendEvent('anchor' if first_anchor else 'tie',
                                   f'{what} by loop {loop_name(loop)}: map->odom moved '
                                   f'{float(np.linalg.norm(move[:3, 3])):.2f} m, '
                                   f'{math.degrees(rotation_angle(move)):.1f} deg'))
        return LoopOutcome(loop, 'anchor' if first_anchor else 'tie')

    def _state(self, result: ScanResult, kf: _Kf | None, loops: tuple[LoopOutcome, ...],
               events: list[BackendEvent], t0: float) -> BackendState:
        pose = cov = None
        if kf is not None:
            key = key_of(kf.index)
            pose = self._solver.pose(key)
            self._correction = np.asarray(pose @ np.linalg.inv(kf.odom), dtype=np.float64)
            try:
                cov = self._solver.marginal(key)
            except GTSAM_ERRORS:
                cov = None
        return BackendState(result.query_index, result.stamp_ns, kf is not None, pose,
                            self._correction.copy(), cov, self._segment, loops, tuple(events),
                            (time.perf_counter() - t0) * 1e3)

    def _skip(self, loops: Sequence[LoopCandidate], reason: str) -> tuple[LoopOutcome, ...]:
        self.counts[reason] += len(loops)
        return tuple(LoopOutcome(loop, reason) for loop in loops)

    def _note_rebuild(self, error: str | None, events: list[BackendEvent]) -> None:
        if error is not None:
            events.append(BackendEvent('rebuild', f'gtsam failed ({error}): the pose graph was '
                                       'rebuilt from its last good state'))

    def _warn(self, events: list[BackendEvent], kind: str, stamp_ns: int, message: str) -> None:
        """At most one warning of a kind per 10 s of stamps, with the count since the last."""
        last, count = self._warned.get(kind, (None, 0))
        count += 1
        if last is None or not 0 <= stamp_ns - last < _WARN_PERIOD_NS:
            more = f' ({count} times since the last warning)' if count > 1 else ''
            events.append(BackendEvent(kind, message + more))
            self._warned[kind] = (stamp_ns, 0)
        else:
            self._warned[kind] = (last, count)

    # ------------------------------------------------------------------------------ results

    def keyframes(self) -> list[Keyframe]:
        """Every keyframe in the graph with its current corrected pose, in order."""
        est = self._solver.estimate() if self._kfs else {}
        return [Keyframe(k.index, k.stamp_ns, k.odom.copy(), est[key_of(k.index)], k.segment)
                for k in self._kfs.values()]

    def keyframe_arrays(self) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64],
                                       FloatArray, FloatArray]:
        """:meth:`keyframes` as arrays: indices, stamps, corrected poses ``(N, 4, 4)`` and
        odometry poses ``(N, 4, 4)``, in order (what the pose graph's hint takes, without an
        object per keyframe)."""
        indices, stamps, odom = self._rows.arrays()
        if not len(indices):
            return indices, stamps, np.zeros((0, 4, 4)), odom
        keys, poses = self._solver.estimate_arrays()
        at = np.searchsorted(keys, _KEY_BASE | indices)
        return indices, stamps, poses[at], odom

    def relative_covariance(self, index_a: int, index_b: int) -> FloatArray | None:
        """Covariance of ``X_a^-1 X_b`` for two of this session's keyframes (ROS order, right
        perturbation in ``b``'s frame): iSAM2's joint marginal, not ``b``'s own marginal, which
        also holds the uncertainty both share since the first keyframe. None when either is
        not in the graph or gtsam cannot give it."""
        if index_a not in self._kfs or index_b not in self._kfs:
            return None
        try:
            _, cov = relative(self._solver, key_of(index_a), key_of(index_b))
        except GTSAM_ERRORS:
            return None
        out: FloatArray = swap_blocks(cov)
        return out if bool(np.all(np.isfinite(out))) else None

    def poses(self) -> dict[int, FloatArray]:
        """Corrected pose ``T_map_sensor`` of every keyframe, by index."""
        return {k.index: k.pose for k in self.keyframes()}

    def placed_map(self) -> dict[tuple[int, int], FloatArray]:
        """The loaded map's fixed keyframe poses by ``(session, index)`` once the newest
        keyframe's segment is tied to that map (the session relocalised in it; empty before:
        the session's poses are then in another frame)."""
        if self._last is None or not self._segs.tied(self._last.segment, MAP):
            return {}
        return dict(self._prior)

    def placed_arrays(self) -> tuple[npt.NDArray[np.int64], FloatArray] | None:
        """:meth:`placed_map` as read-only arrays, ``(M, 2)`` keys and ``(M, 4, 4)`` poses,
        built once (None before the session is tied to the map): the pose graph's hint takes
        them every keyframe, and converting the dict took 21 ms a keyframe in a map of
        20,000 keyframes."""
        if self._last is None or not self._segs.tied(self._last.segment, MAP):
            return None
        if self._placed is None:
            keys = np.array(list(self._prior), dtype=np.int64).reshape(-1, 2)
            poses = np.array(list(self._prior.values()), dtype=np.float64).reshape(-1, 4, 4)
            keys.flags.writeable = poses.flags.writeable = False
            self._placed = (keys, poses)
        return self._placed

    def map_poses(self) -> dict[tuple[int, int], FloatArray]:
        """Map-frame poses by ``(session, index)``: this session's corrected keyframes and the
        loaded map's fixed ones (what a saved database stores)."""
        own = {(self.config.session_id, i): p for i, p in self.poses().items()}
        return {**self._prior, **own}


def _odom_pose(result: ScanResult, odom: OdomSample | None) -> FloatArray | None:
    """The keyframe's 4x4 odometry pose: the sample's, else the detector's; None if neither
    is a finite 4x4 pose."""
    if odom is not None:
        T = np.asarray(odom.pose, dtype=np.float64)
    elif result.pose is not None:
        T = vector_to_matrix(result.pose)
    else:
        return None
    return T if T.shape == (4, 4) and bool(np.all(np.isfinite(T))) else None
