"""sensor_sim and dead_reckoning as real processes over zenoh on loopback, driven from the test."""

from __future__ import annotations

import os

import pytest

from messages import topics
from messages.codec import codec
from messages.types import (
    CompassReading,
    DeadReckonedPose,
    Health,
    OdometryStep,
    SonarScan,
    TruthPose,
    VelocityCommand,
)
from services.runtime import AliveWatcher, query
from services.sensor_sim.driver import RouteCommander
from sim.world import load_world
from tests.conftest import Collector, wait_until

WORLD = load_world("manchester-corridors")
ROUTE = WORLD.routes["outer-loop"]



def _start(processes, endpoint, robot, *sim_args, dr_args=()):
    common = ["--robot", robot, "--connect", endpoint, "--listen", "tcp/127.0.0.1:0"]
    dr = processes.python("services.dead_reckoning", *common, "--duration-s", "60", *dr_args)
    sim = processes.python("services.sensor_sim", *common, "--world", "manchester-corridors", "--duration-s", "60",
                           *sim_args)
    return sim, dr


def _health(session, robot, service) -> Health:
    return query(session, topics.health(robot, service), type_=Health)


def test_poses_arrive_and_health_is_served(hub, processes):
    session, endpoint = hub
    robot = f"busdr{os.getpid()}"
    watcher = AliveWatcher(session, robot)
    dr_poses = Collector(session, topics.dr_pose(robot), DeadReckonedPose)
    truth = Collector(session, topics.truth_pose(robot), TruthPose)
    sonar = Collector(session, topics.sonar(robot), SonarScan)
    # the commander answers ticks 0..199: the lockstep run then waits at tick 200
    commander = RouteCommander(session, ROUTE, robot=robot, source="dr", origin=WORLD.start[:2], until_tick=200)
    try:
        sim, dr = _start(processes, endpoint, robot, "--seed", "3", "--lockstep", "--lockstep-timeout-s", "60")
        assert watcher.wait_alive(["sensor_sim", "dead_reckoning"], 30), watcher.alive
        assert wait_until(lambda: any(p.steps == 200 for p in dr_poses.snapshot()), 40), (
            f"{len(dr_poses.snapshot())} poses; last {dr_poses.snapshot()[-1:]}")
        h_sim = _health(session, robot, "sensor_sim")
        h_dr = _health(session, robot, "dead_reckoning")
        assert processes.stop(sim) == 0 and processes.stop(dr) == 0  # SIGTERM: a clean stop
    finally:
        commander.close()
        for rec in (dr_poses, truth, sonar):
            rec.close()
        watcher.close()
    poses = dr_poses.snapshot()
    moving = [p for p in poses if p.steps > 0]
    assert [p.steps for p in moving] == list(range(1, 201))
    assert [p.seq for p in poses] == list(range(len(poses)))
    assert moving[-1].path_length_m > 5.0 and moving[-1].gaps == 0
    final_truth = [t for t in truth.snapshot() if t.seq == 200][0].pose
    # compass DR after 10 m through a magnetic disturbance: within a metre of the truth
    assert abs(moving[-1].compass.x_m + WORLD.start[0] - final_truth.x_m) < 1.0
    assert abs(moving[-1].compass.y_m + WORLD.start[1] - final_truth.y_m) < 1.0
    assert len(sonar.snapshot()) >= 1 + int(moving[-1].path_length_m / 0.5) - 1
    assert h_sim.pid == sim.pid and h_dr.pid == dr.pid
    assert h_sim.detail["tick"] == 200 and h_sim.detail["started"] == 1 and h_sim.detail["lockstep"] == 1
    assert h_sim.detail["lockstep_timeouts"] == 0 and h_sim.detail["collisions"] == 0
    assert h_sim.messages_out >= 3 * 200 and h_sim.messages_in >= 200
    assert h_dr.detail["steps"] == 200 and h_dr.detail["gaps"] == 0 and h_dr.detail["reordered"] == 0
    assert h_dr.messages_in >= 401 and h_dr.decode_errors == 0


