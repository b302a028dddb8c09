"""Point cloud registration for loop verification: small_gicp's GICP (coarse stage) and
voxelised GICP (fine stage) between a prepared query and source (:mod:`.prepared`).

Registration returns ``T_qm`` (``p_query = T_qm p_match``); callers invert it for the published
``T = T_mq``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from solid_ros.core.geometry import rot_z
from solid_ros.core.verification.prepared import (
    MIN_POINTS,
    Query,
    RegistrationSettings,
    Source,
    load_small_gicp,
)

__all__ = ['Alignment', 'align_coarse', 'align_fine', 'settled']

FloatArray = npt.NDArray[np.float64]

_COARSE_ITERATIONS = 15  # the coarse stage only has to land in the fine stage's basin
_GOOD_COARSE = 0.5  # coarse overlap that ends the search over heading hypotheses
# Coarse convergence: 0.5 deg / 1 cm steps are far inside a coarse voxel (small_gicp's
# defaults, 0.1 deg / 1 mm, kept 80 % of coarse runs going to the iteration cap).
_COARSE_ROTATION_EPS = math.radians(0.5)
_COARSE_TRANSLATION_EPS = 0.01
# A fine run not converged after _FIRST_ITERATIONS is resumed this long; a pose that moves less
# than this (fine voxels, degrees) meanwhile is stationary: converged (see align_fine).
_FIRST_ITERATIONS = 15
_RESUME_ITERATIONS = 5
_STATIONARY_VOXELS = 0.1
_STATIONARY_DEG = 0.5
# Fine runs end at 5 mm steps, not small_gicp's 1 mm, which took 40 % more iterations on
# hku1: the steps shrink fast, so the pose still ends within a millimetre (bench_nees: the
# simulated loops' median error 1-3 mm and their NEES unchanged). No coarser: a step criterion
# does not bound the distance to the minimum, and on weak geometry a 2 cm step stopped a
# restart 0.54 m short of it (test_verifier's single corner: refused as unstable).
_TRANSLATION_EPS = 0.005


@dataclass(frozen=True)
class Alignment:
    """Result of one registration.

    Attributes:
        T_qm: 4x4 transform with ``p_query = T_qm p_match``.
        converged: small_gicp's convergence flag.
        iterations: iterations run.
        coarse_overlap: (coarse stage) fraction of the candidate's coarse structure points
            within half a coarse voxel of the query's after alignment; NaN for fine results.
        hypothesis: index of the start that won (coarse stage: the guesses first, then the
            heading hypotheses), else -1.
        start_z: (coarse stage) the winning start's height, kept where the ground does not
            observe it (:func:`settled`).
    """

    T_qm: FloatArray
    converged: bool
    iterations: int
    coarse_overlap: float = math.nan
    hypothesis: int = -1
    start_z: float = 0.0


def align_coarse(query: Query, source: Source, yaws: list[float],
                 settings: RegistrationSettings,
                 guesses: Sequence[FloatArray] = (), settle: bool = True) -> Alignment | None:
    """Register the structure of ``source`` to the query from each start.

    The starts are the ``guesses`` (full poses, e.g. the pose graph's), then the heading
    hypotheses (rotations about z, no translation). They are tried in order; once one reaches
    a coarse overlap of ``_GOOD_COARSE`` the rest are skipped (the first start is usually
    right).

    Args:
        query: the prepared query.
        source: the prepared candidate.
        yaws: heading hypotheses in the detector's convention (``p_match = Rz(yaw) p_query``).
        settings: registration settings.
        guesses: 4x4 ``T_mq`` (``p_match = T_mq p_query``) to start from before the yaws.

    The kept pose's height is then set on the ground (:func:`settled`, unless ``settle`` is
    False: the verifier settles only the alignments that go on to the fine stage, a quarter of
    them on hku1): upright structure does not pin it.

    Returns:
        The start with the largest coarse overlap (``hypothesis`` is its index: guesses
        first); None when either cloud has too little structure to register.
    """
    starts = [np.linalg.inv(np.asarray(g, dtype=np.float64)) for g in guesses]
    for yaw in yaws:
        init = np.eye(4)
        init[:3, :3] = rot_z(-yaw)  # T_qm = inverse of the hypothesis Rz(yaw)
        starts.append(init)
    if query.coarse.size() < MIN_POINTS or source.coarse.size() < MIN_POINTS or not starts:
        return None
    sg = load_small_gicp()
    best: Alignment | None = None
    src_pts = source.coarse.points()[:, :3]
    for k, init in enumerate(starts):
        res = sg.align(query.coarse, source.coarse, query.coarse_tree, init,
                       registration_type='GICP',
                       max_correspondence_distance=settings.coarse_distance,
                       max_iterations=min(settings.max_iterations, _COARSE_ITERATIONS),
                       rotation_epsilon=_COARSE_ROTATION_EPS,
                       translation_epsilon=_COARSE_TRANSLATION_EPS)
        T = np.asarray(res.T_target_source, dtype=np.float64)
        _, sq = query.coarse_tree.batch_nearest_neighbor_search(src_pts @ T[:3, :3].T + T[:3, 3])
        overlap = float(np.mean(np.asarray(sq) < (0.5 * settings.coarse_voxel) ** 2))
        if best is None or overlap > best.coarse_overlap:
            best = Alignment(T, bool(res.converged), int(res.iterations), overlap, k,
                             float(init[2, 3]))
        if overlap >= _GOOD_COARSE:
            break
    return settled(query, source, best, settings) if settle and best is not None else best


def settled(query: Query, source: Source, alignment: Alignment,
            settings: RegistrationSettings) -> Alignment:
    """A coarse alignment with its height set on the ground (:func:`_settle_height`)."""
    return replace(alignment, T_qm=_settle_height(query, source, alignment.T_qm, settings,
                                                  alignment.start_z))


def _settle_height(query: Query, source: Source, T_qm: FloatArray,
                   settings: RegistrationSettings, start_z: float) -> FloatArray:
    """``T_qm`` moved vertically by the median height step from the candidate's horizontal
    surfaces (its points that are not structure: mostly ground) to the nearest of the query's
    within the coarse correspondence distance, twice.

    Upright structure leaves the height free, so the few edges it has decide it: where cars
    had moved between the scans, the coarse stage moved the graph's guess (0.15 m off in
    height) by 0.6-1.5 m up or down, beyond the fine stage's reach (two voxels), and the
    ground could not pull it back. The median ignores the odd roof or table top. With fewer
    than ``MIN_POINTS`` pairs (no ground in one of the views: a facade filling it) nothing
    observes the height, and the start's (``start_z``: the graph's guess, else level) stays.
    """
    ground = source.points[source.n_struct:]
    tree = query.ground_tree
    T = np.array(T_qm, dtype=np.float64)
    for k in range(2):
        near = np.zeros(0, dtype=bool)
        if tree is not None and len(ground) >= MIN_POINTS:
            moved = ground @ T[:3, :3].T + T[:3, 3]
            idx, sq = tree.batch_nearest_neighbor_search(moved)
            near = np.asarray(sq) < settings.coarse_distance ** 2
        if int(near.sum()) < MIN_POINTS:
            if k == 0:
                T[2, 3] = start_z
            break
        rows = np.asarray(idx, dtype=np.intp)[near]
        T[2, 3] += float(np.median(query.ground[rows, 2] - moved[near, 2]))
    return T


def align_fine(query: Query, source: Source, T_qm: FloatArray,
               settings: RegistrationSettings) -> Alignment:
    """Refine ``T_qm`` with voxelised GICP against the query's voxel map (all points).

    A run that ends without small_gicp's convergence flag after ``_FIRST_ITERATIONS`` is
    continued for ``_RESUME_ITERATIONS``; when that moves the pose by less than
    ``_STATIONARY_VOXELS`` fine voxels and ``_STATIONARY_DEG`` degrees, the pose is stationary
    and counts as converged. Small near-field clouds end that way: the optimiser keeps refusing
    steps at the optimum (its damping grows, the pose does not move) or alternates between two
    correspondence sets a centimetre apart, so its step-size criterion is never met. A pose
    still moving goes on from there for the rest of ``max_iterations`` and is checked the same
    way at its end. (Checked only at the iteration limit, the stationary runs, a sixth of
    hku1's, ran to it: a third of the fine stage's registration time.)
    """
    sg = load_small_gicp()
    fine, _ = source.fine()

    def run(T: FloatArray, iterations: int) -> tuple[FloatArray, bool, int]:
        res = sg.align(query.vmap, fine, T, max_iterations=iterations,
                       max_correspondence_distance=settings.neighbour_distance,
                       translation_epsilon=_TRANSLATION_EPS)
        return (np.asarray(res.T_target_source, dtype=np.float64), bool(res.converged),
                int(res.iterations))

    first = min(settings.max_iterations, _FIRST_ITERATIONS)
    T, converged, iterations = run(np.asarray(T_qm, dtype=np.float64), first)
    for rest in (settings.max_iterations - first - _RESUME_ITERATIONS, 0):
        if converged:
            break
        moved, _, more = run(T, _RESUME_ITERATIONS)
        iterations += more
        step = np.linalg.solve(T, moved)
        cos = min(max((float(np.trace(step[:3, :3])) - 1.0) / 2.0, -1.0), 1.0)
        converged = (float(np.linalg.norm(step[:3, 3])) <= _STATIONARY_VOXELS * settings.voxel
                     and math.degrees(math.acos(cos)) <= _STATIONARY_DEG)
        if converged or rest <= 0:
            break
        T, converged, more = run(moved, rest)
        iterations += more
    return Alignment(T, converged, iterations)
