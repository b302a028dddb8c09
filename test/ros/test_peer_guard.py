"""PeerGuard without ROS: fleet key, replays, allowlist, bounded robots and rate limits."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from solid_ros.core.errors import ConfigError
from solid_ros.formats.peers import CloudRequest, encode, seal
from solid_ros.ros.peer_guard import (
    ADMIT_BURST,
    CATCHUP_GAP_SEC,
    PeerGuard,
    Refused,
    key_file_is_private,
    load_fleet_key,
    parse_allowlist,
)

KEY = b'fleet key of the test, 32 bytes.'
TOPIC = '/solid/cloud_requests'
SEC = 1_000_000_000


class Clocks:
    def __init__(self) -> None:
        self.mono = 100.0
        self.wall = 1_700_000_000 * SEC

    def monotonic(self) -> float:
        return self.mono

    def time_ns(self) -> int:
        return self.wall


def guard(robot: int, key: bytes | None = KEY, clocks: Clocks | None = None,
          **kw: object) -> PeerGuard:
    c = clocks or Clocks()
    return PeerGuard(robot, key, clock=c.monotonic, wall=c.time_ns, **kw)  # type: ignore


def test_sealed_messages_open_once_and_only_with_the_key() -> None:
    clocks = Clocks()
    alice, bob = guard(1, clocks=clocks), guard(2, clocks=clocks)
    inner = encode(CloudRequest(1, 2, 5, 77, 9))
    first, second = alice.seal(TOPIC, inner), alice.seal(TOPIC, inner)
    assert first != second  # a fresh stamp each
    assert bob.open(TOPIC, first) == (1, inner)
    with pytest.raises(Refused) as r:
        bob.open(TOPIC, first)  # played again
    assert r.value.kind == 'replayed'
    assert bob.open(TOPIC, second) == (1, inner)
    for raw in (inner, guard(1, b'another key of at least 16 bytes').seal(TOPIC, inner)):
        with pytest.raises(Refused) as r:
            bob.open(TOPIC, raw)
        assert r.value.kind == 'unauthenticated'
    # Its own messages come back on its own subscription: recognised, not refused.
    assert alice.open(TOPIC, alice.seal(TOPIC, inner)) == (1, b'')
    # A message stamped far from this clock (a recording, or an unsynchronised robot).
    old = seal(inner, KEY, 1, clocks.wall - 61 * SEC, TOPIC)
    with pytest.raises(Refused) as r:
        bob.open(TOPIC, old)
    assert r.value.kind == 'stale' and 'clocks not synchronised' in str(r.value)
    # Without a key nothing is sealed or checked.
    plain = guard(3, key=None)
    assert plain.seal(TOPIC, inner) == inner and plain.open(TOPIC, inner) == (None, inner)


def test_allowlist_robot_table_and_rate_limits() -> None:
    clocks = Clocks()
    g = guard(0, clocks=clocks, allow=parse_allowlist('1, 2,3'), max_robots=2,
              descriptor_rate=10.0, descriptor_burst=20.0, request_rate=5.0)
    with pytest.raises(Refused) as r:
        g.admit(9)
    assert r.value.kind == 'not_allowed'
    for robot in (1, 2, 3):
        g.admit(robot)
        clocks.mono += 1.0
    assert set(g.robots()) == {2, 3} and 1 not in g and g.dropped_robots == 1
    assert sum(g.allow_descriptor(2) for _ in range(100)) == 20  # the burst
    clocks.mono += 1.0
    assert sum(g.allow_descriptor(2) for _ in range(100)) == 10  # then the rate
    assert not g.allow_descriptor(1)  # dropped: not admitted
    assert sum(g.allow_request(3) for _ in range(900)) == 500
    assert g.allow_catchup(3) and not g.allow_catchup(3)
    clocks.mono += CATCHUP_GAP_SEC
    assert g.allow_catchup(3)


def test_a_storm_of_new_robot_ids_is_admitted_slowly() -> None:
    clocks = Clocks()
    g = guard(0, clocks=clocks, max_robots=32)
    admitted = 0
    for robot in range(1, 30_001):
        try:
            g.admit(robot)
            admitted += 1
        except Refused as err:
            assert err.kind == 'robots_full'
    assert admitted == ADMIT_BURST and len(g.robots()) == ADMIT_BURST
    clocks.mono += 60.0
    for robot in range(30_001, 60_001):
        try:
            g.admit(robot)
        except Refused:
            pass
    assert len(g.robots()) == 32  # bounded


def test_fleet_key_files(tmp_path: Path) -> None:
    path = tmp_path / 'fleet.key'
    path.write_bytes(KEY + b'\n')
    path.chmod(0o600)
    assert load_fleet_key(str(path)) == KEY and key_file_is_private(str(path))
    path.chmod(0o644)
    assert not key_file_is_private(str(path))
    short = tmp_path / 'short.key'
    short.write_bytes(b'secret\n')
    for bad, why in ((short, 'at least 16'), (tmp_path / 'missing.key', 'cannot read'),
                     (tmp_path, 'not a regular file')):
        with pytest.raises(ConfigError, match=why) as err:
            load_fleet_key(str(bad))
        assert 'secret' not in str(err.value)
    big = tmp_path / 'big.key'
    big.write_bytes(os.urandom(5000))
    with pytest.raises(ConfigError, match='5000 bytes'):
        load_fleet_key(str(big))
    with pytest.raises(ConfigError, match='peer_allowlist'):
        parse_allowlist('1,x')
    assert parse_allowlist(' ') is None
