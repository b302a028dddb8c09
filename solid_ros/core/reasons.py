"""Why a candidate was or was not published: one typed vocabulary for every module.

Every rule of the judge (:data:`solid_ros.core.verification.judge.RULES`) names its refusals
with a reason of its own, in the order the rules run; the detector adds ``'descriptor'``
(accepted without verification) and ``'best'`` (the nearest stored scan, listed for evaluation
only); fetching another robot's keyframe cloud can fail with the three ``peer_*`` reasons.
"""

from __future__ import annotations

from typing import Literal, get_args

__all__ = ['FETCH_REASONS', 'REASONS', 'Reason', 'RULE_REASONS']

Reason = Literal[
    # the judge's rules, in their order (and 'verified' when none refused)
    'verified', 'no_cloud', 'too_sparse', 'coarse_overlap', 'not_converged', 'overlap', 'rmse',
    'conflict', 'constraint', 'single_object', 'unstable', 'pinned', 'odometry',
    'graph_heading', 'graph_position',
    # the detector
    'descriptor', 'best',
    # another robot's keyframe cloud did not come
    'peer_timeout', 'peer_gone', 'peer_evicted',
]
REASONS: tuple[Reason, ...] = get_args(Reason)
# What the judge can conclude.
RULE_REASONS: tuple[Reason, ...] = REASONS[:REASONS.index('descriptor')]
FETCH_REASONS: tuple[Reason, ...] = ('peer_timeout', 'peer_gone', 'peer_evicted')
