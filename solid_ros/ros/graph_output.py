"""The pose graph behind solid_node, between the verify thread and the executor.

The verify thread hands every verified keyframe to :meth:`GraphOutput.take` after its loops
went out, so the back end never delays a loop. There the loop closure's second half runs
(:meth:`~solid_ros.ros.shared_detector.SharedDetector.commit`: the registered step and the
graph update, under the stage-2 lock, as the replay runs it), the graph's events are logged,
and what the publishers need is kept as one immutable :class:`GraphSnapshot`, taken from the
graph's estimate after the keyframe (:attr:`~solid_ros.core.flow.closure.Step.estimate`, the
hint the loop closure verifies the next keyframe with): the correction ``T_map_odom``, the
newest pose's covariance and the corrected keyframe path, stamped with the clouds' header
stamps. The executor's timers, callbacks and services read the newest snapshot without
waiting for the graph. Its arrays are read-only. No ROS import.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from solid_ros.core.errors import SolidError
from solid_ros.core.flow.closure import Step
from solid_ros.ros.shared_detector import SharedDetector
from solid_ros.ros.stages import Log, Verified

__all__ = ['GraphOutput', 'GraphSnapshot']

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


def _eye() -> FloatArray:
    return np.eye(4)


@dataclass(frozen=True)
class GraphSnapshot:
    """The back end's results after one keyframe (read-only: shared between threads).

    Attributes:
        version: counts the updates that added a keyframe, and resets (0: none yet).
        correction: ``T_map_odom`` (identity until the first keyframe).
        covariance: 6x6 covariance of the newest keyframe pose (ROS order, right perturbation
            in the sensor frame), or None.
        indices: indices of the keyframes in the graph, in order.
        stamps_ns: their clouds' header stamps.
        poses: their corrected poses ``T_map_sensor``, shape (N, 4, 4).
        loops: loops in the graph.
    """

    version: int = 0
    correction: FloatArray = field(default_factory=_eye)
    covariance: FloatArray | None = None
    indices: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    stamps_ns: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    poses: FloatArray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    loops: int = 0

    def __post_init__(self) -> None:
        # Shared with the executor's threads: nobody may write into it.
        for array in (self.correction, self.covariance, self.indices, self.stamps_ns,
                      self.poses):
            if array is not None:
                array.flags.writeable = False


class GraphOutput:
    """Runs the back end's half of each verified keyframe and keeps its newest snapshot.

    Args:
        shared: the loop closure, with its pose graph.
        log: where the back end's events are logged (one line each).
        header_stamps: the clouds' header stamps of detector stamps (the node's
            :class:`~solid_ros.ros.stamp_guard.StampGuard`); None: the same.

    Raises:
        ValueError: the loop closure has no pose graph.
    """

    def __init__(self, shared: SharedDetector, log: Log,
                 header_stamps: Callable[[IntArray], IntArray] | None = None) -> None:
        if shared.closure.graph is None:
            raise ValueError('the loop closure has no pose graph (backend off)')
        self._shared, self._log = shared, log
        self._graph = shared.closure.graph  # reset in place: the same object all along
        self._header_stamps = header_stamps
        self._lock = threading.Lock()  # take() and reset() come from different threads
        self._snapshot = GraphSnapshot()
        self.failures = 0

    @property
    def snapshot(self) -> GraphSnapshot:
        """The newest results."""
        return self._snapshot

    def take(self, verified: Verified) -> Step | None:
        """The keyframe's registered step and graph update (verify thread, keyframe order).

        A failure of the back end is logged and counted; the loops were published already
        and the next keyframe is taken as usual. None: it failed, or a reset came between.
        """
        try:
            step = self._shared.commit(verified.proposal, verified.result, verified.odom,
                                       verified.detector)
        except SolidError as err:
            self.failures += 1
            self._log.error(f'back end: {err}')
            return None
        if step is None or step.backend is None:
            return step
        for event in step.backend.events:
            line = f'back end: {event.message}'
            if event.kind in ('anchor', 'tie', 'confirmed'):
                self._log.info(line)
            else:
                self._log.warning(line)
        if step.estimate is not None:
            self._keep(step, verified)
        return step

    def _keep(self, step: Step, verified: Verified) -> None:
        est = step.estimate
        assert est is not None
        loops = len(self._graph.loops)
        stamps = est.stamps_ns if self._header_stamps is None else self._header_stamps(
            est.stamps_ns)
        with self._lock:
            if verified.detector is not self._shared.detector:
                return  # a reset came after the update: its empty snapshot stays
            self._snapshot = GraphSnapshot(
                self._snapshot.version + 1, est.correction, est.covariance, est.indices,
                np.array(stamps, dtype=np.int64), est.poses, loops)

    def reset(self) -> None:
        """Forget this session's keyframes (``~/reset``, after the loop closure's reset)."""
        with self._lock:
            self._snapshot = GraphSnapshot(self._snapshot.version + 1)

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
