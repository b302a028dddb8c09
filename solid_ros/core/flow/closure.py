"""The per-scan flow of the product: odometry -> loop detector -> pose graph.

One flow for the replay, the demo and the node; the node only wires ROS to it. A scan goes
through three calls, in scan order:

- :meth:`LoopClosure.propose`: the detector's descriptor stage (gate, describe, search, store);
  None for a gated-out scan.
- :meth:`LoopClosure.verify`: the detector's verification of a proposal with the graph as it
  stood after the previous keyframe; its loops are final here.
- :meth:`LoopClosure.commit`: with the back end, the keyframe registered to the previous one
  (``backend_step_registration``) and the pose-graph update, which makes the hint the next
  keyframe is verified with.

:meth:`LoopClosure.finish` is ``commit(verify(...))`` and :meth:`LoopClosure.process` is
``finish(propose(...))`` after pairing the cloud with a pose (the caller's sample, or the
odometry source's, e.g. KISS-ICP); each returns one :class:`Step`. The replay and the demo
call :meth:`~LoopClosure.process`. The node (:mod:`solid_ros.ros.stages`) calls
:meth:`~LoopClosure.propose` on its describe thread under its stage-1 lock, and
:meth:`~LoopClosure.verify` and :meth:`~LoopClosure.commit` on its verify thread under its
stage-2 lock, publishing the loops between the two so that they never wait for the step or
the graph; reset, save and reconfigure take both locks. Nothing here locks: stage 1 touches
only the detector's descriptor side, stage 2 its verification side, the hint and the graph.

The graph hint (:class:`~solid_ros.core.candidates.position.GraphHint`), built here and only
here from the graph's keyframes after each keyframe it added: with ``verify`` and
``graph_candidates`` on, the keyframes near the next one in the corrected estimate become
candidates too and the graph's relative poses seed their registration (the detector ignores
it otherwise). It is also the :attr:`Step.estimate` the node publishes its path and map -> odom
transform from.

A saved database loaded with :meth:`LoopClosure.load` brings its scans (searched and verified
against) and, with the back end on, its keyframes' map-frame poses as the fixed prior map the
session relocalises in.

Other robots (:attr:`LoopClosure.fleet`, with the back end on): the inter-robot loops this
robot publishes, and those a peer publishes against it (:meth:`LoopClosure.add_peer_loop`),
stay out of the pose graph; :meth:`LoopClosure.align` places each peer's map in this robot's
from them and the peers' keyframe poses (:mod:`solid_ros.core.backend.alignment`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from solid_ros.core.backend.alignment import AlignmentSettings, FleetAlignment
from solid_ros.core.candidates.peers import place_peer, placed_peers
from solid_ros.core.candidates.position import GraphHint
from solid_ros.core.candidates.proposal import Proposal
from solid_ros.core.config import SolidConfig
from solid_ros.core.flow.detector import LoopDetector
from solid_ros.core.geometry import pose_to_vector
from solid_ros.core.odometry.track import OdometrySource, OdomSample
from solid_ros.core.results import BackendEvent, LoopCandidate, ScanResult
from solid_ros.core.stamps import check_stamp

if TYPE_CHECKING:
    from solid_ros.core.backend.posegraph import PoseGraph
    from solid_ros.core.results import BackendState

__all__ = ['LoopClosure', 'Step']

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Step:
    """What one scan gave.

    Attributes:
        scan: the detector's result (keyframe, loops, attempts, registered step, stage times).
        odom: the odometry sample the scan was paired with (None: no pose).
        backend: the pose graph's update (None: back end off or not a keyframe).
        estimate: the graph after this keyframe, the hint the next one is verified with
            (None: the graph did not add it).
    """

    scan: ScanResult
    odom: OdomSample | None
    backend: BackendState | None = None
    estimate: GraphHint | None = None


class LoopClosure:
    """Loop detector and, with the back end, the pose graph behind it.

    Args:
        detector: the loop detector (its configuration is the flow's).
        odometry: where :meth:`process` gets a pose when it is not given one (None: scans
            without a sample have no pose). A KISS-ICP odometry (``name`` 'kiss_icp') turns
            an 'auto' ``backend_step_registration`` on, any other off, as solid_replay and
            solid_node resolve it (:meth:`SolidConfig.for_odometry`).
        graph: the pose graph; built from the detector's configuration when omitted and the
            back end is on.
        backend: whether the back end is on (default: the configuration's ``backend``); the
            node turns it off when it has no odometry to build the graph from.

    Raises:
        BackendError: the back end is on and gtsam is missing.
    """

    def __init__(self, detector: LoopDetector, odometry: OdometrySource | None = None,
                 graph: PoseGraph | None = None, *, backend: bool | None = None) -> None:
        self.detector = detector
        self.odometry = odometry
        if odometry is not None:
            detector.resolve_odometry(_scan_only(odometry))
        if graph is None and (detector.config.backend if backend is None else backend):
            from solid_ros.core.backend.posegraph import PoseGraph

            graph = PoseGraph(detector.config)
        self.graph = graph
        self._hint: GraphHint | None = None
        self.fleet: FleetAlignment | None = None
        # Each peer's keyframe poses in its map, as the last align() had them.
        self._peer_maps: dict[int, dict[int, FloatArray]] = {}
        self._new_fleet()

    def _new_fleet(self) -> None:
        cfg = self.detector.config
        self.fleet = (None if self.graph is None else
                      FleetAlignment(cfg.session_id, AlignmentSettings.from_config(cfg)))

    @classmethod
    def load(cls, path: str | Path, config: SolidConfig,
             odometry: OdometrySource | None = None, *,
             backend: bool | None = None) -> LoopClosure:
        """A session that searches the scans saved in ``path`` and, with the back end on,
        relocalises in their map-frame poses.

        Raises:
            DatabaseError: see :meth:`LoopDetector.load`.
        """
        if odometry is not None:
            config = config.for_odometry(_scan_only(odometry))
        detector = LoopDetector.load(path, config)
        graph = None
        if config.backend if backend is None else backend:
            from solid_ros.core.backend.posegraph import PoseGraph
            from solid_ros.core.database.persistence import read_map_poses

            graph = PoseGraph(config, prior_map=read_map_poses(path).poses)
        return cls(detector, odometry, graph, backend=graph is not None)

    @property
    def config(self) -> SolidConfig:
        """The settings in force."""
        return self.detector.config

    @property
    def hint(self) -> GraphHint | None:
        """The graph's estimate the next keyframe is verified with (None: none)."""
        return self._hint

    # -- per scan ----------------------------------------------------------------------------

    def process(self, points: npt.ArrayLike, stamp_ns: int,
                odom: OdomSample | None = None) -> Step:
        """Pair, then :meth:`finish` what :meth:`propose` kept.

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
        proposal = self.propose(points, stamp_ns, odom)
        if proposal is None:  # gated out: what the detector's process() gives
            vec = None if odom is None else pose_to_vector(odom.pose)
            return Step(ScanResult(check_stamp(stamp_ns), pose=vec), odom)
        return self.finish(proposal, odom)

    def propose(self, points: npt.ArrayLike, stamp_ns: int,
                odom: OdomSample | None = None) -> Proposal | None:
        """Stage 1: :meth:`LoopDetector.propose` with the sample's pose (None: gated out).

        Raises:
            CloudError: no usable point (nothing changed).
            SolidError: malformed points, pose or stamp.
        """
        if odom is None:
            return self.detector.propose(points, stamp_ns)
        return self.detector.propose(points, stamp_ns, odom.pose, odom.segment)

    def finish(self, proposal: Proposal, odom: OdomSample | None) -> Step:
        """Stage 2 in one call: :meth:`commit` what :meth:`verify` gave."""
        return self.commit(proposal, self.verify(proposal), odom)

    def verify(self, proposal: Proposal) -> ScanResult:
        """The proposal verified with the graph's hint (keyframe order); its loops are
        final, its registered step handed on by :meth:`commit` (registered here when the
        graph predicts the query from it, see ``VerifyStage.registered_hint`` in
        :mod:`solid_ros.core.flow.verify_stage`)."""
        return self.detector.verify(proposal, self._hint, step=False)

    def commit(self, proposal: Proposal, result: ScanResult,
               odom: OdomSample | None) -> Step:
        """With the back end: register the keyframe's step (when
        ``backend_step_registration`` is 'on'), update the pose graph and, when it added the
        keyframe, the hint. Without it, ``result`` as it is.

        Raises:
            BackendError: gtsam failed beyond recovery (see :meth:`PoseGraph.update`).
        """
        if self.graph is None:
            return Step(result, odom)
        result = self.detector.with_step(result, proposal)
        state = self.graph.update(result, odom)
        if not state.added:
            return Step(result, odom, state)
        if self.fleet is not None:
            for loop in result.loops:
                self.fleet.add(loop)
        self._hint = self._with_peers(GraphHint.of(
            *self.graph.keyframe_arrays(), state.correction, state.covariance,
            partial(self.graph.relative_covariance, index_b=state.index),
            self.graph.placed_arrays()))
        return Step(result, odom, state, self._hint)

    def _with_peers(self, hint: GraphHint) -> GraphHint:
        """The hint with the aligned peers' keyframes placed in this robot's map
        (:mod:`solid_ros.core.candidates.peers`), from their map poses of the last
        :meth:`align` and their odometry poses as sent."""
        if self.fleet is None:
            return hint
        placements = [place_peer(st.peer, st.transform, st.covariance,
                                 self._peer_maps.get(st.peer, {}),
                                 self.detector.peer_odometry(st.peer), self.config)
                      for st in self.fleet.states()
                      if st.aligned and st.transform is not None and st.peer in self._peer_maps]
        return replace(hint, peers=placed_peers(placements)) if placements else hint

    # -- other robots ------------------------------------------------------------------------

    def add_peer_loop(self, loop: LoopCandidate, robot: int) -> bool:
        """Hold a loop that robot ``robot`` published against this robot's keyframe (False:
        back end off, or not such a loop; see :meth:`FleetAlignment.add`)."""
        return self.fleet is not None and self.fleet.add(loop, by=robot)

    def align(self, peers: Mapping[int, Mapping[int, FloatArray]],
              paths: Mapping[int, Mapping[int, float]] | None = None) -> list[BackendEvent]:
        """Place every peer's map in this robot's again, from the loops held and the maps as
        they are now (the graph's poses, and ``peers``: each peer's keyframe poses in its
        own map, by index; ``paths``: see :meth:`FleetAlignment.solve`); returns the lines
        to log."""
        if self.fleet is None or self.graph is None:
            return []
        self._peer_maps = {int(p): dict(poses) for p, poses in peers.items()}
        return self.fleet.solve(self.graph.poses(), peers, paths)

    # -- the session -------------------------------------------------------------------------

    def map_poses(self) -> dict[tuple[int, int], FloatArray]:
        """Map-frame poses of every keyframe the graph holds (this session and a loaded map),
        by ``(session, index)``: what a saved database keeps for relocalisation."""
        return {} if self.graph is None else self.graph.map_poses()

    def save(self, path: str | Path) -> Path:
        """Save the database with its clouds and the graph's map-frame poses."""
        return self.detector.save(path, self.map_poses() or None)

    def reset(self, detector: LoopDetector | None = None) -> None:
        """Forget this session's scans and keyframes (a loaded map stays in the graph).

        Args:
            detector: go on with this one (the node starts a new detector) instead of
                emptying the current one.
        """
        if detector is None:
            self.detector.reset()
        else:
            self.detector = detector
        self._hint = None
        self._peer_maps = {}
        if self.graph is not None:
            self.graph.reset()
        self._new_fleet()  # its loops name keyframes that are gone


def _scan_only(odometry: OdometrySource) -> bool:
    """Whether ``odometry`` is KISS-ICP run here on the same clouds (a scan-only odometry)."""
    return getattr(odometry, 'name', '') == 'kiss_icp'
