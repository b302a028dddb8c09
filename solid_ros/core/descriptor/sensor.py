"""What a LiDAR's first clouds say about it: field of view, ranges, density, scan pattern.

:class:`CloudSample` keeps a thinned copy of the first clouds of a stream (the node's, a
bag's); :func:`measure` reads from it the horizontal coverage (a full turn, or a sector and
its centre), the vertical field of view (elevation percentiles), the ranges, the points per
cloud and whether the returns lie on rings (a spinning multi-beam sensor, or any sensor that
scans a fixed grid) or spread over elevation (a non-repetitive pattern, Livox's rosettes).
:mod:`.sensor_check` compares such a view with a configuration. Pure numpy; nothing here
raises on bad input: a malformed cloud is left out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = ['FIRST_CLOUDS', 'CloudSample', 'SensorView', 'measure']

FloatArray = npt.NDArray[np.float64]

FIRST_CLOUDS = 10  # clouds measured before the node and the replay check the configuration
_MAX_POINTS = 20_000  # kept of each cloud (every k-th point): bounds the cost
_MIN_POINTS = 500  # fewer finite points in the whole sample say nothing
_FULL_TURN_DEG = 270.0  # a wider coverage is a 360-degree sensor with a blocked sector
_AZ_BIN_DEG = 1.0
_EL_BIN_DEG = 0.02  # fine enough for 0.2-degree ring spacing
_RING_PERIOD_DEG = (0.15, 3.0)  # ring spacings looked for (HDL-64E upper block .. VLP-16)
# Power of the ring spacing over the median power of the elevation spectrum: on grids of the
# simulator and raw clouds it is in the hundreds or more; an Ouster bag voxel-downsampled to
# 13k points 62; Livox Avia rosettes 2-10.
_RING_CONTRAST = 30.0


@dataclass(frozen=True)
class SensorView:
    """What :func:`measure` read from the first clouds (angles in degrees, ranges in metres,
    in the frame the clouds were measured in).

    Attributes:
        clouds: clouds measured.
        points_per_cloud: median count of finite points in a cloud.
        horizontal_deg: azimuth span holding returns (360 minus the widest empty sector).
        center_deg: heading of the middle of that span, CCW from +x (0 for a full turn).
        elevation_low_deg: 0.5th percentile of the elevations.
        elevation_high_deg: 99.5th percentile of the elevations.
        range_low_m: 1st percentile of the 3-D ranges.
        range_median_m: median 3-D range.
        range_high_m: 99th percentile of the 3-D ranges.
        ring_spacing_deg: elevation between rings, 0 when the returns lie on no rings.
        rings: rings across the vertical field of view, 0 when there are none.
    """

    clouds: int
    points_per_cloud: int
    horizontal_deg: float
    center_deg: float
    elevation_low_deg: float
    elevation_high_deg: float
    range_low_m: float
    range_median_m: float
    range_high_m: float
    ring_spacing_deg: float
    rings: int

    @property
    def full_turn(self) -> bool:
        """Whether the sensor sees all around (a blocked sector of up to 90 deg allowed)."""
        return self.horizontal_deg >= _FULL_TURN_DEG

    def pattern(self) -> str:
        """The scan pattern in words, e.g. '360-degree, 64 rings'."""
        view = ('360-degree' if self.full_turn else
                f'{self.horizontal_deg:.0f}-degree sector around {self.center_deg:+.0f} deg')
        rings = f'{self.rings} rings' if self.rings else 'no rings (non-repetitive pattern)'
        return f'{view}, {rings}'

    def summary(self) -> str:
        """One line: coverage, pattern, elevations, ranges, points."""
        return (f'{self.pattern()}, elevations {self.elevation_low_deg:+.1f} to '
                f'{self.elevation_high_deg:+.1f} deg, ranges {self.range_low_m:.1f} / '
                f'{self.range_median_m:.1f} / {self.range_high_m:.1f} m (1% / median / 99%), '
                f'{self.points_per_cloud} points a cloud over {self.clouds} clouds')


class CloudSample:
    """A thinned copy of the first clouds of a stream.

    Args:
        clouds: how many clouds make the sample complete.
        max_points: points kept of each cloud (every k-th).
    """

    def __init__(self, clouds: int = FIRST_CLOUDS, max_points: int = _MAX_POINTS) -> None:
        self.wanted = max(1, clouds)
        self._max_points = max(1, max_points)
        self._parts: list[npt.NDArray[np.float32]] = []
        self.counts: list[int] = []

    @property
    def clouds(self) -> int:
        """Clouds taken so far."""
        return len(self.counts)

    @property
    def complete(self) -> bool:
        """Whether it holds the clouds it wants."""
        return self.clouds >= self.wanted

    def add(self, points: npt.ArrayLike) -> bool:
        """Take one cloud ((N, 3+) x, y, z first); a malformed or empty one is left out.

        Returns:
            True when this cloud completed the sample (once), else False.
        """
        if self.complete:
            return False
        try:
            arr = np.asarray(points)
            if arr.ndim != 2 or arr.shape[1] < 3 or arr.dtype.kind not in 'fiu':
                return False
            xyz = arr[:, :3].astype(np.float32, copy=False)
        except (TypeError, ValueError):
            return False
        # Arithmetic only on finite rows: a damaged message's signalling NaNs would warn.
        kept = xyz[np.isfinite(xyz).all(axis=1)]
        kept = kept[(kept != 0.0).any(axis=1)]
        count = len(kept)
        if count == 0:
            return False
        step = -(-count // self._max_points)
        self._parts.append(np.array(kept[::step], dtype=np.float32))
        self.counts.append(count)
        return self.complete

    def points(self) -> FloatArray:
        """The kept points, (N, 3) float64."""
        if not self._parts:
            return np.zeros((0, 3))
        out: FloatArray = np.concatenate(self._parts).astype(np.float64)
        return out


def _coverage(azimuth: FloatArray) -> tuple[float, float]:
    """Azimuth span holding returns and its centre, degrees (360 minus the widest gap)."""
    n = int(round(360.0 / _AZ_BIN_DEG))
    hist = np.bincount(((azimuth + 180.0) / _AZ_BIN_DEG).astype(np.int64) % n, minlength=n)
    # A bin with a handful of stray returns (reflections) does not make a view.
    occupied = hist >= max(1.0, 0.02 * float(np.median(hist[hist > 0])))
    if occupied.all():
        return 360.0, 0.0
    idx = np.flatnonzero(occupied)
    gaps = np.diff(np.r_[idx, idx[0] + n]) - 1  # empty bins after each occupied one
    widest = int(np.argmax(gaps))
    span = (n - int(gaps[widest])) * _AZ_BIN_DEG
    first = idx[(widest + 1) % len(idx)]  # the arc starts after the widest gap
    centre = -180.0 + (first + 0.5 * span / _AZ_BIN_DEG) * _AZ_BIN_DEG
    return span, math.remainder(centre, 360.0)


def _ring_spacing(elevation: FloatArray, low: float, high: float) -> float:
    """Elevation between rings, from the strongest low-frequency peak of the elevation
    histogram's spectrum; 0 when no spacing stands out (no rings)."""
    bins = int((high - low) / _EL_BIN_DEG)
    if bins < 16:
        return 0.0
    hist, _ = np.histogram(elevation, bins, (low, high))
    power = np.abs(np.fft.rfft(hist - hist.mean())) ** 2
    freq = np.fft.rfftfreq(bins, d=_EL_BIN_DEG)
    band = (freq >= 1.0 / _RING_PERIOD_DEG[1]) & (freq <= 1.0 / _RING_PERIOD_DEG[0])
    if np.count_nonzero(band) < 8:
        return 0.0
    inside = np.where(band, power, 0.0)
    floor = float(np.median(power[band]))
    # Harmonics of the spacing can be as strong: the lowest strong peak is the spacing.
    i = int(np.flatnonzero(inside >= 0.25 * inside.max())[0])
    while i + 1 < len(inside) and inside[i + 1] > inside[i]:
        i += 1
    if floor <= 0.0 or inside[i] < _RING_CONTRAST * floor:
        return 0.0
    return float(1.0 / freq[i])


