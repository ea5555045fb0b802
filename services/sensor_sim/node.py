"""sensor_sim on the bus: the simulated clock, velocity commands in, sensor frames and ground truth out."""

from __future__ import annotations

import argparse
import logging
import math
import threading
import time
from dataclasses import dataclass, field

import msgspec
import numpy as np
import zenoh

from messages import topics
from messages.types import CompassReading, OdometryStep, SonarScan, TruthPose, VelocityCommand
from services.runtime import (
    AliveWatcher,
    Node,
    finite_float,
    nonnegative_float,
    nonnegative_int,
    positive_float,
)
from services.runtime.checkpoint import Checkpoint, CheckpointError
from services.sensor_sim import core
from sim.world import World, WorldError, load_world

SERVICE = "sensor_sim"
log = logging.getLogger("relaxmap.sensor_sim")


class SimCheckpoint(msgspec.Struct, frozen=True):
    """What a restarted simulator needs to go on: the state, the frame of that tick, the generator."""

    world: str  # the world's name: a checkpoint of another world is refused
    seed: int
    state: core.SimState
    frame: core.Frame  # published again on resumption (its command is the one awaited)
    rng_state: bytes  # numpy's bit generator state, JSON (its integers exceed 64 bits)


@dataclass(frozen=True)
class SensorSimNodeParams:
    seed: int = 0  # seed of the one random generator behind every sensor
    lockstep: bool = True  # True: tick k+1 only after the command for tick k; False: real-time factor
    rtf: float = 1.0  # real-time factor when not in lockstep (0: as fast as possible)
    lockstep_timeout_s: float = 2.0  # wall time to wait for a tick's command before moving on stopped
    start_repeat_s: float = 0.2  # wall period of tick 0's frame until the first command arrives
    cmd_timeout_s: float = 1.0  # real-time factor mode: stop the robot when commands are older (wall)
    max_sim_time_s: float | None = None  # end the run at this simulated time
    duration_s: float | None = None  # end the run after this wall time
    linger_s: float = 1.0  # wall time to stay on the bus after a bounded run, so the last frame is out
    wait_for: tuple[str, ...] = ()  # services that must be alive (liveliness) before the run starts
    start_pose: tuple[float, float, float] | None = None  # true pose at the first tick (None: the world's start)
    start_tick: int = 0  # the first tick (a run that continues a saved one starts at its last tick)
    state_path: str | None = None  # checkpoint: saved every tick, resumed from when the process restarts
    sim: core.SensorSimParams = field(default_factory=core.SensorSimParams)  # the simulation itself


def run(session: zenoh.Session, world: World, params: SensorSimNodeParams, *,
        robot: str = topics.DEFAULT_ROBOT, stop: threading.Event | None = None) -> core.SimState:
    """Simulate until ``stop``, the simulated or the wall time limit; return the final state.

    A run starts when the first velocity command arrives: until then tick 0 is published every
    ``start_repeat_s``. Then, in lockstep, tick k+1 is computed only once the command answering tick
    k is in (after ``lockstep_timeout_s`` without it, the robot is stopped for that tick and the
    timeout counted in health); with a real-time factor, ticks follow the wall clock and use the
    latest command. Sensor messages are published lossless (congestion control ``block``): when a
    subscriber cannot keep up, the simulation waits for it instead of dropping messages.
    """
    stop = stop or threading.Event()
    with Node(session, SERVICE, robot=robot) as node:
        out = _Outputs(node, robot)
        cmds = _Commands()
        node.detail.update(tick=0, sim_time_s=0.0, started=0, lockstep=float(params.lockstep), rtf=params.rtf,
                           lockstep_timeouts=0, stale_commands=0, commands=0, collisions=0, scans=0,
                           rtf_achieved=0.0, seed=params.seed, ended=0)
        node.subscribe(topics.cmd_velocity(robot), VelocityCommand, cmds.on_cmd_velocity)
        try:
            return _simulate(node, core.SimModel(world, params.sim), params, cmds, out, stop)
        finally:
            out.undeclare()


