"""What a peer message must pass before solid_node acts on it: authentication, replay
protection, the allowlist, a bounded table of robots and per-robot rate limits. No ROS import.

Trust model (see doc/multi_robot.md, "Trust: the fleet key"): with a fleet key
(``peer_key_file``) every message carries an HMAC-SHA256 tag over its topic and bytes
(:func:`solid_ros.formats.peers.seal`), so a participant without the key can neither inject,
alter nor move a message between topics. The envelope's stamp is strictly increasing per
sender (its wall clock, bumped past the last one sent); a receiver accepts a stamp only when
it is newer than the last it accepted from that sender on that topic and within
``window_sec`` of its own clock, so a recorded message cannot be played back. The key
authenticates fleet membership, not one robot: every holder of the key can speak for any
robot id. Without a key nothing is authenticated (a trusted domain) and only the bounds apply.

Bounds: at most ``max_robots`` robots are tracked (the least recently heard one is dropped
for a new one, and new robots are admitted at most ``ADMIT_BURST`` at once, then one every
``1 / ADMIT_RATE`` s); each robot's descriptors and its cloud and catch-up requests go
through token buckets, so a flood costs one dictionary look-up per message.
"""

from __future__ import annotations

import math
import os
import stat
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from solid_ros.core.errors import ConfigError
from solid_ros.formats.peers import (
    PeerAuthError,
    PeerMessageError,
    is_sealed,
    seal,
    unseal,
)

__all__ = ['PeerGuard', 'Refused', 'TokenBucket', 'load_fleet_key', 'parse_allowlist']

MIN_KEY_BYTES = 16
MAX_KEY_BYTES = 4096
ADMIT_BURST = 16.0  # new robots admitted at once
ADMIT_RATE = 0.5  # then new robots per second
REQUEST_BURST = 500.0
SERVE_RATE, SERVE_BURST = 200.0, 1000.0  # cloud replies a second to all requesters together
CATCHUP_GAP_SEC = 2.0  # one catch-up answer per requester within this time
CATCHUP_RATE, CATCHUP_BURST = 0.5, 4.0  # catch-up answers a second to all requesters


class Refused(Exception):
    """A peer message refused before it was acted on; ``kind`` is the counter it adds to."""

    def __init__(self, kind: str, detail: str = '') -> None:
        super().__init__(detail or kind)
        self.kind = kind


class TokenBucket:
    """``rate`` tokens a second up to ``burst``; :meth:`take` spends one when there is one."""

    def __init__(self, rate: float, burst: float, now: float) -> None:
        self.rate, self.burst = float(rate), float(burst)
        self._tokens, self._t = float(burst), now

    def take(self, now: float, n: float = 1.0) -> bool:
        """Spend ``n`` tokens if there are; return whether it did."""
        self._tokens = min(self.burst, self._tokens + (now - self._t) * self.rate)
        self._t = now
        if self._tokens < n:
            return False
        self._tokens -= n
        return True


def load_fleet_key(path: str) -> bytes:
    """Read a fleet key file: its bytes, surrounding white space stripped.

    Any secret of 16 bytes or more works (``head -c 32 /dev/urandom | base64 > fleet.key``).
    Nothing of the key is ever logged; messages name the file only.

    Raises:
        ConfigError: the file is missing, unreadable, not a regular file, too short or long.
    """
    p = Path(path).expanduser()
    try:
        st = os.stat(p)
        if not stat.S_ISREG(st.st_mode):
            raise ConfigError(f'peer_key_file: {p} is not a regular file')
        if st.st_size > MAX_KEY_BYTES:
            raise ConfigError(f'peer_key_file: {p} holds {st.st_size} bytes; a fleet key is '
                              f'{MIN_KEY_BYTES} to {MAX_KEY_BYTES} bytes')
        key = p.read_bytes().strip()
    except OSError as err:
        raise ConfigError(f'peer_key_file: cannot read {p}: {err.strerror or err}') from err
    if len(key) < MIN_KEY_BYTES:
        raise ConfigError(f'peer_key_file: {p} holds {len(key)} bytes; a fleet key needs at '
                          f'least {MIN_KEY_BYTES} (e.g. head -c 32 /dev/urandom | base64)')
    return key


