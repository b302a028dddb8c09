"""SOLiD loop-closure detection for LiDAR SLAM: a ROS-free numpy core with ROS 2 adapters."""

from __future__ import annotations

from solid_ros.config import NodeConfig, SolidConfig
from solid_ros.descriptor import Descriptor, describe
from solid_ros.detector import LoopCandidate, LoopDetector
from solid_ros.errors import BagError, CloudError, ConfigError, DatabaseError, SolidError
from solid_ros.matching import cosine_distance, estimate_yaw

__all__ = [
    'BagError', 'CloudError', 'ConfigError', 'DatabaseError', 'Descriptor', 'LoopCandidate',
    'LoopDetector', 'NodeConfig', 'SolidConfig', 'SolidError', 'cosine_distance', 'describe',
    'estimate_yaw',
]
__version__ = '0.1.0'
