"""The robot's kinematics and walls, and the odometry, compass and sonar models."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sim.robot import Motion, RobotParams, clamp_command, move
from sim.sensors import (
    CompassModel,
    CompassParams,
    OdometryModel,
    OdometryParams,
    SonarModel,
    SonarParams,
)
from sim.world import load_world, world_from_dict

BOX = world_from_dict({"name": "box", "walls": [[0, 0, 10, 0], [10, 0, 10, 6], [10, 6, 0, 6], [0, 6, 0, 0],
                                                 [5, 0, 5, 2.5]],  # a thin wall sticking out of the south side
                       "start": [2, 3, 0]})
CORRIDOR = world_from_dict({"name": "corridor", "walls": [[-30, -1, 30, -1], [-30, 1, 30, 1]], "start": [0, 0, 0],
                            "magnetic_disturbances": [{"x": 10, "y": 0, "radius": 2, "deviation_deg": 20}]})
P = RobotParams()


def test_unicycle_straight_and_arc():
    pose, m = move((2.0, 3.0, 0.0), 0.5, 0.0, 0.1, BOX, P)
    assert pose == pytest.approx((2.05, 3.0, 0.0)) and m == Motion(pytest.approx(0.05), 0.0, False)
    # a quarter circle of radius 1 m: v = 0.5, w = 0.5, for pi seconds
    pose = (2.0, 3.0, 0.0)
    n = 100
    for _ in range(n):
        pose, _ = move(pose, 0.5, 0.5, math.pi / n, BOX, P)
    assert pose == pytest.approx((3.0, 4.0, math.pi / 2), abs=1e-9)


def test_command_limits():
    assert clamp_command(5.0, -9.0, P) == (P.max_speed_mps, -P.max_turn_radps)
    assert clamp_command(float("nan"), float("inf"), P) == (0.0, 0.0)
    pose, m = move((2.0, 3.0, 0.0), 10.0, 0.0, 1.0, BOX, P)
    assert m.distance_m == pytest.approx(P.max_speed_mps)


def test_walls_stop_the_robot():
    pose = (2.0, 3.0, 0.0)  # heading east to the wall at x = 10
    blocked = 0
    for _ in range(300):
        pose, m = move(pose, 0.6, 0.0, 0.1, BOX, P)
        blocked += m.blocked
    assert blocked > 0
    assert pose[0] <= 10.0 - P.radius_m and pose[0] == pytest.approx(10.0 - P.radius_m, abs=0.01)
    # it can turn in place and drive away
    pose, m = move(pose, 0.0, 1.5, 0.1, BOX, P)
    assert not m.blocked
    pose, m = move((pose[0], pose[1], math.pi), 0.5, 0.0, 0.1, BOX, P)
    assert not m.blocked and m.distance_m == pytest.approx(0.05)


def test_a_thin_wall_stops_a_fast_robot():
    # big steps (0.6 m per step) straight at a wall end that is thinner than nothing: never through it
    pose = (3.0, 1.0, 0.0)
    for _ in range(20):
        pose, _ = move(pose, 0.6, 0.0, 1.0, BOX, P)
    assert pose[0] < 5.0 and BOX.clearance(pose[0], pose[1]) >= P.radius_m - 1e-9
    # passing beside its end (y = 2.5 + radius + 5 cm) is free
    pose = (3.0, 2.8, 0.0)
    for _ in range(10):
        pose, m = move(pose, 0.6, 0.0, 1.0, BOX, P)
    assert pose[0] > 6.0


@settings(max_examples=30, deadline=None)
@given(st.lists(st.tuples(st.floats(-1, 1), st.floats(-2, 2)), min_size=1, max_size=60))
def test_the_robot_never_enters_a_wall(commands):
    pose = BOX.start
    for v, w in commands:
        for _ in range(5):
            pose, _ = move(pose, v, w, 0.25, BOX, P)
            assert BOX.clearance(pose[0], pose[1]) >= P.radius_m - 1e-9
            assert 0 < pose[0] < 10 and 0 < pose[1] < 6


# -- odometry ---------------------------------------------------------------------------------------------


def test_odometry_systematic_errors_without_noise():
    p = OdometryParams(distance_noise_m_per_sqrt_m=0.0, rotation_noise_rad_per_sqrt_m=0.0,
                       rotation_noise_rad_per_sqrt_rad=0.0, slip_probability=0.0)
    model = OdometryModel(p)
    rng = np.random.default_rng(0)
    d, r = model.measure(Motion(1.0, 0.0, False), rng)
    assert d == pytest.approx(1.0 + p.distance_scale_error)
    assert r == pytest.approx(p.rotation_drift_rad_per_m)
    d, r = model.measure(Motion(0.0, math.pi / 2, False), rng)
    assert d == 0.0 and r == pytest.approx(math.pi / 2 * (1 + p.rotation_scale_error))
    assert model.measure(Motion(0.0, 0.0, False), rng) == (0.0, 0.0)


def test_raw_odometry_curves_visibly():
    model = OdometryModel()
    rng = np.random.default_rng(1)
    heading = 0.0
    for _ in range(400):  # 20 m straight ahead in 5 cm steps
        _, r = model.measure(Motion(0.05, 0.0, False), rng)
        heading += r
    assert math.degrees(heading) > 10.0  # about 1 deg per metre of drift
    # and the distance scale error is of the order of a percent
    total = sum(model.measure(Motion(0.05, 0.0, False), rng)[0] for _ in range(2000))
    assert total / 100.0 - 1.0 == pytest.approx(0.015, abs=0.01)


# -- compass ------------------------------------------------------------------------------------------------


def test_compass_noise_and_disturbances():
    model = CompassModel(CORRIDOR)
    assert math.degrees(model.deviation_rad(10.0, 0.0)) == pytest.approx(20.0)
    assert model.deviation_rad(12.5, 0.0) == 0.0 and model.deviation_rad(0.0, 0.0) == 0.0
    # smooth: no jump anywhere along the corridor
    xs = np.linspace(6, 14, 801)
    dev = np.degrees([model.deviation_rad(x, 0.0) for x in xs])
    assert np.abs(np.diff(dev)).max() < 0.5
    rng = np.random.default_rng(2)
    readings = np.array([model.measure((0.0, 0.0, 3.1), rng) for _ in range(4000)])
    err = np.degrees(np.angle(np.exp(1j * (readings - 3.1))))
    assert abs(err.mean()) < 0.2 and err.std() == pytest.approx(2.0, rel=0.1)
    assert np.all((readings > -math.pi) & (readings <= math.pi))
    quiet = CompassModel(CORRIDOR, CompassParams(noise_rad=0.0, disturbance_scale=0.0))
    assert quiet.measure((10.0, 0.0, 0.5), rng) == 0.5


# -- sonar --------------------------------------------------------------------------------------------------

EXACT = SonarParams(range_noise_m=0.0, range_noise_fraction=0.0, miss_probability=0.0,
                    specular_max_probability=0.0, rays_per_beam=1)


def test_sonar_ring_geometry_in_a_corridor():
    model = SonarModel(EXACT)
    assert model.rays == 16
    assert np.degrees(np.diff(model.bearings[:8])) == pytest.approx([22.5] * 7)
    ranges = model.measure((0.0, 0.0, 0.0), CORRIDOR, np.random.default_rng(0))
    assert ranges[4] == pytest.approx(1.0) and ranges[12] == pytest.approx(1.0)  # +-90 deg
    assert ranges[0] == EXACT.max_range_m and ranges[8] == EXACT.max_range_m  # along the corridor
    assert ranges[2] == pytest.approx(math.sqrt(2))  # 45 deg
    assert ranges[1] == pytest.approx(1.0 / math.sin(math.radians(22.5)))


def test_sonar_cone_and_clipping():
    wide = SonarModel(SonarParams(range_noise_m=0.0, range_noise_fraction=0.0, miss_probability=0.0,
                                  specular_max_probability=0.0))
    ranges = wide.measure((0.0, 0.0, 0.0), CORRIDOR, np.random.default_rng(0))
    # the beam along the corridor has a 25 deg cone: its edge ray meets a wall at 1 / sin(12.5 deg)
    assert ranges[0] == pytest.approx(1.0 / math.sin(math.radians(12.5)))
    near = world_from_dict({"name": "n", "walls": [[0.3, -5, 0.3, 5], [-9, -5, 9, -5]], "start": [0, 0, 0]})
    ranges = wide.measure((0.0, 0.0, 0.0), near, np.random.default_rng(0))
    assert ranges[0] == pytest.approx(0.3)
    close = world_from_dict({"name": "c", "walls": [[0.1, -5, 0.1, 5], [-9, -5, 9, -5]], "start": [-1, 0, 0]})
    assert wide.measure((0.0, 0.0, 0.0), close, np.random.default_rng(0))[0] == wide.params.min_range_m


def test_sonar_noise_and_specular_misses():
    world = load_world("manchester-corridors")
    model = SonarModel()
    rng = np.random.default_rng(5)
    scans = np.array([model.measure((25.0, 1.25, 0.0), world, rng) for _ in range(1000)])
    mx = model.params.max_range_m
    assert np.all((scans >= model.params.min_range_m) & (scans <= mx))
    side = scans[:, 4]  # 90 deg: the wall 1 m away, head on
    hits = side[side < mx]
    assert hits.mean() == pytest.approx(1.0, abs=0.01) and hits.std() == pytest.approx(0.03, abs=0.01)
    missed = (scans == mx).mean(axis=0)
    assert 0.0 < missed[4] < 0.05  # head on: occasional misses only
    assert missed[4] < missed[1] < 0.5  # 22.5 deg off the corridor axis: oblique, more misses
    assert missed[0] > 0.3  # down the corridor: grazing incidence, mostly lost


def test_same_seed_same_readings():
    world = load_world("orebro-office")
    model = SonarModel()
    a = model.measure(world.start, world, np.random.default_rng(9))
    b = model.measure(world.start, world, np.random.default_rng(9))
    c = model.measure(world.start, world, np.random.default_rng(10))
    assert np.array_equal(a, b) and not np.array_equal(a, c)

