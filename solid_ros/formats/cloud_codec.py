"""Keyframe clouds as peers send them: quantised and deflated.

A cloud reply (:mod:`solid_ros.formats.peers`) carries the cloud the owner hands it: its
structure points and its ground thinned to a coarse grid
(:meth:`~solid_ros.core.flow.detector.LoopDetector.own_cloud`). Here:

- structure coordinates on a grid of ``step`` metres (:func:`cloud_step`: a 16th of the
  cloud's voxel, 4.7 cm for 0.75 m voxels: the points are voxel centroids, and the
  registration's error is several times that), the rest (ground, which only the overlap and
  conflict measures read) on twice that step; int16, so a keyframe reaches 32767 steps (a
  farther point coarsens the step of its cloud, never wraps);
- the structure rows and the rest each sorted by x, y, z with x as differences (structure
  stays first), the six byte planes apart, raw LZMA2 with a 64 kB dictionary (small memory
  both ways) and no literal context (numbers, not text): 1.9 bytes a point on the simulated
  64-beam town at 0.75 m voxels (zlib at 1 cm: 3.2), against 12 for float32 x y z
  (``test/bench/bench_fleet.py`` prints reply sizes). On hku1 cut in two robots the step
  costs no inter-robot loop (35 of 36 places found at a 2 cm step, 34 at a 16th).

Body: ``f32 step, u32 packed bytes, u8[packed]``. Decoding unpacks at most the bytes the
header's point count allows and refuses anything else (a bomb costs one bounded
allocation).
"""

from __future__ import annotations

import lzma
import struct

import numpy as np
import numpy.typing as npt

from solid_ros.core.database.clouds import KeyframeCloud
from solid_ros.core.errors import SolidError

__all__ = ['CloudCodecError', 'STEP_M', 'cloud_step', 'pack_points', 'unpack_points']

STEP_M = 0.02  # a cloud's step when its voxel is not known
VOXEL_STEPS = 16.0
GROUND_STEPS = 2.0  # the rest's step, in structure steps
_HEAD = struct.Struct('<fI')
_FILTERS = [{'id': lzma.FILTER_LZMA2, 'preset': 9 | lzma.PRESET_EXTREME, 'dict_size': 1 << 16,
             'lc': 0, 'lp': 0, 'pb': 0}]
_MAX_INT = 32767


class CloudCodecError(SolidError, ValueError):
    """Bytes that do not unpack to the points a reply announces."""


def cloud_step(cloud: KeyframeCloud) -> float:
    """The grid a cloud's coordinates are sent on: its voxel over ``VOXEL_STEPS``, or
    ``STEP_M`` when the cloud does not say its voxel."""
    return STEP_M if cloud.voxel <= 0.0 else float(cloud.voxel) / VOXEL_STEPS


def _sorted_differences(q: npt.NDArray[np.int32]) -> npt.NDArray[np.int32]:
    q = q[np.lexsort((q[:, 2], q[:, 1], q[:, 0]))]
    if len(q):
        q[1:, 0] = np.diff(q[:, 0])
    return q


def pack_points(points: npt.ArrayLike, n_struct: int, step: float) -> bytes:
    """The body for ``points`` (N, 3), structure first (``n_struct`` rows), on a grid of
    ``step`` metres (module docstring)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    far = float(np.abs(pts).max()) if len(pts) else 0.0
    step = max(float(step), far / _MAX_INT * (1.0 + 1e-6))  # the rest: GROUND_STEPS times
    q = np.concatenate([_sorted_differences(np.round(pts[:n_struct] / step).astype(np.int32)),
                        _sorted_differences(np.round(pts[n_struct:] / (GROUND_STEPS * step)
                                                     ).astype(np.int32))])
    planes = q.astype('<i2').view(np.uint8).reshape(len(q), 6).T.tobytes()
    body = lzma.compress(planes, format=lzma.FORMAT_RAW, filters=_FILTERS)
    return _HEAD.pack(step, len(body)) + body


def unpack_points(raw: bytes | memoryview, n: int, n_struct: int) -> npt.NDArray[np.float32]:
    """The ``n`` points of a body (all of ``raw``), structure first (``n_struct`` rows).

    Raises:
        CloudCodecError: ``raw`` is not a body of exactly ``n`` points.
    """
    raw = bytes(raw)
    if len(raw) < _HEAD.size:
        raise CloudCodecError(f'cloud body of {len(raw)} bytes: shorter than its header')
    step, size = _HEAD.unpack_from(raw)
    if not (np.isfinite(step) and 0.0 < step <= 10.0) or size != len(raw) - _HEAD.size:
        raise CloudCodecError(f'cloud body: step {step} m, {size} packed bytes announced, '
                              f'{len(raw) - _HEAD.size} there')
    want = 6 * int(n)
    unpack = lzma.LZMADecompressor(format=lzma.FORMAT_RAW, filters=_FILTERS)
    try:
        planes = unpack.decompress(raw[_HEAD.size:], want + 1)
    except lzma.LZMAError as exc:
        raise CloudCodecError(f'cloud body does not unpack: {exc}') from exc
    if len(planes) != want or not unpack.eof or unpack.unused_data:
        raise CloudCodecError(f'cloud body unpacks to other than {n} points')
    q = np.frombuffer(planes, dtype=np.uint8).reshape(6, n).T.copy().view('<i2')
    q = q.astype(np.int64).reshape(n, 3)
    q[:n_struct, 0] = np.cumsum(q[:n_struct, 0])
    q[n_struct:, 0] = np.cumsum(q[n_struct:, 0])
    if n and np.abs(q[:, 0]).max() > _MAX_INT:
        raise CloudCodecError('cloud body: x differences leave the grid')
    scale = np.where(np.arange(n) < n_struct, step, GROUND_STEPS * step)[:, None]
    out: npt.NDArray[np.float32] = (q * scale).astype(np.float32)
    return out
