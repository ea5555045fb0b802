"""dead_reckoning on the bus: odometry and compass in, compass-based and raw poses out."""

from __future__ import annotations

import argparse
import logging
import math
import threading
import time
from dataclasses import dataclass, field

import zenoh

from messages import topics
from messages.types import CompassReading, DeadReckonedPose, OdometryStep
from services.dead_reckoning import core
from services.runtime import Node, finite_float, nonnegative_float, nonnegative_int, positive_float
from services.runtime.checkpoint import Checkpoint

SERVICE = "dead_reckoning"
log = logging.getLogger("relaxmap.dead_reckoning")


@dataclass(frozen=True)
class DeadReckoningNodeParams:
    max_sim_time_s: float | None = None  # stop after integrating a step stamped at or past this time
    duration_s: float | None = None  # stop after this wall time
    state_path: str | None = None  # checkpoint: saved with every pose, resumed from after a restart
    filter_params: core.DeadReckoningParams = field(default_factory=core.DeadReckoningParams)  # the filter
    start: core.DrState = field(default_factory=core.DrState)  # the state to start from (a continued run's)


def run(session: zenoh.Session, params: DeadReckoningNodeParams = DeadReckoningNodeParams(), *,
        robot: str = topics.DEFAULT_ROBOT, stop: threading.Event | None = None) -> core.DrState:
    """Integrate the sensor streams until ``stop`` or a limit; return the final filter state."""
    stop = stop or threading.Event()
    ckpt = Checkpoint(params.state_path, core.DrState) if params.state_path else None
    state = (ckpt.load() if ckpt else None) or params.start  # a checkpoint (a restart) wins over the start
    if ckpt is not None and state is not params.start:
        log.info("%s: resumed after %d steps (stamp %.1f s) from %s", SERVICE, state.steps, state.last_stamp,
                 params.state_path)
    with Node(session, SERVICE, robot=robot) as node:
        pub = node.publisher(topics.dr_pose(robot), DeadReckonedPose)
        node.detail.update(steps=0, path_length_m=0.0, last_stamp_s=0.0, gaps=0, gaps_odometry=0,
                           gaps_compass=0, reordered=0, duplicates=0, pending=0, dropped=0)

        def on_sensor(msg: OdometryStep | CompassReading) -> None:
            nonlocal state
            state, poses = core.step(state, msg, params.filter_params)
            if not poses:
                return
            if ckpt is not None:  # before publishing: a pose out is a pose the checkpoint knows
                ckpt.save(state)
            _update_detail(node, state)  # first: whoever has seen a pose finds health that far
            for pose in poses:
                pub.put(pose)
            if params.max_sim_time_s is not None and state.last_stamp >= params.max_sim_time_s - 1e-9:
                log.info("%s: simulated time %.1f s reached", SERVICE, state.last_stamp)
                stop.set()

        node.subscribe(topics.compass(robot), CompassReading, on_sensor)
        node.subscribe(topics.odometry(robot), OdometryStep, on_sensor)
        wall_end = time.monotonic() + params.duration_s if params.duration_s else math.inf

        def on_tick() -> None:
            _update_detail(node, state)
            if time.monotonic() >= wall_end:
                stop.set()

        node.spin(stop, tick=on_tick, period_s=0.1)
        _update_detail(node, state)
        log.info("%s: %d steps, %.1f m, %d gaps, %d reordered, %d duplicates", SERVICE, state.steps,
                 state.path_length_m, state.gaps, state.odometry.reordered + state.compass.reordered,
                 state.odometry.duplicates + state.compass.duplicates)
    return state


def _update_detail(node: Node, state: core.DrState) -> None:
    d = node.detail
    d["steps"] = state.steps
    d["path_length_m"] = state.path_length_m
    d["last_stamp_s"] = state.last_stamp
    d["gaps"] = state.gaps
    d["gaps_odometry"] = state.odometry.gaps
    d["gaps_compass"] = state.compass.gaps
    d["reordered"] = state.odometry.reordered + state.compass.reordered
    d["duplicates"] = state.odometry.duplicates + state.compass.duplicates
    d["pending"] = len(state.pending)
    d["dropped"] = state.dropped



def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seed", type=int, default=0, help="accepted for a uniform command line; the filter "
                                                             "draws no random numbers")
    parser.add_argument("--max-sim-time", type=positive_float, default=None, metavar="S",
                        help="stop after integrating the step that reaches this simulated time")
    parser.add_argument("--duration-s", type=positive_float, default=None, help="stop after this wall time")
    parser.add_argument("--start-xy", type=finite_float, nargs=2, default=None, metavar=("X", "Y"),
                        help="continue a saved run: its last compass dead-reckoned position")
    parser.add_argument("--start-raw", type=finite_float, nargs=3, default=None, metavar=("X", "Y", "HEADING"),
                        help="... its last raw odometry pose (default: --start-xy with the first compass heading)")
    parser.add_argument("--start-steps", type=nonnegative_int, default=0, metavar="N",
                        help="... the odometry steps it had integrated")
    parser.add_argument("--start-path-m", type=nonnegative_float, default=0.0, metavar="M",
                        help="... the distance it had integrated")
    parser.add_argument("--state", metavar="PATH", default=None,
                        help="checkpoint file: saved with every pose; a restarted process resumes from it")


def params_from_args(args: argparse.Namespace) -> DeadReckoningNodeParams:
    start = core.DrState()
    if args.start_xy is not None:
        raw = tuple(args.start_raw) if args.start_raw is not None else None
        start = core.continued_state(tuple(args.start_xy), raw, steps=args.start_steps,
                                     path_length_m=args.start_path_m)
    return DeadReckoningNodeParams(max_sim_time_s=args.max_sim_time, duration_s=args.duration_s, start=start,
                                   state_path=args.state)


def main_run(session: zenoh.Session, args: argparse.Namespace, stop: threading.Event) -> None:
    """What ``python -m services.dead_reckoning`` runs once the session is open."""
    run(session, params_from_args(args), robot=args.robot, stop=stop)
