"""Peers' map frames in this robot's map, from the inter-robot loops that agree.

Each robot keeps its own map; an inter-robot loop does not enter its pose graph. Instead
:class:`FleetAlignment` estimates, for each peer, ``T_own_map<-peer_map`` from the loops
between the two robots (those this robot published and, inverted, those the peer published)
and both robots' keyframe poses in their own map frames:

- every loop implies an alignment; the alignment is decided by a maximum set of mutually
  consistent loops (pairwise consistency maximisation, :mod:`solid_ros.core.backend.consistency`)
  and is the weighted mean of what those loops imply;
- a peer stays unaligned until such a set holds ``min_loops`` loops, and while a set that
  disagrees (a rival of at least ``rival_ratio`` of its size, placing the peer elsewhere) makes
  the choice ambiguous; an aligned peer then keeps its transform. A lone false loop agrees with
  none; a burst of consistent false loops smaller than ``min_loops`` cannot align a peer, and
  once a peer is aligned it cannot move it unless it outgrows the true set twice over;
- :meth:`FleetAlignment.solve` re-decides with the maps as they are now (both graphs move as
  they close loops), so the transform keeps being refined; an ``'aligned'`` event comes when a
  peer is first placed and a ``'jump'`` event when its placement moves by more than
  ``jump_m`` / ``jump_deg`` at its loops' keyframes.

Why maximum-clique PCM and not gtsam's GNC: measured on the same inputs
(``test/bench/bench_fleet_align.py``, doc/multi_robot.md), GNC over one alignment variable
follows whatever the loops of the moment say (three consistent false loops before any true one
place the peer 20 m off) and does not use that two loops at distant keyframes may disagree by
the maps' drift; PCM keeps the peer unaligned until enough loops agree.
Memory: at most ``max_loops`` loops per peer (the oldest outside the consistent set go first).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

from solid_ros.core.backend.consistency import (
    DriftModel,
    adjoint,
    cycle_sigmas,
    implied,
    max_clique,
    mean_alignment,
    moved_by,
)
from solid_ros.core.backend.noise import floored, swap_blocks
from solid_ros.core.config import SolidConfig
from solid_ros.core.odometry.track import usable_covariance
from solid_ros.core.results import BackendEvent, LoopCandidate, PeerAlignment

__all__ = ['AlignmentSettings', 'FleetAlignment', 'path_lengths']

FloatArray = npt.NDArray[np.float64]
Poses = Mapping[int, FloatArray]


@dataclass(frozen=True)
class AlignmentSettings:
    """How peers are aligned (see the module docstring).

    Attributes:
        min_loops: consistent loops needed before a peer is aligned.
        gate: two loops agree when their cycle is within this many sigmas (chi-square, 6
            degrees of freedom: 4.1 is its 99 % quantile).
        rival_ratio: a disagreeing set this large against the best one makes it ambiguous...
        rival_m: ... when it places the peer's loop keyframes this far from where the best
            one does, metres (drifted maps can make two true sets disagree by less: the
            larger one then wins).
        jump_m: a new transform moving the peer's loop keyframes this far is a jump, metres.
        jump_deg: ... or turning it this much, degrees.
        max_loops: loops kept per peer.
        drift: the maps' relative uncertainty over the path between two keyframes.
        floor_m: least translation sigma of a loop, metres.
        floor_deg: least rotation sigma of a loop, degrees.
    """

    min_loops: int = 4
    gate: float = 4.1
    rival_ratio: float = 0.5
    rival_m: float = 3.0
    jump_m: float = 0.5
    jump_deg: float = 2.0
    max_loops: int = 200
    drift: DriftModel = DriftModel()
    floor_m: float = 0.02
    floor_deg: float = 0.1

    @classmethod
    def from_config(cls, config: SolidConfig, **changes: object) -> AlignmentSettings:
        """The back end's odometry model and loop floors from ``config``."""
        drift = DriftModel(config.backend_odom_trans_sigma,
                           math.radians(config.backend_odom_rot_sigma_deg),
                           config.backend_odom_floor_m,
                           math.radians(config.backend_odom_floor_deg))
        base = cls(drift=drift, floor_m=config.backend_loop_floor_m,
                   floor_deg=config.backend_loop_floor_deg)
        return replace(base, **changes)  # type: ignore[arg-type]


