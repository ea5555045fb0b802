"""The simulated robot: a disc with unicycle kinematics that walls stop."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.geometry import point_segment_distance, segment_segment_distance, wrap_angle
from sim.world import ROBOT_RADIUS_M, World

Pose = tuple[float, float, float]  # x_m, y_m, heading_rad
_BISECTIONS = 12  # halvings of the step when it is blocked: the stop lies within step / 4096
_NEAR_M = 1.5  # walls indexed this far around the robot's cell cover any step shorter than this less the radius


@dataclass(frozen=True)
class RobotParams:
    radius_m: float = ROBOT_RADIUS_M  # the robot is a disc of this radius
    max_speed_mps: float = 0.6  # forward and backward speed limit
    max_turn_radps: float = 1.5  # turn-rate limit


@dataclass(frozen=True)
class Motion:
    """What one step really did."""

    distance_m: float  # signed distance travelled along the chord of the step
    rotation_rad: float  # heading change
    blocked: bool  # a wall stopped the robot in this step


def clamp_command(v_mps: float, omega_radps: float, params: RobotParams) -> tuple[float, float]:
    """The command the motors execute: speed and turn rate within the robot's limits (NaN -> 0)."""
    v = 0.0 if not math.isfinite(v_mps) else max(-params.max_speed_mps, min(params.max_speed_mps, v_mps))
    w = 0.0 if not math.isfinite(omega_radps) else max(-params.max_turn_radps,
                                                        min(params.max_turn_radps, omega_radps))
    return v, w


def move(pose: Pose, v_mps: float, omega_radps: float, dt_s: float, world: World,
         params: RobotParams) -> tuple[Pose, Motion]:
    """Integrate one step of unicycle motion; a wall in the way stops the robot where it touches.

    Notes
    -----
    Exact unicycle integration: with ``w != 0`` the robot moves along an arc of radius ``v / w``;
    the collision test uses the chord of that arc (the two differ by under a millimetre at the
    speeds and steps used). The heading always turns by ``w dt``: a disc can always turn in place.
    Invariant: the robot's clearance from every wall stays at least its radius.
    """
    v, w = clamp_command(v_mps, omega_radps, params)
    x, y, th = pose
    dth = w * dt_s
    if abs(dth) > 1e-9:
        r = v / w
        nx = x + r * (math.sin(th + dth) - math.sin(th))
        ny = y - r * (math.cos(th + dth) - math.cos(th))
    else:
        nx = x + v * dt_s * math.cos(th + 0.5 * dth)
        ny = y + v * dt_s * math.sin(th + 0.5 * dth)
    new_th = wrap_angle(th + dth)
    chord = math.hypot(nx - x, ny - y)
    if chord == 0.0:
        return (x, y, new_th), Motion(0.0, dth, False)
    reach = chord + params.radius_m
    near = world.walls_near(x, y, _NEAR_M) if reach < _NEAR_M else world.walls
    if near.shape[0] == 0 or point_segment_distance(np.array(((x, y),)), near).min() >= reach \
            or _clear(x, y, nx, ny, near, params.radius_m):  # the first test: the whole disc sweep is clear
        return (nx, ny, new_th), Motion(math.copysign(chord, v), dth, False)
    lo, hi = 0.0, 1.0  # the largest fraction of the step that stays clear
    for _ in range(_BISECTIONS):
        mid = 0.5 * (lo + hi)
        if _clear(x, y, x + mid * (nx - x), y + mid * (ny - y), near, params.radius_m):
            lo = mid
        else:
            hi = mid
    ex, ey = x + lo * (nx - x), y + lo * (ny - y)
    return (ex, ey, new_th), Motion(math.copysign(lo * chord, v), dth, True)


def _clear(x0: float, y0: float, x1: float, y1: float, walls: np.ndarray, radius: float) -> bool:
    return bool(segment_segment_distance(np.array((x0, y0, x1, y1)), walls).min() >= radius)
