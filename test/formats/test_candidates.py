"""Loop candidates <-> Float64MultiArray rows: layout, exact stamps, decoding errors."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from solid_ros.core.results import EVIDENCE_FIELDS, Evidence, LoopCandidate
from solid_ros.formats.candidates import (
    BASE_COLUMNS,
    CANDIDATE_FIELDS,
    COLUMNS,
    COLUMNS_LABEL,
    MESSAGE_FIELDS,
    CandidateDecodeError,
    candidate_columns,
    candidate_values,
    decode_candidates,
    layout_dims,
    split_stamp,
    to_rows,
)

CANDS = [
    LoopCandidate(313, 20, 1_700_000_123_456_789_012, 1_700_000_001_000_000_001, 0, 0.031, -1.25,
                  0.2),
    LoopCandidate(313, 57, 1_700_000_123_456_789_012, 999_999_999, 3, 0.049, 3.14159, 0.0),
]


def _msg(rows: np.ndarray, labels: str = COLUMNS_LABEL, offset: int = 0) -> SimpleNamespace:
    dims = [SimpleNamespace(label=lab, size=size, stride=stride)
            for lab, size, stride in layout_dims(len(rows))]
    dims[1].label = labels
    data = [0.0] * offset + rows.reshape(-1).tolist()
    return SimpleNamespace(layout=SimpleNamespace(dim=dims, data_offset=offset), data=data)


def test_split_stamp_is_exact_and_nanosec_in_range() -> None:
    assert split_stamp(1_700_000_123_456_789_012) == (1_700_000_123, 456_789_012)
    assert split_stamp(0) == (0, 0)
    sec, ns = split_stamp(-1)
    assert (sec, ns) == (-1, 999_999_999)


def test_columns_are_derived_from_the_candidate_fields() -> None:
    # The wire layout, written out once here: deriving it must not move a column.
    assert BASE_COLUMNS == ('query_index', 'match_index', 'query_stamp_sec',
                            'query_stamp_nanosec', 'match_stamp_sec', 'match_stamp_nanosec',
                            'distance', 'yaw', 'margin', 'match_session')
    assert COLUMNS == (BASE_COLUMNS + ('verified', 'tx', 'ty', 'tz', 'qx', 'qy', 'qz', 'qw',
                                       'fitness', 'rmse')
                       + tuple(f'cov_{i}' for i in range(36)) + ('source',))
    assert set(MESSAGE_FIELDS) <= set(CANDIDATE_FIELDS) | set(EVIDENCE_FIELDS)
    assert candidate_columns(['pose', 'extra', 'query_stamp_ns'], extra=['extra']) == (
        'tx', 'ty', 'tz', 'qx', 'qy', 'qz', 'qw', 'extra', 'query_stamp_ns')
    with pytest.raises(ValueError, match="'tilt' is not a LoopCandidate or Evidence field"):
        candidate_columns(['query_index', 'tilt'])


def test_values_span_their_columns() -> None:
    c = CANDS[0]
    for name in CANDIDATE_FIELDS:
        assert len(candidate_values(c, name)) == len(candidate_columns([name]))
        assert len(candidate_values(c, name, split_stamps=True)) == len(
            candidate_columns([name], split_stamps=True))
    assert candidate_values(c, 'query_stamp_ns', split_stamps=True) == (1_700_000_123,
                                                                       456_789_012)
    assert candidate_values(c, 'pose') == c.pose


def test_rows_follow_columns() -> None:
    rows = to_rows(CANDS)
    assert rows.shape == (2, len(COLUMNS))
    assert rows.dtype == np.float64
    col = {n: i for i, n in enumerate(COLUMNS)}
    assert rows[0, col['query_stamp_sec']] == 1_700_000_123
    assert rows[0, col['query_stamp_nanosec']] == 456_789_012
    assert rows[1, col['match_session']] == 3
    assert rows[1, col['yaw']] == pytest.approx(3.14159)
    assert to_rows([]).shape == (0, len(COLUMNS))


def test_round_trip_keeps_stamps_exact() -> None:
    out = decode_candidates(_msg(to_rows(CANDS), offset=3))
    assert len(out) == 2
    for got, want in zip(out, CANDS):
        assert got['query_index'] == want.query_index
        assert got['match_index'] == want.match_index
        assert got['query_stamp_ns'] == want.query_stamp_ns
        assert got['match_stamp_ns'] == want.match_stamp_ns
        assert got['match_session'] == want.match_session
        assert isinstance(got['match_index'], int)
        assert got['distance'] == pytest.approx(want.distance)
        assert got['yaw'] == pytest.approx(want.yaw)
        assert got['margin'] == pytest.approx(want.margin)


def test_columns_found_by_name_when_reordered_or_extended() -> None:
    rows = to_rows(CANDS)
    names = list(reversed(COLUMNS)) + ['future_column']
    reordered = np.concatenate([rows[:, ::-1], np.full((len(rows), 1), 7.0)], axis=1)
    msg = _msg(reordered, labels=','.join(names))
    msg.layout.dim[1].size = len(names)
    msg.layout.dim[1].stride = len(names)
    out = decode_candidates(msg)
    assert [o['match_index'] for o in out] == [20, 57]
    assert out[0]['yaw'] == pytest.approx(-1.25)


def test_empty_message_decodes_to_no_candidates() -> None:
    assert decode_candidates(_msg(to_rows([]))) == []


def test_missing_column_is_rejected_by_name() -> None:
    with pytest.raises(CandidateDecodeError, match='yaw'):
        decode_candidates(_msg(to_rows(CANDS), labels=COLUMNS_LABEL.replace('yaw', 'heading')))


def test_short_data_is_rejected() -> None:
    msg = _msg(to_rows(CANDS))
    msg.data = msg.data[:-1]
    with pytest.raises(CandidateDecodeError, match='data has'):
        decode_candidates(msg)


def test_not_a_multiarray_is_rejected() -> None:
    with pytest.raises(CandidateDecodeError):
        decode_candidates(object())


def test_real_rclpy_message_decodes() -> None:
    std_msgs = pytest.importorskip('std_msgs.msg', reason='std_msgs (ROS 2) not installed')
    rows = to_rows(CANDS)
    msg = std_msgs.Float64MultiArray()
    msg.layout.dim = [std_msgs.MultiArrayDimension(label=lab, size=size, stride=stride)
                      for lab, size, stride in layout_dims(len(rows))]
    msg.data = rows.reshape(-1).tolist()
    out = decode_candidates(msg)
    assert [o['query_stamp_ns'] for o in out] == [c.query_stamp_ns for c in CANDS]


def test_pose_columns_round_trip_and_old_layout_decodes() -> None:
    cov = tuple(float(i) for i in range(36))
    cand = LoopCandidate(9, 2, 5_000_000_000, 1_000_000_000, 0, 0.1, 0.5, 0.2, verified=True,
                         pose=(1.0, -2.0, 0.5, 0.0, 0.0, 0.2474, 0.9689), fitness=0.8,
                         evidence=Evidence(rmse=0.03), covariance=cov,
                         reason='verified')
    (got,) = decode_candidates(_msg(to_rows([cand])))
    assert got['verified'] == 1 and isinstance(got['verified'], int)
    assert [got[c] for c in ('tx', 'ty', 'tz', 'qx', 'qy', 'qz', 'qw')] == list(cand.pose)
    assert (got['fitness'], got['rmse']) == (0.8, 0.03)
    assert [got[f'cov_{i}'] for i in range(36)] == list(cov)
    # A 10-column message of an older publisher: the new columns decode as unknown.
    old = to_rows([cand])[:, :10]
    msg = _msg(old, labels=','.join(COLUMNS[:10]))
    msg.layout.dim[0].stride, msg.layout.dim[1].size, msg.layout.dim[1].stride = 10, 10, 10
    (got,) = decode_candidates(msg)
    assert got['verified'] == 0 and np.isnan(got['tx']) and np.isnan(got['cov_35'])
    assert got['query_stamp_ns'] == 5_000_000_000
