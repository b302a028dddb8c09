"""ROS domain ids for the tests: two pytest-xdist workers of one run never share one.

Each test module that talks over DDS picks a random domain so that parallel runs do not hear
each other; drawn from one range for all workers, two modules running at once on two workers
met in the same domain about once in a hundred, and a node then stored the other test's clouds.
Each worker draws from its own share of 1..200 instead.
"""

from __future__ import annotations

import os
import random

__all__ = ['pick_domain']

_DOMAINS = 200  # 1..200: valid ids, clear of the ports of ids above 232


def pick_domain() -> int:
    """A random ROS domain id from this xdist worker's share of 1..200 (all of it when the
    tests run in one process)."""
    worker = os.environ.get('PYTEST_XDIST_WORKER', 'gw0')
    count = max(int(os.environ.get('PYTEST_XDIST_WORKER_COUNT', '1')), 1)
    index = int(worker[2:]) if worker[2:].isdigit() else 0
    span = max(_DOMAINS // count, 1)
    return 1 + (index % count) * span + random.randrange(span)
