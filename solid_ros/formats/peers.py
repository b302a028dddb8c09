"""Messages robots exchange: keyframe descriptors, cloud requests and replies, catch-up.

Each message is the ``data`` of a ``std_msgs/UInt8MultiArray`` (no custom interface package
to build), little-endian, starting with a 4-byte kind and a version byte (3: version 2 sent
descriptors as float32 and clouds as float32 x y z, version 1 had no stamps in requests and
replies; the versions refuse each other's messages):

``SLD1`` descriptor (``/solid/descriptors``)::

    4s kind, u8 version, u8 flags (bit 0: pose follows), u16 reserved,
    i32 robot, i64 keyframe index, i64 stamp ns, 8s settings fingerprint,
    u16 N_r, u16 N_a, f16[N_r] R-SOLiD (unit), f16[N_a] heading signature (unit),
    [f32[7] pose x y z qx qy qz qw]

    40 bytes + 2 (N_r + N_a) (+ 28 with the pose): 240 bytes for the usual 40 x 60 bins
    (half floats: a unit vector's bins keep 3 significant digits, a thousandth of the
    distances the detector tells places apart by).

``SLQ1`` cloud request (``/solid/cloud_requests``)::

    4s, u8 version, u8, u16, i32 requester, i32 owner, i64 keyframe index,
    i64 keyframe stamp ns, u32 request id (random)

``SLC1`` cloud reply (``/solid/clouds``)::

    4s, u8 version, u8 status (0 ok, 1 evicted/unknown), u16, i32 owner, i32 requester,
    i64 keyframe index, i64 keyframe stamp ns, u32 request id, i32 structure points,
    u32 points, then the keyframe cloud (structure first) quantised and deflated
    (:mod:`solid_ros.formats.cloud_codec`: about 2.5 to 3 bytes a point)

``SLK1`` catch-up request (``/solid/cloud_requests``)::

    4s, u8 version, u8, u16, i32 requester, u32 most descriptors wanted

``SLA1`` authenticated envelope (any of the topics, with a fleet key)::

    4s, u8 version, u8, u16, i32 sender, i64 stamp ns (strictly increasing per sender, near
    its wall clock), the message above, u8[32] HMAC-SHA256 tag

    The tag covers ``'solid_ros/peers'``, the topic name and every byte before it, so a
    message can be neither changed nor moved to another topic without the key; the stamp lets
    the receiver refuse a replay (see :mod:`solid_ros.ros.peer_guard`).

Robot ids are session ids: 0 to 2**31 - 1. Decoding checks the kind, version, sizes against
the byte count, limits, ids and finiteness, and raises :class:`PeerMessageError` for anything
else, so a malformed or hostile message is refused whole.
"""

from __future__ import annotations

import hashlib
import hmac
import struct
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from solid_ros.core.database.clouds import KeyframeCloud
from solid_ros.core.errors import SolidError
from solid_ros.formats.cloud_codec import CloudCodecError, cloud_step, pack_points, unpack_points

__all__ = ['CatchUpRequest', 'CloudReply', 'CloudRequest', 'DescriptorMessage',
           'MAX_CLOUD_POINTS', 'MAX_DESCRIPTOR_BYTES', 'PeerAuthError', 'PeerMessageError',
           'Sealed', 'TAG_BYTES', 'decode', 'encode', 'is_sealed', 'key_id', 'reply_bytes',
           'reply_requester', 'seal', 'unseal']

VERSION = 3
MAX_BINS = 4096
MAX_CLOUD_POINTS = 2_000_000
MAX_ROBOT = 2**31 - 1  # robot ids are session ids
TAG_BYTES = 32
_DESC = struct.Struct('<4sBBHiqq8sHH')
_REQ = struct.Struct('<4sBBHiiqqI')
_REPLY = struct.Struct('<4sBBHiiqqIiI')
_CATCH = struct.Struct('<4sBBHiI')
_SEAL = struct.Struct('<4sBBHiq')
MAX_DESCRIPTOR_BYTES = _DESC.size + 4 * MAX_BINS + 28
_CONTEXT = b'solid_ros/peers\x00'


class PeerMessageError(SolidError, ValueError):
    """A peer message that cannot be trusted: wrong kind, version, size or values."""


class PeerAuthError(PeerMessageError):
    """An authenticated envelope whose tag does not match (another key, or altered)."""


@dataclass(frozen=True)
class DescriptorMessage:
    """One stored keyframe of a robot, as its descriptor."""

    robot: int
    index: int
    stamp_ns: int
    fingerprint: str
    r_solid: npt.NDArray[np.float32]
    heading: npt.NDArray[np.float32]
    pose: tuple[float, ...] | None = None


@dataclass(frozen=True)
class CloudRequest:
    """``requester`` asks ``owner`` for the cloud of its keyframe ``index`` stamped
    ``stamp_ns``."""

    requester: int
    owner: int
    index: int
    request_id: int
    stamp_ns: int


@dataclass(frozen=True)
class CloudReply:
    """The owner's answer: the cloud, or ``cloud`` None when it no longer has it."""

    owner: int
    requester: int
    index: int
    request_id: int
    stamp_ns: int
    cloud: KeyframeCloud | None


