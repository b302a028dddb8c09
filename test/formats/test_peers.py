"""Peer messages: exact round trips, the documented sizes, and refusal of anything malformed."""

from __future__ import annotations

import numpy as np
import pytest

from solid_ros.core.database.clouds import KeyframeCloud
from solid_ros.formats.cloud_codec import GROUND_STEPS, STEP_M
from solid_ros.formats.peers import (
    CatchUpRequest,
    CloudReply,
    CloudRequest,
    DescriptorMessage,
    PeerAuthError,
    PeerMessageError,
    decode,
    encode,
    is_sealed,
    key_id,
    reply_bytes,
    reply_requester,
    seal,
    unseal,
)

RNG = np.random.default_rng(2)
DESC = DescriptorMessage(7, 123, 1_700_000_000_123_456_789, '0123456789abcdef',
                         RNG.random(40).astype(np.float32), RNG.random(60).astype(np.float32))


def test_descriptor_round_trip_and_size() -> None:
    raw = encode(DESC)
    assert len(raw) == 240
    got = decode(raw)
    assert isinstance(got, DescriptorMessage)
    assert (got.robot, got.index, got.stamp_ns, got.fingerprint) == (7, 123, DESC.stamp_ns,
                                                                     DESC.fingerprint)
    # Half floats: 3 significant digits.
    assert np.allclose(got.r_solid, DESC.r_solid, rtol=1e-3, atol=1e-4)
    assert np.allclose(got.heading, DESC.heading, rtol=1e-3, atol=1e-4)
    with_pose = DescriptorMessage(**{**DESC.__dict__, 'pose': (1.0, 2.0, 3.0, 0, 0, 0, 1.0)})
    assert len(encode(with_pose)) == 268
    assert decode(encode(with_pose)).pose == (1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0)  # type: ignore


def test_requests_and_replies_round_trip() -> None:
    for msg in (CloudRequest(1, 2, 99, 5, 123), CatchUpRequest(3, 1000),
                CloudReply(2, 1, 99, 5, 123, None)):
        assert decode(encode(msg)) == msg
    assert len(encode(CloudRequest(1, 2, 99, 5, 123))) == 36
    cloud = KeyframeCloud(RNG.normal(size=(500, 3)).astype(np.float32), 200)
    got = decode(encode(CloudReply(2, 1, 99, 5, 123, cloud)))
    assert isinstance(got, CloudReply) and got.cloud is not None
    assert (got.owner, got.requester, got.index, got.request_id, got.stamp_ns) == (
        2, 1, 99, 5, 123)
    # Quantised (structure first, each part in its own order): every point within half a
    # step of one sent (the rest's step is GROUND_STEPS times the structure's).
    assert got.cloud.n_struct == 200 and len(got.cloud.points) == 500
    for a, b, k in ((got.cloud.points[:200], cloud.points[:200], 1.0),
                    (got.cloud.points[200:], cloud.points[200:], GROUND_STEPS)):
        d = np.linalg.norm(a[:, None] - b[None], axis=2).min(axis=1)
        assert d.max() <= 0.5 * k * STEP_M * 3**0.5 + 1e-6
    raw = encode(CloudReply(2, 1, 99, 5, 123, cloud))
    assert 44 + 8 < len(raw) <= reply_bytes(500) < 44 + 12 * 500
    assert reply_requester(raw[:100]) == 1 and reply_requester(encode(DESC)) is None
    # A receiver's cap refuses a bigger cloud before reading its points.
    with pytest.raises(PeerMessageError, match='at most 499 points'):
        decode(raw, max_cloud_points=499)


def test_malformed_messages_are_refused() -> None:
    good = encode(DESC)
    nan = bytearray(good)
    nan[40:44] = np.float32(np.nan).tobytes()
    bad = {
        'empty': b'',
        'kind': b'XXXX\x01' + good[5:],
        'version': good[:4] + b'\x01' + good[5:],
        'truncated': good[:-3],
        'padded': good + b'\x00',
        'nan': bytes(nan),
        'sizes': good[:36] + (0).to_bytes(2, 'little') + good[38:],
        'fingerprint-only': good[:40],
        'reply-count': encode(CloudReply(2, 1, 9, 5, 0, KeyframeCloud(
            np.zeros((4, 3), np.float32), 9))),
        'negative index': encode(CloudRequest(1, 2, -4, 1, 0)),
        'negative robot': encode(DescriptorMessage(**{**DESC.__dict__, 'robot': -3})),
        'negative requester': encode(CloudRequest(-1, 2, 4, 1, 0)),
        'negative owner': encode(CloudReply(-5, 1, 9, 5, 0, None)),
        'sealed without a key': seal(good, b'k' * 32, 7, 1, '/solid/descriptors'),
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


KEY = b'0123456789abcdef0123456789abcdef'


def test_sealed_messages_authenticate_their_bytes_and_topic() -> None:
    inner = encode(DESC)
    raw = seal(inner, KEY, 7, 1_700_000_000_000_000_000, '/solid/descriptors')
    assert is_sealed(raw) and len(raw) == 20 + len(inner) + 32
    opened = unseal(raw, KEY, '/solid/descriptors')
    assert (opened.sender, opened.stamp_ns, opened.inner) == (7, 1_700_000_000_000_000_000,
                                                              inner)
    with pytest.raises(PeerAuthError):
        unseal(raw, b'another key of 32 bytes, or so..', '/solid/descriptors')
    with pytest.raises(PeerAuthError):  # moved to another topic
        unseal(raw, KEY, '/solid/clouds')
    for pos in (0, 8, 12, 30, len(raw) - 40, len(raw) - 1):  # any byte changed
        bad = bytearray(raw)
        bad[pos] ^= 0x01
        with pytest.raises(PeerMessageError):
            unseal(bytes(bad), KEY, '/solid/descriptors')
    with pytest.raises(PeerMessageError):
        unseal(inner, KEY, '/solid/descriptors')  # not sealed at all
    with pytest.raises(PeerMessageError):
        unseal(raw[:30], KEY, '/solid/descriptors')
    # A reply to another robot is recognised inside its envelope without the key.
    reply = seal(encode(CloudReply(2, 9, 1, 5, 3, None)), KEY, 2, 1, '/solid/clouds')
    assert reply_requester(reply) == 9
    assert len(key_id(KEY)) == 8 and key_id(KEY) not in KEY.hex()
