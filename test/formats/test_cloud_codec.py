"""Cloud bodies of peer replies: quantised, structure first, deflated; bombs and junk refused."""

from __future__ import annotations

import lzma
import struct

import numpy as np
import pytest

from solid_ros.core.database.clouds import KeyframeCloud
from solid_ros.formats.cloud_codec import (
    GROUND_STEPS,
    STEP_M,
    CloudCodecError,
    cloud_step,
    pack_points,
    unpack_points,
)

RNG = np.random.default_rng(1)


def _nearest(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(a[:, None] - b[None], axis=2).min(axis=1)


def test_points_come_back_on_the_grid_structure_first() -> None:
    pts = RNG.uniform(-80.0, 80.0, (600, 3)).astype(np.float32)
    body = pack_points(pts, 250, STEP_M)
    back = unpack_points(body, 600, 250)
    half = 0.5 * STEP_M * 3**0.5 + 1e-5
    assert _nearest(back[:250], pts[:250]).max() <= half
    assert _nearest(back[250:], pts[250:]).max() <= GROUND_STEPS * half  # the ground's grid
    # Far less than float32 x y z even for points spread at random.
    assert len(body) < 0.6 * pts.nbytes
    # A point beyond the int16 grid coarsens the step; nothing wraps around.
    far = np.array([[2000.0, -1.0, 0.5], [1.0, 2.0, 3.0]], dtype=np.float32)
    got = unpack_points(pack_points(far, 2, STEP_M), 2, 2)
    assert _nearest(got, far).max() < 0.05
    assert cloud_step(KeyframeCloud(pts, 0)) == STEP_M
    assert cloud_step(KeyframeCloud(pts, 0, 0.72)) == pytest.approx(0.045)


def test_bad_bodies_are_refused() -> None:
    pts = RNG.uniform(-10.0, 10.0, (50, 3))
    body = pack_points(pts, 10, STEP_M)
    for bad, n in ((body[:-1], 50), (body + b'\0', 50), (body, 49), (body, 51), (b'', 0)):
        with pytest.raises(CloudCodecError):
            unpack_points(bad, n, 0)
    # A bomb: a few kB that unpack to 10 MB stop at the bytes the count allows.
    bomb = lzma.compress(bytes(10_000_000), format=lzma.FORMAT_RAW,
                         filters=[{'id': lzma.FILTER_LZMA2, 'dict_size': 1 << 16}])
    with pytest.raises(CloudCodecError, match='other than 10 points'):
        unpack_points(struct.pack('<fI', STEP_M, len(bomb)) + bomb, 10, 0)
    with pytest.raises(CloudCodecError, match='step'):
        unpack_points(struct.pack('<fI', float('nan'), 0), 0, 0)
    for _ in range(100):
        junk = struct.pack('<fI', STEP_M, 40) + bytes(RNG.integers(0, 256, 40, dtype=np.uint8))
        with pytest.raises(CloudCodecError):
            unpack_points(junk, 20, 0)
