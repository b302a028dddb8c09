"""What the detector's stages share: its settings, the stores and this session's keyframes.

The descriptor stage (:mod:`solid_ros.core.flow.proposer`) writes each keyframe's database
sequence number, view centre and odometry path; the verification stage
(:mod:`solid_ros.core.flow.verify_stage`, :mod:`solid_ros.core.flow.acceptance`) reads them,
on another thread in the node. :class:`~solid_ros.core.flow.detector.LoopDetector` holds the
one :class:`DetectorState` they all see, so a reconfiguration or a reset reaches every stage.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from solid_ros.core.candidates.views import KeyframeViews
from solid_ros.core.config import SolidConfig
from solid_ros.core.database.clouds import CloudStore
from solid_ros.core.database.descriptors import DescriptorDatabase
from solid_ros.core.descriptor.mount import Mount
from solid_ros.core.flow.own_pairs import OwnKeyframes
from solid_ros.core.odometry.track import OdometryPath
from solid_ros.core.verification.calibration import Calibration
from solid_ros.core.verification.judge import Bars
from solid_ros.core.verification.judge import bars as judge_bars
from solid_ros.core.verification.verifier import Verifier

__all__ = ['DetectorState']


@dataclass
class DetectorState:
    """The detector's shared state (mutable: the stages write into it).

    Attributes:
        config: current settings (replaced by a reconfiguration).
        database: the descriptor database (replaced on reset).
        clouds: keyframe clouds by database sequence number.
        verifier: the registration procedure; None without ``verify``.
        mount: the sensor's mount (levelling).
        path: path driven up to each own keyframe; a jump (reset) starts a new segment.
        calibration: what right alignments and the odometry's drift look like on this run.
        own_seqs: database sequence number of each own keyframe, by index: written by the
            descriptor stage, read by verification (where the database's own map may move).
        views: view centre (keyframe cloud centroid, sensor frame) of each own keyframe, by
            index, for candidates by what they saw (:mod:`solid_ros.core.candidates.position`).
    """

    config: SolidConfig
    database: DescriptorDatabase
    clouds: CloudStore
    verifier: Verifier | None
    mount: Mount
    path: OdometryPath
    calibration: Calibration = field(default_factory=Calibration)
    own_seqs: dict[int, int] = field(default_factory=dict)
    views: KeyframeViews = field(init=False)

    def __post_init__(self) -> None:
        self.views = KeyframeViews(self.config.capacity)

    @property
    def bars(self) -> Bars:
        """The judge's thresholds now: the settings and what the run learned."""
        if self.verifier is not None:
            return self.verifier.bars
        return judge_bars(self.config, self.calibration.learned)

    @property
    def own(self) -> OwnKeyframes:
        """This session's stored keyframes for the registrations to them (a view: the
        database is replaced on reset and load)."""
        return OwnKeyframes(self.database, self.clouds, self.own_seqs, self.path,
                            self.mount, self.config.session_id)
