"""The node's odometry: the core's pairing plus a short wait for odometry that lags its cloud.

Pairing is :class:`~solid_ros.core.odometry.track.StampedOdometry`, the rule the replay and the
fleet replay use too. What the node adds is timing: odometry often arrives just after its
cloud, so :meth:`OdometryWait.pair` waits up to ``wait_sec`` for a pose stamped at or past
the cloud, but only when someone publishes odometry (an unused topic must not slow every
scan), and not while a silent publisher has let ``max_misses`` waits in a row pass without a
message. The subscription callback calls :meth:`~OdometryWait.add`, the describe thread
:meth:`~OdometryWait.pair`; no ROS import.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import numpy.typing as npt

from solid_ros.core.errors import PoseError
from solid_ros.core.odometry.track import OdomSample, StampedOdometry

__all__ = ['OdometryWait']

ODOM_BUFFER = 512
ODOM_WAIT_SEC = 0.25
ODOM_MAX_MISSES = 3  # waits in a row that saw no odometry before the node stops waiting


class OdometryWait:
    """Odometry poses for clouds, with a bounded wait for late odometry.

    Args:
        tolerance_ns: largest stamp difference of a pairing (settable while running).
        capacity: newest poses kept.
        wait_sec: longest wait for odometry at or past a cloud's stamp.
        max_misses: waits in a row without odometry after which ``pair`` stops waiting
            (until odometry arrives again).
    """

    def __init__(self, tolerance_ns: int, capacity: int = ODOM_BUFFER,
                 wait_sec: float = ODOM_WAIT_SEC, max_misses: int = ODOM_MAX_MISSES) -> None:
        self.wait_sec, self.max_misses = wait_sec, max_misses
        self.frame_id = ''  # of the newest odometry
        self._odom = StampedOdometry(tolerance_ns, capacity, name='odometry topic')
        self._cv = threading.Condition()
        self._misses = 0
        self._closed = False
        self._newest: OdomSample | None = None

    @property
    def tolerance_ns(self) -> int:
        """Largest stamp difference of a pairing."""
        return self._odom.tolerance_ns

    @tolerance_ns.setter
    def tolerance_ns(self, value: int) -> None:
        with self._cv:
            self._odom.tolerance_ns = int(value)

    @property
    def latest_stamp_ns(self) -> int | None:
        """Stamp of the newest odometry (None: none yet)."""
        with self._cv:
            return self._odom.latest_stamp_ns

    def add(self, stamp_ns: int, pose: npt.ArrayLike, covariance: npt.ArrayLike | None = None,
            frame_id: str = '') -> OdomSample:
        """Add an odometry pose (4x4) in arrival order and wake a waiting :meth:`pair`.

        Raises:
            PoseError: the pose is not a finite 4x4 matrix, or the covariance holds NaN or
                infinite values (an all-zero one means unknown and is fine); nothing changes.
        """
        if covariance is not None and not np.all(np.isfinite(np.asarray(covariance,
                                                                         dtype=np.float64))):
            raise PoseError('odometry covariance is not finite')
        with self._cv:
            sample = self._newest = self._odom.add(stamp_ns, pose, covariance)
            self.frame_id = frame_id
            self._misses = 0
            self._cv.notify_all()
        return sample

    def pair(self, stamp_ns: int, wait: bool) -> tuple[OdomSample | None, int | None]:
        """The pose for the cloud at ``stamp_ns``, after waiting (when ``wait``) for odometry
        at or past it.

        Returns:
            ``(sample, gap_ns)``: the pose within the tolerance (else None), and the cloud's
            stamp minus the nearest odometry stamp whatever the tolerance (None: no odometry
            yet), which tells another clock apart from a late message.
        """
        deadline = time.monotonic() + self.wait_sec
        with self._cv:
            waited = False
            while (wait and self._misses < self.max_misses and self._behind(stamp_ns)
                   and not self._closed and time.monotonic() < deadline):
                waited = True
                self._cv.wait(deadline - time.monotonic())
            if waited and self._behind(stamp_ns):
                self._misses += 1
            return self._odom.pose_for(stamp_ns), self._odom.nearest_gap_ns(stamp_ns)

    def newest(self) -> OdomSample | None:
        """The newest odometry, whatever its stamp (for a cloud whose stamp cannot be
        trusted: arrival order)."""
        with self._cv:
            return self._newest

    def close(self) -> None:
        """End any wait now and wait no more (the node is shutting down)."""
        with self._cv:
            self._closed = True
            self._cv.notify_all()

    def _behind(self, stamp_ns: int) -> bool:
        latest = self._odom.latest_stamp_ns
        return latest is None or latest < stamp_ns