def key_file_is_private(path: str) -> bool:
    """Whether only its owner may read the key file (group and others may not)."""
    try:
        return not os.stat(Path(path).expanduser()).st_mode & 0o077
    except OSError:
        return False


def parse_allowlist(text: str) -> frozenset[int] | None:
    """``'1,2, 5'`` -> {1, 2, 5}; empty -> None (any robot).

    Raises:
        ConfigError: an entry is not a robot id (0 to 2**31 - 1).
    """
    if not text.strip():
        return None
    out = set()
    for item in text.replace(' ', '').split(','):
        if not item.isdigit() or int(item) > 2**31 - 1:
            raise ConfigError(f'peer_allowlist: {item!r} is not a robot id (0 to 2147483647); '
                              "write ids separated by commas, e.g. '1,2,3'")
        out.add(int(item))
    return frozenset(out)


@dataclass
class _Robot:
    heard: float
    descriptors: TokenBucket
    requests: TokenBucket
    catchup_at: float = -math.inf


class PeerGuard:
    """Authentication, replay protection, allowlist, robot table and rate limits.

    Args:
        robot: this robot's id.
        key: the fleet key, or None (no authentication).
        allow: robot ids accepted (None: any).
        max_robots: robots tracked at most.
        window_sec: largest difference between a message's stamp and this clock.
        descriptor_rate: descriptors a second per robot (burst: ``descriptor_burst``).
        descriptor_burst: descriptors a robot may send at once (a catch-up answer).
        request_rate: cloud requests a second per requester (burst ``REQUEST_BURST``).
        clock: monotonic seconds; ``wall``: wall-clock nanoseconds (injectable for tests).
    """

    def __init__(self, robot: int, key: bytes | None, *, allow: frozenset[int] | None = None,
                 max_robots: int = 32, window_sec: float = 60.0,
                 descriptor_rate: float = 50.0, descriptor_burst: float = 2100.0,
                 request_rate: float = 100.0, clock: Callable[[], float] = time.monotonic,
                 wall: Callable[[], int] = time.time_ns) -> None:
        self.robot, self.key, self.allow = int(robot), key, allow
        self.max_robots, self.window_ns = int(max_robots), int(window_sec * 1e9)
        self.descriptor_rate, self.descriptor_burst = descriptor_rate, descriptor_burst
        self.request_rate = request_rate
        self._clock, self._wall = clock, wall
        self._lock = threading.Lock()
        self._last_sent = 0
        self._robots: OrderedDict[int, _Robot] = OrderedDict()
        self._stamps: dict[tuple[int, str], int] = {}  # (sender, topic) -> last accepted
        now = clock()
        self._admit = TokenBucket(ADMIT_RATE, ADMIT_BURST, now)
        self._serve = TokenBucket(SERVE_RATE, SERVE_BURST, now)
        self._catchups = TokenBucket(CATCHUP_RATE, CATCHUP_BURST, now)
        self.dropped_robots = 0

    # -- out ---------------------------------------------------------------------------------

    def seal(self, topic: str, raw: bytes) -> bytes:
        """``raw`` as sent on ``topic``: sealed with a fresh stamp when there is a key.

        Call it and publish under one lock per topic, so stamps go out in order.
        """
        if self.key is None:
            return raw
        with self._lock:
            stamp = self._last_sent = max(self._wall(), self._last_sent + 1)
        return seal(raw, self.key, self.robot, stamp, topic)

    # -- in ----------------------------------------------------------------------------------

    def open(self, topic: str, raw: bytes) -> tuple[int | None, bytes]:
        """Authenticate a received message: ``(sender or None without a key, message)``.

        Returns ``(self.robot, b'')`` for this robot's own messages (which come back on its
        own subscriptions): the caller ignores them.

        Raises:
            Refused: ``'unauthenticated'`` (no envelope, wrong key or altered),
                ``'replayed'`` (a stamp not newer than the last from its sender) or
                ``'stale'`` (stamped outside the window of this clock).
        """
        if self.key is None:
            return None, raw
        if not is_sealed(raw):
            raise Refused('unauthenticated', 'a message without an authentication tag')
        try:
            sealed = unseal(raw, self.key, topic)
        except PeerAuthError as err:
            raise Refused('unauthenticated', str(err)) from err
        except PeerMessageError as err:
            raise Refused('malformed', str(err)) from err
        if sealed.sender == self.robot:
            return self.robot, b''
        now = self._wall()
        if abs(sealed.stamp_ns - now) > self.window_ns:
            raise Refused('stale', f'robot {sealed.sender} stamped its message '
                                   f'{(sealed.stamp_ns - now) / 1e9:+.1f} s from this clock '
                                   f'(window {self.window_ns / 1e9:g} s): clocks not '
                                   'synchronised?')
        slot = (sealed.sender, topic)
        with self._lock:
            if sealed.stamp_ns <= self._stamps.get(slot, -1):
                raise Refused('replayed', f'a message of robot {sealed.sender} played again')
            if sealed.sender in self._robots or len(self._stamps) < 4 * self.max_robots:
                self._stamps[slot] = sealed.stamp_ns
        return sealed.sender, sealed.inner

    def admit(self, robot: int) -> None:
        """Note a message from ``robot`` (its own id checked against the envelope already).

        Raises:
            Refused: ``'not_allowed'`` (not on the allowlist) or ``'robots_full'`` (a new
                robot beyond the admission rate).
        """
        if self.allow is not None and robot not in self.allow:
            raise Refused('not_allowed', f'robot {robot} is not on peer_allowlist')
        now = self._clock()
        with self._lock:
            entry = self._robots.get(robot)
            if entry is not None:
                entry.heard = now
                self._robots.move_to_end(robot)
                return
            if not self._admit.take(now):
                raise Refused('robots_full', f'robot {robot}: too many new robots at once')
            self._robots[robot] = _Robot(
                now, TokenBucket(self.descriptor_rate, self.descriptor_burst, now),
                TokenBucket(self.request_rate, REQUEST_BURST, now))
            while len(self._robots) > self.max_robots:
                gone, _ = self._robots.popitem(last=False)
                self.dropped_robots += 1
                for t in [k for k in self._stamps if k[0] == gone]:
                    del self._stamps[t]

    def allow_descriptor(self, robot: int) -> bool:
        """Whether ``robot`` (admitted) may have one more descriptor looked at now."""
        now = self._clock()
        with self._lock:
            entry = self._robots.get(robot)
            return entry is not None and entry.descriptors.take(now)

    def allow_request(self, robot: int) -> bool:
        """Whether ``robot`` (admitted) may have one more cloud request answered now (its
        own rate, and ``SERVE_RATE`` for all requesters together)."""
        now = self._clock()
        with self._lock:
            entry = self._robots.get(robot)
            return entry is not None and entry.requests.take(now) and self._serve.take(now)

    def allow_catchup(self, robot: int) -> bool:
        """Whether ``robot`` may have a catch-up answered: one per ``CATCHUP_GAP_SEC`` each,
        and ``CATCHUP_RATE`` for all requesters together."""
        now = self._clock()
        with self._lock:
            entry = self._robots.get(robot)
            if entry is None or now - entry.catchup_at < CATCHUP_GAP_SEC:
                return False
            if not self._catchups.take(now):
                return False
            entry.catchup_at = now
            return True

    # -- reports -----------------------------------------------------------------------------

    def robots(self) -> dict[int, float]:
        """Robots tracked now -> monotonic time last heard (a copy)."""
        with self._lock:
            return {r: e.heard for r, e in self._robots.items()}

    def __contains__(self, robot: object) -> bool:
        return robot in self._robots
