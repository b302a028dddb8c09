"""A keyframe's candidates on their way from the descriptor stage to verification.

:class:`Proposal` is what ``LoopDetector.propose`` found for one keyframe (its descriptor,
cloud and the descriptor's hits); :class:`Hit` one candidate in it, the descriptor's or the
pose graph's (:mod:`solid_ros.core.candidates.hits`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from solid_ros.core.results import Descriptor, LoopCandidate, Match, Source

__all__ = ['Hit', 'Proposal']

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Hit:
    """A candidate to verify: the descriptor's (from ``LoopDetector.propose``) or the
    pose graph's (added by ``verify``); ``guess`` is the graph's ``T_mq`` in the levelled
    frames, the first start of the coarse registration (None: the graph has none); ``near``:
    among the keyframes near the query in the graph's estimate (verified first); ``view``:
    among those whose view centre lies near the query's (verified next); ``shared``: among
    those that share the query's coarse structure in the graph's estimate (verified last);
    ``heading_tol_deg``: how far a loop the graph proposed may turn from the guess;
    ``sigma_m``: the query's position sigma in the graph, its view centre as the lever;
    ``place_sigma``: the same relative to the match keyframe, asked of the graph only when
    :func:`~solid_ros.core.candidates.tolerance.knows_place` needs it (None: use ``sigma_m``)."""

    match: Match
    margin: float
    heading: npt.NDArray[np.float32]
    source: Source = 'descriptor'
    guess: FloatArray | None = None
    near: bool = False
    heading_tol_deg: float = 180.0
    view: bool = False
    sigma_m: float = math.inf
    place_sigma: Callable[[], float] | None = None
    shared: bool = False


@dataclass(frozen=True)
class Proposal:
    """What ``LoopDetector.propose`` found for one keyframe, for ``verify`` (which neither
    changes it nor keeps it: its own candidates by position join a copy).

    Attributes:
        query_index: index of the keyframe in this session.
        stamp_ns: its stamp.
        seq: its database sequence number.
        heading: its heading signature.
        r_solid: its R-SOLiD (shared with peer robots).
        pose: its pose vector ``(x, y, z, qx, qy, qz, qw)``, when known.
        cloud_points: its keyframe cloud points (levelled, gated, clipped, voxelised), or
            None without verification.
        hits: descriptor candidates, nearest first.
        best: the nearest stored scan by descriptor, accepted or not.
        descriptor: its descriptor (None when given as a descriptor).
        describe_ms: time spent levelling and describing, milliseconds.
        search_ms: time spent searching and storing the descriptor, milliseconds.
        tight: the cloud is on the tight-space grid (see ``verify_tight_range``).
    """

    query_index: int
    stamp_ns: int
    seq: int
    heading: FloatArray
    cloud_points: FloatArray | None
    r_solid: FloatArray | None = None
    pose: FloatArray | None = None
    hits: tuple[Hit, ...] = ()
    best: LoopCandidate | None = None
    descriptor: Descriptor | None = None
    describe_ms: float = math.nan
    search_ms: float = math.nan
    tight: bool = False
