"""Local controller, planner and a whole exploration with a kinematic robot and a perfect recognizer."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from messages.types import Pose2
from services.explorer import Explorer, ExplorerParams, PlaceFix, velocity_command
from services.explorer.planner import dijkstra, path_to, reachable
from tests.unit._sonar_rooms import box, scan_at

P = ExplorerParams()
LIMITS = dict(max_speed_mps=P.max_speed_mps, max_turn_radps=P.max_turn_radps, heading_gain=P.heading_gain,
              turn_in_place_rad=P.turn_in_place_rad, stop_distance_m=P.stop_distance_m,
              slow_distance_m=P.slow_distance_m, avoid_distance_m=P.avoid_distance_m,
              avoid_gain=P.avoid_gain, front_half_angle_rad=P.front_half_angle_rad)
ROOM = box(-4, -4, 4, 4)


def test_straight_ahead_full_speed():
    c = velocity_command(0, 0, 0, 2, 0, scan_at(0, 0, 0, ROOM)[0], **LIMITS)
    assert (c.v_mps, c.omega_radps, c.blocked) == (0.3, 0.0, False)


def test_turns_in_place_towards_a_target_behind():
    c = velocity_command(0, 0, 0, 0, 2, None, **LIMITS)  # 90 deg left: 1.5 * pi/2 clipped to 1
    assert c.v_mps == 0.0 and c.omega_radps == pytest.approx(1.0)
    c = velocity_command(0, 0, 0, 2, -0.4, None, **LIMITS)  # small error: v = 0.3 cos(e)
    e = math.atan2(-0.4, 2)
    assert c.v_mps == pytest.approx(0.3 * math.cos(e)) and c.omega_radps == pytest.approx(1.5 * e)


def test_slows_then_stops_before_an_obstacle():
    wall_at = lambda d: box(-4, -4, d, 4)  # noqa: E731
    slow = velocity_command(0, 0, 0, 3, 0, scan_at(0, 0, 0, wall_at(0.55))[0], **LIMITS)
    # front clearance 0.55: v = 0.3 (0.55 - 0.3) / (0.8 - 0.3) = 0.15
    assert slow.front_clearance_m == pytest.approx(0.55)
    assert slow.v_mps == pytest.approx(0.15) and not slow.blocked
    stop = velocity_command(0, 0, 0, 3, 0, scan_at(0, 0, 0, wall_at(0.25))[0], **LIMITS)
    assert stop.v_mps == 0.0 and stop.blocked
    near_target = velocity_command(0, 0, 0, 0.2, 0, scan_at(0, 0, 0, wall_at(0.25))[0], **LIMITS)
    assert not near_target.blocked  # the target lies before the obstacle


def test_turns_away_from_a_close_wall_on_the_left():
    walls = box(-4, -4, 4, 0.4)  # wall 0.4 m to the left
    c = velocity_command(0, 0, 0, 3, 0, scan_at(0, 0, 0, walls)[0], **LIMITS)
    assert c.omega_radps < 0.0


@settings(max_examples=60, deadline=None)
@given(x=st.floats(-3, 3), y=st.floats(-3, 3), h=st.floats(-math.pi, math.pi),
       tx=st.floats(-3, 3), ty=st.floats(-3, 3))
def test_commands_stay_within_limits(x, y, h, tx, ty):
    c = velocity_command(x, y, h, tx, ty, scan_at(x, y, h, ROOM, rays_per_beam=1)[0], **LIMITS)
    assert 0.0 <= c.v_mps <= P.max_speed_mps
    assert abs(c.omega_radps) <= P.max_turn_radps


def test_dijkstra_path_and_reachability():
    g = {0: {1: 1.0, 2: 4.0}, 1: {0: 1.0, 2: 1.0, 3: 5.0}, 2: {0: 4.0, 1: 1.0, 3: 1.0}, 3: {1: 5.0, 2: 1.0}, 4: {}}
    dist, prev = dijkstra(g, 0)
    assert dist == {0: 0.0, 1: 1.0, 2: 2.0, 3: 3.0}
    assert path_to(prev, 0, 3) == [0, 1, 2, 3]
    assert path_to(prev, 0, 4) == []
    assert reachable(g, 0) == {0, 1, 2, 3}


def _explore(walls, start, *, max_steps=20000, dt=0.1):
    """A kinematic robot with perfect odometry and a recognizer that knows the true place."""
    ex = Explorer()
    x, y, h = start
    out = None
    last_fix = None
    for k in range(max_steps):
        t = k * dt
        scan = scan_at(x, y, h, walls, rays_per_beam=3)[0] if k % 3 == 0 else None
        fix = None
        if k % 3 == 0 and ex.places:
            confirmed = [q for q in ex.places.values() if q.confirmed]
            q = min(confirmed, key=lambda q: math.hypot(q.x_m - x, q.y_m - y))
            pid = q.place_id if math.hypot(q.x_m - x, q.y_m - y) < 0.3 else -1
            if pid != last_fix:
                fix = PlaceFix(pid, x - q.x_m, y - q.y_m, t)
                last_fix = pid
        out = ex.step(t, Pose2(x_m=x, y_m=y, heading_rad=h), scan, fix)
        if out.status.complete:
            return ex, out, t
        x += out.command.v_mps * math.cos(h) * dt
        y += out.command.v_mps * math.sin(h) * dt
        h = (h + out.command.omega_radps * dt + math.pi) % (2 * math.pi) - math.pi
    return ex, out, max_steps * dt


def test_explores_an_l_shaped_corridor_to_completion():
    # an L: 6 m east along y in [0, 1.6], then 4 m north along x in [4.4, 6]
    walls = [(0, 0, 6, 0), (6, 0, 6, 5.6), (6, 5.6, 4.4, 5.6), (4.4, 5.6, 4.4, 1.6), (4.4, 1.6, 0, 1.6), (0, 1.6, 0, 0)]
    ex, out, t = _explore(walls, (0.8, 0.8, 0.0))
    assert out.status.complete, f"not complete after {t:.0f} s: {out.status}"
    confirmed = [q for q in ex.places.values() if q.confirmed]
    assert out.status.predicted == 0
    assert 7 <= len(confirmed) <= 14
    # every confirmed place lies inside the corridor, the far ends were reached
    for q in confirmed:
        assert (0 < q.x_m < 6 and 0 < q.y_m < 1.6) or (4.4 < q.x_m < 6 and 0 < q.y_m < 5.6)
    assert max(q.x_m for q in confirmed) > 4.5 and max(q.y_m for q in confirmed) > 3.5
    # consecutive places about 1 m apart along the traversed links
    lengths = [ex.distance(a, b) for (a, b), link in ex.links.items() if link.kind == "traversed"]
    assert np.median(lengths) == pytest.approx(1.0, abs=0.2)
