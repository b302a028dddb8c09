"""Which parts of the pose graph loops have tied together.

The graph's keyframes fall into segments (a new one after each odometry jump or reset). Two
more nodes stand for the frames segments can be tied to: :data:`ORIGIN`, the session's start
(segment 0's anchor, map = odom), and :data:`MAP`, a loaded map's fixed keyframes. A loop ties
its two ends' components; until then a segment only has a weak prior that keeps map->odom
continuous, so its distance to the rest means nothing and a loop between them is not gated:
it places the segment instead: :func:`tie_move` finds the rigid move of the side that is not
fixed that makes the loop hold, :func:`move_rigidly` applies it to the graph and rebuilds it.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from solid_ros.core.backend.solver import FactorRecord, GraphSolver

__all__ = ['MAP', 'ORIGIN', 'Segments', 'move_rigidly', 'tie_move']

FloatArray = npt.NDArray[np.float64]

ORIGIN = -1
MAP = -2


class Segments:
    """Union-find over segment ids and :data:`ORIGIN` / :data:`MAP`."""

    def __init__(self) -> None:
        self._parent: dict[int, int] = {ORIGIN: ORIGIN, MAP: MAP}
        self.count = 0
        self.anchored = False  # the session moved into the loaded map: ORIGIN holds no more

    def new(self) -> int:
        """A new segment (the first is tied to :data:`ORIGIN`); returns its id."""
        seg = self.count
        self.count += 1
        self._parent[seg] = seg
        if seg == 0:
            self.join(seg, ORIGIN)
        return seg

    def find(self, node: int) -> int:
        """The representative of ``node``'s component."""
        root = node
        while self._parent[root] != root:
            root = self._parent[root]
        while self._parent[node] != root:
            self._parent[node], node = root, self._parent[node]
        return root

    def tied(self, a: int, b: int) -> bool:
        """Whether ``a`` and ``b`` are in one component."""
        return self.find(a) == self.find(b)

    def join(self, a: int, b: int) -> None:
        """Tie the components of ``a`` and ``b``."""
        self._parent[self.find(a)] = self.find(b)

    def members(self, node: int) -> set[int]:
        """Segment ids (not :data:`ORIGIN` / :data:`MAP`) in ``node``'s component."""
        root = self.find(node)
        return {s for s in range(self.count) if self.find(s) == root}

    def fixed(self, node: int) -> bool:
        """Whether ``node``'s component stays put when tied to another: it holds the loaded
        map, or the session's origin before the session moved into that map."""
        return self.tied(node, MAP) or (not self.anchored and self.tied(node, ORIGIN))


def tie_move(segs: Segments, solver: GraphSolver, query: int, match: int | None,
             rec: FactorRecord) -> tuple[set[int], FloatArray] | None:
    """The segments a loop record places and the rigid move that makes it hold, or None when
    its ends are tied already (it is then gated like any loop).

    Args:
        segs: the segments.
        solver: the graph (its current estimate).
        query: the query keyframe's segment.
        match: the match keyframe's segment; None for a loop to the loaded map.
        rec: the loop's record (``'loop'`` or ``'map_loop'``).
    """
    inv = np.linalg.inv
    if match is None:
        if segs.anchored and segs.tied(query, MAP):
            return None
        moved = segs.members(query) if segs.anchored else set(range(segs.count))
        return moved, rec.measured @ inv(solver.pose(rec.keys[0]))
    if segs.tied(match, query):
        return None
    x_m, x_q = solver.pose(rec.keys[0]), solver.pose(rec.keys[1])
    if not segs.fixed(query):  # move the query's side onto the match
        return segs.members(query), x_m @ rec.measured @ inv(x_q)
    return segs.members(match), x_q @ inv(rec.measured) @ inv(x_m)


def move_rigidly(solver: GraphSolver, keys: set[int], move: FloatArray, rec: FactorRecord,
                 weaken: FloatArray | None = None) -> bool:
    """Move the variables ``keys`` and their unary priors by ``move``, add ``rec`` and rebuild
    the graph there; with ``weaken``, every anchor becomes a prior of that covariance (the
    session leaves its origin for a loaded map). On failure everything is put back.

    Returns:
        Whether gtsam solved the moved graph.
    """
    saved = [(r, r.kind, r.measured, r.covariance) for r in solver.records]
    for r in solver.records:
        if r.kind in ('anchor', 'prior') and r.keys[0] in keys:
            r.measured = move @ r.measured
            if weaken is not None:
                r.kind, r.covariance = 'prior', weaken
    old = dict(solver.values)
    solver.records.append(rec)
    if solver.reset_to({k: move @ v if k in keys else v for k, v in old.items()}):
        return True
    for r, kind, measured, cov in saved:
        r.kind, r.measured, r.covariance = kind, measured, cov
    solver.records.pop()
    solver.reset_to(old)
    return False
