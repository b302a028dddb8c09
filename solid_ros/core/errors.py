"""Exception family of solid_ros: every error the package raises on purpose."""

from __future__ import annotations


class SolidError(Exception):
    """Base class of all solid_ros errors."""


class ConfigError(SolidError, ValueError):
    """A configuration value or file is invalid; the message names the key."""


class DatabaseError(SolidError):
    """A saved database cannot be read or does not match the configuration."""


class CloudError(SolidError, ValueError):
    """A point cloud cannot be decoded or holds no usable point."""


class BagError(SolidError):
    """A bag file cannot be read or lacks what was asked for."""


class PoseError(SolidError, ValueError):
    """A pose or times file cannot be read, or poses and stamps do not fit together."""


class BackendError(SolidError):
    """The pose graph back end cannot run (gtsam missing) or was given unusable input."""


class OdometryUnavailable(SolidError):
    """The odometry source cannot register a cloud now (its process ended and is not
    restarted yet): the caller skips the cloud."""
