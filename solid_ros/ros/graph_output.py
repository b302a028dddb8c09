"""The pose graph behind solid_node, between the verify thread and the executor.

The verify thread hands every verified keyframe (its :class:`~solid_ros.core.results.ScanResult`
and paired :class:`~solid_ros.core.odometry.track.OdomSample`) to :meth:`GraphOutput.take`, after
its
loops went out, so the back end never delays a loop. The graph is updated there, its events are
logged, and what the publishers need is copied into one immutable :class:`GraphSnapshot`: the
correction ``T_map_odom``, the newest pose's covariance and the corrected keyframe path. The
executor's timers, callbacks and services read the newest snapshot without waiting for the
graph, and so does the verify thread: :meth:`GraphOutput.hint` hands the detector the graph
after the previous keyframe (taken on that thread, so the node verifies with the same graph as
the replay) for its candidates by position (:mod:`solid_ros.core.candidates.position`). Its arrays
are
read-only. No ROS import.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from solid_ros.core.backend.posegraph import PoseGraph
from solid_ros.core.candidates.position import GraphHint
from solid_ros.core.errors import SolidError
from solid_ros.core.results import BackendState
from solid_ros.ros.stages import Log, Verified

__all__ = ['GraphOutput', 'GraphSnapshot']

FloatArray = npt.NDArray[np.float64]
# Back-end events after which earlier keyframes may have moved (a full snapshot is read).
_MOVING_EVENTS = ('anchor', 'tie', 'rebuild', 'confirmed', 'segment')


def _eye() -> FloatArray:
    return np.eye(4)


@dataclass(frozen=True)
class GraphSnapshot:
    """The back end's results after one keyframe (read-only: shared between threads).

    Attributes:
        version: counts the updates that added a keyframe (0: none yet).
        correction: ``T_map_odom`` (identity until the first keyframe).
        covariance: 6x6 covariance of the newest keyframe pose (ROS order, right perturbation
            in the sensor frame), or None.
        indices: indices of the keyframes in the graph, in order.
        stamps_ns: their stamps.
        poses: their corrected poses ``T_map_sensor``, shape (N, 4, 4).
        odom: their odometry poses ``T_odom_sensor``, shape (N, 4, 4).
        loops: loops in the graph.
    """

    version: int = 0
    correction: FloatArray = field(default_factory=_eye)
    covariance: FloatArray | None = None
    indices: npt.NDArray[np.int64] = field(
        default_factory=lambda: np.zeros(0, dtype=np.int64))
    stamps_ns: npt.NDArray[np.int64] = field(
        default_factory=lambda: np.zeros(0, dtype=np.int64))
    poses: FloatArray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    odom: FloatArray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    loops: int = 0

    def __post_init__(self) -> None:
        # Shared with the executor's threads and the detector: nobody may write into it.
        for array in (self.correction, self.covariance, self.indices, self.stamps_ns,
                      self.poses, self.odom):
            if array is not None:
                array.flags.writeable = False

    def hint(self, relative: Callable[[int], FloatArray | None] | None = None
             ) -> GraphHint | None:
        """The detector's view of the graph (None before the first keyframe), with
        ``relative`` as :attr:`GraphHint.relative`."""
        if not len(self.indices):
            return None
        return GraphHint(self.indices, self.stamps_ns, self.poses, self.odom, self.correction,
                         self.covariance, relative)


class GraphOutput:
    """Updates the pose graph with each verified keyframe and keeps its newest snapshot.

    Args:
        graph: the pose graph (its loaded map, if any, already in it).
        log: where the back end's events are logged (one line each).
    """

    def __init__(self, graph: PoseGraph, log: Log) -> None:
        self._graph, self._log = graph, log
        self._lock = threading.Lock()  # take() and reset() come from different threads
        self._snapshot = GraphSnapshot()
        self._resets = 0  # a hint from before a reset must not ask the new graph
        self.failures = 0

    @property
    def graph(self) -> PoseGraph:
        """The pose graph (update it only through :meth:`take`)."""
        return self._graph

    @property
    def snapshot(self) -> GraphSnapshot:
        """The newest results."""
        return self._snapshot

    def hint(self) -> GraphHint | None:
        """The newest snapshot as the detector's hint (see :meth:`GraphSnapshot.hint`); its
        relative covariances are asked of the graph under the lock, on demand."""
        snap, resets = self._snapshot, self._resets
        if not len(snap.indices):
            return None
        newest = int(snap.indices[-1])

        def relative(index: int) -> FloatArray | None:
            with self._lock:
                if self._resets != resets:
                    return None
                return self._graph.relative_covariance(index, newest)

        return snap.hint(relative)

    def take(self, verified: Verified) -> BackendState | None:
        """Add a verified keyframe and its loops to the graph (verify thread, keyframe order).

        A failure of the back end is logged and counted; the loops were published already
        and the next keyframe is taken as usual.
        """
        with self._lock:
            try:
                state = self._graph.update(verified.result, verified.odom)
            except SolidError as err:
                self.failures += 1
                self._log.error(f'back end: {err}')
                return None
            for event in state.events:
                line = f'back end: {event.message}'
                if event.kind in ('anchor', 'tie', 'confirmed'):
                    self._log.info(line)
                else:
                    self._log.warning(line)
            if state.added:
                self._snapshot = self._snap(state, verified)
            return state

    def reset(self) -> None:
        """Forget this session's keyframes (``~/reset``); a loaded map stays."""
        with self._lock:
            self._graph.reset()
            self._resets += 1
            self._snapshot = GraphSnapshot(self._snapshot.version + 1)

    def map_poses(self) -> dict[tuple[int, int], FloatArray]:
        """Map-frame poses of every keyframe in the graph (this session and a loaded map),
        by ``(session, index)``: what a saved database keeps for relocalisation."""
        with self._lock:
            return self._graph.map_poses()

    def values(self) -> dict[str, object]:
        """/diagnostics values of the back end."""
        snap, graph = self._snapshot, self._graph
        out: dict[str, object] = {
            'backend_keyframes': len(snap.stamps_ns), 'backend_loops': snap.loops,
            'backend_anchored': graph.anchored, 'backend_rebuilds': graph.rebuilds,
            'backend_failures': self.failures, 'backend_steps': graph.steps}
        for reason, count in sorted(dict(graph.counts).items()):
            out[f'backend_loop_{reason}'] = count
        return out

    def _snap(self, state: BackendState, verified: Verified) -> GraphSnapshot:
        prev = self._snapshot
        moved = (any(o.accepted for o in state.loops)
                 or any(e.kind in _MOVING_EVENTS for e in state.events))
        if not moved and verified.odom is not None and state.pose is not None:
            # Without a loop the earlier keyframes keep their poses (iSAM2's relinearisation
            # moves them by micrometres): append the new one instead of reading every pose
            # out of gtsam (11 ms at 2,000 keyframes).
            return GraphSnapshot(
                version=prev.version + 1,
                correction=np.array(state.correction, dtype=np.float64),
                covariance=None if state.covariance is None else np.array(state.covariance),
                indices=np.append(prev.indices, state.index),
                stamps_ns=np.append(prev.stamps_ns, state.stamp_ns),
                poses=np.concatenate([prev.poses, state.pose[None]]),
                odom=np.concatenate([prev.odom, verified.odom.pose[None]]),
                loops=prev.loops)
        kfs = self._graph.keyframes()
        return GraphSnapshot(
            version=prev.version + 1,
            correction=np.array(state.correction, dtype=np.float64),
            covariance=None if state.covariance is None else np.array(state.covariance),
            indices=np.array([k.index for k in kfs], dtype=np.int64),
            stamps_ns=np.array([k.stamp_ns for k in kfs], dtype=np.int64),
            poses=np.array([k.pose for k in kfs]).reshape(-1, 4, 4),
            odom=np.array([k.odom for k in kfs]).reshape(-1, 4, 4),
            loops=len(self._graph.loops))
