"""Loop candidates by position: earlier keyframes near the query in the pose graph's estimate.

The descriptor finds a place by how it looks; the back end knows where the keyframes are.
Systems people pick find most of their loops by position (LIO-SAM and FAST-LIO-SAM search
the keyframes within 15-35 m of the current pose, GLIM within 5 m), which finds what the
descriptor misses: places seen from another heading or offset. Here the two are combined:
besides the descriptor's candidates, the keyframes near the query in the corrected estimate
are verified by the same tests, and every candidate the graph knows gets its relative pose
from the graph as the first start of the coarse registration.

Rule, for query keyframe ``q`` with odometry pose ``O_q`` and a :class:`GraphHint` (the graph
after keyframe ``q - 1``):

* Predicted pose ``P_q = C O_q``, ``C = T_map_odom`` of the newest keyframe in the graph.
* Radius ``r`` around it: :func:`~solid_ros.core.candidates.tolerance.search_radius`.
* Eligible: this session's keyframes ``j`` in the graph outside the detector's exclusion
  window (``j < q - exclude_recent_frames``, ``stamp_q - stamp_j >= exclude_recent_sec``)
  with at least ``graph_candidate_min_path_m`` of odometry path driven from ``j`` to ``q``
  (summed over the graph's keyframes: a loop to a keyframe just driven past tells the graph
  nothing the odometry does not).
* Those within ``r`` of ``P_q`` (3-D distance of the sensor positions), nearest first, at
  most ``graph_candidates``; each with the graph's relative pose ``T_mq = P_j^-1 P_q``.
* Seen places (``view_keyframes``): a narrow field of view sees the place ahead of the
  sensor, not where it stands, so a street driven the other way, or crossed, is seen from
  keyframes tens of metres from the query, and one beside it may see nothing in common. Each
  keyframe's view centre ``c`` is the centroid of its keyframe cloud (sensor frame); keyframes
  whose view centre ``P_j c_j`` lies within ``r_v`` of the query's ``P_q c_q`` are proposed
  too, nearest first, at most ``graph_candidates``, unless a keyframe proposed by position
  already saw it (its view centre lies within ``r_v`` too: nothing new to try). Only for a
  one-sided view: the query's view centre lies farther from its sensor than its view extent
  ``e`` (below). A spinning sensor's view centre lies within a tenth to a third of its extent
  from the sensor (simulated drives), where the position rule already stands for the view; a
  70-90 degree view's lies 1.2-2.3 extents ahead (streets, the room).
  ``r_v`` is ``r`` with the view centre as the lever of the heading uncertainty (its offset
  from the newest keyframe, where the sensor position is used for ``r``) and the query's view
  extent ``e`` (RMS horizontal distance of its cloud's points from their centroid) as the
  floor when larger than ``graph_candidate_radius_m``: two views share most of what they
  saw while their centres lie within one extent (about 14 m for the simulated Avia on
  streets, 2-3 m in a room), capped at ``graph_candidate_max_radius_m``.
* What a loop the graph proposed must agree with (heading, position, the known place):
  :mod:`solid_ros.core.candidates.tolerance`.

Plain numpy: the node hands the hint over from an immutable snapshot (its relative
covariances are asked of the graph through a callable, under the back end's lock); nothing
here imports gtsam.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import numpy.typing as npt

from solid_ros.core.candidates.tolerance import position_sigma, search_radius
from solid_ros.core.candidates.views import KeyframeViews, ViewCentres
from solid_ros.core.config import SolidConfig

__all__ = ['GraphCandidate', 'GraphHint', 'MapCandidate', 'PeerCandidate', 'PeerPlacement',
           'PlacedArrays', 'eligible', 'map_keyframes', 'map_view_keyframes', 'near_keyframes',
           'peer_keyframes', 'view_keyframes']

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
# A placed map as read-only arrays: (M, 2) (session, index) and (M, 4, 4) poses.
PlacedArrays = tuple[IntArray, FloatArray]


def _frozen(a: npt.ArrayLike, dtype: type, shape: tuple[int, ...]) -> npt.NDArray[np.generic]:
    out: npt.NDArray[np.generic] = np.array(a, dtype=dtype).reshape(shape)
    out.flags.writeable = False  # shared between threads: nobody may change it
    return out


@dataclass(frozen=True, eq=False)
class PeerPlacement:
    """Aligned peers' keyframes placed in this robot's map
    (:func:`solid_ros.core.candidates.peers.place_peer`; read-only arrays).

    Attributes:
        keys: (P, 2) ``(robot, index)`` of each placed keyframe.
        poses: (P, 4, 4) its placed pose in this robot's map.
        sigma_m: (P,) its position sigma there (the alignment's, and the peer's odometry drift
            from the keyframe its map pose was known at), metres.
        yaw_sigma_rad: (P,) its heading sigma, radians.
    """

    keys: IntArray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    poses: FloatArray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    sigma_m: FloatArray = field(default_factory=lambda: np.zeros(0))
    yaw_sigma_rad: FloatArray = field(default_factory=lambda: np.zeros(0))

    @classmethod
    def of(cls, keys: npt.ArrayLike, poses: npt.ArrayLike, sigma_m: npt.ArrayLike,
           yaw_sigma_rad: npt.ArrayLike) -> PeerPlacement:
        """A placement holding read-only copies of the arrays."""
        n = len(np.asarray(sigma_m).reshape(-1))
        return cls(_frozen(keys, np.int64, (n, 2)),  # type: ignore[arg-type]
                   _frozen(poses, np.float64, (n, 4, 4)),  # type: ignore[arg-type]
                   _frozen(sigma_m, np.float64, (n,)),  # type: ignore[arg-type]
                   _frozen(yaw_sigma_rad, np.float64, (n,)))  # type: ignore[arg-type]


@dataclass(frozen=True, eq=False)
class GraphHint:
    """What the back end knows when a keyframe is verified (read-only arrays).

    Attributes:
        indices: (N,) this session's keyframes in the graph, ascending.
        stamps_ns: (N,) their stamps.
        poses: (N, 4, 4) their corrected poses ``T_map_sensor``.
        odom: (N, 4, 4) their odometry poses ``T_odom_sensor``.
        correction: ``T_map_odom`` of the newest keyframe.
        covariance: 6x6 marginal covariance of the newest keyframe's pose (ROS order), or
            None when unknown.
        relative: ``relative(j)``: 6x6 covariance (ROS order) of keyframe ``j``'s pose
            relative to the newest one, ``X_j^-1 X_newest`` (the graph's joint marginal, asked
            of gtsam on demand), or None when unknown; None: only ``covariance`` is known.
        map_keys: (M, 2) ``(session, index)`` of a loaded map's keyframes, once the session
            is relocalised in that map (empty before).
        map_poses: (M, 4, 4) their fixed poses in the map frame (this session's map frame).
        peers: aligned peers' keyframes placed in this session's map frame (empty before a
            peer is aligned).
    """

    indices: IntArray
    stamps_ns: IntArray
    poses: FloatArray
    odom: FloatArray
    correction: FloatArray
    covariance: FloatArray | None = None
    relative: Callable[[int], FloatArray | None] | None = None
    map_keys: IntArray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    map_poses: FloatArray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    peers: PeerPlacement = field(default_factory=PeerPlacement)

    @classmethod
    def of(cls, indices: npt.ArrayLike, stamps_ns: npt.ArrayLike, poses: npt.ArrayLike,
           odom: npt.ArrayLike, correction: npt.ArrayLike,
           covariance: npt.ArrayLike | None = None,
           relative: Callable[[int], FloatArray | None] | None = None,
           placed_map: Mapping[tuple[int, int], npt.ArrayLike] | PlacedArrays | None = None
           ) -> GraphHint:
        """A hint holding read-only copies of the arrays (``placed_map``: a loaded map's
        keyframe poses by ``(session, index)`` once the session is relocalised in it, or
        those as read-only arrays, kept as they are)."""
        n = len(np.asarray(indices).reshape(-1))
        cov = None if covariance is None else _frozen(covariance, np.float64, (6, 6))
        if isinstance(placed_map, tuple):
            map_keys, map_poses = placed_map
        else:
            placed = dict(placed_map or {})
            m = len(placed)
            map_keys = _frozen(list(placed), np.int64, (m, 2))  # type: ignore[assignment]
            map_poses = _frozen(  # type: ignore[assignment]
                [placed[k] for k in placed], np.float64, (m, 4, 4))  # type: ignore[arg-type]
        return cls(_frozen(indices, np.int64, (n,)),  # type: ignore[arg-type]
                   _frozen(stamps_ns, np.int64, (n,)),  # type: ignore[arg-type]
                   _frozen(poses, np.float64, (n, 4, 4)),  # type: ignore[arg-type]
                   _frozen(odom, np.float64, (n, 4, 4)),  # type: ignore[arg-type]
                   _frozen(correction, np.float64, (4, 4)), cov,  # type: ignore[arg-type]
                   relative, map_keys, map_poses)

    def map_pose_of(self, session: int, index: int) -> FloatArray | None:
        """A placed map keyframe's pose (None: not in the placed map)."""
        hit = np.flatnonzero((self.map_keys[:, 0] == session) & (self.map_keys[:, 1] == index))
        if not len(hit):
            return None
        out: FloatArray = self.map_poses[int(hit[0])]
        return out

    def predict(self, odom_pose: npt.ArrayLike) -> FloatArray:
        """Corrected pose ``T_map_odom @ odom_pose`` of a pose of the odometry."""
        out: FloatArray = self.correction @ np.asarray(odom_pose, dtype=np.float64)
        return out

    def pose_of(self, index: int) -> FloatArray | None:
        """Corrected pose of keyframe ``index`` (None: not in the graph)."""
        k = int(np.searchsorted(self.indices, index))
        if k < len(self.indices) and int(self.indices[k]) == index:
            out: FloatArray = self.poses[k]
            return out
        return None

    def sigma_to(self, index: int, config: SolidConfig, step: npt.ArrayLike | None = None,
                 view: npt.ArrayLike | None = None) -> float:
        """The query's position sigma relative to keyframe ``index``
        (:func:`~solid_ros.core.candidates.tolerance.position_sigma` of :attr:`relative`), or
        the newest keyframe's own when the graph gives no relative
        covariance. The own marginal also holds what both share since the first keyframe:
        on the simulator's narrow-view streets it was 5-20 times the error of the graph's
        guess (median 0.05 sigma), which made the known place
        (:func:`~solid_ros.core.candidates.tolerance.knows_place`) rare."""
        cov = None if self.relative is None else self.relative(index)
        return position_sigma(self.covariance if cov is None else cov, config, step, view)

    @cached_property
    def path_m(self) -> FloatArray:
        """Odometry path driven up to each keyframe, metres (from the first one)."""
        steps = np.linalg.norm(np.diff(self.odom[:, :3, 3], axis=0), axis=1)
        out: FloatArray = np.concatenate(([0.0], np.cumsum(steps)))
        return out


@dataclass(frozen=True)
class GraphCandidate:
    """An earlier keyframe near the query in the graph's estimate.

    Attributes:
        index: the keyframe's index in this session.
        stamp_ns: its stamp.
        distance_m: its distance from the query's predicted position, metres.
        T_mq: the graph's relative pose (query sensor in the keyframe's sensor frame).
        share: for one proposed by shared structure, the share of the query's coarse
            structure it holds (:mod:`solid_ros.core.candidates.covisibility`); NaN otherwise.
    """

    index: int
    stamp_ns: int
    distance_m: float
    T_mq: FloatArray
    share: float = math.nan

def eligible(hint: GraphHint, query_index: int, stamp_ns: int, odom: FloatArray,
             config: SolidConfig) -> npt.NDArray[np.bool_]:
    """The keyframes outside the exclusion window with enough path driven since them."""
    path = hint.path_m[-1] + float(np.linalg.norm(odom[:3, 3] - hint.odom[-1, :3, 3]))
    ok: npt.NDArray[np.bool_] = hint.indices < query_index - config.exclude_recent_frames
    ok &= path - hint.path_m >= config.graph_candidate_min_path_m
    if config.exclude_recent_sec > 0.0:
        ok &= stamp_ns - hint.stamps_ns >= round(config.exclude_recent_sec * 1e9)
    return ok


def _nearest(hint: GraphHint, ok: npt.NDArray[np.bool_], dist: FloatArray,
             predicted: FloatArray, count: int) -> list[GraphCandidate]:
    picked = np.flatnonzero(ok)
    picked = picked[np.argsort(dist[picked], kind='stable')][:count]
    return [GraphCandidate(int(hint.indices[k]), int(hint.stamps_ns[k]), float(dist[k]),
                           np.linalg.solve(hint.poses[k], predicted)) for k in picked]


def near_keyframes(hint: GraphHint, query_index: int, stamp_ns: int, odom_pose: npt.ArrayLike,
                   config: SolidConfig) -> list[GraphCandidate]:
    """The eligible keyframes near the query's predicted pose, nearest first.

    Args:
        hint: the graph's estimate.
        query_index: the query keyframe's index.
        stamp_ns: its stamp.
        odom_pose: its 4x4 odometry pose.
        config: ``graph_candidate*`` and the exclusion window.
    """
    if config.graph_candidates <= 0 or len(hint.indices) == 0:
        return []
    odom = np.asarray(odom_pose, dtype=np.float64)
    predicted = hint.predict(odom)
    ok = eligible(hint, query_index, stamp_ns, odom, config)
    dist = np.linalg.norm(hint.poses[:, :3, 3] - predicted[:3, 3], axis=1)
    ok &= dist <= search_radius(hint.covariance, config, np.linalg.solve(hint.odom[-1], odom))
    return _nearest(hint, ok, dist, predicted, config.graph_candidates)


@dataclass(frozen=True)
class MapCandidate:
    """A keyframe of a loaded map near the query in the graph's estimate.

    Attributes:
        session: its session in the map.
        index: its index in that session.
        distance_m: its distance from the query's predicted position, metres.
        T_mq: the graph's relative pose (query sensor in the keyframe's sensor frame).
    """

    session: int
    index: int
    distance_m: float
    T_mq: FloatArray


def map_keyframes(hint: GraphHint, odom_pose: npt.ArrayLike,
                  config: SolidConfig) -> list[MapCandidate]:
    """The loaded map's keyframes near the query's predicted pose once the session is
    relocalised in that map (:attr:`GraphHint.map_keys`), nearest first, at most
    ``graph_candidates``, within the radius of :func:`near_keyframes`: a new session that
    revisits a mapped place finds it by position as it finds its own, not only by
    descriptor."""
    if config.graph_candidates <= 0 or len(hint.map_keys) == 0 or len(hint.indices) == 0:
        return []
    odom = np.asarray(odom_pose, dtype=np.float64)
    predicted = hint.predict(odom)
    dist = np.linalg.norm(hint.map_poses[:, :3, 3] - predicted[:3, 3], axis=1)
    radius = search_radius(hint.covariance, config, np.linalg.solve(hint.odom[-1], odom))
    return _nearest_mapped(hint, dist <= radius, dist, predicted, config.graph_candidates)


def _nearest_mapped(hint: GraphHint, ok: npt.NDArray[np.bool_], dist: FloatArray,
                    predicted: FloatArray, count: int) -> list[MapCandidate]:
    """:func:`_nearest` among the loaded map's keyframes."""
    picked = np.flatnonzero(ok)
    picked = picked[np.argsort(dist[picked], kind='stable')][:count]
    return [MapCandidate(int(hint.map_keys[k, 0]), int(hint.map_keys[k, 1]), float(dist[k]),
                         np.linalg.solve(hint.map_poses[k], predicted)) for k in picked]


def _view_distances(poses: FloatArray, centres: FloatArray, predicted: FloatArray,
                    view: FloatArray) -> FloatArray:
    """Distance from each keyframe's view centre (``centres`` (N, 3), in its sensor frame;
    NaN: it has none, NaN out) placed at its pose to the query's ``view`` placed at
    ``predicted``."""
    seen = np.einsum('nij,nj->ni', poses[:, :3, :3], centres) + poses[:, :3, 3]
    with np.errstate(invalid='ignore'):
        out: FloatArray = np.linalg.norm(seen - (predicted[:3, :3] @ view + predicted[:3, 3]),
                                         axis=1)
    return out


def map_view_keyframes(hint: GraphHint, odom_pose: npt.ArrayLike, view: npt.ArrayLike,
                       extent: float, map_views: ViewCentres,
                       config: SolidConfig) -> list[MapCandidate]:
    """:func:`view_keyframes` in a loaded map once the session is relocalised in it: the
    map's keyframes whose view centre lies near the query's (``distance_m``: between the view
    centres), nearest first; none when the query's view is not one-sided. A narrow view
    revisits a place from a few metres off, where the saved keyframes nearest the sensor look
    elsewhere. Unlike :func:`view_keyframes`, a map keyframe proposed by position among them
    does not stand for the others: on hku1's second half in its first half's map that rule
    kept the cross-session revisit recall at 41 of 51, without it 45.

    Args:
        hint: the graph's estimate, with the placed map.
        odom_pose: the query's 4x4 odometry pose.
        view: its view centre (sensor frame, 3-vector).
        extent: its view extent, metres.
        map_views: the map keyframes' view centres (a keyframe without one is not
            proposed).
        config: ``graph_candidate*``.
    """
    c_q = np.asarray(view, dtype=np.float64).reshape(3)
    if (config.graph_candidates <= 0 or len(hint.map_keys) == 0 or len(hint.indices) == 0
            or not float(np.linalg.norm(c_q)) > extent):
        return []
    odom = np.asarray(odom_pose, dtype=np.float64)
    predicted = hint.predict(odom)
    dist = _view_distances(hint.map_poses, map_views.at(hint.map_keys), predicted, c_q)
    ok = np.isfinite(dist) & (dist <= search_radius(
        hint.covariance, config, np.linalg.solve(hint.odom[-1], odom), c_q, extent))
    return _nearest_mapped(hint, ok, dist, predicted, config.graph_candidates)


def view_keyframes(hint: GraphHint, query_index: int, stamp_ns: int, odom_pose: npt.ArrayLike,
                   view: npt.ArrayLike, extent: float, views: KeyframeViews,
                   config: SolidConfig, near: Sequence[int] = ()) -> list[GraphCandidate]:
    """The eligible keyframes whose view centre lies near the query's, nearest first
    (``distance_m``: between the view centres); none when one of ``near`` is among them or
    the query's view is not one-sided (see the module docstring).

    Args:
        hint: the graph's estimate.
        query_index: the query keyframe's index.
        stamp_ns: its stamp.
        odom_pose: its 4x4 odometry pose.
        view: its view centre (sensor frame, 3-vector).
        extent: its view extent, metres (see the module docstring).
        views: view centres of earlier keyframes (a keyframe without one is not proposed).
        config: ``graph_candidate*`` and the exclusion window.
        near: the keyframes already proposed by position.
    """
    c_q = np.asarray(view, dtype=np.float64).reshape(3)
    if (config.graph_candidates <= 0 or len(hint.indices) == 0
            or not float(np.linalg.norm(c_q)) > extent):
        return []
    odom = np.asarray(odom_pose, dtype=np.float64)
    predicted = hint.predict(odom)
    dist = _view_distances(hint.poses, views.at(hint.indices), predicted, c_q)
    ok = eligible(hint, query_index, stamp_ns, odom, config) & np.isfinite(dist)
    ok &= dist <= search_radius(hint.covariance, config, np.linalg.solve(hint.odom[-1], odom),
                                c_q, extent)
    if bool(np.any(ok & np.isin(hint.indices, np.asarray(near, dtype=np.int64)))):
        return []
    return _nearest(hint, ok, dist, predicted, config.graph_candidates)


@dataclass(frozen=True)
class PeerCandidate:
    """An aligned peer's keyframe near the query in this robot's map.

    Attributes:
        session: the peer's robot id.
        index: the keyframe's index in that robot's session.
        distance_m: its distance from the query's predicted position, metres.
        T_mq: the relative pose of the placement (query sensor in the keyframe's sensor frame).
        sigma_m: the placement's position sigma, metres (:class:`PeerPlacement`).
        yaw_sigma_rad: its heading sigma, radians.
    """

    session: int
    index: int
    distance_m: float
    T_mq: FloatArray
    sigma_m: float
    yaw_sigma_rad: float


def peer_keyframes(hint: GraphHint, odom_pose: npt.ArrayLike,
                   config: SolidConfig) -> list[PeerCandidate]:
    """Aligned peers' placed keyframes (:attr:`GraphHint.peers`) near the query's predicted
    pose, nearest first, at most ``graph_candidates``: within the radius of
    :func:`near_keyframes` with the placement's sigma added to the query's (capped at
    ``graph_candidate_max_radius_m``)."""
    peers = hint.peers
    if config.graph_candidates <= 0 or len(peers.keys) == 0 or len(hint.indices) == 0:
        return []
    odom = np.asarray(odom_pose, dtype=np.float64)
    predicted = hint.predict(odom)
    own = position_sigma(hint.covariance, config, np.linalg.solve(hint.odom[-1], odom))
    dist = np.linalg.norm(peers.poses[:, :3, 3] - predicted[:3, 3], axis=1)
    sigma = np.sqrt(own ** 2 + peers.sigma_m ** 2)
    radius = np.minimum(config.graph_candidate_max_radius_m,
                        config.graph_candidate_radius_m + config.graph_candidate_sigmas * sigma)
    picked = np.flatnonzero(dist <= radius)
    picked = picked[np.argsort(dist[picked], kind='stable')][:config.graph_candidates]
    return [PeerCandidate(int(peers.keys[k, 0]), int(peers.keys[k, 1]), float(dist[k]),
                          np.linalg.solve(peers.poses[k], predicted), float(peers.sigma_m[k]),
                          float(peers.yaw_sigma_rad[k])) for k in picked]
