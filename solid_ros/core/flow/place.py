"""What the detector knows of one candidate's place besides the clouds, for the judge.

A :class:`HitPlace` answers the verifier's :class:`~solid_ros.core.verification.measures.Place`
questions for one hit: whether a pose puts the query where the pose graph predicted it, how
far it is from this session's odometry and from the graph's guess, and what each allows. Poses
are ``T_mq`` in the levelled frames. :func:`same_place` says when two matches are one place
(the margins, and the distinct places ``max_candidates`` counts).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from solid_ros.core.candidates.hits import graph_stray, graph_turn, hit_knows_place
from solid_ros.core.candidates.proposal import Hit
from solid_ros.core.config import SolidConfig
from solid_ros.core.results import Match

__all__ = ['HitPlace', 'same_place']

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class HitPlace:
    """One hit's place.

    Attributes:
        hit: the candidate (its graph guess and sigmas, when the graph placed it).
        centre: the query's view centre (its keyframe cloud's centroid, levelled frame).
        config: the detector's settings.
        odom: ``odom(T_mq)``: ``(odom_error_m, odom_allowed_m)`` of the odometry check.
    """

    hit: Hit
    centre: FloatArray
    config: SolidConfig
    odom: Callable[[FloatArray], tuple[float, float]]

    @property
    def graph(self) -> bool:
        """The pose graph proposed the candidate."""
        return self.hit.source == 'graph'

    def known(self, T_mq: FloatArray, coarse_voxel: float) -> bool:
        """The pose puts the query's view where the graph predicted it."""
        return (self.hit.guess is not None
                and hit_knows_place(self.hit, self.centre, self.config, T_mq, coarse_voxel))

    def odometry(self, T_mq: FloatArray) -> tuple[float, float]:
        """The odometry check's reading."""
        return self.odom(T_mq)

    def heading(self, T_mq: FloatArray) -> tuple[float, float]:
        """The turn from the graph's heading and its tolerance."""
        return graph_turn(self.hit, T_mq)

    def position(self, T_mq: FloatArray, voxel: float) -> tuple[float, float]:
        """The view's distance from the graph's guess and what it allows."""
        return graph_stray(self.hit, self.centre, self.config, T_mq, voxel)


def same_place(a: Match, b: Match, hood: int) -> bool:
    """``a`` and ``b`` are one place: the same session, within ``hood`` indices."""
    return a.session == b.session and abs(a.index - b.index) <= hood