@dataclass(frozen=True)
class Sealed:
    """An authenticated envelope, opened: who sent it, its stamp and the message bytes."""

    sender: int
    stamp_ns: int
    inner: bytes


@dataclass(frozen=True)
class CatchUpRequest:
    """A robot that joined late asks every peer for up to ``limit`` stored descriptors."""

    requester: int
    limit: int


Message = DescriptorMessage | CloudRequest | CloudReply | CatchUpRequest


def _fingerprint_bytes(text: str) -> bytes:
    try:
        raw = bytes.fromhex(text)
    except ValueError as err:
        raise PeerMessageError(f'fingerprint {text!r} is not 16 hex digits') from err
    if len(raw) != 8:
        raise PeerMessageError(f'fingerprint {text!r} is not 16 hex digits')
    return raw


def encode(msg: Message) -> bytes:
    """Bytes of one message (see the module docstring)."""
    if isinstance(msg, DescriptorMessage):
        r = np.ascontiguousarray(msg.r_solid, dtype='<f2').ravel()
        a = np.ascontiguousarray(msg.heading, dtype='<f2').ravel()
        flags = 1 if msg.pose is not None else 0
        head = _DESC.pack(b'SLD1', VERSION, flags, 0, msg.robot, msg.index, msg.stamp_ns,
                          _fingerprint_bytes(msg.fingerprint), len(r), len(a))
        tail = np.asarray(msg.pose, dtype='<f4').tobytes() if msg.pose is not None else b''
        return head + r.tobytes() + a.tobytes() + tail
    if isinstance(msg, CloudRequest):
        return _REQ.pack(b'SLQ1', VERSION, 0, 0, msg.requester, msg.owner, msg.index,
                         msg.stamp_ns, msg.request_id)
    if isinstance(msg, CloudReply):
        cloud = msg.cloud
        if cloud is None:
            return _REPLY.pack(b'SLC1', VERSION, 1, 0, msg.owner, msg.requester, msg.index,
                               msg.stamp_ns, msg.request_id, 0, 0)
        return _REPLY.pack(b'SLC1', VERSION, 0, 0, msg.owner, msg.requester, msg.index,
                           msg.stamp_ns, msg.request_id, cloud.n_struct, len(cloud.points)
                           ) + pack_points(cloud.points, cloud.n_struct, cloud_step(cloud))
    return _CATCH.pack(b'SLK1', VERSION, 0, 0, msg.requester, msg.limit)


def reply_bytes(points: int) -> int:
    """Largest size of a cloud reply of ``points`` points (the cap a receiver checks first:
    6 bytes a point before deflating, plus zlib's worst case)."""
    return _REPLY.size + 8 + 6 * int(points) + int(points) // 16 + 64


def reply_requester(raw: bytes) -> int | None:
    """The requester a cloud reply (plain or in an envelope) names, read without decoding or
    authenticating it, so that replies to other robots cost nothing (None: not a reply)."""
    offset = _SEAL.size if is_sealed(raw) else 0
    if bytes(raw[offset:offset + 4]) != b'SLC1' or len(raw) < offset + _REPLY.size:
        return None
    requester: int = struct.unpack_from('<i', raw, offset + 12)[0]
    return requester


def key_id(key: bytes) -> str:
    """A short name of a fleet key for logs (derived with HMAC: it reveals nothing of the
    key), so robots can be seen to share one."""
    return hmac.new(key, b'solid_ros key id', hashlib.sha256).hexdigest()[:8]


def _tag(key: bytes, topic: str, body: bytes) -> bytes:
    return hmac.new(key, _CONTEXT + topic.encode() + b'\x00' + body, hashlib.sha256).digest()


def seal(inner: bytes, key: bytes, sender: int, stamp_ns: int, topic: str) -> bytes:
    """Wrap an encoded message in an authenticated envelope for ``topic``."""
    body = _SEAL.pack(b'SLA1', VERSION, 0, 0, sender, stamp_ns) + inner
    return body + _tag(key, topic, body)


def is_sealed(raw: bytes | bytearray | memoryview) -> bool:
    """Whether ``raw`` is an authenticated envelope (by its kind; not yet checked)."""
    return bytes(raw[:4]) == b'SLA1'


def unseal(raw: bytes, key: bytes, topic: str) -> Sealed:
    """Check an envelope's tag with ``key`` and return what it carries.

    Raises:
        PeerAuthError: the tag does not match (another key, another topic, or altered).
        PeerMessageError: not an envelope of this version, or too short.
    """
    if len(raw) < _SEAL.size + TAG_BYTES + 5 or not is_sealed(raw):
        raise PeerMessageError(f'{len(raw)} bytes: not an authenticated peer message')
    if raw[4] != VERSION:
        raise PeerMessageError(f'authenticated message version {raw[4]}; this solid_ros '
                               f'reads {VERSION}')
    body, tag = raw[:-TAG_BYTES], raw[-TAG_BYTES:]
    if not hmac.compare_digest(tag, _tag(key, topic, body)):
        raise PeerAuthError('authentication tag does not match the fleet key')
    _, _, _, _, sender, stamp = _SEAL.unpack_from(body)
    return Sealed(_robot(sender), stamp, body[_SEAL.size:])


