"""The alignment messages: inter-robot loops, keyframe poses, path requests."""

from __future__ import annotations

import numpy as np
import pytest

from solid_ros.formats.fleet_msgs import (
    MAX_ALIGN_BYTES,
    MAX_POSES,
    LoopMessage,
    PathRequest,
    PosesMessage,
    decode_align,
    encode_align,
)
from solid_ros.formats.peers import PeerMessageError

POSE = (1.0, -2.0, 0.5, 0.0, 0.0, 0.38268343, 0.92387953)
COV = tuple((np.diag([1e-4, 2e-4, 3e-4, 1e-6, 2e-6, 3e-6]) + 1e-7).ravel())


def _loop() -> LoopMessage:
    return LoopMessage(1, 40, 10**18, 0, 12, 10**18 - 5, POSE, COV, POSE, 37.5)


def test_messages_round_trip_within_float32() -> None:
    raw = encode_align(_loop())
    assert len(raw) == 192
    back = decode_align(raw)
    assert isinstance(back, LoopMessage)
    assert (back.robot, back.query_index, back.match_robot, back.match_index) == (1, 40, 0, 12)
    assert back.query_stamp_ns == 10**18 and back.match_stamp_ns == 10**18 - 5
    assert np.allclose(back.pose, POSE, atol=1e-6) and np.allclose(back.query_pose, POSE)
    assert np.allclose(back.covariance, COV, rtol=1e-6)
    assert back.query_path_m == pytest.approx(37.5)
    poses = PosesMessage(3, tuple((i, POSE, float(i)) for i in range(5)), True, 1, 2)
    raw = encode_align(poses)
    assert len(raw) == 16 + 36 * 5
    got = decode_align(raw)
    assert isinstance(got, PosesMessage) and got.whole and (got.part, got.parts) == (1, 2)
    assert [p[0] for p in got.poses] == list(range(5))
    assert decode_align(encode_align(PathRequest(2, 7))) == PathRequest(2, 7)
    full = PosesMessage(1, tuple((i, POSE, 0.0) for i in range(MAX_POSES)))
    assert len(encode_align(full)) == MAX_ALIGN_BYTES


def test_bad_messages_are_refused_whole() -> None:
    raw = encode_align(_loop())
    for bad in (raw[:-1], raw + b'\0', b'SLL1', b'XXXX' + raw[4:], raw[:4] + b'\x09' + raw[5:]):
        with pytest.raises(PeerMessageError):
            decode_align(bad)
    nan = bytearray(raw)
    nan[-4:] = np.array([np.nan], dtype='<f4').tobytes()
    with pytest.raises(PeerMessageError, match='NaN'):
        decode_align(bytes(nan))
    zero_q = LoopMessage(1, 40, 0, 0, 12, 0, (0.0,) * 7, COV, POSE, 1.0)
    with pytest.raises(PeerMessageError, match='quaternion'):
        decode_align(encode_align(zero_q))
    with pytest.raises(PeerMessageError, match='out of range'):
        decode_align(encode_align(PathRequest(-1, 0)))
    poses = encode_align(PosesMessage(1, ((1, POSE, 1.0),)))
    with pytest.raises(PeerMessageError):
        decode_align(poses[:-3])
    with pytest.raises(PeerMessageError, match='part'):
        decode_align(encode_align(PosesMessage(1, (), False, 3, 2)))
    with pytest.raises(PeerMessageError, match='at most'):
        encode_align(PosesMessage(1, tuple((i, POSE, 0.0) for i in range(MAX_POSES + 1))))
    rng = np.random.default_rng(0)
    for _ in range(200):  # random bytes never get through
        junk = bytes(rng.integers(0, 256, int(rng.integers(0, 300)), dtype=np.uint8))
        with pytest.raises(PeerMessageError):
            decode_align(junk)
