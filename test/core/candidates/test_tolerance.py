"""What a graph-proposed loop must agree with (solid_ros.core.candidates.tolerance): the search
radius, the position sigma, the heading tolerance, the known place."""

from __future__ import annotations

import math

import numpy as np
import pytest
from planar_poses import planar_pose as _pose
from planar_poses import position_cov as _cov

from solid_ros.core.candidates.tolerance import (
    HEADING_FLOOR_DEG,
    heading_tolerance_deg,
    knows_place,
    position_sigma,
    search_radius,
)
from solid_ros.core.config import SolidConfig
from solid_ros.core.geometry import rot_z

CFG = SolidConfig(graph_candidate_radius_m=5.0, graph_candidate_sigmas=3.0,
                  graph_candidate_max_radius_m=15.0)


def test_radius_grows_with_the_covariance_from_the_floor_to_the_cap() -> None:
    assert search_radius(_cov(0.0), CFG) == pytest.approx(5.0)  # certain: the floor
    assert search_radius(_cov(1.0), CFG) == pytest.approx(8.0)  # 5 m + 3 sigma
    assert search_radius(_cov(2.0), CFG) == pytest.approx(11.0)
    assert search_radius(_cov(10.0), CFG) == pytest.approx(15.0)  # the cap
    # The largest direction counts, whatever the frame.
    cov = np.zeros((6, 6))
    cov[:3, :3] = np.diag([0.01, 4.0, 0.01])
    assert search_radius(cov, CFG) == pytest.approx(11.0)
    # The step from the newest keyframe to the query adds the odometry model's variance and
    # the newest heading's uncertainty over the step's length.
    cov = _cov(1.0)
    cov[3:, 3:] = np.eye(3) * 0.01 ** 2  # 0.01 rad
    step = _pose(100.0)
    want = 5.0 + 3.0 * math.sqrt(1.0 + CFG.backend_odom_trans_sigma ** 2 * 100.0
                                 + CFG.backend_odom_floor_m ** 2 + (100.0 * 0.01) ** 2)
    assert search_radius(cov, CFG, step) == pytest.approx(want)
    assert search_radius(cov, CFG, np.eye(4)) == pytest.approx(
        5.0 + 3.0 * math.sqrt(1.0 + CFG.backend_odom_floor_m ** 2))
    # Unknown or unusable covariance: the cap.
    assert search_radius(None, CFG) == 15.0
    assert search_radius(np.full((6, 6), np.nan), CFG) == 15.0
    assert search_radius(np.eye(3), CFG) == 15.0


def test_heading_tolerance_follows_the_yaw_uncertainty() -> None:
    cfg = SolidConfig(graph_candidate_sigmas=3.0)
    assert heading_tolerance_deg(None, cfg) == 180.0
    assert heading_tolerance_deg(np.full((6, 6), np.nan), cfg) == 180.0
    cov = np.eye(6) * 1e-6
    cov[5, 5] = math.radians(2.0) ** 2  # 2 deg of yaw
    assert heading_tolerance_deg(cov, cfg) == pytest.approx(HEADING_FLOOR_DEG + 6.0)
    turn = np.eye(4)
    turn[:3, :3] = rot_z(math.pi / 2)  # turning adds the odometry model's yaw variance
    assert heading_tolerance_deg(cov, cfg, turn) > heading_tolerance_deg(cov, cfg)


def test_position_sigma_is_what_the_search_radius_grows_with() -> None:
    cov = _cov(0.2)
    cov[3:, 3:] = np.eye(3) * 0.002 ** 2
    step, view = _pose(3.0), np.array([20.0, 0.0, 0.0])
    sigma = position_sigma(cov, CFG, step, view)
    assert sigma > 0.2  # the step and the heading's lever add to the marginal
    assert search_radius(cov, CFG, step, view) == pytest.approx(5.0 + 3.0 * sigma)
    assert position_sigma(None, CFG) == math.inf
    assert position_sigma(np.full((6, 6), np.nan), CFG) == math.inf


def test_a_place_is_known_only_within_one_coarse_voxel_counting_the_graph_s_doubt() -> None:
    cfg = CFG.replace(verify_coarse_voxel_size=1.5)
    guess, centre = _pose(2.0, 1.0, 0.3), np.array([15.0, 0.0, 0.0])
    assert knows_place(guess, guess, centre, 0.1, 5.0, cfg)  # 0 + 3 x 0.1 <= 1.5
    # The deviation is measured at the view centre: 1 deg turns a point 15 m ahead by 0.26 m.
    turned = guess @ _pose(0.0, 0.0, math.radians(1.0))
    assert knows_place(guess, turned, centre, 0.1, 5.0, cfg)
    assert not knows_place(guess, turned, centre, 0.1, 0.5, cfg)  # turned beyond the tolerance
    assert knows_place(guess, guess, centre, 0.42, 5.0, cfg)  # 0 + 1.26 <= 1.5
    assert not knows_place(guess, turned, centre, 0.42, 5.0, cfg)  # 0.26 + 1.26 > 1.5
    shifted = guess @ _pose(1.0, 0.0)
    assert knows_place(guess, shifted, centre, 0.1, 5.0, cfg)  # 1.0 + 0.3
    # Two tight-space keyframes register on a finer coarse grid, which bounds it instead.
    assert not knows_place(guess, shifted, centre, 0.1, 5.0, cfg, coarse_voxel=0.75)
    assert knows_place(guess, guess, centre, 0.1, 5.0, cfg, coarse_voxel=0.75)
    assert not knows_place(guess, guess @ _pose(1.3, 0.0), centre, 0.1, 5.0, cfg)
    # A graph unsure by more than a coarse voxel knows no place, however close the pose.
    assert not knows_place(guess, guess, centre, 0.6, 5.0, cfg)
    assert not knows_place(guess, guess, centre, math.inf, 5.0, cfg)
