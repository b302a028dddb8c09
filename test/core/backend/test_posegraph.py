"""The pose-graph back end on synthetic square drives with drifting odometry."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from drifting_odometry import Drift, drifting_odometry, square

from solid_ros.core.backend.noise import rotation_angle
from solid_ros.core.config import SolidConfig
from solid_ros.core.database.descriptors import DescriptorDatabase
from solid_ros.core.database.persistence import read_map_poses, save_database
from solid_ros.core.geometry import matrix_to_vector, rot_z
from solid_ros.core.odometry.track import OdomSample
from solid_ros.core.results import LoopCandidate, ScanResult

pytest.importorskip('gtsam', reason='gtsam is not installed')

from solid_ros.core.backend.posegraph import BackendState, PoseGraph  # noqa: E402
from solid_ros.core.backend.solver import GraphSolver  # noqa: E402

CFG = SolidConfig(backend=True)
LOOP_COV = tuple(np.diag([1e-4] * 3 + [1e-6] * 3).ravel())
SEC = 10**9



def loop(ref: np.ndarray, q: int, m: int, session: int = 0, T: Any = None,
         cov: tuple[float, ...] = LOOP_COV, ref_m: np.ndarray | None = None) -> LoopCandidate:
    """A loop from keyframe q to keyframe m (of ``ref_m``, default ``ref``): the true
    relative pose unless ``T`` is given."""
    match = (ref if ref_m is None else ref_m)[m]
    rel = np.linalg.solve(match, ref[q]) if T is None else T
    return LoopCandidate(q, m, q * SEC, m * SEC, session, 0.1, 0.0, 1.0, True,
                         tuple(matrix_to_vector(rel)), covariance=cov, reason='verified')


def feed(pg: PoseGraph, odo: np.ndarray, loops: dict[int, tuple[LoopCandidate, ...]] | None
         = None, covs: list[Any] | None = None) -> list[BackendState]:
    out = []
    for k, T in enumerate(odo):
        res = ScanResult(k * SEC, True, k, matrix_to_vector(T), (loops or {}).get(k, ()))
        sample = OdomSample(k * SEC, T, None if covs is None else covs[k])
        out.append(pg.update(res, sample))
    return out


def end_error(pg: PoseGraph, ref: np.ndarray) -> float:
    poses = pg.poses()
    last = max(poses)
    return float(np.linalg.norm(poses[last][:3, 3] - ref[last][:3, 3]))


def ate(pg: PoseGraph, ref: np.ndarray) -> float:
    poses = pg.poses()
    return float(np.sqrt(np.mean([np.sum((poses[k][:3, 3] - ref[k][:3, 3]) ** 2)
                                  for k in poses])))


def test_one_loop_corrects_a_drifting_square() -> None:
    ref = square(170)
    odo = drifting_odometry(ref, Drift())
    pg = PoseGraph(CFG)
    states = feed(pg, odo, {165: (loop(ref, 165, 5),)})
    assert [o.reason for o in states[165].loops] == ['added']
    odo_err = float(np.linalg.norm(odo[-1, :3, 3] - ref[-1, :3, 3]))
    assert odo_err > 3.0
    assert end_error(pg, ref) < odo_err / 5.0
    # map->odom of the newest keyframe turns its odometry pose into its corrected pose.
    np.testing.assert_allclose(pg.correction() @ odo[-1], pg.poses()[169], atol=1e-6)
    assert states[-1].pose is not None
    np.testing.assert_allclose(states[-1].pose, pg.poses()[169], atol=1e-6)


def test_latest_covariance_is_ros_order_and_grows_with_the_drive() -> None:
    ref = square(120)
    states = feed(PoseGraph(CFG), drifting_odometry(ref, Drift()))
    early, late = states[10].covariance, states[119].covariance
    assert early is not None and late is not None
    for cov in (early, late):
        np.testing.assert_allclose(cov, cov.T, atol=1e-12)
        assert np.all(np.linalg.eigvalsh(cov) > 0.0)
        # Translation first: metres^2 of 5 cm per sqrt-metre dwarf radians^2.
        assert np.diag(cov)[:3].min() > 10.0 * np.diag(cov)[3:].max()
    assert np.trace(late[:3, :3]) > 5.0 * np.trace(early[:3, :3])


def test_relative_covariance_is_what_two_keyframes_do_not_share() -> None:
    ref = square(120)
    pg = PoseGraph(CFG)
    states = feed(pg, drifting_odometry(ref, Drift()))
    own = states[119].covariance
    assert own is not None
    # From the first keyframe (held by the prior) it is the newest one's own marginal.
    first = pg.relative_covariance(0, 119)
    assert first is not None
    np.testing.assert_allclose(first, own, rtol=0.05, atol=1e-9)
    # Between neighbours it is one odometry step, not the whole drive's drift.
    near = pg.relative_covariance(118, 119)
    assert near is not None
    np.testing.assert_allclose(near, near.T, atol=1e-12)
    assert np.trace(near[:3, :3]) < 0.05 * np.trace(own[:3, :3])
    mid = pg.relative_covariance(60, 119)
    assert mid is not None
    assert np.trace(near[:3, :3]) < np.trace(mid[:3, :3]) < np.trace(own[:3, :3])
    assert pg.relative_covariance(500, 119) is None  # not in the graph


def test_bad_odometry_covariance_falls_back_to_the_model_with_a_throttled_warning() -> None:
    ref = square(60)
    odo = drifting_odometry(ref, Drift())
    nan = np.full((6, 6), math.nan)
    states = feed(PoseGraph(CFG), odo, covs=[nan] * len(odo))
    warnings = [e for s in states for e in s.events if e.kind == 'odom_covariance']
    assert len(warnings) == 6  # keyframes 1 s apart: one per 10 s
    assert 'times since the last warning' in warnings[1].message
    plain = feed(PoseGraph(CFG), odo)  # the model: same factors, same poses
    for a, b in zip(states, plain):
        assert a.pose is not None and b.pose is not None
        np.testing.assert_allclose(a.pose, b.pose, atol=1e-9)


def test_odometry_jump_starts_a_segment_that_a_loop_ties_back() -> None:
    ref = square(170)
    odo = drifting_odometry(ref, Drift())
    reset = np.eye(4)
    reset[:3, 3] = [-300.0, 40.0, 0.0]
    odo[80:] = reset @ odo[80:]  # the odometry resets 300 m away at keyframe 80
    pg = PoseGraph(CFG)
    states = feed(pg, odo, {165: (loop(ref, 165, 5),)})
    segments = [e for s in states for e in s.events if e.kind == 'segment']
    assert len(segments) == 1 and 'keyframes 79 and 80' in segments[0].message
    assert states[79].segment == 0 and states[80].segment == 1
    # Until a loop ties it, map->odom stays where it was: the corrected pose jumps with the
    # odometry.
    c79, c80 = states[79].correction, states[80].correction
    assert float(np.linalg.norm(c80 - c79)) < 1e-6 * max(1.0, float(np.linalg.norm(c79)))
    # The loop places the second segment where it belongs (not gated: nothing tied it yet).
    assert [o.reason for o in states[165].loops] == ['tie']
    assert [e.kind for e in states[165].events] == ['tie']
    assert end_error(pg, ref) < 2.0
    assert [k.segment for k in pg.keyframes()][78:82] == [0, 0, 1, 1]


def test_an_odometry_source_reset_starts_a_segment_even_without_a_jump() -> None:
    ref = square(120)
    odo = drifting_odometry(ref, Drift())
    pg = PoseGraph(CFG)
    states = []
    for k, T in enumerate(odo):  # a registration-based source lost track at keyframe 60
        res = ScanResult(k * SEC, True, k, matrix_to_vector(T))
        sample = OdomSample(k * SEC, T, segment=int(k >= 60),
                            reason='cloud did not register' if k == 60 else None)
        states.append(pg.update(res, sample))
    (event,) = [e for s in states for e in s.events if e.kind == 'segment']
    assert 'odometry reset (cloud did not register)' in event.message
    assert 'keyframes 59 and 60' in event.message
    assert [s.segment for s in states[58:62]] == [0, 0, 1, 1]


def test_gtsam_failure_rebuilds_the_graph_and_keeps_the_loop(
        monkeypatch: pytest.MonkeyPatch) -> None:
    ref = square(170)
    odo = drifting_odometry(ref, Drift())
    original = GraphSolver.isam_update
    calls = {'n': 0}

    def failing(self: GraphSolver, graph: Any = None, values: Any = None) -> None:
        calls['n'] += 1
        if graph is not None and graph.size() and any(
                r.kind == 'loop' for r in self.records[-graph.size():]) and calls['n'] < 1000:
            calls['n'] = 1000
            raise RuntimeError('Indeterminant linear system detected near variable x165')
        original(self, graph, values)

    monkeypatch.setattr(GraphSolver, 'isam_update', failing)
    pg = PoseGraph(CFG)
    states = feed(pg, odo, {165: (loop(ref, 165, 5),)})
    rebuilt = [e for e in states[165].events if e.kind == 'rebuild']
    assert len(rebuilt) == 1 and 'Indeterminant' in rebuilt[0].message
    assert [o.reason for o in states[165].loops] == ['added'] and pg.rebuilds == 1
    assert end_error(pg, ref) < 2.0


def test_loops_gtsam_cannot_solve_are_dropped_not_fatal(
        monkeypatch: pytest.MonkeyPatch) -> None:
    ref = square(170)
    odo = drifting_odometry(ref, Drift())
    original_rebuild = GraphSolver._rebuild

    def update(self: GraphSolver, graph: Any = None, values: Any = None) -> None:
        if any(r.kind == 'loop' and not r.dropped for r in self.records):
            raise RuntimeError('Indeterminant linear system')
        if graph is None:
            self._isam.update()
        else:
            self._isam.update(graph, values)

    def rebuild(self: GraphSolver) -> bool:
        if any(r.kind == 'loop' and not r.dropped for r in self.records):
            return False
        return original_rebuild(self)

    monkeypatch.setattr(GraphSolver, 'isam_update', update)
    monkeypatch.setattr(GraphSolver, '_rebuild', rebuild)
    pg = PoseGraph(CFG)
    states = feed(pg, odo, {165: (loop(ref, 165, 5),)})
    assert [o.reason for o in states[165].loops] == ['failed']
    assert 'dropped' in states[165].events[-1].message
    assert states[-1].added and len(pg.poses()) == 170


def _session0(tmp_path: Path) -> tuple[np.ndarray, dict[tuple[int, int], Any]]:
    """A corrected lap of the square saved as a database with map poses; returns the
    reference poses and the map read back."""
    ref = square(170)
    pg = PoseGraph(CFG)
    feed(pg, drifting_odometry(ref, Drift()), {k: (loop(ref, k, k - 160),)
                                              for k in range(160, 170)})
    db = DescriptorDatabase(CFG)
    rng = np.random.default_rng(0)
    for k in range(170):
        db.add(rng.random(CFG.num_range), rng.random(CFG.num_angle), k * SEC, None)
    path = save_database(db, tmp_path / 'map.npz', map_poses=pg.map_poses())
    prior = read_map_poses(path)
    assert prior.source == 'map' and len(prior.poses) == 170
    np.testing.assert_allclose(prior.poses[(0, 7)], pg.poses()[7], atol=1e-9)
    return ref, prior.poses


def test_relocalises_in_a_saved_map_with_offset_odometry(tmp_path: Path) -> None:
    ref, prior = _session0(tmp_path)
    offset = np.eye(4)
    offset[:3, :3] = rot_z(math.pi / 2)
    offset[:3, 3] = [50.0, 0.0, 0.0]
    ref1 = ref[:120]
    odo1 = drifting_odometry(ref1, Drift(seed=1), start=offset @ ref1[0])
    cfg = CFG.replace(session_id=1)
    pg = PoseGraph(cfg, prior_map=prior)
    loops = {k: (loop(ref1, k, k, session=0, ref_m=ref),) for k in (3, 30, 60, 90, 110)}
    states = feed(pg, odo1, loops)
    np.testing.assert_allclose(states[2].correction, np.eye(4), atol=1e-9)  # map = odom yet
    anchor = [e for e in states[3].events if e.kind == 'anchor']
    assert len(anchor) == 1 and pg.anchored
    assert [o.reason for o in states[3].loops] == ['anchor']
    jump = states[3].correction
    assert float(np.linalg.norm(jump[:3, 3])) > 40.0  # map->odom moved by the offset
    assert [o.reason for k in (30, 60, 90, 110) for o in states[k].loops] == ['added'] * 4
    poses = pg.poses()
    for k in range(3, 120):
        saved = prior[(0, k)]
        assert float(np.linalg.norm(poses[k][:3, 3] - saved[:3, 3])) < 0.3, k
        assert math.degrees(rotation_angle(np.linalg.solve(saved, poses[k]))) < 1.0, k
    # Saving again keeps the loaded map's poses and adds this session's.
    both = pg.map_poses()
    assert (0, 169) in both and (1, 119) in both


def _tied_drive() -> tuple[np.ndarray, np.ndarray, dict[int, tuple[LoopCandidate, ...]]]:
    """Two laps of the square; every 4th keyframe of the second lap loops to the first."""
    ref = square(320)
    odo = drifting_odometry(ref, Drift())
    return ref, odo, {k: (loop(ref, k, k - 160),) for k in range(162, 320, 4)}


def _false(ref: np.ndarray, q: int, m: int) -> LoopCandidate:
    """A loop from q to m that puts q 20 m from where it is, with a 1 cm covariance."""
    shift = np.eye(4)
    shift[:3, 3] = [14.0, 14.0, 0.0]
    return loop(ref, q, m, T=np.linalg.solve(ref[m], shift @ ref[q]))


def test_a_false_loop_and_a_burst_of_five_are_refused_where_the_map_is_tied() -> None:
    ref, odo, loops = _tied_drive()
    base = PoseGraph(CFG)
    feed(base, odo, loops)
    single = dict(loops)
    single[251] = (_false(ref, 251, 91),)
    pg = PoseGraph(CFG)
    states = feed(pg, odo, single)
    assert [o.reason for o in states[251].loops] == ['gate']
    assert states[251].loops[0].sigmas > CFG.backend_loop_refuse
    assert abs(ate(pg, ref) / ate(base, ref) - 1.0) < 0.01
    burst = dict(loops)
    for k in range(271, 276):
        burst[k] = (_false(ref, k, k - 160),)
    pg = PoseGraph(CFG)
    states = feed(pg, odo, burst)
    assert [o.reason for k in range(271, 276) for o in states[k].loops] == ['gate'] * 5
    assert abs(ate(pg, ref) / ate(base, ref) - 1.0) < 0.01


def test_a_lone_surprising_loop_waits_and_expires_a_second_one_confirms() -> None:
    ref = square(200)
    odo = drifting_odometry(ref, Drift())
    cfg = CFG.replace(backend_loop_gate=0.5)  # every loop here is surprising
    pg = PoseGraph(cfg)
    states = feed(pg, odo, {165: (_false(ref, 165, 5),)})
    assert [o.reason for o in states[165].loops] == ['pending']
    expired = [e for s in states for e in s.events if e.kind == 'unconfirmed']
    assert len(expired) == 1 and pg.counts['unconfirmed'] == 1
    np.testing.assert_allclose(pg.poses()[199], odo[199], atol=1e-6)  # nothing moved
    pg = PoseGraph(cfg)
    states = feed(pg, odo, {165: (loop(ref, 165, 5),), 166: (loop(ref, 166, 6),)})
    assert [o.reason for o in states[165].loops] == ['pending']
    assert [o.reason for o in states[166].loops] == ['added']
    assert any(e.kind == 'confirmed' for e in states[166].events)
    assert len(pg.loops) == 2 and end_error(pg, ref) < 2.0


def test_two_loops_of_one_keyframe_that_disagree_are_not_taken_together() -> None:
    ref = square(170)
    odo = drifting_odometry(ref, Drift())
    shift = np.eye(4)
    shift[:3, 3] = [1.0, 1.0, 0.0]  # 1.4 m off: within the drift, far from the true loop
    wrong = loop(ref, 165, 5, T=np.linalg.solve(ref[5], shift @ ref[165]))
    pg = PoseGraph(CFG)
    states = feed(pg, odo, {165: (loop(ref, 165, 5), wrong)})
    assert all(o.sigmas < CFG.backend_loop_gate for o in states[165].loops)
    assert sorted(o.reason for o in states[165].loops) == ['added', 'pending']
    assert len(pg.loops) == 1


def test_what_cannot_become_a_factor_is_said() -> None:
    ref = square(80)
    odo = drifting_odometry(ref, Drift())
    pg = PoseGraph(CFG)
    nan_cov = loop(ref, 70, 5, cov=(math.nan,) * 36)
    other = loop(ref, 71, 5, session=7)
    ahead = loop(ref, 72, 79)
    states = feed(pg, odo, {70: (nan_cov,), 71: (other,), 72: (ahead,)})
    assert [s.loops[0].reason for s in states[70:73]] == [
        'no_covariance', 'unknown_session', 'unknown_keyframe']
    # No pose at all: not added, its loops skipped, one line; a repeated index is ignored.
    st = pg.update(ScanResult(90 * SEC, True, 80, None, (loop(ref, 79, 5),)))
    assert not st.added and st.loops[0].reason == 'no_pose'
    assert [e.kind for e in st.events] == ['no_pose']
    st = pg.update(ScanResult(91 * SEC, True, 50, matrix_to_vector(odo[50])))
    assert not st.added and [e.kind for e in st.events] == ['ignored']
    assert not pg.update(ScanResult(92 * SEC)).added  # gated out: nothing happens


def test_keyframes_carry_what_rebuilds_the_chain() -> None:
    ref = square(50)
    odo = drifting_odometry(ref, Drift())
    pg = PoseGraph(CFG)
    feed(pg, odo)
    kfs = pg.keyframes()
    assert [k.index for k in kfs] == list(range(50))
    assert [k.stamp_ns for k in kfs] == [k * SEC for k in range(50)]
    np.testing.assert_allclose(np.array([k.odom for k in kfs]), odo)
    # Without loops the corrected chain is the odometry chain itself.
    np.testing.assert_allclose(np.array([k.pose for k in kfs]), odo, atol=1e-6)
    pg.reset()
    assert pg.keyframes() == [] and np.array_equal(pg.correction(), np.eye(4))


def test_keyframe_arrays_are_the_keyframes_exactly() -> None:
    ref = square(170)
    odo = drifting_odometry(ref, Drift())
    pg = PoseGraph(CFG)
    assert [len(a) for a in pg.keyframe_arrays()] == [0, 0, 0, 0]
    feed(pg, odo, {165: (loop(ref, 165, 5),)})  # 170 rows: the arrays grew past 64 and 128
    indices, stamps, poses, odom = pg.keyframe_arrays()
    kfs = pg.keyframes()
    np.testing.assert_array_equal(indices, [k.index for k in kfs])
    np.testing.assert_array_equal(stamps, [k.stamp_ns for k in kfs])
    np.testing.assert_array_equal(odom, [k.odom for k in kfs])
    np.testing.assert_array_equal(poses, [k.pose for k in kfs])  # bit for bit
    # They are copies: the graph's own rows stay as they were.
    odom[0] = 0.0
    np.testing.assert_array_equal(pg.keyframe_arrays()[3][0], odo[0])
    pg.reset()
    assert [len(a) for a in pg.keyframe_arrays()] == [0, 0, 0, 0]


def test_a_long_loop_free_chain_stays_solvable() -> None:
    # 1,700 one-metre steps sideways while turning: the heading's uncertainty swings lever arms
    # of a kilometre; a Cholesky iSAM2 called this indeterminant at keyframe 1,657.
    pg = PoseGraph(CFG)
    for k in range(1700):
        T = np.eye(4)
        T[:3, :3] = rot_z(k * 0.01)
        T[0, 3] = float(k)
        state = pg.update(ScanResult(k * SEC, True, k, matrix_to_vector(T)),
                          OdomSample(k * SEC, T))
    assert state.added and state.covariance is not None and pg.rebuilds == 0
    assert np.all(np.isfinite(state.covariance))


STEPS = CFG.replace(backend_step_registration='on')


def _step(ref: np.ndarray, k: int, cov: tuple[float, ...] = LOOP_COV,
          match: int | None = None) -> LoopCandidate:
    """Keyframe k registered to keyframe ``match`` (default k - 1): the true step."""
    m = k - 1 if match is None else match
    rel = np.linalg.solve(ref[m], ref[k])
    return LoopCandidate(k, m, k * SEC, m * SEC, 0, math.nan, 0.0, math.nan, True,
                         tuple(matrix_to_vector(rel)), covariance=cov, reason='verified',
                         source='step')


def test_registered_steps_pull_back_an_odometry_that_ran_away() -> None:
    ref = square(60)
    odo = ref.copy()
    kick = np.eye(4)
    kick[:3, 3] = [0.0, 0.8, 0.0]  # KISS-ICP in a corridor: 0.8 m sideways at keyframe 30
    odo[30:] = np.einsum('ij,kjl->kil', ref[29] @ kick @ np.linalg.inv(ref[29]), ref[30:])
    # Registered as well as the odometry's model says it drives: the graph must still not
    # split the difference.
    cov = tuple(np.diag([0.05 ** 2] * 3 + [math.radians(0.3) ** 2] * 3).ravel())
    steps = {k: _step(ref, k, cov) for k in range(1, 60)}
    steps[45] = _step(ref, 45, cov, match=43)  # not to the previous keyframe: no factor
    del steps[50]  # no registration: the odometry alone
    pg, plain = PoseGraph(STEPS), PoseGraph(CFG)
    online = []
    for k, T in enumerate(odo):
        res = ScanResult(k * SEC, True, k, matrix_to_vector(T), step=steps.get(k))
        online.append(pg.update(res, OdomSample(k * SEC, T)).pose)
        plain.update(ScanResult(k * SEC, True, k, matrix_to_vector(T)), OdomSample(k * SEC, T))
    assert pg.steps == 57 and plain.steps == 0
    assert ate(plain, ref) > 0.5
    assert ate(pg, ref) < 0.1  # the odometry factor is robust where a registered step exists
    # Already online, at the keyframe of the runaway (iSAM2 starts it from the registered step).
    assert float(np.linalg.norm(online[30][:3, 3] - ref[30][:3, 3])) < 0.1


def test_no_registered_step_across_a_segment_break() -> None:
    ref = square(40)
    odo = ref.copy()
    reset = np.eye(4)
    reset[:3, 3] = [-300.0, 40.0, 0.0]
    odo[20:] = reset @ odo[20:]
    pg = PoseGraph(STEPS)
    states = [pg.update(ScanResult(k * SEC, True, k, matrix_to_vector(T), step=_step(ref, k)
                                   if k else None), OdomSample(k * SEC, T))
              for k, T in enumerate(odo)]
    assert [s.segment for s in states[19:21]] == [0, 1]
    assert pg.steps == 38  # all but keyframe 0 and the first of the new segment



def test_an_unchecked_step_of_a_scan_only_odometry_is_as_uncertain_as_it_is_long() -> None:
    ref = square(40)
    cov = tuple(np.diag([0.02 ** 2] * 3 + [math.radians(0.1) ** 2] * 3).ravel())
    grown = {}
    for missing in (None, 30):  # keyframe 30's registration failed a test, or did not
        pg = PoseGraph(STEPS)
        states = [pg.update(ScanResult(k * SEC, True, k, matrix_to_vector(T),
                                       step=_step(ref, k, cov) if k and k != missing else None),
                            OdomSample(k * SEC, T)) for k, T in enumerate(ref)]
        before, after = states[29].covariance, states[30].covariance
        assert before is not None and after is not None
        grown[missing] = float(np.trace(after[:3, :3]) - np.trace(before[:3, :3]))
    assert grown[None] < 0.01  # checked: the model's and the registration's few centimetres
    assert grown[30] > 2.5  # unchecked: 1 m sigmas on x, y, z (the step is 1 m long)
