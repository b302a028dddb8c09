"""Scoring a replay against reference poses: each keyframe's best match and every loop.

The reference pose of a keyframe is the track's pose paired with it: by order for a KITTI
file without stamps, else the nearest stamp within ``odom_tolerance_sec``. Best matches give
the descriptor metrics (:mod:`solid_ros.tools.evaluation`); every candidate looked at is
scored by its relative pose (:mod:`solid_ros.tools.loops`), which gives the published loops'
precision, recall and the sweep for a target precision.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.config import SolidConfig
from solid_ros.core.errors import PoseError
from solid_ros.core.odometry.track import nearest_stamp
from solid_ros.core.results import LoopCandidate, ScanResult
from solid_ros.formats.poses import PoseTrack
from solid_ros.tools.evaluation import Evaluation, evaluate, recommend_threshold
from solid_ros.tools.loops import (
    REVISIT_MIN_PATH_M,
    REVISIT_RADIUS_M,
    LoopRecord,
    overlap_sweep,
    pose_error,
    revisit_recall,
    revisits,
    score_loops,
)
from solid_ros.tools.options import ReplayOptions
from solid_ros.tools.pipeline import ScanLog, published_best

__all__ = ['Scores', 'reference_poses', 'score']

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Scores:
    """A replay scored against reference poses (all empty without them).

    Attributes:
        source: what the reference poses are (a file, an Odometry topic), None without.
        reference: per keyframe, the reference pose (NaN where unknown).
        evaluation: the descriptor metrics of the best matches.
        records: every candidate looked at, scored by its relative pose.
        loops: the published loops' scores (:func:`~solid_ros.tools.loops.score_loops`).
        loop_sweep: the sweep for the target precision.
    """

    source: str | None = None
    reference: FloatArray | None = None
    evaluation: Evaluation | None = None
    records: list[LoopRecord] = field(default_factory=list)
    loops: dict[str, Any] | None = None
    loop_sweep: dict[str, Any] | None = None


def reference_poses(track: PoseTrack, seqs: Sequence[int], stamps_ns: npt.ArrayLike,
                    tolerance_ns: int, tolerance_sec: float) -> FloatArray:
    """The pose of ``track`` for each keyframe (NaN where none pairs).

    Args:
        track: reference poses; without stamps they pair by message order (``seqs``).
        seqs: each keyframe's position in the cloud topic.
        stamps_ns: each keyframe's stamp.
        tolerance_ns: largest stamp difference of a pairing.
        tolerance_sec: the same in seconds, for the message.

    Raises:
        PoseError: no pose pairs with any keyframe.
    """
    if track.stamps_ns is None:
        idx = np.asarray(seqs, dtype=np.intp)
    else:
        idx = nearest_stamp(track.stamps_ns, stamps_ns, tolerance_ns)
    reference = np.full((len(idx), 4, 4), np.nan)
    have = idx >= 0
    reference[have] = track.poses[idx[have]]
    if len(idx) and not have.any():
        raise PoseError(f'no reference pose of {track.source} lies within '
                        f'{tolerance_sec} s of a scan stamp')
    return reference


def score(log: ScanLog, track: PoseTrack | None, config: SolidConfig,
          options: ReplayOptions) -> Scores:
    """Score a run against ``track`` (nothing without one).

    Raises:
        PoseError: no reference pose pairs with any keyframe.
    """
    if track is None:
        return Scores()
    results = log.results
    stamps = np.asarray([res.stamp_ns for res in results], dtype=np.int64)
    reference = reference_poses(track, [seq for seq, _ in log.keyframes], stamps,
                                options.tolerance_ns, options.node_config.odom_tolerance_sec)
    ev = _evaluate(config, results, stamps, reference, options)
    records = _records(config, results, log.candidates, reference)
    limits = {'max_error_m': options.max_pose_error_m,
              'max_error_deg': options.max_pose_error_deg}
    loops = score_loops(records, ev.truth.has_loop, **limits)
    revisiting = revisits(reference[:, :3, 3], rotations=reference[:, :3, :3],
                          max_heading_deg=options.max_heading_deg)
    loops['revisits'] = {'radius_m': REVISIT_RADIUS_M, 'min_path_m': REVISIT_MIN_PATH_M,
                         **revisit_recall(records, revisiting, **limits)}
    if config.verify:
        sweep = overlap_sweep(records, ev.truth.has_loop, config.verify_min_overlap,
                              target_precision=options.target_precision, **limits)
    else:
        sweep = _distance_for_precision(ev, options.target_precision)
    return Scores(track.source, reference, ev, records, loops, sweep)


def _evaluate(cfg: SolidConfig, results: list[ScanResult], stamps: npt.NDArray[np.int64],
              reference: FloatArray, options: ReplayOptions) -> Evaluation:
    """The descriptor metrics of each keyframe's best match."""
    n = len(results)
    match = np.full(n, -1, dtype=np.intp)
    dist = np.full(n, np.nan)
    yaw = np.zeros(n)
    foreign = np.zeros(n, bool)
    for i, res in enumerate(results):
        b = res.best
        if b is None:
            continue
        dist[i], yaw[i] = b.distance, b.yaw
        if b.match_session == cfg.session_id and 0 <= b.match_index < n:
            match[i] = b.match_index
        else:  # a loaded session: no reference pose, so it counts as false
            foreign[i] = True
    accepted = np.asarray([published_best(res) for res in results], dtype=bool)
    return evaluate(reference[:, :3, 3], match, dist, yaw, accepted, radius=options.radius,
                    rotations=reference[:, :3, :3], max_heading_deg=options.max_heading_deg,
                    stamps_ns=stamps, exclude_frames=cfg.exclude_recent_frames,
                    exclude_sec=cfg.exclude_recent_sec, foreign=foreign)


def _records(cfg: SolidConfig, results: list[ScanResult], published: list[LoopCandidate],
             reference: FloatArray) -> list[LoopRecord]:
    """Every attempt scored against the reference relative pose."""
    shown = {id(c) for c in published}
    out = []
    for res in results:
        for c in res.attempts:
            te = re_ = gd = math.nan
            if c.match_session == cfg.session_id and 0 <= c.match_index < len(reference):
                q, m = reference[c.query_index], reference[c.match_index]
                te, re_ = pose_error(c.matrix(), np.linalg.solve(m, q))
                gd = float(np.linalg.norm(q[:3, 3] - m[:3, 3]))
            out.append(LoopRecord(c.query_index, c.match_index, c.match_session,
                                  id(c) in shown, c.verified, c.reason, c.overlap, c.distance,
                                  te, re_, gd, c.source, c.evidence.coarse_overlap))
    return out


def _distance_for_precision(ev: Evaluation, target: float) -> dict[str, Any]:
    """Descriptor-only mode: the largest distance_threshold whose precision reaches ``target``
    (places within the radius count as correct, as in the PR curve)."""
    c = ev.curve
    ok = np.flatnonzero(c.precision >= target)
    k = int(ok[-1]) if ok.size else -1
    return {'parameter': 'distance_threshold', 'target_precision': target,
            'recommended': recommend_threshold(c, k) if k >= 0 else None,
            'recall': float(c.recall[k]) if k >= 0 else None}
