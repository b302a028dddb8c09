"""Why a candidate was or was not published: one typed vocabulary for every module.

The verification tests (:mod:`solid_ros.core.verification.verifier`) name their rejections; the
detector adds ``'descriptor'`` (accepted without verification), ``'best'`` (the nearest stored
scan, listed for evaluation only) and ``'odometry'`` (this session's odometry contradicts
the loop); fetching another robot's keyframe cloud can fail with the three ``peer_*`` reasons.
"""

from __future__ import annotations

from typing import Literal, get_args

__all__ = ['FETCH_REASONS', 'REASONS', 'Reason', 'VERIFY_REASONS']

Reason = Literal[
    # verification, in the order of its tests
    'verified', 'no_cloud', 'too_sparse', 'coarse_overlap', 'not_converged', 'overlap', 'rmse',
    'conflict', 'constraint', 'single_object', 'unstable',
    # the detector
    'odometry', 'descriptor', 'best',
    # another robot's keyframe cloud did not come
    'peer_timeout', 'peer_gone', 'peer_evicted',
]
REASONS: tuple[Reason, ...] = get_args(Reason)
# What a registration can conclude (the odometry check can still refuse a verified loop).
VERIFY_REASONS: tuple[Reason, ...] = REASONS[:REASONS.index('descriptor')]
FETCH_REASONS: tuple[Reason, ...] = ('peer_timeout', 'peer_gone', 'peer_evicted')