def _lockstep_run(session, processes, endpoint, robot, seed, ticks):
    """One DR-driven lockstep run, both processes bounded by the simulated time."""
    truth = Collector(session, topics.truth_pose(robot), TruthPose)
    odo = Collector(session, topics.odometry(robot), OdometryStep)
    commander = RouteCommander(session, ROUTE, robot=robot, source="dr", origin=WORLD.start[:2])
    # a generous timeout: a tick that timed out would change the trajectory, however loaded the machine
    sim, dr = _start(processes, endpoint, robot, "--seed", str(seed), "--lockstep", "--lockstep-timeout-s", "30",
                     "--max-sim-time", str(ticks / 10), dr_args=("--max-sim-time", str(ticks / 10)))
    return truth, odo, commander, sim, dr


def test_same_seed_same_trajectory_across_processes(hub, processes):
    session, endpoint = hub
    ticks = 150
    runs = {}
    try:
        # three runs at once, each its own pair of processes under its own robot name
        for name, seed in (("a", 11), ("b", 11), ("c", 12)):
            runs[name] = _lockstep_run(session, processes, endpoint, f"repro{name}{os.getpid()}", seed, ticks)
        for name, (truth, *_rest) in runs.items():
            assert wait_until(lambda t=truth: any(m.seq == ticks for m in t.snapshot()), 60), name
        for name, (_t, _o, _c, sim, dr) in runs.items():
            assert sim.wait(15) == 0 and dr.wait(15) == 0, name  # both end by themselves
    finally:
        for truth, odo, commander, *_ in runs.values():
            commander.close()
            truth.close()
            odo.close()

    def trajectory(name):
        by_tick = {m.seq: m.pose for m in runs[name][0].snapshot()}
        return [by_tick[k] for k in range(ticks + 1)]

    def odometry(name):
        by_seq = {m.seq: m for m in runs[name][1].snapshot()}
        return [by_seq[k] for k in range(ticks)]

    a, b, c = trajectory("a"), trajectory("b"), trajectory("c")
    assert a == b, "same seed, different trajectory"
    assert odometry("a") == odometry("b")
    assert a != c and odometry("a") != odometry("c")
    assert a[-1].x_m - a[0].x_m > 3.0  # the robot really drove


def test_real_time_factor_mode_keeps_pace(hub, processes):
    session, endpoint = hub
    robot = f"rtf{os.getpid()}"
    watcher = AliveWatcher(session, robot)
    truth = Collector(session, topics.truth_pose(robot), TruthPose)
    commander = RouteCommander(session, ROUTE, robot=robot, source="truth")
    try:
        sim, _dr = _start(processes, endpoint, robot, "--rtf", "10", "--max-sim-time", "10")
        assert watcher.wait_alive(["sensor_sim"], 30)
        assert wait_until(lambda: any(m.seq == 100 for m in truth.snapshot()), 30)
        h = _health(session, robot, "sensor_sim")
        assert sim.wait(15) == 0
    finally:
        commander.close()
        truth.close()
        watcher.close()
    assert h.detail["lockstep"] == 0 and h.detail["rtf"] == 10
    assert h.detail["rtf_achieved"] == pytest.approx(10.0, rel=0.25)
    moved = [m for m in truth.snapshot() if m.seq == 100][0].pose
    assert moved.x_m - WORLD.start[0] > 2.0  # it drove with the latest commands


