"""A fleet in one map: the robots' alignments in a fleet replay, their trajectories in robot 0's
map frame, and how well they fit the reference together.

With the back end on, every robot of :mod:`solid_ros.tools.fleet` runs a
:class:`~solid_ros.core.flow.closure.LoopClosure` of its own: each keeps its map, and places
the others' maps in it from the inter-robot loops between them
(:mod:`solid_ros.core.backend.alignment`). :class:`FleetAligner` does here what the peer
exchange does on live robots: it hands each inter-robot loop to the other robot too (both
align from the loops of both), gives each robot the others' keyframe poses as they are now,
and has a robot decide again whenever it got new loops, and all of them at the end.

The fleet frame is robot 0's map. Robot ``i`` is placed by robot 0's alignment of it, else
through a chain of aligned robots (``0 -> j -> i``); a robot no chain reaches stays out.
:func:`fleet_trajectories` gives each placed robot's keyframes in that frame, and
:func:`fleet_errors` scores them: each robot's ATE and the joint ATE of all placed robots'
keyframes after one SE(3) alignment to the reference.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.flow.closure import LoopClosure
from solid_ros.core.results import LoopCandidate
from solid_ros.tools.trajectory_metrics import ate_rmse

__all__ = ['FleetAligner', 'FleetTrajectory', 'alignment_rows', 'fleet_errors', 'fleet_frames',
           'fleet_trajectories']

FloatArray = npt.NDArray[np.float64]


@dataclass
class FleetAligner:
    """Alignment bookkeeping of a fleet replay (module docstring).

    Attributes:
        closures: robot ``i``'s loop closure at ``i``.
        events: ``(robot, stamp_ns, line)`` of every alignment event, in order.
    """

    closures: Sequence[LoopClosure]
    events: list[tuple[int, int, str]] = field(default_factory=list)
    _dirty: set[int] = field(default_factory=set)

    def loops(self, robot: int, loops: Sequence[LoopCandidate]) -> None:
        """Robot ``robot`` published ``loops``: its inter-robot ones go to the peer too."""
        for loop in loops:
            peer = loop.match_session
            if peer == robot or not 0 <= peer < len(self.closures):
                continue
            if loop.verified and self.closures[robot].fleet is not None:
                self._dirty.add(robot)  # its closure held it when it committed the keyframe
            if self.closures[peer].add_peer_loop(loop, robot):
                self._dirty.add(peer)

    def align(self, stamp_ns: int, everyone: bool = False) -> None:
        """Robots that got loops since the last call (or all) decide their peers again."""
        todo = range(len(self.closures)) if everyone else sorted(self._dirty)
        self._dirty.clear()
        if not todo:
            return
        poses = [c.graph.poses() if c.graph is not None else {} for c in self.closures]
        for robot in todo:
            peers = {j: p for j, p in enumerate(poses) if j != robot}
            for event in self.closures[robot].align(peers):
                self.events.append((robot, stamp_ns, event.message))


def _link(closures: Sequence[LoopClosure], a: int, b: int) -> FloatArray | None:
    """``T_map_a <- map_b``: robot a's alignment of b, else the inverse of b's of a."""
    for owner, peer, inverse in ((a, b, False), (b, a, True)):
        fleet = closures[owner].fleet
        st = None if fleet is None else fleet.state(peer)
        if st is not None and st.aligned and st.transform is not None:
            T = np.asarray(st.transform, dtype=np.float64)
            return np.asarray(np.linalg.inv(T), dtype=np.float64) if inverse else T
    return None


def fleet_frames(closures: Sequence[LoopClosure]) -> list[FloatArray | None]:
    """``T_map0 <- map_i`` for every robot (None: no chain of alignments reaches it)."""
    frames: list[FloatArray | None] = [None] * len(closures)
    if not closures:
        return frames
    frames[0] = np.eye(4)
    queue = [0]
    while queue:
        a = queue.pop(0)
        for b in range(len(closures)):
            if frames[b] is None and (T := _link(closures, a, b)) is not None:
                frames[b] = frames[a] @ T  # type: ignore[operator]
                queue.append(b)
    return frames


@dataclass(frozen=True)
class FleetTrajectory:
    """One robot's keyframes in the fleet frame.

    Attributes:
        robot: its id.
        stamps_ns: each keyframe's stamp.
        poses: (K, 4, 4) its corrected poses in robot 0's map (its own map's when not placed).
        placed: whether a chain of alignments placed it in robot 0's map.
        odometry: (K, 4, 4) its odometry poses (its own odometry frame).
    """

    robot: int
    stamps_ns: npt.NDArray[np.int64]
    poses: FloatArray
    placed: bool
    odometry: FloatArray


def fleet_trajectories(closures: Sequence[LoopClosure]) -> list[FleetTrajectory]:
    """Every robot's final graph keyframes, in the fleet frame where it is placed."""
    out = []
    for robot, (closure, frame) in enumerate(zip(closures, fleet_frames(closures))):
        kfs = closure.graph.keyframes() if closure.graph is not None else []
        stamps = np.array([k.stamp_ns for k in kfs], dtype=np.int64)
        poses = np.array([k.pose for k in kfs], dtype=np.float64).reshape(-1, 4, 4)
        odom = np.array([k.odom for k in kfs], dtype=np.float64).reshape(-1, 4, 4)
        if frame is not None:
            poses = frame @ poses
        out.append(FleetTrajectory(robot, stamps, poses, frame is not None, odom))
    return out


def alignment_rows(closures: Sequence[LoopClosure]) -> list[dict[str, Any]]:
    """The report's ``alignments``: each robot's state of each peer it holds loops of."""
    rows = []
    for robot, closure in enumerate(closures):
        for st in closure.fleet.states() if closure.fleet is not None else []:
            rows.append({'robot': robot, 'peer': st.peer, 'aligned': st.aligned,
                         'loops': st.loops, 'inliers': st.inliers, 'rival': st.rival,
                         'jumps': st.jumps})
    return rows


def _paired(traj: FleetTrajectory, stamps: Sequence[int],
            reference: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The trajectory's poses, odometry poses and reference poses where the reference is
    finite."""
    ref_of = dict(zip(stamps, reference))
    ref = np.array([ref_of.get(int(s), np.full((4, 4), np.nan)) for s in traj.stamps_ns])
    ref = ref.reshape(-1, 4, 4)
    ok = np.isfinite(ref).all(axis=(1, 2))
    return traj.poses[ok], traj.odometry[ok], ref[ok]


def fleet_errors(trajs: Sequence[FleetTrajectory], stamps: Sequence[Sequence[int]],
                 reference: Sequence[FloatArray]) -> dict[str, Any]:
    """The report's ``fleet_map``: per robot whether it is placed, its ATE and its odometry's
    (each under its own SE(3) alignment), and ``joint_ate_m``: all placed robots' keyframes
    under one SE(3) alignment to the reference (the fleet map's error)."""
    rows: list[dict[str, Any]] = []
    est: list[FloatArray] = []
    ref: list[FloatArray] = []
    for t in trajs:
        e, o, r = _paired(t, stamps[t.robot], reference[t.robot])
        rows.append({'robot': t.robot, 'placed': t.placed, 'keyframes': len(t.poses),
                     'ate_m': ate_rmse(e, r) if len(e) else None,
                     'odometry_ate_m': ate_rmse(o, r) if len(o) else None})
        if t.placed:
            est.append(e)
            ref.append(r)
    joint = (ate_rmse(np.concatenate(est), np.concatenate(ref))
             if est and sum(len(e) for e in est) else None)
    return {'frame': 'robot 0 map', 'robots': rows, 'joint_ate_m': joint}
