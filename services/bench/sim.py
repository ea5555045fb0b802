"""``relaxmap bench sim``: simulation steps/s, ray casts/s, and the real-time factor of sensor_sim +
dead_reckoning as processes on the bus."""

from __future__ import annotations

import argparse

TARGET_RTF = 200.0  # sim + DR over the bus, on 2 cores


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--world", default="manchester-corridors",
                        help="world to drive in (default manchester-corridors)")
    parser.add_argument("--route", default=None, help="route of the world to drive (default: its first)")
    parser.add_argument("--steps", type=int, default=5000, help="simulation steps per in-process run")
    parser.add_argument("--sim-time", type=float, default=300.0, help="simulated seconds per bus run")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--no-bus", action="store_true", help="leave out the runs over the bus")


def main(args: argparse.Namespace) -> int:
    import os
    import time

    import numpy as np

    from services.bench.table import print_table, time_call
    from services.dead_reckoning import core as dr
    from services.sensor_sim import core as sim
    from sim.geometry import ray_cast
    from sim.route import RouteDriver
    from sim.world import load_world

    world = load_world(args.world)
    route = world.routes[args.route or next(iter(world.routes))]
    dt = sim.SensorSimParams().dt_s

    def in_process(params: sim.SensorSimParams, with_dr: bool) -> tuple[float, int]:
        model = sim.SimModel(world, params)
        rng = np.random.default_rng(args.seed)
        state, frame = sim.start(model, rng)
        filt, _ = dr.step(dr.DrState(), frame.compass)
        driver = RouteDriver(route)
        scans = 0
        t0 = time.perf_counter()
        for _ in range(args.steps):
            state, frame = sim.step(state, driver.command(state.pose), model, rng)
            scans += frame.sonar is not None
            if with_dr:
                filt, _ = dr.step(filt, frame.compass)
                filt, _ = dr.step(filt, frame.odometry)
        return args.steps / (time.perf_counter() - t0), scans

    rows = []
    base, _ = in_process(sim.SensorSimParams(sonar_every_m=0.0), False)
    rows.append(("sim step, no sonar (reference)", base, base * dt, 1.0))
    for label, params in (("sim step, sonar every 0.5 m", sim.SensorSimParams()),
                          ("sim step, sonar every tick", sim.SensorSimParams(sonar_every_m=0.0, sonar_period_s=dt))):
        rate, scans = in_process(params, False)
        rows.append((f"{label} ({scans} scans)", rate, rate * dt, rate / base))
    rate, _ = in_process(sim.SensorSimParams(), True)
    rows.append(("sim step + dead reckoning, one process", rate, rate * dt, rate / base))

    # ray casting: one sonar ring (16 beams x 5 rays) against the walls in range, and against all walls
    model = sim.SimModel(world)
    rays = model.sonar.rays
    x, y = route[0]
    near = world.walls_near(x, y, model.params.sonar.max_range_m)
    angles = np.linspace(-np.pi, np.pi, rays, endpoint=False)
    origin = np.array([x, y])
    t_near = time_call(lambda: ray_cast(origin, angles, near, 6.5))
    t_all = time_call(lambda: ray_cast(origin, angles, world.walls, 6.5))
    t_scan = time_call(lambda: model.sonar.measure((x, y, 0.0), world, np.random.default_rng(0)))
    ray_rows = [
        (f"{rays} rays x {len(near)} walls in range", rays / t_near, t_near * 1e6),
        (f"{rays} rays x all {len(world.walls)} walls", rays / t_all, t_all * 1e6),
        ("one sonar scan (noise and misses included)", rays / t_scan, t_scan * 1e6),
    ]

    bus_rows = []
    if not args.no_bus:
        for label, lockstep, source in (("rtf 0 (as fast as possible), commands from truth", False, "truth"),
                                        ("lockstep, commands from truth", True, "truth"),
                                        ("lockstep, commands from dead-reckoned poses", True, "dr")):
            bus_rows.append((label, *_bus_run(args, world, route, dt, lockstep, source)))

    print_table(f"sim: simulation steps in one process ({world.name}, {args.steps} steps of {dt:g} s)",
                ["what", "steps/s", "real-time factor", "ratio to reference"], rows)
    print_table("sim: ray casting (vectorised numpy)", ["what", "rays/s", "us per call"], ray_rows)
    if bus_rows:
        print_table(f"sim: sensor_sim + dead_reckoning as processes over zenoh ({args.sim_time:g} s simulated, "
                    f"{os.cpu_count()} cores)",
                    ["what", "ticks/s", "real-time factor", "vs target", "DR gaps", "collisions"], bus_rows,
                    note=f"target: {TARGET_RTF:g}x real time for sim + DR on 2 cores; the commander runs in the "
                         "benchmark's own process, a third one.")
    return 0


