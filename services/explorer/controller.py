"""Local controller (go to a point with sonar obstacle avoidance) and the sonar free-space classifier."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from messages.types import SonarScan
from sim.geometry import wrap_angle


@dataclass(frozen=True)
class Command:
    """A velocity command and what the controller saw."""

    v_mps: float
    omega_radps: float
    blocked: bool  # an obstacle closer than the stop distance stands between the robot and the target
    front_clearance_m: float  # nearest sonar range in the frontal sector (inf without a scan)


def velocity_command(x_m: float, y_m: float, heading_rad: float, target_x_m: float, target_y_m: float,
                     scan: SonarScan | None, *, max_speed_mps: float, max_turn_radps: float,
                     heading_gain: float, turn_in_place_rad: float, stop_distance_m: float,
                     slow_distance_m: float, avoid_distance_m: float, avoid_gain: float,
                     front_half_angle_rad: float) -> Command:
    """Drive towards a target point, slowing and turning away when the sonar sees obstacles.

    Notes
    -----
    ``omega = heading_gain * e`` for the heading error ``e`` to the target; ``v = max_speed *
    cos(e)``, zero while ``|e| > turn_in_place_rad``, and at most the distance to the target per
    second. The frontal clearance ``f`` (nearest range of the beams within ``front_half_angle_rad``
    of the heading) scales ``v`` by ``(f - stop) / (slow - stop)`` below ``slow_distance_m`` and
    stops the robot below ``stop_distance_m`` (``blocked`` when the target lies beyond ``f``).
    Every beam in the front half with range ``r < avoid_distance_m`` adds
    ``-avoid_gain * sign(a) * (1 - r / avoid)`` to ``omega`` (turn away from the side of bearing
    ``a``). Both outputs are clipped to the limits.

    Examples
    --------
    >>> c = velocity_command(0, 0, 0, 2, 0, None, max_speed_mps=0.3, max_turn_radps=1.0,
    ...     heading_gain=1.5, turn_in_place_rad=0.8, stop_distance_m=0.3, slow_distance_m=0.8,
    ...     avoid_distance_m=0.6, avoid_gain=0.8, front_half_angle_rad=0.5)
    >>> c.v_mps, c.omega_radps, c.blocked
    (0.3, 0.0, False)
    """
    dx, dy = target_x_m - x_m, target_y_m - y_m
    dist = float(np.hypot(dx, dy))
    err = float(wrap_angle(np.arctan2(dy, dx) - heading_rad)) if dist > 0.0 else 0.0
    omega = heading_gain * err
    v = 0.0 if abs(err) > turn_in_place_rad else max_speed_mps * max(0.0, np.cos(err))
    v = min(v, dist)
    front = float("inf")
    blocked = False
    if scan is not None and len(scan.ranges_m):
        angles = wrap_angle(np.asarray(scan.angles_rad, dtype=float))
        ranges = np.asarray(scan.ranges_m, dtype=float)
        in_front = np.abs(angles) <= front_half_angle_rad
        if in_front.any():
            front = float(ranges[in_front].min())
        if front < stop_distance_m:
            v = 0.0
            blocked = dist > front
        elif front < slow_distance_m:
            v *= (front - stop_distance_m) / (slow_distance_m - stop_distance_m)
        near = (np.abs(angles) < np.pi / 2) & (ranges < avoid_distance_m) & (np.abs(angles) > 1e-9)
        omega += float(-avoid_gain * (np.sign(angles[near]) * (1.0 - ranges[near] / avoid_distance_m)).sum())
    omega = float(np.clip(omega, -max_turn_radps, max_turn_radps))
    return Command(v_mps=float(np.clip(v, 0.0, max_speed_mps)), omega_radps=omega, blocked=blocked,
                   front_clearance_m=front)


def clear_towards(heading_rad: float, scan: SonarScan, direction_rad: float, length_m: float, *,
                  half_width_m: float, sample_step_m: float, edge_length_m: float | None = None) -> bool:
    """Whether the sonar has seen a free corridor of ``length_m`` in world direction ``direction_rad``.

    Notes
    -----
    Free-space classifier from positive evidence: a beam with range ``r`` shows its whole cone free
    up to ``r`` (its echo is the nearest surface inside the cone). The corridor (length ``length_m``,
    half width ``half_width_m``, along the direction from the robot) is sampled every
    ``sample_step_m`` on its centre line and both edges; it is clear when every sample lies inside
    some beam's cone no further than that beam's range. Unseen space or space behind an echo is
    never clear. ``edge_length_m`` (default ``length_m``) shortens the edges: far ahead, the edge
    samples fall into the side beams, whose echoes are the corridor's own walls.
    """
    angles = heading_rad + np.asarray(scan.angles_rad, dtype=float)
    ranges = np.asarray(scan.ranges_m, dtype=float)
    n = max(int(np.ceil(length_m / sample_step_m)), 1) + 1
    along = np.linspace(0.0, length_m, n)
    across = np.array([-half_width_m, 0.0, half_width_m])
    a, c = np.meshgrid(along, across, indexing="ij")
    edge = length_m if edge_length_m is None else edge_length_m
    keep = (c == 0.0) | (a <= edge + 1e-9)
    a, c = a[keep], c[keep]
    cos_d, sin_d = np.cos(direction_rad), np.sin(direction_rad)
    px, py = (a * cos_d - c * sin_d).ravel(), (a * sin_d + c * cos_d).ravel()
    dist = np.hypot(px, py)
    bearing = np.arctan2(py, px)
    in_cone = np.abs(wrap_angle(bearing[None, :] - angles[:, None])) <= scan.beam_width_rad / 2.0
    seen_free = (in_cone & (dist[None, :] <= ranges[:, None])).any(axis=0)
    return bool((seen_free | (dist < 1e-9)).all())


def open_directions(heading_rad: float, scan: SonarScan, *, directions: int, length_m: float,
                    half_width_m: float, sample_step_m: float, edge_length_m: float | None = None) -> list[float]:
    """World directions ``2 pi k / directions`` in which :func:`clear_towards` sees ``length_m`` free,
    coarse to fine: east, west, then the halves between them, their halves, and so on (with 16, the
    four axes, the diagonals, then the eight between), so that a caller keeping the first of two close
    candidates builds the coarse lattice where all are open and the fine directions only fill gaps.

    Examples
    --------
    >>> [k for k in _coarse_to_fine(8)]
    [0, 4, 2, 6, 1, 3, 5, 7]
    """
    cands = [2.0 * np.pi * k / directions for k in _coarse_to_fine(directions)]
    return [float(wrap_angle(c)) for c in cands
            if clear_towards(heading_rad, scan, c, length_m, half_width_m=half_width_m,
                             sample_step_m=sample_step_m, edge_length_m=edge_length_m)]


def _coarse_to_fine(n: int) -> list[int]:
    """``0..n-1`` ordered by how coarse a subdivision of the circle each index belongs to."""
    return sorted(range(n), key=lambda k: (-(k & -k) if k else -n - 1, k))