def test_lockstep_never_waits_forever(hub, processes):
    session, endpoint = hub
    robot = f"stall{os.getpid()}"
    watcher = AliveWatcher(session, robot)
    truth = Collector(session, topics.truth_pose(robot), TruthPose)
    pub = session.declare_publisher(topics.cmd_velocity(robot))
    try:
        sim, _dr = _start(processes, endpoint, robot, "--lockstep", "--lockstep-timeout-s", "0.3",
                          "--max-sim-time", "0.5")
        assert watcher.wait_alive(["sensor_sim"], 30)
        assert wait_until(lambda: truth.snapshot(), 30)
        assert wait_until(lambda: pub.matching_status.matching, 10)
        # one command, for tick 0 only: the robot drives for one tick, then every tick times out
        pub.put(codec(VelocityCommand).encode(VelocityCommand(stamp=0.0, seq=0, v_mps=0.5, omega_radps=0.0, tick=0)))
        assert wait_until(lambda: any(m.seq == 2 for m in truth.snapshot()), 10)
        assert wait_until(lambda: _health(session, robot, "sensor_sim").detail["lockstep_timeouts"] >= 1, 10)
        assert sim.wait(15) == 0
    finally:
        pub.undeclare()
        truth.close()
        watcher.close()
    poses = {m.seq: m.pose for m in truth.snapshot()}
    assert poses[1].x_m == pytest.approx(WORLD.start[0] + 0.05)
    assert poses[5].x_m == poses[1].x_m  # stopped on every timeout


def test_the_last_command_ends_the_run(hub, processes):
    """A command marked final (the explorer's once exploration is complete) is the last tick computed:
    the commander would answer more, and the simulator stops there and exits by itself."""
    session, endpoint = hub
    robot = f"final{os.getpid()}"
    watcher = AliveWatcher(session, robot)
    truth = Collector(session, topics.truth_pose(robot), TruthPose)
    commander = RouteCommander(session, ROUTE, robot=robot, origin=WORLD.start[:2], final_tick=30)
    try:
        sim, _dr = _start(processes, endpoint, robot, "--lockstep", "--lockstep-timeout-s", "0.3")
        assert watcher.wait_alive(["sensor_sim"], 30)
        assert wait_until(lambda: _health(session, robot, "sensor_sim").detail["ended"] == 1, 30)
        h = _health(session, robot, "sensor_sim")
        assert sim.wait(15) == 0
    finally:
        commander.close()
        truth.close()
        watcher.close()
    assert h.detail["tick"] == 30 and h.detail["lockstep_timeouts"] == 0
    assert max(m.seq for m in truth.snapshot()) == 30
    assert commander.last_tick == 30


def test_dead_reckoning_reports_gaps_in_health(hub, processes):
    session, endpoint = hub
    robot = f"gaps{os.getpid()}"
    watcher = AliveWatcher(session, robot)
    dr = processes.python("services.dead_reckoning", "--robot", robot, "--connect", endpoint,
                          "--listen", "tcp/127.0.0.1:0", "--duration-s", "30")
    pub_c = session.declare_publisher(topics.compass(robot))
    pub_o = session.declare_publisher(topics.odometry(robot))
    try:
        assert watcher.wait_alive(["dead_reckoning"], 30)
        assert wait_until(lambda: pub_c.matching_status.matching and pub_o.matching_status.matching, 10)
        cenc, oenc = codec(CompassReading), codec(OdometryStep)
        for k in (0, 1, 2, 4, 5):  # compass seq 3 lost
            pub_c.put(cenc.encode(CompassReading(stamp=0.1 * k, seq=k, heading_rad=0.0)))
        for k in (0, 1, 3, 2):  # odometry: 2 arrives after 3
            pub_o.put(oenc.encode(OdometryStep(stamp=0.1 * (k + 1), seq=k, distance_m=0.1, rotation_rad=0.0, dt_s=0.1)))
        assert wait_until(lambda: _health(session, robot, "dead_reckoning").detail["steps"] == 4, 10)
        h = _health(session, robot, "dead_reckoning")
    finally:
        pub_c.undeclare()
        pub_o.undeclare()
        watcher.close()
    assert h.detail["gaps_compass"] == 1 and h.detail["gaps_odometry"] == 0 and h.detail["reordered"] == 1
    assert h.detail["gaps"] == 1 and h.detail["path_length_m"] == pytest.approx(0.4)
    assert dr.poll() is None


def test_bad_world_is_a_clear_error(processes, tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text('{"walls": [], "start": [0, 0, 0]}')
    proc = processes.python("services.sensor_sim", "--world", str(bad), "--listen", "tcp/127.0.0.1:0")
    out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 2
    assert f"{bad}: no walls" in out.decode()