def _bus_run(args: argparse.Namespace, world, route, dt: float, lockstep: bool, source: str) -> tuple:
    """One run of sensor_sim and dead_reckoning as processes, driven from this process; from the first
    command to the dead-reckoned pose of the last tick."""
    import os
    import subprocess
    import sys
    import threading
    import time

    import zenoh

    from messages import topics
    from messages.codec import codec
    from messages.types import DeadReckonedPose, Health
    from services.runtime import AliveWatcher, QueryFailed, loopback_config, query
    from services.runtime.procs import free_port, stop_group
    from services.sensor_sim.driver import RouteCommander

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    robot = f"bench{os.getpid()}"
    T = args.sim_time
    done = threading.Event()
    end_at = [float("nan")]
    dec = codec(DeadReckonedPose)

    def on_dr(sample: zenoh.Sample) -> None:
        msg = dec.decode(sample.payload.to_bytes())
        if msg.stamp >= T - 1e-9 and not done.is_set():
            end_at[0] = time.monotonic()
            done.set()

    common = ["--robot", robot, "--connect", endpoint, "--listen", "tcp/127.0.0.1:0"]
    clock = ["--lockstep"] if lockstep else ["--rtf", "0"]
    procs = []
    with zenoh.open(loopback_config(listen=[endpoint])) as session:
        watcher = AliveWatcher(session, robot)
        sub = session.declare_subscriber(topics.dr_pose(robot), on_dr)
        commander = RouteCommander(session, route, robot=robot, source=source, origin=world.start[:2])
        try:
            procs.append(subprocess.Popen([sys.executable, "-m", "services.dead_reckoning", *common,
                                           "--duration-s", str(120)], start_new_session=True,
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
            if not watcher.wait_alive(["dead_reckoning"], 30):
                raise RuntimeError("dead_reckoning did not start")
            procs.append(subprocess.Popen([sys.executable, "-m", "services.sensor_sim", *common, "--world",
                                           args.world, "--seed", str(args.seed), *clock, "--max-sim-time", str(T),
                                           "--duration-s", str(120)], start_new_session=True,
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
            deadline = time.monotonic() + 150
            while not done.wait(0.5) and time.monotonic() < deadline:
                # the last pose may be lost to congestion: then the filter's own clock tells the end
                try:
                    h = query(session, topics.health(robot, "dead_reckoning"), type_=Health, timeout_s=2)
                except QueryFailed:
                    continue
                if h.detail.get("last_stamp_s", 0.0) >= T - 1e-9:
                    end_at[0] = time.monotonic()
                    done.set()
            if not done.is_set() or commander.first_command_at is None:
                raise RuntimeError("the run did not reach its end")
            wall = end_at[0] - commander.first_command_at
            try:
                dr_health = query(session, topics.health(robot, "dead_reckoning"), type_=Health)
                sim_health = query(session, topics.health(robot, "sensor_sim"), type_=Health)
                gaps, collisions = int(dr_health.detail["gaps"]), int(sim_health.detail["collisions"])
            except QueryFailed:
                gaps = collisions = -1
        finally:
            for p in procs:
                stop_group(p)
            commander.close()
            sub.undeclare()
            watcher.close()
    rtf = T / wall
    return T / dt / wall, rtf, f"{rtf / TARGET_RTF:.2f}x", gaps, collisions
