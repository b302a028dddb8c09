"""SharedDetector without ROS: no lock is held while a peer's cloud is awaited."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from solid_ros.core.config import SolidConfig
from solid_ros.core.database.clouds import KeyframeCloud
from solid_ros.core.descriptor.solid import describe
from solid_ros.core.flow.closure import LoopClosure
from solid_ros.core.flow.detector import LoopDetector
from solid_ros.ros.shared_detector import IN_FLIGHT, SharedDetector

SEC = 1_000_000_000
CFG = SolidConfig().replace(distance_threshold=1e-6, exclude_recent_frames=0, num_candidates=12)


class SlowPeer:
    """A cloud source whose replies come only when ``release`` is set."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.requested: list[tuple[int, int, int]] = []
        self.most_in_flight = 0
        self._in_flight = 0

    def request(self, robot: int, index: int, stamp_ns: int) -> Any:
        self.requested.append((robot, index, stamp_ns))
        self._in_flight += 1
        self.most_in_flight = max(self.most_in_flight, self._in_flight)
        return (robot, index)

    def collect(self, ticket: Any) -> KeyframeCloud | str:
        self.release.wait(30.0)
        self._in_flight -= 1
        return 'peer_timeout'


def scene(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = rng.uniform([-40, -40, -2], [40, 40, 6], size=(6000, 3))
    return pts[np.hypot(pts[:, 0], pts[:, 1]) > 4.0]


def test_saving_and_serving_never_wait_for_a_peer(tmp_path: Path) -> None:
    shared = SharedDetector(LoopClosure(LoopDetector(CFG)))
    peer = SlowPeer()
    shared.set_cloud_source(peer)
    pts = scene(1)
    d = describe(pts, CFG)
    for i in range(20):  # a peer's keyframes like this place: 20 candidates to fetch
        shared.detector.add_peer_keyframe(5, i, i * SEC, d.r_solid, d.heading)
    own = shared.propose(scene(2), SEC, None)
    assert own is not None
    shared.verify(own)  # keyframe 0 of this robot, no peer candidate near it
    proposal = shared.propose(pts, 2 * SEC, None)
    assert proposal is not None and {h.match.session for h in proposal.hits} == {5}
    done: list[Any] = []
    worker = threading.Thread(target=lambda: done.append(shared.verify(proposal)))
    worker.start()
    deadline = time.monotonic() + 10.0
    while not peer.requested and time.monotonic() < deadline:
        time.sleep(0.01)
    assert peer.requested and not done  # waiting for the peer
    t0 = time.monotonic()
    size, backup = shared.save(str(tmp_path / 'db.npz'))  # took both locks
    assert own_cloud_served(shared)
    assert time.monotonic() - t0 < 5.0 and size == 22 and backup is None
    assert not done
    peer.release.set()
    worker.join(30.0)
    result, _ = done[0]
    assert {c.reason for c in result.attempts} == {'peer_timeout'} and not result.loops
    # At most IN_FLIGHT requests were out at once; each keyframe asked once.
    assert peer.most_in_flight <= IN_FLIGHT and len(peer.requested) == 12


def own_cloud_served(shared: SharedDetector) -> bool:
    seq = shared.detector.database.own_seq(0)
    assert seq is not None
    stamp = shared.detector.database.match_info(seq)[2]
    return (shared.own_cloud(0, stamp) is not None and shared.own_cloud(0, stamp + 1) is None)
