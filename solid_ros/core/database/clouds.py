"""Keyframe clouds kept for verification, bounded in count and bytes.

Each stored keyframe may have a downsampled float32 cloud (:class:`KeyframeCloud`), keyed by
the database sequence number of its scan. Clouds are dropped oldest first when the store
exceeds ``cloud_capacity`` clouds or ``cloud_memory_mb``, and together with their scan when the
database evicts it. A scan without a cloud stays searchable but its matches cannot be verified
(reason ``no_cloud``).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = ['CloudStore', 'KeyframeCloud']


@dataclass(frozen=True)
class KeyframeCloud:
    """A stored keyframe cloud: float32 points, structure first.

    Attributes:
        points: (N, 3) float32 in the keyframe's levelled sensor frame.
        n_struct: the first ``n_struct`` rows are structure points.
        voxel: the grid it was downsampled on, metres (0: the configuration's
            ``verify_voxel_size``; finer in a tight space, see ``verify_tight_range``).
    """

    points: npt.NDArray[np.float32]
    n_struct: int
    voxel: float = 0.0

    @property
    def nbytes(self) -> int:
        """Bytes held by the points."""
        return int(self.points.nbytes)


class CloudStore:
    """Clouds by sequence number, oldest first.

    Args:
        max_clouds: most clouds kept (0 keeps none).
        max_bytes: most bytes of points kept.
    """

    def __init__(self, max_clouds: int, max_bytes: int) -> None:
        self.max_clouds = int(max_clouds)
        self.max_bytes = int(max_bytes)
        self._clouds: OrderedDict[int, KeyframeCloud] = OrderedDict()
        self._bytes = 0
        self.dropped = 0  # clouds dropped for the limits (not with their scan)

    def __len__(self) -> int:
        return len(self._clouds)

    def __contains__(self, seq: object) -> bool:
        return seq in self._clouds

    @property
    def nbytes(self) -> int:
        """Bytes of the stored points."""
        return self._bytes

    def get(self, seq: int) -> KeyframeCloud | None:
        """The cloud of scan ``seq``, or None."""
        return self._clouds.get(seq)

    def put(self, seq: int, cloud: KeyframeCloud) -> None:
        """Store the cloud of scan ``seq`` (newer than every stored one), then apply limits."""
        old = self._clouds.pop(seq, None)
        if old is not None:
            self._bytes -= old.nbytes
        self._clouds[seq] = cloud
        self._bytes += cloud.nbytes
        while self._clouds and (len(self._clouds) > self.max_clouds
                                or self._bytes > self.max_bytes):
            _, gone = self._clouds.popitem(last=False)
            self._bytes -= gone.nbytes
            self.dropped += 1

    def drop_before(self, seq: int) -> None:
        """Forget clouds of scans older than ``seq`` (evicted from the database)."""
        while self._clouds:
            first = next(iter(self._clouds))
            if first >= seq:
                break
            self._bytes -= self._clouds.pop(first).nbytes

    def clear(self) -> None:
        """Forget every cloud."""
        self._clouds.clear()
        self._bytes = 0

    def items(self) -> list[tuple[int, KeyframeCloud]]:
        """``(seq, cloud)`` pairs, oldest first."""
        return list(self._clouds.items())