def _simulate(node: Node, model: core.SimModel, params: SensorSimNodeParams, cmds: _Commands,
              out: _Outputs, stop: threading.Event) -> core.SimState:
    """The clock: the start phase, then one tick per command (lockstep) or per wall period."""
    # a continued run draws from a generator of its own: seeded by the seed and the tick it starts at
    rng = np.random.default_rng(params.seed if params.start_tick == 0 else (params.seed, params.start_tick))
    dt = params.sim.dt_s
    ckpt = Checkpoint(params.state_path, SimCheckpoint) if params.state_path else None
    saved = ckpt.load() if ckpt else None
    if saved is not None:
        if (saved.world, saved.seed) != (model.world.name, params.seed):
            raise CheckpointError(f"{params.state_path} holds world {saved.world!r} seed {saved.seed}, "
                                  f"not {model.world.name!r} seed {params.seed}")
        state, frame = saved.state, saved.frame
        rng.bit_generator.state = msgspec.json.decode(saved.rng_state)
        cmds.started, cmds.tick = True, state.tick
        log.info("%s: resumed at tick %d from %s", SERVICE, state.tick, params.state_path)
        out.publish(frame)  # again: the killed process may have died before publishing all of it
    else:
        state, frame = core.start(model, rng, pose=params.start_pose, tick=params.start_tick)
    node.announce()
    wall_end = time.monotonic() + params.duration_s if params.duration_s else math.inf
    log.info("%s: world %s, seed %d, %s, tick %d, waiting for the first command on %s", SERVICE,
             model.world.name, params.seed, "lockstep" if params.lockstep else f"real-time factor {params.rtf:g}",
             state.tick, topics.cmd_velocity(node.robot))

    # -- start: repeat tick 0 until a command arrives (and every awaited service is alive) ---------------
    watcher = AliveWatcher(node.session, node.robot) if params.wait_for else None

    def all_alive() -> bool:
        return watcher is None or set(params.wait_for) <= watcher.alive

    def ready() -> bool:
        return cmds.started and all_alive()

    # tick 0 goes out once every awaited service is alive, i.e. subscribed: what one of them answers to
    # it (the recognizer's localization of the first scan) then reaches the others (the explorer)
    while not stop.is_set() and time.monotonic() < wall_end and saved is None and not all_alive():
        node.spin_once(0.05)
    while not stop.is_set() and time.monotonic() < wall_end and saved is None and not ready():
        out.publish(frame)
        deadline = time.monotonic() + params.start_repeat_s
        while not ready() and not stop.is_set() and (now := time.monotonic()) < deadline:
            node.spin_once(deadline - now)
    if watcher is not None:
        watcher.close()
        if saved is None and ready():
            # once more: a service declares its token after its subscribers, so every awaited one
            # hears this frame, even one that became alive just after the last repeat
            out.publish(frame)
    t_run = time.monotonic()
    node.detail["started"] = 1
    last_cmd_wall = time.monotonic()

    # -- run --------------------------------------------------------------------------------------------
    while not stop.is_set() and cmds.started:
        now = time.monotonic()
        if now >= wall_end:
            break
        if cmds.final_tick is not None and cmds.final_tick <= state.tick:
            # the run's last command is in: no tick after it, so a run ends where the in-process loop does
            log.info("%s: the last command of the run answered tick %d: no further tick", SERVICE, cmds.final_tick)
            node.detail["ended"] = 1
            break
        if params.lockstep:
            cmd = cmds.take(state.tick)
            if cmd is None:
                waited = now - last_cmd_wall
                if waited < params.lockstep_timeout_s:
                    node.spin_once(min(params.lockstep_timeout_s - waited, 0.1))
                    continue
                cmds.timeouts += 1
                log.warning("%s: no command for tick %d within %.1f s: the robot stops for one tick",
                            SERVICE, state.tick, params.lockstep_timeout_s)
                cmd = (0.0, 0.0)
            last_cmd_wall = time.monotonic()
        else:
            while node.spin_once(0):
                pass
            if params.rtf > 0:
                due = t_run + (state.tick + 1) * dt / params.rtf
                while (now := time.monotonic()) < due and not stop.is_set():
                    node.spin_once(due - now)
            fresh = time.monotonic() - cmds.latest_wall < params.cmd_timeout_s
            cmd = cmds.latest if fresh else (0.0, 0.0)
        state, frame = core.step(state, cmd, model, rng)
        cmds.tick = state.tick
        if ckpt is not None:  # before publishing: whoever heard of a tick finds it in the checkpoint
            ckpt.save(SimCheckpoint(world=model.world.name, seed=params.seed, state=state, frame=frame,
                                    rng_state=msgspec.json.encode(rng.bit_generator.state)))
        # health first: whoever has seen a tick's messages finds health at least that far
        _update_detail(node, state, cmds, dt, time.monotonic() - t_run)
        out.publish(frame)
        if params.max_sim_time_s is not None and frame.truth.stamp >= params.max_sim_time_s - 1e-9:
            log.info("%s: simulated time %.1f s reached", SERVICE, frame.truth.stamp)
            break
    _update_detail(node, state, cmds, dt, time.monotonic() - t_run)
    # stay a moment: zenoh drops what is still queued when the session closes
    linger_end = time.monotonic() + params.linger_s
    while not stop.is_set() and (now := time.monotonic()) < linger_end:
        node.spin_once(linger_end - now)
    log.info("%s: %d ticks, %.1f s simulated, %d collisions, %d lockstep timeouts", SERVICE,
             state.tick - params.start_tick, state.tick * dt, state.collisions, cmds.timeouts)
    return state