def measure(sample: CloudSample, rotation: npt.ArrayLike | None = None) -> SensorView | None:
    """Measure the sensor from a sample of its first clouds.

    Args:
        sample: the clouds (complete or not).
        rotation: 3x3 rotation applied to the points first (the mounting that levels them);
            the ring pattern is always read in the sensor's own frame.

    Returns:
        The view, or None when the sample holds too few finite points to say anything.
    """
    pts = sample.points()
    if len(pts) < _MIN_POINTS:
        return None
    sensor_el = np.degrees(np.arctan2(pts[:, 2], np.hypot(pts[:, 0], pts[:, 1])))
    if rotation is not None:
        pts = pts @ np.asarray(rotation, dtype=np.float64).T
    horizontal = np.hypot(pts[:, 0], pts[:, 1])
    elevation = np.degrees(np.arctan2(pts[:, 2], horizontal))
    azimuth = np.degrees(np.arctan2(pts[:, 1], pts[:, 0]))
    ranges = np.linalg.norm(pts, axis=1)
    low, high = (float(v) for v in np.percentile(elevation, [0.5, 99.5]))
    s_low, s_high = (float(v) for v in np.percentile(sensor_el, [0.5, 99.5]))
    span, centre = _coverage(azimuth)
    r1, r50, r99 = (float(v) for v in np.percentile(ranges, [1.0, 50.0, 99.0]))
    spacing = _ring_spacing(sensor_el, s_low, s_high)
    rings = int(round((s_high - s_low) / spacing)) + 1 if spacing > 0.0 else 0
    return SensorView(clouds=sample.clouds, points_per_cloud=int(np.median(sample.counts)),
                      horizontal_deg=span, center_deg=centre, elevation_low_deg=low,
                      elevation_high_deg=high, range_low_m=r1, range_median_m=r50,
                      range_high_m=r99, ring_spacing_deg=spacing, rings=rings)
