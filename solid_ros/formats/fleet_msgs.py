"""Messages for placing the robots' maps in each other's: inter-robot loops, keyframe poses,
path requests (topic ``/solid/alignment``; sealed like the others, :mod:`solid_ros.formats.peers`).

Little-endian, each starting with a 4-byte kind and the peer messages' version byte:

``SLL1`` an inter-robot loop a robot published (192 bytes)::

    4s, u8 version, u8, u16, i32 robot, i64 query index, i64 query stamp ns,
    i32 match robot, i64 match index, i64 match stamp ns,
    f32[7] T (query sensor in the match sensor frame: x y z qx qy qz qw),
    f32[21] its covariance (ROS order, upper triangle by rows),
    f32[7] the query keyframe's pose in the sender's map, f32 the path driven to it (m)

``SLP1`` keyframe poses of the sender's map (16 + 36 per pose, at most 512)::

    4s, u8 version, u8 flags (bit 0: part of a whole path asked for), u16 reserved,
    i32 robot, u16 part, u16 parts, then per pose: u32 keyframe index, f32[7] pose,
    f32 path driven to it (m)

``SLR1`` a robot asks another for its whole corrected path (16 bytes)::

    4s, u8 version, u8, u16, i32 requester, i32 owner

Decoding checks kind, version, size, ids and finiteness and raises
:class:`~solid_ros.formats.peers.PeerMessageError` for anything else.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from solid_ros.formats.peers import MAX_ROBOT, VERSION, PeerMessageError

__all__ = ['LoopMessage', 'MAX_ALIGN_BYTES', 'MAX_POSES', 'PathRequest', 'PosesMessage',
           'decode_align', 'encode_align']

MAX_POSES = 512
_LOOP = struct.Struct('<4sBBHiqqiqq')
_POSES = struct.Struct('<4sBBHiHH')
_REQ = struct.Struct('<4sBBHii')
_ENTRY = np.dtype([('index', '<u4'), ('pose', '<f4', (7,)), ('path', '<f4')])
_LOOP_FLOATS = 7 + 21 + 7 + 1
MAX_ALIGN_BYTES = _POSES.size + _ENTRY.itemsize * MAX_POSES
_TRIU = np.triu_indices(6)
_MAX_COORD = 1e7  # metres: beyond it a float32 pose means nothing


@dataclass(frozen=True)
class LoopMessage:
    """An inter-robot loop of ``robot``'s keyframe ``query_index`` against ``match_robot``'s
    ``match_index``, with the query keyframe's map pose and path when it was sent."""

    robot: int
    query_index: int
    query_stamp_ns: int
    match_robot: int
    match_index: int
    match_stamp_ns: int
    pose: tuple[float, ...]
    covariance: tuple[float, ...]
    query_pose: tuple[float, ...]
    query_path_m: float


@dataclass(frozen=True)
class PosesMessage:
    """Poses of ``robot``'s keyframes in its map: ``(index, x y z qx qy qz qw, path_m)``."""

    robot: int
    poses: tuple[tuple[int, tuple[float, ...], float], ...]
    whole: bool = False
    part: int = 0
    parts: int = 1


@dataclass(frozen=True)
class PathRequest:
    """``requester`` asks ``owner`` for its whole corrected path."""

    requester: int
    owner: int


AlignMessage = LoopMessage | PosesMessage | PathRequest


def encode_align(msg: AlignMessage) -> bytes:
    """Bytes of one message (see the module docstring)."""
    if isinstance(msg, LoopMessage):
        cov = np.asarray(msg.covariance, dtype=np.float64).reshape(6, 6)[_TRIU]
        floats = np.concatenate([msg.pose, cov, msg.query_pose, [msg.query_path_m]])
        return _LOOP.pack(b'SLL1', VERSION, 0, 0, msg.robot, msg.query_index,
                          msg.query_stamp_ns, msg.match_robot, msg.match_index,
                          msg.match_stamp_ns) + floats.astype('<f4').tobytes()
    if isinstance(msg, PosesMessage):
        if len(msg.poses) > MAX_POSES:
            raise PeerMessageError(f'{len(msg.poses)} poses in one message (at most '
                                   f'{MAX_POSES})')
        rows = np.zeros(len(msg.poses), dtype=_ENTRY)
        for k, (index, pose, path) in enumerate(msg.poses):
            rows[k] = (index, pose, path)
        return _POSES.pack(b'SLP1', VERSION, int(msg.whole), 0, msg.robot, msg.part,
                           msg.parts) + rows.tobytes()
    return _REQ.pack(b'SLR1', VERSION, 0, 0, msg.requester, msg.owner)


