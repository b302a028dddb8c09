"""Peer messages: exact round trips, the documented sizes, and refusal of anything malformed."""

from __future__ import annotations

import numpy as np
import pytest

from solid_ros.core.keyframes import KeyframeCloud
from solid_ros.formats.peers import (
    CatchUpRequest,
    CloudReply,
    CloudRequest,
    DescriptorMessage,
    PeerMessageError,
    decode,
    encode,
)

RNG = np.random.default_rng(2)
DESC = DescriptorMessage(7, 123, 1_700_000_000_123_456_789, '0123456789abcdef',
                         RNG.random(40).astype(np.float32), RNG.random(60).astype(np.float32))


def test_descriptor_round_trip_and_size() -> None:
    raw = encode(DESC)
    assert len(raw) == 440
    got = decode(raw)
    assert isinstance(got, DescriptorMessage)
    assert (got.robot, got.index, got.stamp_ns, got.fingerprint) == (7, 123, DESC.stamp_ns,
                                                                     DESC.fingerprint)
    assert np.array_equal(got.r_solid, DESC.r_solid) and np.array_equal(got.heading,
                                                                        DESC.heading)
    with_pose = DescriptorMessage(**{**DESC.__dict__, 'pose': (1.0, 2.0, 3.0, 0, 0, 0, 1.0)})
    assert len(encode(with_pose)) == 468
    assert decode(encode(with_pose)).pose == (1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0)  # type: ignore


def test_requests_and_replies_round_trip() -> None:
    for msg in (CloudRequest(1, 2, 99, 5), CatchUpRequest(3, 1000),
                CloudReply(2, 1, 99, 5, None)):
        assert decode(encode(msg)) == msg
    cloud = KeyframeCloud(RNG.normal(size=(500, 3)).astype(np.float32), 200)
    got = decode(encode(CloudReply(2, 1, 99, 5, cloud)))
    assert isinstance(got, CloudReply) and got.cloud is not None
    assert got.cloud.n_struct == 200 and np.array_equal(got.cloud.points, cloud.points)
    assert len(encode(CloudReply(2, 1, 99, 5, cloud))) == 36 + 12 * 500


def test_malformed_messages_are_refused() -> None:
    good = encode(DESC)
    nan = bytearray(good)
    nan[40:44] = np.float32(np.nan).tobytes()
    bad = {
        'empty': b'',
        'kind': b'XXXX\x01' + good[5:],
        'version': good[:4] + b'\x02' + good[5:],
        'truncated': good[:-3],
        'padded': good + b'\x00',
        'nan': bytes(nan),
        'sizes': good[:36] + (0).to_bytes(2, 'little') + good[38:],
        'fingerprint-only': good[:40],
        'reply-count': encode(CloudReply(2, 1, 9, 5, KeyframeCloud(
            np.zeros((4, 3), np.float32), 9))),
        'negative index': encode(CloudRequest(1, 2, -4, 1)),
    }
    for name, raw in bad.items():
        with pytest.raises(PeerMessageError):
            decode(raw)
            pytest.fail(name)
    rng = np.random.default_rng(11)
    for _ in range(300):  # random byte flips never crash the decoder
        raw = bytearray(good)
        for _ in range(3):
            raw[int(rng.integers(len(raw)))] = int(rng.integers(256))
        try:
            decode(bytes(raw))
        except PeerMessageError:
            pass