@dataclass(frozen=True)
class _Link:
    """One loop between this robot and a peer, normalised: ``Z`` is this robot's keyframe
    sensor in the peer keyframe's sensor frame, ``cov`` its covariance (gtsam order)."""

    own: int
    theirs: int
    Z: FloatArray
    cov: FloatArray


@dataclass
class _Peer:
    links: list[_Link] = field(default_factory=list)
    keys: set[tuple[int, int]] = field(default_factory=set)
    inliers: list[_Link] = field(default_factory=list)
    state: PeerAlignment = PeerAlignment(-1)


def path_lengths(poses: Poses) -> dict[int, float]:
    """Distance driven up to each keyframe along the poses in index order, metres."""
    order = sorted(poses)
    if not order:
        return {}
    pos = np.array([np.asarray(poses[i])[:3, 3] for i in order])
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    return dict(zip(order, dist.tolist()))


class FleetAlignment:
    """The alignment of every peer robot's map to this robot's (module docstring).

    Args:
        robot: this robot's id (its session id).
        settings: how peers are aligned.
    """

    def __init__(self, robot: int, settings: AlignmentSettings = AlignmentSettings()) -> None:
        self.robot = int(robot)
        self.settings = settings
        self._peers: dict[int, _Peer] = {}

    def add(self, loop: LoopCandidate, by: int | None = None) -> bool:
        """Hold an inter-robot loop: one this robot published (``by`` None or its id), or one
        peer ``by`` published against this robot's keyframe (inverted here).

        Returns:
            Whether it was taken (False: within one robot, not verified, no usable covariance,
            not finite, or held already).
        """
        pub = self.robot if by is None else int(by)
        if (pub == self.robot) == (loop.match_session == self.robot) or not loop.verified:
            return False
        cov = usable_covariance(loop.covariance)
        T = loop.matrix()
        if cov is None or not np.all(np.isfinite(T)):
            return False
        s = self.settings
        cov = swap_blocks(floored(cov, s.floor_m, math.radians(s.floor_deg)))
        if pub == self.robot:
            peer, link = loop.match_session, _Link(loop.query_index, loop.match_index, T, cov)
        else:  # the peer's query in our match frame: Z is its inverse, the covariance moved
            ad = adjoint(T)
            inv = np.asarray(np.linalg.inv(T), dtype=np.float64)
            peer, link = pub, _Link(loop.match_index, loop.query_index, inv, ad @ cov @ ad.T)
        entry = self._peers.setdefault(peer, _Peer(state=PeerAlignment(peer)))
        if (link.own, link.theirs) in entry.keys:
            return False
        entry.keys.add((link.own, link.theirs))
        entry.links.append(link)
        if len(entry.links) > s.max_loops:
            keep = {id(k) for k in entry.inliers}
            drop = next((k for k in entry.links if id(k) not in keep), entry.links[0])
            entry.links.remove(drop)
            entry.keys.discard((drop.own, drop.theirs))
        entry.state = replace(entry.state, loops=len(entry.links))
        return True

    def peers(self) -> list[int]:
        """Peers with loops held, ascending."""
        return sorted(self._peers)

    def state(self, peer: int) -> PeerAlignment:
        """The alignment of ``peer`` (unaligned when nothing is known of it)."""
        entry = self._peers.get(int(peer))
        return entry.state if entry is not None else PeerAlignment(int(peer))

    def states(self) -> list[PeerAlignment]:
        """Every peer's alignment, by peer id."""
        return [self._peers[p].state for p in self.peers()]

    def forget(self, peer: int) -> None:
        """Drop a peer (it left, or the caller bounds the robots it tracks)."""
        self._peers.pop(int(peer), None)

    def solve(self, own: Poses, peers: Mapping[int, Poses],
              paths: Mapping[int, Mapping[int, float]] | None = None) -> list[BackendEvent]:
        """Decide every peer's alignment again with the maps as they are now.

        Args:
            own: this robot's keyframe poses in its map, by index.
            peers: each peer's keyframe poses in its own map, by index.
            paths: distance driven up to keyframes, by robot and index, where the poses are
                not every keyframe's (a peer sends only those of its loops'); the others'
                are :func:`path_lengths` of their poses.

        Returns:
            The lines to log: ``'aligned'`` (first placed), ``'jump'`` (placement moved).
        """
        events: list[BackendEvent] = []
        paths = paths or {}
        own_path = paths.get(self.robot) or path_lengths(own)
        for peer, entry in self._peers.items():
            theirs = peers.get(peer, {})
            their_path = paths.get(peer) or path_lengths(theirs)
            links = [k for k in entry.links if k.own in own and k.theirs in theirs
                     and k.own in own_path and k.theirs in their_path]
            if len(links) >= self.settings.min_loops:
                self._decide(entry, links, own, theirs, (own_path, their_path), events)
        return events

    def _decide(self, entry: _Peer, links: list[_Link], own: Poses, theirs: Poses,
                paths: tuple[Mapping[int, float], Mapping[int, float]],
                events: list[BackendEvent]) -> None:
        s = self.settings
        X = np.array([own[k.own] for k in links], dtype=np.float64)
        Y = np.array([theirs[k.theirs] for k in links], dtype=np.float64)
        Z = np.array([k.Z for k in links])
        cov_z = np.array([k.cov for k in links])
        own_path, their_path = paths
        sig = cycle_sigmas(X, Z, Y, cov_z, np.array([own_path[k.own] for k in links]),
                           np.array([their_path[k.theirs] for k in links]), s.drift)
        agree = sig <= s.gate
        best, _ = max_clique(agree)
        A, cov_a = implied(X, Z, Y, cov_z)
        rest = [i for i in range(len(links)) if i not in set(best)]
        rival, _ = max_clique(agree, rest)
        state = replace(entry.state, loops=len(entry.links))
        if len(best) < s.min_loops:
            entry.state = replace(state, rival=len(rival))
            return
        T, cov = mean_alignment(A[best], cov_a[best])
        points = Y[best][:, :3, 3]
        if len(rival) >= max(s.min_loops, s.rival_ratio * len(best)):
            other, _ = mean_alignment(A[rival], cov_a[rival])
            if moved_by(T, other, points)[0] > s.rival_m:  # two places: decide nothing
                entry.state = replace(state, rival=len(rival))
                return
        peer = state.peer
        old = state.transform
        jumps = state.jumps
        if old is None:
            events.append(BackendEvent('aligned', f'robot {peer} aligned: its map is '
                                       f'{_placement(T)} from ours, by {len(best)} of '
                                       f'{len(links)} inter-robot loops in agreement'
                                       f'{_sigmas(cov)}'))
        elif self._jumped(old, T, points):
            dist, deg = moved_by(old, T, points)
            jumps += 1
            events.append(BackendEvent('jump', f'robot {peer} alignment jumped {dist:.2f} m, '
                                       f'{deg:.2f} deg at its loops, by {len(best)} of '
                                       f'{len(links)} inter-robot loops in agreement'
                                       f'{_sigmas(cov)}'))
        entry.inliers = [links[i] for i in best]
        entry.state = replace(state, aligned=True, transform=T, covariance=swap_blocks(cov),
                              inliers=len(best), rival=len(rival), jumps=jumps)

    def _jumped(self, a: FloatArray, b: FloatArray, points: FloatArray) -> bool:
        dist, deg = moved_by(a, b, points)
        return dist > self.settings.jump_m or deg > self.settings.jump_deg


def _placement(T: FloatArray) -> str:
    yaw = math.degrees(math.atan2(float(T[1, 0]), float(T[0, 0])))
    return f'{float(np.linalg.norm(T[:3, 3])):.1f} m and {yaw:.0f} deg'


def _sigmas(cov: FloatArray) -> str:
    d = np.sqrt(np.maximum(np.diag(cov), 0.0))
    return (f' (sigma {float(np.linalg.norm(d[3:])):.2f} m, '
            f'{math.degrees(float(np.linalg.norm(d[:3]))):.2f} deg)')