class _Outputs:
    """The four sensor publishers, lossless (a slow subscriber slows the simulation down)."""

    def __init__(self, node: Node, robot: str) -> None:
        self._truth = node.publisher(topics.truth_pose(robot), TruthPose)
        self._compass = node.publisher(topics.compass(robot), CompassReading)
        self._odometry = node.publisher(topics.odometry(robot), OdometryStep)
        self._sonar = node.publisher(topics.sonar(robot), SonarScan)

    def publish(self, frame: core.Frame) -> None:
        """Truth first (a scripted commander may key on it); compass before odometry, because dead
        reckoning pairs a step with the compass reading of its end; the scan before the odometry step
        that names it (``sonar_seq``)."""
        self._truth.put(frame.truth)
        self._compass.put(frame.compass)
        if frame.sonar is not None:
            self._sonar.put(frame.sonar)
        if frame.odometry is not None:
            self._odometry.put(frame.odometry)

    def undeclare(self) -> None:
        for pub in (self._truth, self._compass, self._odometry, self._sonar):
            try:
                pub.undeclare()
            except zenoh.ZError:
                pass


class _Commands:
    """Velocity commands received: by tick (lockstep) and the latest one (real-time factor)."""

    def __init__(self) -> None:
        self.tick = 0  # the tick whose command is awaited
        self.by_tick: dict[int, tuple[float, float]] = {}
        self.latest = (0.0, 0.0)
        self.latest_wall = -math.inf
        self.started = False
        self.count = 0
        self.stale = 0
        self.timeouts = 0
        self.final_tick: int | None = None  # the tick the run's last command answered

    def on_cmd_velocity(self, msg: VelocityCommand) -> None:
        self.count += 1
        self.started = True
        if msg.final and msg.tick >= self.tick and (self.final_tick is None or msg.tick < self.final_tick):
            self.final_tick = msg.tick
        self.latest = (msg.v_mps, msg.omega_radps)
        self.latest_wall = time.monotonic()
        if msg.tick < self.tick:
            self.stale += 1
        elif msg.tick < self.tick + 10_000:  # far-future ticks are nonsense: never stored
            self.by_tick[msg.tick] = self.latest

    def take(self, tick: int) -> tuple[float, float] | None:
        """The command answering ``tick``, if it is in."""
        return self.by_tick.pop(tick, None)


