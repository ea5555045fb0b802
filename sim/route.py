"""A scripted route driver: velocity commands that take the robot through a list of waypoints."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.geometry import wrap_angle


@dataclass(frozen=True)
class RouteParams:
    cruise_speed_mps: float = 0.5  # forward speed on straight legs
    max_turn_radps: float = 1.2  # turn-rate limit of the commands
    heading_gain_per_s: float = 2.0  # turn rate commanded per radian of heading error
    turn_in_place_rad: float = 0.4  # heading error beyond which the robot stops and turns first
    arrive_radius_m: float = 0.2  # a waypoint is reached within this distance
    approach_radius_m: float = 0.6  # the last waypoint of an open route is approached slowing down


@dataclass(frozen=True)
class RouteState:
    index: int = 0  # the waypoint being driven to
    laps: int = 0  # completed laps (closed routes)
    done: bool = False  # an open route is finished


def drive(state: RouteState, pose: tuple[float, float, float], waypoints: np.ndarray, *, loop: bool,
          params: RouteParams = RouteParams()) -> tuple[RouteState, tuple[float, float]]:
    """One command ``(v_mps, omega_radps)`` towards the current waypoint from ``pose``.

    Parameters
    ----------
    state : RouteState
    pose : (x_m, y_m, heading_rad)
    waypoints : (K, 2) array
    loop : bool
        True: after the last waypoint drive to the first again (one lap more each time).

    Returns
    -------
    The new state and the command; ``(0, 0)`` once an open route is done.
    """
    if state.done:
        return state, (0.0, 0.0)
    k = waypoints.shape[0]
    index, laps = state.index, state.laps
    x, y, th = pose
    for _ in range(k):  # skip every waypoint already reached (at most one full round)
        tx, ty = waypoints[index]
        if math.hypot(tx - x, ty - y) > params.arrive_radius_m:
            break
        index += 1
        if index == k:
            if not loop:
                return RouteState(index=k - 1, laps=laps + 1, done=True), (0.0, 0.0)
            index, laps = 0, laps + 1
    tx, ty = waypoints[index]
    dist = math.hypot(tx - x, ty - y)
    err = wrap_angle(math.atan2(ty - y, tx - x) - th)
    omega = max(-params.max_turn_radps, min(params.max_turn_radps, params.heading_gain_per_s * err))
    if abs(err) > params.turn_in_place_rad:
        v = 0.0
    else:
        v = params.cruise_speed_mps * math.cos(err)
        if not loop and index == k - 1:
            v *= max(0.2, min(1.0, dist / params.approach_radius_m))
    return RouteState(index=index, laps=laps), (v, omega)


class RouteDriver:
    """:func:`drive` with its state kept: ``command(pose)`` per step."""

    def __init__(self, waypoints: np.ndarray | list, *, loop: bool = True,
                 params: RouteParams = RouteParams()) -> None:
        self.waypoints = np.asarray(waypoints, dtype=float).reshape(-1, 2)
        if self.waypoints.shape[0] < 1:
            raise ValueError("a route needs at least one waypoint")
        self.loop = loop
        self.params = params
        self.state = RouteState()

    def command(self, pose: tuple[float, float, float]) -> tuple[float, float]:
        self.state, cmd = drive(self.state, pose, self.waypoints, loop=self.loop, params=self.params)
        return cmd
