"""JSON reports of the offline tools: the replay's report, in plain types (non-finite numbers
as null)."""

from __future__ import annotations

import json
import math
import platform
import resource
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from solid_ros.core.flow.closure import LoopClosure
from solid_ros.core.flow.detector import LoopDetector
from solid_ros.tools.evaluation import sweep_table
from solid_ros.tools.options import ReplayOptions
from solid_ros.tools.pipeline import STAGES, BagInputs, ScanLog
from solid_ros.tools.scoring import Scores
from solid_ros.tools.trajectory import Trajectory, keyframe_rows

__all__ = ['closure_report', 'jsonable', 'replay_report', 'write_json']

PROG = 'solid_replay'


def jsonable(obj: Any) -> Any:
    """``obj`` with numpy scalars as Python numbers and NaN / inf as None (strict JSON)."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    return obj


def write_json(path: Path, obj: Any) -> None:
    """Write ``obj`` as indented strict JSON (OSError propagates)."""
    path.write_text(json.dumps(jsonable(obj), indent=2) + '\n', encoding='utf-8')


def replay_report(inputs: BagInputs, log: ScanLog, scores: Scores, detector: LoopDetector,
                  options: ReplayOptions, wall_sec: float) -> dict[str, Any]:
    """The report of one replay (``report.json``; keys documented in doc/replay.md).

    Args:
        inputs: what was read from the bag.
        log: what the run gave.
        scores: its scores (empty without reference poses).
        detector: the detector after the run (its database, clouds and verdicts).
        options: the run's options.
        wall_sec: time spent reading, decoding and detecting.
    """
    cfg = detector.config
    ev = scores.evaluation
    return {
        'tool': PROG,
        'versions': _versions(),
        'bag': inputs.name,
        'format': 'ros1' if inputs.ros1 else 'ros2',
        'integrity': inputs.integrity,
        'topic': inputs.topic,
        'odom_topic': inputs.odom_topic,
        'odometry_fed_to_detector': inputs.odometry_fed,
        'reference': scores.source,
        'params_file': None if options.params_file is None else str(options.params_file),
        'config': cfg.to_dict(),
        'config_fingerprint': cfg.fingerprint(),
        'node_config': options.node_config.to_dict(),
        'scans': {'messages': log.messages, 'decoded': log.decoded,
                  'skipped': len(log.skipped), 'keyframes': len(log.keyframes),
                  'accepted_loops': len(log.candidates),
                  'skip_reasons': [{'seq': s, 'reason': r} for s, r in log.skipped[:20]]},
        'timings': _timings(log, wall_sec),
        'keyframe_clouds': _clouds(detector),
        'verification': {'enabled': cfg.verify, 'reasons': dict(sorted(detector.reasons.items())),
                         'calibration': detector.calibration.learned.as_dict(),
                         'max_conflict': detector.bars.max_conflict},
        'loops': scores.loops,
        'loop_sweep': scores.loop_sweep,
        'database': _database(detector),
        'metrics': None if ev is None else ev.metrics(),
        'threshold_sweep': None if ev is None else sweep_table(ev),
        'loaded_database': None if options.load_db is None else str(options.load_db),
        'saved_database': None if options.save_db is None else str(options.save_db),
    }


def closure_report(inputs: BagInputs, log: ScanLog, closure: LoopClosure, traj: Trajectory,
                   errors: dict[str, Any] | None) -> dict[str, Any]:
    """The report's sections on the odometry, the back end and the keyframe trajectory.

    Args:
        inputs: what was read from the bag (the odometry source).
        log: what the run gave (events, odometry per keyframe).
        closure: the loop closure after the run.
        traj: the keyframes' odometry and corrected poses.
        errors: :func:`~solid_ros.tools.trajectory.trajectory_errors` (None: no reference).
    """
    graph = closure.graph
    backend = None if graph is None else {
        'loops': {k: v for k, v in sorted(graph.counts.items()) if v},  # no zero counts
        'loops_in_graph': len(graph.loops), 'steps': graph.steps,
        'segments': len(set(traj.segments[traj.segments >= 0].tolist())),
        'anchored': graph.anchored, 'rebuilds': graph.rebuilds,
        'correction': [float(v) for v in graph.correction().ravel()]}
    return {
        'odometry': {'source': inputs.odometry_source, 'topic': inputs.odom_topic,
                     'posed_scans': log.posed, 'resets': log.events['odometry_reset']},
        'backend': backend,
        'events': {'counts': dict(sorted(log.events.items())), 'lines': log.lines},
        'sensor': {'measured': log.sensor or None, 'contradiction': log.sensor_check or None},
        'trajectory': errors,
        'keyframes': keyframe_rows(traj),
    }


def _percentiles(ms: Sequence[float]) -> dict[str, float | None]:
    if not ms:
        return {'mean': None, 'p50': None, 'p90': None, 'p99': None, 'max': None}
    a = np.asarray(ms, dtype=np.float64)
    p50, p90, p99 = np.percentile(a, [50, 90, 99])
    return {'mean': float(a.mean()), 'p50': float(p50), 'p90': float(p90),
            'p99': float(p99), 'max': float(a.max())}


def _timings(log: ScanLog, wall_sec: float) -> dict[str, Any]:
    return {'wall_sec': wall_sec,
            'scans_per_sec': log.decoded / wall_sec if wall_sec > 0 else None,
            'read_decode_ms': _percentiles(log.read_ms),
            'detect_ms': _percentiles(log.detect_ms),
            'odometry_ms': _percentiles(log.odom_ms),
            'backend_ms': _percentiles(log.backend_ms),
            **{f'{stage}_ms': _percentiles([v for v in log.stage_ms(stage) if math.isfinite(v)])
               for stage in STAGES}}


def _clouds(detector: LoopDetector) -> dict[str, Any]:
    clouds = detector.clouds
    return {'kept': len(clouds), 'mb': clouds.nbytes / 1e6, 'dropped': clouds.dropped,
            'bytes_per_keyframe': clouds.nbytes / max(len(clouds), 1)}


def _database(detector: LoopDetector) -> dict[str, Any]:
    db = detector.database
    return {'size': db.size, 'bytes': db.stored_bytes, 'allocated_bytes': db.nbytes,
            'bytes_per_scan': db.bytes_per_scan,
            'peak_rss_mb': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}


def _versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    import solid_ros

    out = {'solid_ros': solid_ros.__version__, 'python': platform.python_version()}
    for pkg in ('numpy', 'scipy', 'rosbags', 'matplotlib'):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = 'absent'
    return out
