"""Input health of solid_node, without ROS: what is wrong with its input, as lines to log and
values for /diagnostics.

The problems (each lasting while its cause does; windows in seconds of ``clock``): no cloud
on the points topic for ``silence_sec`` since start or since the last one; with odometry, none
for as long, or odometry whose stamps lie more than ``max(CLOCK_GAP_SEC, 10 x
odom_tolerance_sec)`` from the cloud stamps (another clock); clouds rejected, dropped because
a stage falls behind, or failed with an error in the last ``silence_sec``; odometry refused
(not finite) or clouds whose stamps cannot be trusted (zero, repeated, going back; see
:mod:`solid_ros.ros.stamp_guard`) in the last ``silence_sec``. Each distinct reason for a
rejection (numbers aside) is logged when it first occurs, its repeats at most every
``WARN_THROTTLE_SEC``; so are refused odometry and untrusted stamps, each kind on its own.

The clock is injectable so that tests can step time instead of waiting for it.
"""

from __future__ import annotations

import re
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable

from solid_ros.core.stamps import NS_PER_SEC
from solid_ros.ros.stats import NodeStats

__all__ = ['InputHealth', 'SILENCE_SEC', 'WARN_THROTTLE_SEC']

WARN_THROTTLE_SEC = 5.0
SILENCE_SEC = 5.0  # no cloud / no odometry this long (since start or the last one) is a problem
REPEAT_SEC = 30.0  # a lasting problem is logged again this often
CLOCK_GAP_SEC = 1.0  # least cloud-odometry stamp gap taken for another clock
REASON_KINDS = 32  # distinct rejection reasons remembered for throttling

_TROUBLE = {
    'skipped': '{n} PointCloud2 dropped so far: processing falls behind (latest {ago:.0f} s ago)',
    'verify_skipped': '{n} keyframes dropped so far: verification falls behind (latest '
                      '{ago:.0f} s ago)',
    'failed': '{n} clouds failed with an error so far (latest {ago:.0f} s ago; see the log)',
    'odom_rejected': '{n} odometry messages refused so far (latest {ago:.0f} s ago: {why})',
    'cloud_stamps': '{n} PointCloud2 with stamps that cannot be trusted so far (latest {ago:.0f} '
                    's ago: {why}); processed in arrival order',
}
_STAMP_KINDS = {'zero': 'stamps_zero', 'repeated': 'stamps_repeated',
                'backward': 'stamps_backward'}
_SELF_LOGGED = ('rejected', *_TROUBLE)  # logged where they happen, not by check()
_RECOVERED = {'no_clouds': 'PointCloud2 arriving', 'no_odom': 'odometry arriving',
              'odom_clock': 'odometry stamps match the clouds again'}


