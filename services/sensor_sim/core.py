"""The simulation step of sensor_sim: robot motion and every sensor, one tick at a time (pure)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from messages.types import CompassReading, OdometryStep, Pose2, SonarScan, TruthPose
from sim.robot import Pose, RobotParams, move
from sim.sensors import CompassModel, CompassParams, OdometryModel, OdometryParams, SonarModel, SonarParams
from sim.world import World


@dataclass(frozen=True)
class SensorSimParams:
    dt_s: float = 0.1  # simulated time per tick
    sonar_every_m: float = 0.5  # scan after this much odometry travel (0: never by distance)
    sonar_period_s: float = 0.0  # also scan after this much simulated time (0: never by time)
    robot: RobotParams = field(default_factory=RobotParams)  # kinematics and size
    odometry: OdometryParams = field(default_factory=OdometryParams)  # wheel odometry errors
    compass: CompassParams = field(default_factory=CompassParams)  # compass noise
    sonar: SonarParams = field(default_factory=SonarParams)  # sonar ring

    def __post_init__(self) -> None:
        if not self.dt_s > 0:
            raise ValueError(f"dt_s must be positive, got {self.dt_s}")
        if self.sonar_every_m < 0 or self.sonar_period_s < 0:
            raise ValueError("sonar_every_m and sonar_period_s must not be negative")


class SimModel:
    """A world with the sensor models built for it (immutable after construction)."""

    def __init__(self, world: World, params: SensorSimParams = SensorSimParams()) -> None:
        self.world = world
        self.params = params
        self.odometry = OdometryModel(params.odometry)
        self.compass = CompassModel(world, params.compass)
        self.sonar = SonarModel(params.sonar)
        self.sonar_angles = [float(a) for a in self.sonar.bearings]


@dataclass(frozen=True)
class SimState:
    tick: int  # the tick whose frame was produced last
    pose: Pose  # true pose at that tick
    travel_since_scan_m: float  # odometry distance since the last scan
    time_since_scan_s: float  # simulated time since the last scan
    scans: int  # scans produced so far (the next scan's seq)
    collisions: int  # steps in which a wall stopped the robot
    path_length_m: float  # true distance travelled


@dataclass(frozen=True)
class Frame:
    """Everything published at one tick. ``odometry`` covers the step that ended at this tick."""

    tick: int
    truth: TruthPose
    compass: CompassReading
    odometry: OdometryStep | None  # None at tick 0
    sonar: SonarScan | None  # None when no scan is due


def start(model: SimModel, rng: np.random.Generator, *, pose: Pose | None = None,
          tick: int = 0) -> tuple[SimState, Frame]:
    """The state and frame of the first tick, with a first scan.

    By default tick 0 with the robot at the world's start; a run that continues a saved one starts
    at its last ``tick`` with the robot at its last true ``pose``.
    """
    if tick < 0:
        raise ValueError(f"the first tick must not be negative, got {tick}")
    pose = model.world.start if pose is None else (float(pose[0]), float(pose[1]), float(pose[2]))
    stamp = tick * model.params.dt_s
    state = SimState(tick=tick, pose=pose, travel_since_scan_m=0.0, time_since_scan_s=0.0, scans=0,
                     collisions=0, path_length_m=0.0)
    compass = model.compass.measure(pose, rng)
    scan = _scan(model, pose, state, stamp, rng)
    return (_after_scan(state) if scan else state), Frame(
        tick=tick, truth=_truth(pose, tick, stamp),
        compass=CompassReading(stamp=stamp, seq=tick, heading_rad=compass), odometry=None, sonar=scan)


def step(state: SimState, command: tuple[float, float], model: SimModel,
         rng: np.random.Generator) -> tuple[SimState, Frame]:
    """Execute ``command = (v_mps, omega_radps)`` for one tick; return the next state and its frame.

    Random numbers are drawn in a fixed order (odometry, compass, sonar when due), so that a seeded
    generator and the same commands give the same frames.
    """
    p = model.params
    pose, motion = move(state.pose, float(command[0]), float(command[1]), p.dt_s, model.world, p.robot)
    dist, rot = model.odometry.measure(motion, rng)
    tick = state.tick + 1
    stamp = tick * p.dt_s
    heading = model.compass.measure(pose, rng)
    state = SimState(tick=tick, pose=pose, travel_since_scan_m=state.travel_since_scan_m + abs(dist),
                     time_since_scan_s=state.time_since_scan_s + p.dt_s, scans=state.scans,
                     collisions=state.collisions + motion.blocked,
                     path_length_m=state.path_length_m + abs(motion.distance_m))
    due = ((p.sonar_every_m > 0 and state.travel_since_scan_m >= p.sonar_every_m)
           or (p.sonar_period_s > 0 and state.time_since_scan_s >= p.sonar_period_s - 1e-9))
    scan = _scan(model, pose, state, stamp, rng) if due else None
    if scan is not None:
        state = _after_scan(state)
    odometry = OdometryStep(stamp=stamp, seq=tick - 1, distance_m=dist, rotation_rad=rot, dt_s=p.dt_s,
                            sonar_seq=state.scans - 1)  # the scans of this tick and earlier
    return state, Frame(
        tick=tick, truth=_truth(pose, tick, stamp),
        compass=CompassReading(stamp=stamp, seq=tick, heading_rad=heading), odometry=odometry, sonar=scan)


def _truth(pose: Pose, tick: int, stamp: float) -> TruthPose:
    return TruthPose(stamp=stamp, seq=tick, pose=Pose2(x_m=pose[0], y_m=pose[1], heading_rad=pose[2]))


def _scan(model: SimModel, pose: Pose, state: SimState, stamp: float, rng: np.random.Generator) -> SonarScan:
    sp = model.params.sonar
    ranges = model.sonar.measure(pose, model.world, rng)
    return SonarScan(stamp=stamp, seq=state.scans, angles_rad=model.sonar_angles, ranges_m=ranges.tolist(),
                     beam_width_rad=sp.beam_width_rad, min_range_m=sp.min_range_m, max_range_m=sp.max_range_m)


def _after_scan(state: SimState) -> SimState:
    return SimState(tick=state.tick, pose=state.pose, travel_since_scan_m=0.0, time_since_scan_s=0.0,
                    scans=state.scans + 1, collisions=state.collisions, path_length_m=state.path_length_m)
