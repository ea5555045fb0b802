"""A scripted commander for sensor_sim over the bus: answers every pose with the route driver's command.

Stands in for the explorer in tests, benchmarks and demonstrations. It keys on ground-truth poses
(``source="truth"``) or on dead-reckoned poses (``source="dr"``, the way a real planner would, so
that sensor noise changes the trajectory); either way the tick it answers is ``round(stamp / dt_s)``.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np
import zenoh

from messages import topics
from messages.codec import codec
from messages.types import DeadReckonedPose, TruthPose, VelocityCommand
from sim.route import RouteDriver, RouteParams


class RouteCommander:
    """Drives the robot along ``waypoints`` (world frame) by answering each pose with a command.

    Parameters
    ----------
    session : zenoh.Session
    waypoints : (K, 2) array
    robot : str
    source : "truth" or "dr"
    origin : (x_m, y_m)
        Where the dead-reckoning frame's origin lies in the world (the world's start); ``dr`` only.
    dt_s : float
        sensor_sim's tick, to turn stamps into ticks.
    until_tick : int, optional
        Answer no tick from this one on (a lockstep run then waits there).
    final_tick : int, optional
        Mark the command of this tick as the run's last (``VelocityCommand.final``): the simulator ends there.
    on_pose : callable, optional
        Called with every pose message received (in zenoh's thread), e.g. to record a trajectory.
    """

    def __init__(self, session: zenoh.Session, waypoints: np.ndarray, *, robot: str = topics.DEFAULT_ROBOT,
                 source: str = "truth", origin: tuple[float, float] = (0.0, 0.0), dt_s: float = 0.1,
                 loop: bool = True, params: RouteParams = RouteParams(), until_tick: int | None = None,
                 final_tick: int | None = None,
                 on_pose: Callable[[TruthPose | DeadReckonedPose], None] | None = None) -> None:
        if source not in ("truth", "dr"):
            raise ValueError(f"source must be 'truth' or 'dr', got {source!r}")
        self.driver = RouteDriver(waypoints, loop=loop, params=params)
        self._source = source
        self._origin = origin
        self._dt = dt_s
        self._on_pose = on_pose
        self._until = until_tick
        self._final = final_tick
        self._lock = threading.Lock()
        self._seq = 0
        self.last_tick = -1  # the latest tick answered
        self.first_command_at: float | None = None  # time.monotonic() of the first command sent
        self._last_cmd = (0.0, 0.0)
        self._pub = session.declare_publisher(topics.cmd_velocity(robot),
                                              encoding=zenoh.Encoding("application/msgpack"))
        if source == "truth":
            self._dec = codec(TruthPose)
            key = topics.truth_pose(robot)
        else:
            self._dec = codec(DeadReckonedPose)
            key = topics.dr_pose(robot)
        self._enc = codec(VelocityCommand)
        self._sub = session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        msg = self._dec.decode(sample.payload.to_bytes())
        if self._source == "truth":
            pose = (msg.pose.x_m, msg.pose.y_m, msg.pose.heading_rad)
        else:
            c = msg.compass
            pose = (c.x_m + self._origin[0], c.y_m + self._origin[1], c.heading_rad)
        tick = round(msg.stamp / self._dt)
        with self._lock:
            if self._on_pose is not None:
                self._on_pose(msg)
            if tick < self.last_tick or (self._until is not None and tick >= self._until):
                return  # an old pose (its tick is answered already), or past the end
            v, w = self.driver.command(pose) if tick > self.last_tick else self._last_cmd
            self._last_cmd = (v, w)
            self.last_tick = tick
            self._pub.put(self._enc.encode(VelocityCommand(stamp=msg.stamp, seq=self._seq, v_mps=v, omega_radps=w,
                                                           tick=tick, final=tick == self._final)))
            if self.first_command_at is None:
                self.first_command_at = time.monotonic()
            self._seq += 1

    @property
    def matched(self) -> bool:
        """Whether sensor_sim's command subscriber is known to this publisher."""
        return bool(self._pub.matching_status.matching)

    def close(self) -> None:
        self._sub.undeclare()
        self._pub.undeclare()
