"""View centres of this session's keyframes by index, read in bulk.

Candidates by view (:func:`~solid_ros.core.candidates.position.view_keyframes`) compare the
query's view centre with every keyframe's in the graph on every keyframe. A dictionary lookup
per keyframe cost 6 ms a query at 5,000 keyframes and 113 ms at the database's default capacity
of 100,000; one array read here takes 0.2 and 10 ms, as
:class:`~solid_ros.core.candidates.position.ViewCentres` does for a loaded map.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import numpy.typing as npt

__all__ = ['KeyframeViews']

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

_FIRST_ROWS = 256  # rows allocated at first; they double up to the capacity


class KeyframeViews:
    """A ring of the newest ``capacity`` keyframes' view centres (sensor frames), by index.

    Keyframe ``i`` lives in row ``i % capacity``; a row remembers whose centre it holds, so a
    keyframe overwritten by a newer one reads as having none. One thread writes
    (:meth:`put`, the describe stage), another reads (:meth:`at`, the verify stage): a row's
    centre is written before its index, and the arrays are replaced whole when they grow, so a
    reader sees a keyframe's centre complete or not at all.

    Args:
        capacity: keyframes kept (the database's ``capacity``).
    """

    def __init__(self, capacity: int) -> None:
        self._capacity = max(int(capacity), 1)
        self._rows = self._empty(0)

    @classmethod
    def of(cls, views: Mapping[int, npt.ArrayLike], capacity: int = 100_000) -> KeyframeViews:
        """From view centres by keyframe index."""
        out = cls(capacity)
        for index, centre in sorted(views.items()):
            out.put(index, centre)
        return out

    def put(self, index: int, centre: npt.ArrayLike) -> None:
        """Keep keyframe ``index``'s view centre (3-vector)."""
        row = int(index) % self._capacity
        indices, centres = self._rows
        if row >= len(indices):
            grown = self._empty(min(self._capacity, max(row + 1, 2 * len(indices),
                                                        _FIRST_ROWS)))
            grown[0][:len(indices)] = indices
            grown[1][:len(indices)] = centres
            self._rows = grown  # readers hold the old pair or the new one, never a mix
            indices, centres = grown
        centres[row] = np.asarray(centre, dtype=np.float64).reshape(3)
        indices[row] = int(index)

    def at(self, indices: npt.ArrayLike) -> FloatArray:
        """(K, 3) view centres of keyframes ``indices``, NaN where none is kept."""
        want = np.asarray(indices, dtype=np.int64).reshape(-1)
        kept, centres = self._rows
        out = np.full((len(want), 3), np.nan)
        rows = want % self._capacity
        found = rows < len(kept)
        found[found] = kept[rows[found]] == want[found]
        out[found] = centres[rows[found]]
        return out

    def clear(self) -> None:
        """Forget every centre (after a reset)."""
        self._rows = self._empty(0)

    @staticmethod
    def _empty(rows: int) -> tuple[IntArray, FloatArray]:
        return np.full(rows, -1, dtype=np.int64), np.zeros((rows, 3))
