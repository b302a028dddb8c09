"""What one replay produced: :class:`ReplayResult`."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from solid_ros.core.backend.mapping import MapCloud
from solid_ros.core.config import SolidConfig
from solid_ros.core.results import LoopCandidate
from solid_ros.tools.evaluation import Evaluation
from solid_ros.tools.loops import LoopRecord
from solid_ros.tools.pipeline import BagInputs, ScanLog, published_best
from solid_ros.tools.scoring import Scores
from solid_ros.tools.trajectory import Trajectory

__all__ = ['ReplayResult']


@dataclass
class ReplayResult:
    """Everything one replay produced.

    Attributes:
        inputs: what was read from the bag (path, topics, odometry).
        config: the detector settings.
        log: what the run gave, keyframe by keyframe.
        scores: its scores against the reference poses (empty without them).
        report: the JSON report (also written to ``out_dir/report.json``).
        wall_sec: time spent reading, decoding and detecting.
        trajectory: the keyframes' odometry and corrected poses.
        map: the keyframe clouds at their corrected poses (None: not asked for).
        files: files written.
    """

    inputs: BagInputs
    config: SolidConfig
    log: ScanLog
    scores: Scores
    report: dict[str, Any]
    wall_sec: float
    trajectory: Trajectory
    map: MapCloud | None = None
    files: list[Path] = field(default_factory=list)

    @property
    def bag(self) -> Path:
        """The bag replayed."""
        return self.inputs.path

    @property
    def topic(self) -> str:
        """The cloud topic replayed."""
        return self.inputs.topic

    @property
    def messages(self) -> int:
        """Cloud messages read."""
        return self.log.messages

    @property
    def skipped(self) -> int:
        """Clouds skipped (undecodable or refused by the detector)."""
        return len(self.log.skipped)

    @property
    def keyframes(self) -> int:
        """Keyframes stored."""
        return len(self.log.keyframes)

    @property
    def candidates(self) -> list[LoopCandidate]:
        """Published loops in order (what the node would publish)."""
        return self.log.candidates

    @property
    def best(self) -> list[LoopCandidate | None]:
        """Per keyframe, its best match accepted or not (None: no eligible scan)."""
        return [res.best for res in self.log.results]

    @property
    def accepted(self) -> npt.NDArray[np.bool_]:
        """Per keyframe, whether its best match was published."""
        return np.asarray([published_best(res) for res in self.log.results], dtype=bool)

    @property
    def attempts(self) -> list[list[LoopCandidate]]:
        """Per keyframe, every candidate it looked at (published or not)."""
        return [list(res.attempts) for res in self.log.results]

    @property
    def stamps_ns(self) -> npt.NDArray[np.int64]:
        """Per keyframe, its stamp."""
        return np.asarray([res.stamp_ns for res in self.log.results], dtype=np.int64)

    @property
    def reference(self) -> npt.NDArray[np.float64] | None:
        """Per keyframe, the reference pose (NaN where unknown), or None."""
        return self.scores.reference

    @property
    def evaluation(self) -> Evaluation | None:
        """Descriptor metrics when reference poses were available."""
        return self.scores.evaluation

    @property
    def records(self) -> list[LoopRecord]:
        """The attempts scored against the reference poses (empty without them)."""
        return self.scores.records

    @property
    def metrics(self) -> dict[str, Any] | None:
        """``report['metrics']`` (None without reference poses)."""
        return self.report.get('metrics')

    @property
    def scans_per_sec(self) -> float:
        """End-to-end throughput (read + decode + detect) over decoded scans."""
        return (self.messages - self.skipped) / self.wall_sec if self.wall_sec > 0 else 0.0
