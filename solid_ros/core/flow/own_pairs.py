"""A keyframe registered to this session's own stored keyframes, started from the odometry.

Two users, both outside loop acceptance: the run's calibration (:func:`calibrate`: a partner a
few metres back along the odometry, and, where the odometry is lost, a triangle with the
partner's own partner; see :mod:`solid_ros.core.verification.calibration`) and the registered
step (:meth:`OwnKeyframes.step`: the previous keyframe, for the pose graph). Both run the
loops' coarse and fine stages from the odometry's relative pose.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from solid_ros.core.candidates.proposal import Proposal
from solid_ros.core.database.clouds import CloudStore
from solid_ros.core.database.descriptors import DescriptorDatabase
from solid_ros.core.descriptor.mount import Mount
from solid_ros.core.geometry import angle_deg, rotation_deg, vector_to_matrix
from solid_ros.core.odometry.track import OdometryPath
from solid_ros.core.verification.calibration import (
    AGREE_DEG,
    AGREE_M,
    PAIR_MAX_BACK,
    PAIR_MAX_TURN_DEG,
    PAIR_PATH_M,
    Calibration,
    closes,
)
from solid_ros.core.verification.judge import judge
from solid_ros.core.verification.measures import PoseMeasures
from solid_ros.core.verification.prepared import Query
from solid_ros.core.verification.verifier import Verification, Verifier

__all__ = ['OwnKeyframes', 'calibrate']

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class OwnKeyframes:
    """This session's stored keyframes, as the registrations to them read them.

    Attributes:
        database: the descriptor database (poses, what is stored).
        clouds: the keyframe clouds.
        seqs: this session's keyframe index -> database sequence number.
        path: the odometry path driven up to each keyframe.
        mount: the sensor's mount (registrations start from levelled poses).
        session_id: this session's id.
    """

    database: DescriptorDatabase
    clouds: CloudStore
    seqs: Mapping[int, int]
    path: OdometryPath
    mount: Mount
    session_id: int

    def partner(self, index: int, pose: FloatArray) -> tuple[int, int, float] | None:
        """The keyframe a few metres back along the odometry (how many keyframes back, its
        sequence number and the path between): the newest one :data:`PAIR_PATH_M` back or
        turned :data:`PAIR_MAX_TURN_DEG` from ``pose``, else the oldest within
        :data:`PAIR_MAX_BACK` keyframes; None when none is stored on the segment."""
        best: tuple[int, int, float] | None = None
        for back in range(1, PAIR_MAX_BACK + 1):
            seq = self.seqs.get(index - back)
            path = self.path.between(index - back, index)
            if seq is None or path is None or not self.database.is_stored(seq):
                break
            other = self.database.pose(seq)
            turned = (other is not None and rotation_deg(
                pose[3:], np.asarray(other[3:], dtype=np.float64)) > PAIR_MAX_TURN_DEG)
            if turned and best is not None:
                break  # the one before shares more of the view
            best = (back, seq, path)
            if path >= PAIR_PATH_M or turned:
                break
        return best

    def register(self, verifier: Verifier, query: Query, pose: FloatArray,
                 seq: int) -> tuple[PoseMeasures, FloatArray] | None:
        """Register ``query`` (a keyframe of this session at odometry ``pose``) to the stored
        keyframe ``seq`` from the odometry's relative pose: the measures of the pose it
        converged to, unjudged, and that start (levelled ``T_mq``); None when the keyframe's
        pose or cloud is gone or the coarse stage refused."""
        pose_j, cloud = self.database.pose(seq), self.clouds.get(seq)
        if pose_j is None or cloud is None:
            return None
        odo = np.linalg.solve(vector_to_matrix(pose_j), vector_to_matrix(pose))
        guess = self.mount.level_pose(np.asarray(odo, dtype=np.float64))
        coarse = verifier.coarse(query, (self.session_id, seq), cloud, [], (guess,))
        if coarse.rejection is not None:
            return None
        return verifier.measure(query, coarse), guess

    def closes(self, verifier: Verifier, query: Query, pose: FloatArray, a: int,
               T_ak: FloatArray, min_overlap: float) -> bool:
        """Whether the query's registration ``T_ak`` to its partner, keyframe ``a``, closes a
        triangle with the partner's own partner ``b``: a->b and query->b registered, both
        converged with ``min_overlap`` (see
        :func:`~solid_ros.core.verification.calibration.closes`)."""
        seq_a = self.seqs.get(a)
        stored = None if seq_a is None else self.database.pose(seq_a)
        cloud_a = None if seq_a is None else self.clouds.get(seq_a)
        if stored is None or cloud_a is None:
            return False
        pose_a: FloatArray = np.asarray(stored, dtype=np.float64)
        partner = self.partner(a, pose_a)
        if partner is None:
            return False
        legs = []
        for q, p in ((verifier.query_of(cloud_a), pose_a), (query, pose)):
            got = self.register(verifier, q, p, partner[1])
            if got is None or not (got[0].converged == 1.0 and got[0].overlap >= min_overlap):
                return False
            legs.append(got[0].T_mq)
        return closes(T_ak, legs[0], legs[1])

    def step(self, verifier: Verifier, proposal: Proposal,
             query: Query) -> tuple[Verification, int] | None:
        """The keyframe (``query``: its cloud prepared) registered to this session's previous
        one from the odometry step, judged as a step (the loops' tests but the single-object
        one): the verification and the previous keyframe's sequence number; None without a
        pose, a cloud or a verified alignment."""
        seq = self.seqs.get(proposal.query_index - 1)
        if (proposal.pose is None or seq is None
                or not self.database.is_stored(seq)):
            return None
        pose_prev = self.database.pose(seq)
        cloud = self.clouds.get(seq)
        if pose_prev is None or cloud is None:
            return None
        step = np.linalg.solve(vector_to_matrix(pose_prev), vector_to_matrix(proposal.pose))
        fine = verifier.fine(query, verifier.coarse(
            query, (self.session_id, seq), cloud, [],
            (self.mount.level_pose(np.asarray(step, dtype=np.float64)),)), step=True)
        return (fine, seq) if fine.verified else None


def calibrate(own: OwnKeyframes, verifier: Verifier, calibration: Calibration,
              proposal: Proposal, query: Query, min_overlap: float) -> None:
    """Register the keyframe (``query``: its cloud prepared) to a partner a few metres back
    along the odometry and teach ``calibration`` what a right alignment and the odometry's
    drift look like here; the verifier then judges by what it learned (``min_overlap``:
    ``verify_min_overlap``)."""
    if (not query.usable or proposal.pose is None
            or not calibration.wants(proposal.query_index)):
        return
    partner = own.partner(proposal.query_index, proposal.pose)
    if partner is None:
        return
    back, seq, path = partner
    if own.database.pose(seq) is None or own.clouds.get(seq) is None:
        return
    got = own.register(verifier, query, proposal.pose, seq)
    if got is None:
        calibration.add(False, math.nan, False, math.nan, path)
    else:
        m, guess = got
        off = np.linalg.solve(guess, m.T_mq)
        error = float(np.linalg.norm(off[:3, 3]))
        fits = m.converged == 1.0 and m.overlap >= min_overlap
        agreed = fits and error < AGREE_M and angle_deg(off) < AGREE_DEG
        # Away from the odometry: right all the same if a triangle of registrations closes
        # (a lost odometry is no judge).
        right = agreed or (fits and calibration.wants_triangle(proposal.query_index)
                           and own.closes(verifier, query, proposal.pose,
                                          proposal.query_index - back, m.T_mq, min_overlap))
        # The drift only from poses the judge stands by as loops: a room aliases a few
        # metres off, a street seen from a car slides along itself (riv281: 2-12 m).
        verified = judge(m, verifier.bars, 'fine').verified
        calibration.add(right, m.conflict if right else math.nan, verified, error, path,
                        agreed)
    verifier.learn(calibration.learned)