class InputHealth:
    """The node's input counters and the problems they show.

    Args:
        points_topic: resolved name of the clouds' topic.
        odom_topic: resolved name of the odometry topic; None when odometry is not used.
        qos_reliability: reliability of the points subscription (named in a hint).
        odom_tolerance_sec: the pairing tolerance (settable; the clock check allows 10 x it).
        publishers: number of publishers of a topic (``Node.count_publishers``).
        clock: monotonic seconds.
        silence_sec: the window of the problems (``SILENCE_SEC`` when None).
    """

    def __init__(self, points_topic: str, odom_topic: str | None, qos_reliability: str,
                 odom_tolerance_sec: float, publishers: Callable[[str], int],
                 clock: Callable[[], float] = time.monotonic,
                 silence_sec: float | None = None) -> None:
        self.stats = NodeStats()
        self.points_topic, self.odom_topic = points_topic, odom_topic
        self.qos_reliability = qos_reliability
        self.odom_tolerance_sec = odom_tolerance_sec
        self.silence_sec = SILENCE_SEC if silence_sec is None else silence_sec
        self._publishers = publishers
        self._clock = clock
        self._started = clock()
        self._last_cloud: float | None = None
        self._last_odom: float | None = None
        self._odom_gap: tuple[float, int] | None = None  # (when, cloud minus odometry stamp)
        self._lock = threading.Lock()  # the rejection and trouble records below
        self._rejected_at: deque[float] = deque(maxlen=10_000)
        # Latest time a cloud was dropped (falling behind) or failed, by kind: a WARN while
        # recent, not for the rest of the run.
        self._trouble_at: dict[str, float] = {}
        self._reasons: OrderedDict[str, list[float]] = OrderedDict()
        self._last_reason = ''
        self._why: dict[str, str] = {}  # latest detail of odom_rejected and cloud_stamps
        self._logged_at: dict[str, float] = {}  # throttle of odom_rejected and cloud_stamps
        self._logged: dict[str, float] = {}  # problems logged by check(), when

    # -- events ------------------------------------------------------------------------------

    def cloud_received(self) -> None:
        """A PointCloud2 arrived (decodable or not)."""
        self.stats.received += 1
        self._last_cloud = self._clock()

    def odom_received(self) -> None:
        """A usable odometry message arrived."""
        self._last_odom = self._clock()

    def odom_paired(self, gap_ns: int) -> None:
        """A cloud's stamp minus the nearest odometry stamp, whatever the tolerance."""
        self._odom_gap = (self._clock(), int(gap_ns))

    def trouble(self, kind: str) -> int:
        """Count a cloud dropped (``'skipped'``, ``'verify_skipped'``) or failed (``'failed'``);
        return the count so far."""
        with self._lock:
            self._trouble_at[kind] = self._clock()
            count: int = getattr(self.stats, kind) + 1
            setattr(self.stats, kind, count)
        return count

    def odom_rejected(self, reason: str) -> str | None:
        """Count an odometry message refused (not finite); return the warning to log, or None
        within ``WARN_THROTTLE_SEC`` of the last one."""
        with self._lock:
            self.stats.odom_rejected += 1
        return self._note('odom_rejected', reason, self.stats.odom_rejected,
                          f'odometry message on {self.odom_topic} refused')

    def untrusted_stamp(self, problem: str, header_ns: int) -> str | None:
        """Count a cloud whose header stamp is ``'zero'``, ``'repeated'`` or ``'backward by
        ...'``; return the warning to log, or None within ``WARN_THROTTLE_SEC`` of the last."""
        counter = _STAMP_KINDS[problem.split()[0]]
        with self._lock:
            setattr(self.stats, counter, getattr(self.stats, counter) + 1)
        s = self.stats
        total = s.stamps_zero + s.stamps_repeated + s.stamps_backward
        return self._note('cloud_stamps', f'stamp {header_ns / NS_PER_SEC:.3f} s is {problem}',
                          total, f'PointCloud2 on {self.points_topic} processed in arrival '
                          'order')

    def _note(self, kind: str, why: str, total: int, what: str) -> str | None:
        now = self._clock()
        with self._lock:
            self._trouble_at[kind] = now
            self._why[kind] = why
            if now - self._logged_at.get(kind, -WARN_THROTTLE_SEC) < WARN_THROTTLE_SEC:
                return None
            self._logged_at[kind] = now
        return f'{what}: {why} ({total} so far)'

    def reject(self, reason: str) -> str | None:
        """Count a rejected cloud; return the warning to log, or None while its kind of reason
        was logged less than ``WARN_THROTTLE_SEC`` ago."""
        now = self._clock()
        kind = re.sub(r'\d+', '#', reason)  # the same reason for clouds of other sizes
        with self._lock:
            self.stats.rejected += 1
            self._rejected_at.append(now)
            self._last_reason = reason
            seen = self._reasons.get(kind)
            if seen is None:
                seen = self._reasons[kind] = [now, 0.0]
                while len(self._reasons) > REASON_KINDS:
                    self._reasons.popitem(last=False)
                text = 'first of its kind'
            else:
                self._reasons.move_to_end(kind)
                seen[1] += 1
                if now - seen[0] < WARN_THROTTLE_SEC:
                    return None
                text = f'{int(seen[1])} more like it since it was last logged'
                seen[:] = [now, 0.0]
            total = self.stats.rejected
        return (f'rejected PointCloud2 on {self.points_topic}: {reason} ({text}; {total} '
                'rejected so far)')

    # -- reports -----------------------------------------------------------------------------

    def problems(self) -> dict[str, str]:
        """The input problems now, by kind, each as one line naming the topic."""
        now = self._clock()
        out = self._silence(now)
        if self.odom_topic is not None:
            out.update(self._odom_problems(now, self.odom_topic))
        with self._lock:
            while self._rejected_at and now - self._rejected_at[0] > self.silence_sec:
                self._rejected_at.popleft()
            recent, reason = len(self._rejected_at), self._last_reason
            trouble = {k: t for k, t in self._trouble_at.items() if now - t <= self.silence_sec}
        if recent:
            out['rejected'] = (f'{recent} PointCloud2 rejected on {self.points_topic} in the '
                               f'last {self.silence_sec:.0f} s (latest: {reason})')
        s = self.stats
        counts = {'odom_rejected': s.odom_rejected,
                  'cloud_stamps': s.stamps_zero + s.stamps_repeated + s.stamps_backward}
        for kind, t in trouble.items():
            n = counts[kind] if kind in counts else getattr(s, kind)
            out[kind] = _TROUBLE[kind].format(n=n, ago=now - t, why=self._why.get(kind, ''))
        return out

    def _silence(self, now: float) -> dict[str, str]:
        points, last = self.points_topic, self._last_cloud
        if last is None and now - self._started > self.silence_sec:
            pubs = self._publishers(points)
            hint = (f'{pubs} publisher(s): check their QoS against qos_reliability '
                    f'{self.qos_reliability!r}' if pubs else
                    'no publisher: check the topic name or remap points:=<your topic>')
            return {'no_clouds': f'no PointCloud2 received on {points} in the '
                                 f'{now - self._started:.0f} s since start ({hint})'}
        if last is not None and now - last > self.silence_sec:
            return {'no_clouds': f'no PointCloud2 received on {points} for the last '
                                 f'{now - last:.0f} s ({self.stats.received} before)'}
        return {}

    def _odom_problems(self, now: float, odom: str) -> dict[str, str]:
        out: dict[str, str] = {}
        since = self._last_odom if self._last_odom is not None else self._started
        if now - since > self.silence_sec:
            when = (f'for {now - since:.0f} s' if self._last_odom is not None
                    else f'in the {now - since:.0f} s since start')
            out['no_odom'] = (f'use_odom is on but no nav_msgs/Odometry received on {odom} '
                              f'{when} ({self._publishers(odom)} publisher(s)); '
                              'clouds are processed without pose')
        gap = self._odom_gap
        limit = max(CLOCK_GAP_SEC, 10.0 * self.odom_tolerance_sec)
        if (gap is not None and now - gap[0] <= self.silence_sec
                and abs(gap[1]) > limit * NS_PER_SEC):
            out['odom_clock'] = (f'odometry on {odom} is stamped {-gap[1] / NS_PER_SEC:+.3f} s '
                                 f'from the clouds on {self.points_topic} (tolerance '
                                 f'{self.odom_tolerance_sec:g} s): another clock? '
                                 '(use_sim_time, the bag clock, the driver time source); '
                                 'clouds are processed without pose')
        return out

    def check(self) -> tuple[list[str], list[str]]:
        """Warnings for problems that appeared or lasted another ``REPEAT_SEC`` since they
        were last logged, and notes for those that ended: ``(warnings, recoveries)``."""
        now = self._clock()
        problems = self.problems()
        warnings = []
        for kind, text in problems.items():
            if kind in _SELF_LOGGED:
                continue
            last = self._logged.get(kind)
            if last is None or now - last >= REPEAT_SEC:
                self._logged[kind] = now
                warnings.append(text)
        recovered = [k for k in self._logged if k not in problems]
        for kind in recovered:
            del self._logged[kind]
        return warnings, [f'recovered: {_RECOVERED[k]}' for k in recovered]

    def summary(self, problems: dict[str, str]) -> str:
        """The /diagnostics status message: the problems, then the counts."""
        s = self.stats
        return '; '.join([*problems.values(), (f'{s.processed} processed, {s.skipped} skipped, '
                                               f'{s.rejected} rejected, {s.loops} loops')])

    def values(self, problems: dict[str, str]) -> dict[str, object]:
        """The input's /diagnostics values (call after :meth:`problems`, which prunes)."""
        now = self._clock()
        gap, s = self._odom_gap, self.stats
        return {
            'points_topic': self.points_topic,
            'seconds_since_last_cloud': _age(now, self._last_cloud),
            'odom_topic': self.odom_topic or '',
            'seconds_since_last_odom': _age(now, self._last_odom),
            'odom_stamp_offset_sec': 'nan' if gap is None else f'{-gap[1] / NS_PER_SEC:.3f}',
            'clouds_rejected_recently': len(self._rejected_at),
            'last_reject_reason': self._last_reason,
            'problems': ', '.join(problems) or 'none',
            'clouds_received': s.received, 'clouds_processed': s.processed,
            'clouds_skipped': s.skipped, 'clouds_rejected': s.rejected,
            'clouds_failed': s.failed, 'clouds_without_odom': s.without_odom,
            'loop_candidates': s.loops,
            'clouds_downsampled': s.downsampled, 'odom_rejected': s.odom_rejected,
            'cloud_stamps_zero': s.stamps_zero, 'cloud_stamps_repeated': s.stamps_repeated,
            'cloud_stamps_backward': s.stamps_backward,
        }


def _age(now: float, then: float | None) -> str:
    return 'never' if then is None else f'{now - then:.1f}'
