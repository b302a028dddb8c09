"""Tests of solid_ros.tools.outputs: CSV columns derived from LoopCandidate, rows that fit them."""

from __future__ import annotations

import math
from collections import Counter

from solid_ros.core.results import EVIDENCE_FIELDS, Evidence, LoopCandidate
from solid_ros.formats.candidates import CANDIDATE_FIELDS
from solid_ros.tools.fleet import FLEET_CSV_COLUMNS
from solid_ros.tools.outputs import CSV_COLUMNS, CSV_EXTRA, CSV_LAYOUT, candidate_cells

CAND = LoopCandidate(12, 3, 1_700_000_000_000_000_123, 1_699_999_990_000_000_000, 0, 0.0312,
                     -0.25, math.inf, verified=True, pose=(1.0, -2.0, 0.5, 0.0, 0.0, 0.1, 0.99),
                     fitness=0.8, reason='verified',
                     evidence=Evidence(rmse=0.05, overlap=0.6))


def test_replay_csv_holds_every_candidate_field_once() -> None:
    fields = Counter(name for name in CSV_LAYOUT if name not in CSV_EXTRA)
    assert set(fields) == set(CANDIDATE_FIELDS) and max(fields.values()) == 1
    assert len(CSV_COLUMNS) == len(set(CSV_COLUMNS)) == (len(CSV_LAYOUT) + 6 + 35
                                                         + len(EVIDENCE_FIELDS) - 1)
    assert CSV_COLUMNS[:8] == ('query_index', 'match_index', 'query_stamp_ns', 'match_stamp_ns',
                               'match_session', 'distance', 'yaw', 'margin')
    assert CSV_COLUMNS[-38:-37] == ('pose_correct',) and CSV_COLUMNS[-2] == 'cov_35'
    assert CSV_COLUMNS[-1] == 'source'  # added last: the columns before keep their place


def test_cells_fill_the_layout_in_order() -> None:
    extra = dict.fromkeys(CSV_EXTRA, 'x')
    row = candidate_cells(CAND, CSV_LAYOUT, {'distance': lambda v: f'{v:.2f}'}, extra)
    assert len(row) == len(CSV_COLUMNS)
    cell = dict(zip(CSV_COLUMNS, row))
    assert cell['distance'] == '0.03' and cell['yaw'] == -0.25  # unformatted: as it is
    assert cell['query_stamp_ns'] == 1_700_000_000_000_000_123
    assert [cell[k] for k in ('tx', 'ty', 'tz', 'qw')] == [1.0, -2.0, 0.5, 0.99]
    assert cell['reason'] == 'verified' and cell['accepted'] == 'x'
    assert math.isnan(cell['cov_0'])


def test_fleet_csv_columns() -> None:
    assert FLEET_CSV_COLUMNS == (
        'robot', 'query_index', 'query_stamp_ns', 'match_session', 'match_index',
        'match_stamp_ns', 'distance', 'yaw', 'tx', 'ty', 'tz', 'qx', 'qy', 'qz', 'qw',
        'fitness', 'rmse', 'overlap', 'inter_robot', 'trans_err_m', 'rot_err_deg',
        'pose_correct')