def decode(data: bytes | bytearray | memoryview | npt.ArrayLike,
           max_cloud_points: int = MAX_CLOUD_POINTS) -> Message:
    """Parse one message.

    Args:
        data: the message bytes.
        max_cloud_points: a cloud reply with more points is refused.

    Raises:
        PeerMessageError: not a valid message of a known kind (the message says why).
    """
    raw = data if isinstance(data, (bytes, bytearray, memoryview)) else \
        np.asarray(data, dtype=np.uint8).tobytes()
    raw = bytes(raw)
    if len(raw) < 5:
        raise PeerMessageError(f'{len(raw)} bytes: too short for a peer message')
    kind, version = raw[:4], raw[4]
    if version != VERSION:
        raise PeerMessageError(f'{kind!r} version {version}; this solid_ros reads {VERSION}')
    if kind == b'SLD1':
        return _descriptor(raw)
    if kind == b'SLQ1':
        _size(raw, _REQ.size, 'cloud request')
        _, _, _, _, requester, owner, index, stamp, rid = _REQ.unpack(raw)
        return CloudRequest(_robot(requester), _robot(owner), _index(index), rid, stamp)
    if kind == b'SLC1':
        return _reply(raw, max_cloud_points)
    if kind == b'SLK1':
        _size(raw, _CATCH.size, 'catch-up request')
        _, _, _, _, requester, limit = _CATCH.unpack(raw)
        return CatchUpRequest(_robot(requester), limit)
    if kind == b'SLA1':
        raise PeerMessageError('an authenticated message: this robot has no fleet key '
                               '(peer_key_file)')
    raise PeerMessageError(f'unknown message kind {kind!r}')


def _size(raw: bytes, want: int, what: str) -> None:
    if len(raw) != want:
        raise PeerMessageError(f'{what} of {len(raw)} bytes; expected {want}')


def _robot(robot: int) -> int:
    if not 0 <= robot <= MAX_ROBOT:
        raise PeerMessageError(f'robot id {robot} out of range (0 to {MAX_ROBOT})')
    return robot


def _index(index: int) -> int:
    if index < 0:
        raise PeerMessageError(f'keyframe index {index} is negative')
    return index


def _descriptor(raw: bytes) -> DescriptorMessage:
    if len(raw) < _DESC.size:
        raise PeerMessageError(f'descriptor of {len(raw)} bytes: shorter than its header')
    _, _, flags, _, robot, index, stamp, fp, n_r, n_a = _DESC.unpack_from(raw)
    if not (0 < n_r <= MAX_BINS and 0 < n_a <= MAX_BINS):
        raise PeerMessageError(f'descriptor sizes {n_r} x {n_a} out of range')
    want = _DESC.size + 2 * (n_r + n_a) + (28 if flags & 1 else 0)
    _size(raw, want, 'descriptor')
    bins = np.frombuffer(raw, dtype='<f2', count=n_r + n_a, offset=_DESC.size)
    tail = np.frombuffer(raw, dtype='<f4', offset=_DESC.size + 2 * (n_r + n_a))
    vals = bins.astype(np.float32)
    if not (np.all(np.isfinite(vals)) and np.all(np.isfinite(tail))):
        raise PeerMessageError('descriptor holds NaN or infinite values')
    r, a = vals[:n_r], vals[n_r:n_r + n_a]
    if np.any(r < 0.0) or np.any(a < 0.0):
        raise PeerMessageError('descriptor holds negative bins')
    pose = tuple(float(v) for v in tail) if flags & 1 else None
    return DescriptorMessage(_robot(robot), _index(index), stamp, fp.hex(), r, a, pose)


def _reply(raw: bytes, max_points: int) -> CloudReply:
    if len(raw) < _REPLY.size:
        raise PeerMessageError(f'cloud reply of {len(raw)} bytes: shorter than its header')
    _, _, status, _, owner, requester, index, stamp, rid, n_struct, n = _REPLY.unpack_from(raw)
    owner, requester, index = _robot(owner), _robot(requester), _index(index)
    if status == 1:
        _size(raw, _REPLY.size, 'empty cloud reply')
        return CloudReply(owner, requester, index, rid, stamp, None)
    if status != 0 or not 0 < n <= min(max_points, MAX_CLOUD_POINTS) or not 0 <= n_struct <= n:
        raise PeerMessageError(f'cloud reply status {status}, {n} points, {n_struct} '
                               f'structure points: out of range (at most {max_points} points)')
    try:
        pts = unpack_points(memoryview(raw)[_REPLY.size:], n, n_struct)
    except CloudCodecError as exc:
        raise PeerMessageError(str(exc)) from exc
    if np.abs(pts).max() > 1e5:
        raise PeerMessageError('cloud holds implausibly far points')
    return CloudReply(owner, requester, index, rid, stamp, KeyframeCloud(pts, n_struct))
