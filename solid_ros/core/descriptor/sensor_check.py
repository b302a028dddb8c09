"""Where a configuration contradicts what the sensor's first clouds show, and what to set.

:func:`findings` compares a :class:`~.sensor.CloudSample` with a :class:`SolidConfig`, the way
the descriptor will use the points (levelled by the mounting, range-gated, clipped, binned),
and reports only settings that waste or distort much of the data:

- elevation: over ``CLAMP_FRACTION`` of the points fall outside ``fov_down_deg`` ..
  ``fov_up_deg`` (the descriptor clamps them into its first or last elevation bin), or the
  clouds never reach the lowest third of that span (the ground always returns: the sensor
  does not look that low, and those bins stay empty);
- range: over ``RANGE_FRACTION`` of the points lie at or beyond ``max_range``, or within
  ``min_range`` (dropped);
- horizontal clip: ``fov_width_deg`` around ``fov_center_deg`` keeps under ``CLIP_KEEPS`` of
  the points (the clip looks away from the data);
- heading: the clouds cover under ``NARROW_DEG`` but ``heading_match`` is ``'full'``.

Each :class:`Finding` is one line with the values to set; :func:`check_line` joins them for
the node's warning and the replay. :func:`suggest_settings` applies them to a configuration
(``solid_replay --suggest-params``). Pure numpy over the base modules.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import SolidConfig
from solid_ros.core.descriptor.sensor import CloudSample, SensorView, measure
from solid_ros.core.geometry import rpy_matrix

__all__ = ['CLAMP_FRACTION', 'CLIP_KEEPS', 'NARROW_DEG', 'RANGE_FRACTION', 'Finding',
           'check_line', 'findings', 'suggest_settings']

FloatArray = npt.NDArray[np.float64]

CLAMP_FRACTION = 0.2
RANGE_FRACTION = 0.2
CLIP_KEEPS = 0.1
NARROW_DEG = 180.0
_EMPTY_BELOW = 1.0 / 3.0
_MIN_POINTS = 500


@dataclass(frozen=True)
class Finding:
    """One contradiction between the clouds and the configuration.

    Attributes:
        topic: what it is about: 'elevation', 'max_range', 'min_range', 'fov_clip' or
            'heading_match'.
        message: one line: what the clouds show, what the settings say, what to set.
        settings: the values to set.
    """

    topic: str
    message: str
    settings: Mapping[str, Any] = field(default_factory=dict)


def _up(value: float) -> float:
    # Outward to half a degree, after float32 points' last digits are dropped.
    return math.ceil(round(value, 2) * 2.0) / 2.0


def _down(value: float) -> float:
    return math.floor(round(value, 2) * 2.0) / 2.0


def _round_range(value: float) -> float:
    return float(min(5 * max(1, math.ceil(value / 5.0)), 1000))  # the settings' upper limit


def _mount(config: SolidConfig) -> FloatArray:
    return rpy_matrix(math.radians(config.mount_roll_deg), math.radians(config.mount_pitch_deg),
                      math.radians(config.mount_yaw_deg))


def _range_findings(dist: FloatArray, config: SolidConfig) -> list[Finding]:
    out = []
    far = float(np.mean(dist >= config.max_range))
    if far > RANGE_FRACTION:
        reach = _round_range(float(np.percentile(dist, 99.0)))
        out.append(Finding(
            'max_range', f'{far:.0%} of the points lie at or beyond max_range '
            f'{config.max_range:g} m (99% within {np.percentile(dist, 99.0):.1f} m): set '
            f'max_range: {reach}, max_distance: {reach}',
            {'max_range': reach, 'max_distance': reach}))
    near = float(np.mean(dist <= config.min_range))
    if near > RANGE_FRACTION:
        low = math.floor(float(np.percentile(dist, 1.0)) * 10.0) / 10.0
        out.append(Finding(
            'min_range', f'min_range {config.min_range:g} m drops {near:.0%} of the points '
            f'(median range {np.median(dist):.1f} m): set min_range: {low}',
            {'min_range': low}))
    return out


def _clip_keeps(azimuth: FloatArray, config: SolidConfig) -> npt.NDArray[np.bool_]:
    if config.fov_width_deg >= 360.0:
        return np.ones(len(azimuth), dtype=bool)
    off = (azimuth - config.fov_center_deg + 180.0) % 360.0 - 180.0
    keep: npt.NDArray[np.bool_] = np.abs(off) <= 0.5 * config.fov_width_deg
    return keep


def _clip_findings(kept: float, view: SensorView, config: SolidConfig) -> list[Finding]:
    if config.fov_width_deg >= 360.0 or kept >= CLIP_KEEPS:
        return []
    if view.full_turn:
        what, settings = 'all around', {'fov_width_deg': 360.0}
        fix = 'fov_width_deg: 360.0'
    else:
        centre = float(round(view.center_deg))
        what = f'{view.horizontal_deg:.0f} deg around {view.center_deg:+.0f} deg'
        settings, fix = {'fov_center_deg': centre}, f'fov_center_deg: {centre}'
    return [Finding('fov_clip', f'fov_width_deg {config.fov_width_deg:g} around '
                    f'fov_center_deg {config.fov_center_deg:g} keeps {kept:.0%} of the points '
                    f'(the clouds cover {what}): set {fix}', settings)]


def _elevation_findings(elevation: FloatArray, config: SolidConfig) -> list[Finding]:
    up, down = config.fov_up_deg, config.fov_down_deg
    lo, hi = (float(v) for v in np.percentile(elevation, [0.5, 99.5]))
    above = float(np.mean(elevation >= up))
    below = float(np.mean(elevation < down))
    empty = lo - down > _EMPTY_BELOW * (up - down)
    if above <= CLAMP_FRACTION and below <= CLAMP_FRACTION and not empty:
        return []
    why = []
    if above > CLAMP_FRACTION:
        why.append(f'{above:.0%} of the points fall into the top elevation bin')
    if below > CLAMP_FRACTION:
        why.append(f'{below:.0%} into the bottom one' if why else
                   f'{below:.0%} of the points fall into the bottom elevation bin')
    if empty:
        why.append(f'the bins below {lo:+.1f} deg stay empty')
    # Once the span is wrong, fit both ends that the clouds pass or fall short of below.
    new_up = _up(hi) if round(hi, 2) > up else up
    new_down = _down(lo) if (round(lo, 2) < down or empty) else down
    if new_up <= new_down:
        new_up = new_down + 0.5
    return [Finding('elevation', f'the clouds reach elevations {lo:+.1f} to {hi:+.1f} deg but '
                    f'fov_up_deg/fov_down_deg say {up:+.1f}/{down:+.1f} ({", ".join(why)}): '
                    f'set fov_up_deg: {new_up}, fov_down_deg: {new_down}',
                    {'fov_up_deg': new_up, 'fov_down_deg': new_down})]


def findings(sample: CloudSample, config: SolidConfig) -> list[Finding]:
    """The contradictions between the sampled clouds and ``config`` (none when the sample
    holds too few points to tell)."""
    view = measure(sample, _mount(config))
    if view is None:
        return []
    pts = sample.points() @ _mount(config).T
    dist = np.linalg.norm(pts, axis=1)
    out = _range_findings(dist, config)
    gated = pts[(dist > config.min_range) & (dist < config.max_range)]
    if len(gated) < _MIN_POINTS:
        return out
    horizontal = np.hypot(gated[:, 0], gated[:, 1])
    azimuth = np.degrees(np.arctan2(gated[:, 1], gated[:, 0]))
    keep = _clip_keeps(azimuth, config)
    out += _clip_findings(float(np.mean(keep)), view, config)
    binned = keep & (horizontal < config.max_distance)
    if np.count_nonzero(binned) >= _MIN_POINTS:
        out += _elevation_findings(np.degrees(np.arctan2(gated[binned, 2],
                                                         horizontal[binned])), config)
    seen = min(view.horizontal_deg, config.fov_width_deg)
    if seen < NARROW_DEG and config.heading_match == 'full':
        out.append(Finding('heading_match', f'the clouds cover {seen:.0f} deg but '
                           "heading_match is 'full' (whole 360-degree signatures): set "
                           "heading_match: 'overlap'", {'heading_match': 'overlap'}))
    return out


def check_line(sample: CloudSample, config: SolidConfig) -> str | None:
    """The one line the node logs (and the replay prints) when the first clouds contradict
    ``config``; None when they do not."""
    found = findings(sample, config)
    if not found:
        return None
    return (f'the first {sample.clouds} clouds contradict the parameters: '
            + '; '.join(f.message for f in found))


def suggest_settings(sample: CloudSample, base: SolidConfig) -> dict[str, Any]:
    """What to change in ``base`` for the sampled clouds: the settings :func:`findings` asks
    for, and nothing that the clouds do not contradict (``solid_replay --suggest-params``).

    Returns:
        Only the changed settings (empty when nothing contradicts, or the sample holds too
        few points to tell).
    """
    out: dict[str, Any] = {}
    config = base
    for _ in range(3):  # a fix may show the next (points kept by a wider range gate)
        found = findings(sample, config)
        if not found:
            break
        for finding in found:
            out.update(finding.settings)
        config = base.replace(**out)
    return {k: v for k, v in out.items() if getattr(base, k) != v}