def _update_detail(node: Node, state: core.SimState, cmds: _Commands, dt: float, wall_s: float) -> None:
    d = node.detail
    d["tick"] = state.tick
    d["sim_time_s"] = state.tick * dt
    d["collisions"] = state.collisions
    d["scans"] = state.scans
    d["commands"] = cmds.count
    d["stale_commands"] = cmds.stale
    d["lockstep_timeouts"] = cmds.timeouts
    d["rtf_achieved"] = state.tick * dt / wall_s if wall_s > 0 else 0.0


# -- command line -----------------------------------------------------------------------------------------


def _world_arg(text: str) -> World:
    try:
        return load_world(text)
    except WorldError as e:
        raise argparse.ArgumentTypeError(str(e)) from None




def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--world", type=_world_arg, default="orebro-office",
                        help="built-in world name, JSON world file or ROS map .yaml (default: orebro-office)")
    parser.add_argument("--seed", type=int, default=0, help="seed of every random draw (default 0)")
    clock = parser.add_mutually_exclusive_group()
    clock.add_argument("--lockstep", dest="rtf", action="store_const", const=None,
                       help="tick k+1 starts once the command for tick k is in (the default)")
    clock.add_argument("--rtf", type=nonnegative_float, metavar="FACTOR",
                       help="real-time factor instead of lockstep: 1 real time, 10 ten times faster, "
                            "0 as fast as possible")
    parser.add_argument("--dt-s", type=positive_float, default=0.1, help="simulated time per tick (default 0.1)")
    parser.add_argument("--sonar-every-m", type=nonnegative_float, default=0.5,
                        help="sonar scan after this much travel (0: never by distance; default 0.5)")
    parser.add_argument("--sonar-period-s", type=nonnegative_float, default=0.0,
                        help="sonar scan at this simulated period as well (0: off, the default)")
    parser.add_argument("--lockstep-timeout-s", type=positive_float, default=2.0,
                        help="wall time to wait for a tick's command before stopping the robot for that tick")
    parser.add_argument("--max-sim-time", type=positive_float, default=None, metavar="S",
                        help="end the run at this simulated time (seconds)")
    parser.add_argument("--duration-s", type=positive_float, default=None, help="end the run after this wall time")
    parser.add_argument("--state", metavar="PATH", default=None,
                        help="checkpoint file: saved every tick; a restarted process resumes from it")
    parser.add_argument("--wait-for", action="append", default=[], metavar="SERVICE",
                        help="do not start before SERVICE is alive on the bus (repeatable)")
    parser.add_argument("--start-pose", type=finite_float, nargs=3, default=None, metavar=("X", "Y", "HEADING"),
                        help="true pose at the first tick, metres and radians (default: the world's start)")
    parser.add_argument("--start-tick", type=nonnegative_int, default=0, metavar="N",
                        help="the first tick, to continue a saved run (default 0)")


def params_from_args(args: argparse.Namespace) -> SensorSimNodeParams:
    sim = core.SensorSimParams(dt_s=args.dt_s, sonar_every_m=args.sonar_every_m, sonar_period_s=args.sonar_period_s)
    return SensorSimNodeParams(seed=args.seed, lockstep=args.rtf is None,
                               rtf=args.rtf if args.rtf is not None else 1.0,
                               lockstep_timeout_s=args.lockstep_timeout_s, max_sim_time_s=args.max_sim_time,
                               duration_s=args.duration_s, wait_for=tuple(args.wait_for),
                               start_pose=tuple(args.start_pose) if args.start_pose else None,
                               start_tick=args.start_tick, state_path=args.state, sim=sim)


def main_run(session: zenoh.Session, args: argparse.Namespace, stop: threading.Event) -> None:
    """What ``python -m services.sensor_sim`` runs once the session is open."""
    world = args.world if isinstance(args.world, World) else _world_arg(args.world)
    run(session, world, params_from_args(args), robot=args.robot, stop=stop)
