"""Loop candidates as rows of a std_msgs/Float64MultiArray, without ROS imports.

The node publishes the accepted candidates of one query as one message: ``layout.dim[0]`` is
``candidates`` (one row per candidate), ``layout.dim[1]`` is the columns, whose ``label`` is the
comma-separated column names of :data:`COLUMNS`. Row ``i`` column ``j`` is
``data[data_offset + i * dim[1].stride + j]``. Stamps are split into ``sec`` / ``nanosec``
(both exact in float64) so a back end can match them to its own keyframe header stamps.

After the first ten columns (the layout of older publishers) come ``verified`` (1 or 0), the
relative pose ``T`` = pose of the query sensor in the match sensor's frame (``p_match = T
p_query``) as ``tx ty tz qx qy qz qw``, ``fitness``, ``rmse`` and the 6x6 covariance of ``T``
row-major as ``cov_0`` ... ``cov_35`` (ROS order x, y, z, roll, pitch, yaw), then ``source``
(what proposed the loop: 0 the descriptor, 1 the pose graph's estimate; see
:data:`SOURCE_CODES`), the last column since the graph's candidates came. Columns are found
by name, so a decoder reads older messages too: their missing columns decode as ``verified``
0, ``source`` 0 (the descriptor: nothing else proposed loops then) and NaN.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import fields
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.errors import SolidError
from solid_ros.core.results import EVIDENCE_FIELDS, LoopCandidate
from solid_ros.core.stamps import join_stamp, split_stamp

__all__ = ['BASE_COLUMNS', 'CANDIDATE_FIELDS', 'COLUMNS', 'COLUMNS_LABEL', 'COV_COLUMNS',
           'INT_COLUMNS', 'MESSAGE_FIELDS', 'POSE_COLUMNS', 'ROWS_LABEL', 'SOURCE_CODES', 'SPANS',
           'CandidateDecodeError', 'candidate_columns', 'candidate_values', 'decode_candidates',
           'layout_dims', 'split_stamp', 'to_rows']

# Columns of a LoopCandidate field that spans several; every other field is one column of its
# own name. Rows of messages split the stamps (see split_stamp).
POSE_COLUMNS: tuple[str, ...] = ('tx', 'ty', 'tz', 'qx', 'qy', 'qz', 'qw')
COV_COLUMNS: tuple[str, ...] = tuple(f'cov_{i}' for i in range(36))
SPANS: dict[str, tuple[str, ...]] = {'pose': POSE_COLUMNS, 'covariance': COV_COLUMNS,
                                     'evidence': EVIDENCE_FIELDS}
_SPLIT = {'query_stamp_ns': ('query_stamp_sec', 'query_stamp_nanosec'),
          'match_stamp_ns': ('match_stamp_sec', 'match_stamp_nanosec')}
CANDIDATE_FIELDS: tuple[str, ...] = tuple(f.name for f in fields(LoopCandidate))
# The message's fields in column order; the first eight (ten columns) are the layout of older
# publishers; columns are only ever appended.
MESSAGE_FIELDS: tuple[str, ...] = (
    'query_index', 'match_index', 'query_stamp_ns', 'match_stamp_ns', 'distance', 'yaw',
    'margin', 'match_session', 'verified', 'pose', 'fitness', 'rmse', 'covariance', 'source')
# A string field's value as a number in the message, and back.
SOURCE_CODES: dict[str, int] = {'descriptor': 0, 'graph': 1}
_CODES: dict[str, dict[str, int]] = {'source': SOURCE_CODES}


def candidate_columns(layout: Iterable[str], *, extra: Iterable[str] = (),
                      split_stamps: bool = False) -> tuple[str, ...]:
    """The column names of a row layout, derived from :class:`LoopCandidate`.

    Args:
        layout: names in column order: LoopCandidate fields (``pose`` spans ``tx`` ... ``qw``,
            ``covariance`` ``cov_0`` ... ``cov_35``, ``evidence`` one column per Evidence
            field), single Evidence fields, and names from ``extra``.
        extra: columns that are no field (what a tool adds), one column each.
        split_stamps: a stamp spans ``*_stamp_sec`` and ``*_stamp_nanosec``.

    Raises:
        ValueError: a name is neither a LoopCandidate field nor in ``extra``.
    """
    others = set(extra)
    out: list[str] = []
    for name in layout:
        if name in others:
            out.append(name)
        elif name not in CANDIDATE_FIELDS and name not in EVIDENCE_FIELDS:
            raise ValueError(f'{name!r} is not a LoopCandidate or Evidence field')
        elif split_stamps and name in _SPLIT:
            out.extend(_SPLIT[name])
        else:
            out.extend(SPANS.get(name, (name,)))
    return tuple(out)


def candidate_values(candidate: Any, name: str, *, split_stamps: bool = False) -> tuple[Any, ...]:
    """The values of one LoopCandidate field (or of its evidence), one per column of
    :func:`candidate_columns`."""
    if name not in CANDIDATE_FIELDS and name in EVIDENCE_FIELDS:
        return (getattr(candidate.evidence, name),)
    value = getattr(candidate, name)
    if name in SPANS:
        return tuple(value)
    if split_stamps and name in _SPLIT:
        return split_stamp(value)
    return (value,)


BASE_COLUMNS: tuple[str, ...] = candidate_columns(MESSAGE_FIELDS[:8], split_stamps=True)
COLUMNS: tuple[str, ...] = candidate_columns(MESSAGE_FIELDS, split_stamps=True)
# Columns holding integers (decoded as int).
INT_COLUMNS = frozenset({'query_index', 'match_index', 'query_stamp_sec', 'query_stamp_nanosec',
                         'match_stamp_sec', 'match_stamp_nanosec', 'match_session', 'verified',
                         'source'})
# What a column an older publisher did not send decodes as (the rest: NaN).
_ABSENT: dict[str, float] = {'verified': 0.0, 'source': 0.0}
ROWS_LABEL = 'candidates'
COLUMNS_LABEL = ','.join(COLUMNS)


class CandidateDecodeError(SolidError):
    """A Float64MultiArray does not hold loop candidates in the documented layout."""


def to_rows(candidates: Iterable[Any]) -> npt.NDArray[np.float64]:
    """Return an ``(n, len(COLUMNS))`` float64 array, one row per candidate.

    Args:
        candidates: :class:`~solid_ros.core.results.LoopCandidate` objects (or any with its
            attributes).
    """
    rows = [[_CODES[name][v] if name in _CODES else v for name in MESSAGE_FIELDS
             for v in candidate_values(c, name, split_stamps=True)] for c in candidates]
    if not rows:
        return np.empty((0, len(COLUMNS)), dtype=np.float64)
    return np.asarray(rows, dtype=np.float64)


def layout_dims(num_rows: int) -> list[tuple[str, int, int]]:
    """Return ``(label, size, stride)`` of the two MultiArrayDimensions for ``num_rows`` rows."""
    ncol = len(COLUMNS)
    return [(ROWS_LABEL, num_rows, num_rows * ncol), (COLUMNS_LABEL, ncol, ncol)]


def decode_candidates(msg: Any) -> list[dict[str, float | int]]:
    """Decode a loop-candidate Float64MultiArray (rclpy or rosbags message) into dicts.

    Columns are found by name from ``layout.dim[1].label``, so a newer publisher that appends
    columns still decodes, and so does an older one without the pose or source columns
    (``verified`` 0, ``source`` 0, the rest NaN). Each dict holds every column of
    :data:`COLUMNS` (integers as ``int``) plus ``query_stamp_ns`` and ``match_stamp_ns`` in
    integer nanoseconds.

    Raises:
        CandidateDecodeError: the layout is not two-dimensional, lacks one of the first ten
            columns, or the data is shorter than the layout says.
    """
    try:
        dims = list(msg.layout.dim)
        offset = int(msg.layout.data_offset)
        data = np.asarray(msg.data, dtype=np.float64).reshape(-1)
    except (AttributeError, TypeError, ValueError) as err:
        raise CandidateDecodeError(f'not a Float64MultiArray: {err}') from err
    if len(dims) != 2:
        raise CandidateDecodeError(f'expected 2 layout dimensions, got {len(dims)}')
    names = [n.strip() for n in str(dims[1].label).split(',')]
    missing = [c for c in BASE_COLUMNS if c not in names]
    if missing:
        raise CandidateDecodeError(f'column {missing[0]!r} missing from layout label '
                                   f'{dims[1].label!r}')
    nrow, ncol, stride = int(dims[0].size), int(dims[1].size), int(dims[1].stride)
    if ncol != len(names) or stride < ncol:
        raise CandidateDecodeError(f'{len(names)} labels but size {ncol}, stride {stride}')
    if nrow == 0:
        return []
    if data.size < offset + (nrow - 1) * stride + ncol:
        raise CandidateDecodeError(f'data has {data.size} values, layout needs '
                                   f'{offset + (nrow - 1) * stride + ncol}')
    col = {n: i for i, n in enumerate(names)}
    out: list[dict[str, float | int]] = []
    for r in range(nrow):
        row = data[offset + r * stride: offset + r * stride + ncol]
        item: dict[str, float | int] = {}
        for name in COLUMNS:
            value = float(row[col[name]]) if name in col else _ABSENT.get(name, math.nan)
            item[name] = int(value) if name in INT_COLUMNS else value
        item['query_stamp_ns'] = join_stamp(int(item['query_stamp_sec']),
                                            int(item['query_stamp_nanosec']))
        item['match_stamp_ns'] = join_stamp(int(item['match_stamp_sec']),
                                            int(item['match_stamp_nanosec']))
        out.append(item)
    return out
