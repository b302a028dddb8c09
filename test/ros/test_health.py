"""InputHealth without ROS or waiting: a fake clock steps time, a dict stands for the graph."""

from __future__ import annotations

import pytest

from solid_ros.core.stamps import NS_PER_SEC
from solid_ros.ros.health import REPEAT_SEC, SILENCE_SEC, WARN_THROTTLE_SEC, InputHealth


class FakeClock:
    def __init__(self, now: float = 100.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now

    def advance(self, sec: float) -> None:
        self.now += sec


def make(clock: FakeClock, odom: bool = True, publishers: dict[str, int] | None = None,
         tolerance: float = 0.05) -> InputHealth:
    pubs = publishers if publishers is not None else {}
    return InputHealth('/points', '/odom' if odom else None, 'best_effort', tolerance,
                       lambda topic: pubs.get(topic, 0), clock=clock)


def test_quiet_start_is_fine_until_the_silence_window_passes() -> None:
    clock = FakeClock()
    health = make(clock)
    assert health.problems() == {}
    clock.advance(SILENCE_SEC + 0.5)
    problems = health.problems()
    assert set(problems) == {'no_clouds', 'no_odom'}
    assert problems['no_clouds'] == (
        'no PointCloud2 received on /points in the 6 s since start (no publisher: check the '
        'topic name or remap points:=<your topic>)')
    assert problems['no_odom'] == (
        'use_odom is on but no nav_msgs/Odometry received on /odom in the 6 s since start '
        '(0 publisher(s)); clouds are processed without pose')


def test_a_publisher_that_delivers_nothing_gets_the_qos_hint() -> None:
    clock = FakeClock()
    health = make(clock, odom=False, publishers={'/points': 2})
    clock.advance(10.0)
    assert health.problems() == {'no_clouds': (
        "no PointCloud2 received on /points in the 10 s since start (2 publisher(s): check "
        "their QoS against qos_reliability 'best_effort')")}


def test_clouds_that_stop_arriving_and_come_back() -> None:
    clock = FakeClock()
    health = make(clock, odom=False)
    health.cloud_received()
    health.cloud_received()
    clock.advance(SILENCE_SEC - 0.1)
    assert health.problems() == {}
    clock.advance(2.0)
    assert health.problems() == {'no_clouds': 'no PointCloud2 received on /points for the '
                                              'last 7 s (2 before)'}
    health.cloud_received()
    assert health.problems() == {}


def test_odometry_on_another_clock_is_reported_while_recent() -> None:
    clock = FakeClock()
    health = make(clock)
    health.cloud_received()
    health.odom_received()
    health.odom_paired(-1000 * NS_PER_SEC + NS_PER_SEC // 5)  # odometry 999.8 s ahead
    problems = health.problems()
    assert list(problems) == ['odom_clock']
    assert problems['odom_clock'].startswith(
        'odometry on /odom is stamped +999.800 s from the clouds on /points (tolerance 0.05 s)')
    assert health.values(problems)['odom_stamp_offset_sec'] == '999.800'
    # Within max(1 s, 10 x tolerance) it is only late odometry, not another clock.
    health.odom_paired(NS_PER_SEC // 2)
    assert health.problems() == {}
    # A larger tolerance (set at runtime) widens the check.
    health.odom_tolerance_sec = 0.2
    health.odom_paired(int(1.5 * NS_PER_SEC))
    assert health.problems() == {}


def test_rejections_log_each_kind_once_per_throttle_period() -> None:
    clock = FakeClock()
    health = make(clock, odom=False)
    first = health.reject('data has 36 bytes, expected 40')
    assert first == ('rejected PointCloud2 on /points: data has 36 bytes, expected 40 '
                     '(first of its kind; 1 rejected so far)')
    # The same reason with other numbers is the same kind: throttled.
    assert health.reject('data has 76 bytes, expected 80') is None
    assert health.reject("cloud has no field 'z'") is not None  # another kind
    clock.advance(WARN_THROTTLE_SEC)
    again = health.reject('data has 116 bytes, expected 120')
    assert again is not None and '(2 more like it since it was last logged; 4 rejected' in again
    assert health.stats.rejected == 4
    problems = health.problems()
    assert problems['rejected'] == ('4 PointCloud2 rejected on /points in the last 5 s '
                                    '(latest: data has 116 bytes, expected 120)')
    clock.advance(SILENCE_SEC + 0.1)
    assert 'rejected' not in health.problems()
    assert health.values({})['clouds_rejected_recently'] == 0


def test_drops_and_failures_count_and_warn_while_recent() -> None:
    clock = FakeClock()
    health = make(clock, odom=False)
    health.cloud_received()
    assert health.trouble('skipped') == 1
    assert health.trouble('skipped') == 2
    assert health.trouble('verify_skipped') == 1
    assert health.trouble('failed') == 1
    assert (health.stats.skipped, health.stats.verify_skipped, health.stats.failed) == (2, 1, 1)
    clock.advance(2.0)
    problems = health.problems()
    assert problems['skipped'] == ('2 PointCloud2 dropped so far: processing falls behind '
                                   '(latest 2 s ago)')
    assert problems['verify_skipped'].startswith('1 keyframes dropped so far')
    assert problems['failed'].startswith('1 clouds failed with an error so far')
    health.cloud_received()
    clock.advance(SILENCE_SEC - 1.0)
    assert health.problems() == {}  # the counters stay, the WARN ends
    assert health.values({})['clouds_failed'] == 1


def test_check_logs_new_problems_repeats_lasting_ones_and_notes_recovery() -> None:
    clock = FakeClock()
    health = make(clock)
    clock.advance(SILENCE_SEC + 1.0)
    warnings, recovered = health.check()
    assert len(warnings) == 2 and recovered == []
    assert health.check() == ([], [])  # still there: not again yet
    clock.advance(REPEAT_SEC)
    health.odom_received()
    warnings, recovered = health.check()
    assert [w.split(' received')[0] for w in warnings] == ['no PointCloud2']
    assert recovered == ['recovered: odometry arriving']
    # Rejections, drops and failures are logged where they happen, never by check().
    health.cloud_received()
    health.reject('bad')
    health.trouble('failed')
    assert health.check() == ([], ['recovered: PointCloud2 arriving'])


def test_summary_and_values_keep_their_keys_and_order() -> None:
    clock = FakeClock()
    health = make(clock)
    health.cloud_received()
    health.stats.processed, health.stats.loops = 1, 3
    assert health.summary({}) == '1 processed, 0 skipped, 0 rejected, 3 loops'
    assert health.summary({'x': 'trouble'}) == ('trouble; 1 processed, 0 skipped, 0 rejected, '
                                                '3 loops')
    clock.advance(1.5)
    values = health.values({})
    assert list(values) == [
        'points_topic', 'seconds_since_last_cloud', 'odom_topic', 'seconds_since_last_odom',
        'odom_stamp_offset_sec', 'clouds_rejected_recently', 'last_reject_reason', 'problems',
        'clouds_received', 'clouds_processed', 'clouds_skipped', 'clouds_rejected',
        'clouds_failed', 'clouds_without_odom', 'loop_candidates', 'clouds_downsampled',
        'odom_rejected', 'cloud_stamps_zero', 'cloud_stamps_repeated', 'cloud_stamps_backward']
    assert values['seconds_since_last_cloud'] == '1.5'
    assert values['seconds_since_last_odom'] == 'never'
    assert values['odom_stamp_offset_sec'] == 'nan' and values['problems'] == 'none'
    assert make(clock, odom=False).values({})['odom_topic'] == ''


@pytest.mark.parametrize('window', [1.0, 3.0])
def test_the_window_is_configurable(window: float) -> None:
    clock = FakeClock()
    health = InputHealth('/p', None, 'reliable', 0.05, lambda t: 0, clock=clock,
                         silence_sec=window)
    health.trouble('failed')
    clock.advance(window - 0.01)
    assert set(health.problems()) == {'failed'}
    clock.advance(0.02)
    assert set(health.problems()) == {'no_clouds'}  # the same window for silence


def test_refused_odometry_and_untrusted_stamps_are_counted_warned_once_and_clear() -> None:
    clock = FakeClock()
    health = make(clock)
    health.cloud_received()
    health.odom_received()
    first = health.odom_rejected('odometry pose is not finite')
    assert first == ('odometry message on /odom refused: odometry pose is not finite (1 so far)')
    assert health.odom_rejected('odometry covariance is not finite') is None  # throttled
    line = health.untrusted_stamp('backward by 200.000 s', 5 * 10**9)
    assert line == ('PointCloud2 on /points processed in arrival order: stamp 5.000 s is '
                    'backward by 200.000 s (1 so far)')
    assert health.untrusted_stamp('zero', 0) is None and health.untrusted_stamp('zero', 0) is None
    problems = health.problems()
    assert set(problems) == {'odom_rejected', 'cloud_stamps'}
    assert '2 odometry messages refused so far' in problems['odom_rejected']
    assert 'covariance is not finite' in problems['odom_rejected']
    assert '3 PointCloud2 with stamps that cannot be trusted' in problems['cloud_stamps']
    values = health.values(problems)
    assert (values['odom_rejected'], values['cloud_stamps_zero'],
            values['cloud_stamps_backward'], values['cloud_stamps_repeated']) == (2, 2, 1, 0)
    clock.advance(6.0)
    health.cloud_received()
    health.odom_received()
    assert health.problems() == {}  # the WARN clears, the counters stay
    assert health.odom_rejected('odometry pose is not finite') is not None  # logged again