def _robot(robot: int) -> int:
    if not 0 <= robot <= MAX_ROBOT:
        raise PeerMessageError(f'robot id {robot} out of range (0 to {MAX_ROBOT})')
    return robot


def _pose(values: npt.NDArray[np.float64], what: str) -> tuple[float, ...]:
    q = values[3:7]
    norm = float(np.linalg.norm(q))
    if np.abs(values[:3]).max() > _MAX_COORD or not 0.5 < norm < 2.0:
        raise PeerMessageError(f'{what}: implausible position or quaternion of norm {norm:.3g}')
    return tuple(float(v) for v in np.concatenate([values[:3], q / norm]))


def decode_align(data: bytes) -> AlignMessage:
    """Parse one message.

    Raises:
        PeerMessageError: not a valid message of these kinds (the message says why).
    """
    raw = bytes(data)
    if len(raw) < 5 or raw[4] != VERSION:
        raise PeerMessageError(f'{len(raw)} bytes: not an alignment message of version '
                               f'{VERSION}')
    kind = raw[:4]
    if kind == b'SLL1':
        return _loop(raw)
    if kind == b'SLP1':
        return _poses(raw)
    if kind == b'SLR1':
        if len(raw) != _REQ.size:
            raise PeerMessageError(f'path request of {len(raw)} bytes; expected {_REQ.size}')
        _, _, _, _, requester, owner = _REQ.unpack(raw)
        return PathRequest(_robot(requester), _robot(owner))
    raise PeerMessageError(f'unknown alignment message kind {kind!r}')


def _loop(raw: bytes) -> LoopMessage:
    want = _LOOP.size + 4 * _LOOP_FLOATS
    if len(raw) != want:
        raise PeerMessageError(f'loop message of {len(raw)} bytes; expected {want}')
    _, _, _, _, robot, qi, qs, match, mi, ms = _LOOP.unpack_from(raw)
    vals = np.frombuffer(raw, dtype='<f4', offset=_LOOP.size).astype(np.float64)
    if not np.all(np.isfinite(vals)) or qi < 0 or mi < 0 or vals[-1] < 0.0:
        raise PeerMessageError('loop message holds NaN, infinite or negative values')
    cov = np.zeros((6, 6))
    cov[_TRIU] = vals[7:28]
    cov = cov + np.triu(cov, 1).T
    return LoopMessage(_robot(robot), qi, qs, _robot(match), mi, ms, _pose(vals[:7], 'loop'),
                       tuple(float(v) for v in cov.ravel()), _pose(vals[28:35], 'query pose'),
                       float(vals[35]))


def _poses(raw: bytes) -> PosesMessage:
    body = len(raw) - _POSES.size
    if body < 0 or body % _ENTRY.itemsize or body // _ENTRY.itemsize > MAX_POSES:
        raise PeerMessageError(f'poses message of {len(raw)} bytes: not a header and at most '
                               f'{MAX_POSES} poses')
    _, _, flags, _, robot, part, parts = _POSES.unpack_from(raw)
    if not 0 <= part < parts:
        raise PeerMessageError(f'poses message part {part} of {parts}')
    rows = np.frombuffer(raw, dtype=_ENTRY, offset=_POSES.size)
    vals = rows['pose'].astype(np.float64)
    if not (np.all(np.isfinite(vals)) and np.all(np.isfinite(rows['path']))
            and np.all(rows['path'] >= 0.0)):
        raise PeerMessageError('poses message holds NaN, infinite or negative values')
    poses = tuple((int(r['index']), _pose(v, 'pose'), float(r['path']))
                  for r, v in zip(rows, vals))
    return PosesMessage(_robot(robot), poses, bool(flags & 1), part, parts)
