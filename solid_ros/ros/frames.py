"""The frames of solid_node's transforms on ``/tf``: never one from a frame to itself.

A transform whose parent and child are the same frame (``map -> map``) breaks every TF
listener that looks that frame up, so the node refuses settings that make one at start-up
(:func:`frame_conflict`: ``map_frame`` equal to ``odom_frame``, or with KISS-ICP
``odom_frame`` equal to ``sensor_frame``) and, when the frame comes from the messages (an
odometry whose ``header.frame_id`` is ``map``, clouds in ``odom``), broadcasts no such
transform and says so once (:class:`SelfTransformGuard`). Nothing here imports rclpy.
"""

from __future__ import annotations

from collections.abc import Callable

from solid_ros.core.config import NodeConfig

__all__ = ['DEFAULT_ODOM_FRAME', 'FRAME_KEYS', 'SelfTransformGuard', 'frame_conflict',
           'map_odom_advice', 'odom_sensor_advice']

# KISS-ICP's odometry frame when odom_frame is empty.
DEFAULT_ODOM_FRAME = 'odom'
# The settings that decide the frames of the node's transforms.
FRAME_KEYS = ('map_frame', 'odom_frame', 'sensor_frame', 'odometry_source')


def map_odom_advice(frame: str) -> str:
    """What is wrong, and what to set, when ``map_frame`` and the odometry frame are one."""
    return (f"map_frame and odom_frame (empty: the odometry's header.frame_id) are both "
            f"'{frame}': map -> odom would be {frame} -> {frame}, which breaks every TF lookup "
            f"of '{frame}'; set map_frame to another name (e.g. map_frame: solid_map) or "
            "odom_frame to the odometry's real frame")


def odom_sensor_advice(frame: str) -> str:
    """What is wrong, and what to set, when KISS-ICP's odometry and sensor frames are one."""
    return (f"odom_frame and sensor_frame (empty: the clouds' header.frame_id) are both "
            f"'{frame}': KISS-ICP's odom -> sensor would be {frame} -> {frame}, which breaks "
            f"every TF lookup of '{frame}'; set sensor_frame to the LiDAR's frame or "
            'odom_frame to another name (e.g. odom_frame: kiss_odom)')


def frame_conflict(cfg: NodeConfig) -> str | None:
    """The problem, in one line, when the settings alone make a transform from a frame to
    itself (None: they do not; frames taken from messages are checked as they come)."""
    kiss = cfg.odometry_source == 'kiss_icp'
    odom = cfg.odom_frame or (DEFAULT_ODOM_FRAME if kiss else '')
    if odom and odom == cfg.map_frame:
        return map_odom_advice(odom)
    if kiss and cfg.sensor_frame and cfg.sensor_frame == odom:
        return odom_sensor_advice(odom)
    return None


class SelfTransformGuard:
    """Lets through transforms between two frames; one from a frame to itself is dropped and
    ``warn`` gets ``advice(frame)`` the first time for that frame.

    Args:
        warn: where the one line goes (the node's logger at WARN).
        advice: the line for a frame (:func:`map_odom_advice`, :func:`odom_sensor_advice`).
    """

    def __init__(self, warn: Callable[[str], object], advice: Callable[[str], str]) -> None:
        self._warn = warn
        self._advice = advice
        self._warned: set[str] = set()

    def allows(self, parent: str, child: str) -> bool:
        """Whether ``parent -> child`` may go on /tf (False: they are the same frame)."""
        if parent != child:
            return True
        if child not in self._warned:
            self._warned.add(child)
            self._warn(self._advice(child))
        return False
