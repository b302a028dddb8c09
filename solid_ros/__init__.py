"""SOLiD loop-closure detection for LiDAR SLAM: a ROS-free numpy core with ROS 2 adapters."""

from __future__ import annotations

from solid_ros.core.config import NodeConfig, SolidConfig
from solid_ros.core.descriptor.matching import cosine_distance, estimate_yaw
from solid_ros.core.descriptor.solid import describe
from solid_ros.core.errors import (
    BagError,
    CloudError,
    ConfigError,
    DatabaseError,
    PoseError,
    SolidError,
)
from solid_ros.core.flow.detector import LoopDetector
from solid_ros.core.results import Descriptor, LoopCandidate

__all__ = [
    'BagError', 'CloudError', 'ConfigError', 'DatabaseError', 'Descriptor', 'LoopCandidate',
    'LoopDetector', 'NodeConfig', 'PoseError', 'SolidConfig', 'SolidError', 'cosine_distance',
    'describe',
    'estimate_yaw',
]
__version__ = '0.1.0'
