"""The per-scan flow of the product: odometry -> loop detector -> pose graph, one call per scan.

:meth:`LoopClosure.process` pairs the cloud with a pose (the caller's sample, or the odometry
source's, e.g. KISS-ICP), runs the detector and, for a kept keyframe with the back end on,
updates the pose graph; it returns one :class:`Step` that the replay, the demo and the node
consume alike. The node runs the same work on two threads: the detector's
:meth:`~solid_ros.core.flow.detector.LoopDetector.propose` on one, then :meth:`LoopClosure.finish`
(verification and the back end) on the other.

With the back end and ``graph_candidates`` on, each keyframe is verified with the graph as it
stood after the previous keyframe (a :class:`~solid_ros.core.candidates.position.GraphHint`): the
keyframes near it in the corrected estimate become candidates too, and the graph's relative
poses seed their registration. The node hands the verify thread the same hint from its graph
snapshot, taken after the previous keyframe on that thread, so both verify alike.

A saved database loaded with :meth:`LoopClosure.load` brings its scans (searched and verified
against) and, with the back end on, its keyframes' map-frame poses as the fixed prior map the
session relocalises in.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from solid_ros.core.candidates.position import GraphHint
from solid_ros.core.candidates.proposal import Proposal
from solid_ros.core.config import SolidConfig
from solid_ros.core.flow.detector import LoopDetector
from solid_ros.core.odometry.track import OdometrySource, OdomSample
from solid_ros.core.results import ScanResult

if TYPE_CHECKING:
    from solid_ros.core.backend.posegraph import PoseGraph
    from solid_ros.core.results import BackendState

__all__ = ['LoopClosure', 'Step']

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Step:
    """What one scan gave.

    Attributes:
        scan: the detector's result (keyframe, loops, attempts, stage times).
        odom: the odometry sample the scan was paired with (None: no pose).
        backend: the pose graph after the keyframe (None: back end off or not a keyframe).
    """

    scan: ScanResult
    odom: OdomSample | None
    backend: BackendState | None


class LoopClosure:
    """Loop detector and, with ``config.backend``, the pose graph behind it.

    Args:
        detector: the loop detector (its configuration is the pipeline's).
        odometry: where poses come from when :meth:`process` is not given one (None: scans
            without a sample have no pose).
        graph: the pose graph; built from the detector's configuration when omitted and
            ``backend`` is on.

    Raises:
        BackendError: the back end is on and gtsam is missing.
    """

    def __init__(self, detector: LoopDetector, odometry: OdometrySource | None = None,
                 graph: PoseGraph | None = None) -> None:
        self.detector = detector
        self.odometry = odometry
        if graph is None and detector.config.backend:
            from solid_ros.core.backend.posegraph import PoseGraph

            graph = PoseGraph(detector.config)
        self.graph = graph
        self._hint: GraphHint | None = None

    @classmethod
    def load(cls, path: str | Path, config: SolidConfig,
             odometry: OdometrySource | None = None) -> LoopClosure:
        """A session that searches the scans saved in ``path`` and, with the back end on,
        relocalises in their map-frame poses.

        Raises:
            DatabaseError: see :meth:`LoopDetector.load`.
        """
        detector = LoopDetector.load(path, config)
        graph = None
        if config.backend:
            from solid_ros.core.backend.posegraph import PoseGraph
            from solid_ros.core.database.persistence import read_map_poses

            graph = PoseGraph(config, prior_map=read_map_poses(path).poses)
        return cls(detector, odometry, graph)

    @property
    def config(self) -> SolidConfig:
        """The settings in force."""
        return self.detector.config

    def process(self, points: npt.ArrayLike, stamp_ns: int,
                odom: OdomSample | None = None) -> Step:
        """Pair, detect and (for a keyframe) update the pose graph.

        Args:
            points: (N, 3+) cloud in the sensor frame.
            stamp_ns: its stamp.
            odom: its odometry sample; asked of the odometry source when omitted.

        Raises:
            CloudError: no usable point (nothing changed, see the detector).
            SolidError: malformed points or stamp.
        """
        if odom is None and self.odometry is not None:
            odom = self.odometry.pose_for(stamp_ns, np.asarray(points))
        scan = self.detector.process(points, stamp_ns, None if odom is None else odom.pose,
                                     self._hint)
        return Step(scan, odom, self._update(scan, odom))

    def finish(self, proposal: Proposal, odom: OdomSample | None) -> Step:
        """The second half of :meth:`process` for a proposal of the detector's
        :meth:`~LoopDetector.propose`: verify it and update the pose graph (keyframe order)."""
        scan = self.detector.verify(proposal, self._hint)
        return Step(scan, odom, self._update(scan, odom))

    @property
    def hint(self) -> GraphHint | None:
        """The graph's estimate the next keyframe is verified with (None: none)."""
        return self._hint

    def _update(self, scan: ScanResult, odom: OdomSample | None) -> BackendState | None:
        if self.graph is None or not scan.keyframe:
            return None
        state = self.graph.update(scan, odom)
        if state.added and self.config.graph_candidates > 0 and self.config.verify:
            self._hint = GraphHint.from_keyframes(
                self.graph.keyframes(), state.correction, state.covariance,
                partial(self.graph.relative_covariance, index_b=state.index))
        return state

    def map_poses(self) -> dict[tuple[int, int], FloatArray]:
        """Map-frame poses of every keyframe the graph holds (this session and a loaded map),
        by ``(session, index)``: what a saved database keeps for relocalisation."""
        return {} if self.graph is None else self.graph.map_poses()

    def save(self, path: str | Path) -> Path:
        """Save the database with its clouds and the graph's map-frame poses."""
        return self.detector.save(path, self.map_poses() or None)

    def reset(self) -> None:
        """Forget this session's scans and keyframes (a loaded map stays in the graph)."""
        self.detector.reset()
        self._hint = None
        if self.graph is not None:
            self.graph.reset()
