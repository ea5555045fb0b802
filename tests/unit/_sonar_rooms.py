"""Test helper: a ring sonar in rooms made of wall segments (nearest echo inside each cone)."""

from __future__ import annotations

import numpy as np

from messages.types import Pose2, SonarScan
from sim.geometry import ray_cast

RING_ANGLES = [2.0 * np.pi * k / 16 for k in range(16)]
BEAM_WIDTH_RAD = np.deg2rad(22.5)
MAX_RANGE_M = 5.0
MIN_RANGE_M = 0.15


def box(x0: float, y0: float, x1: float, y1: float) -> list[tuple[float, float, float, float]]:
    return [(x0, y0, x1, y0), (x1, y0, x1, y1), (x1, y1, x0, y1), (x0, y1, x0, y0)]


def scan_at(x: float, y: float, heading: float, walls, *, rays_per_beam: int = 5,
            beam_width_rad: float = BEAM_WIDTH_RAD, max_range_m: float = MAX_RANGE_M,
            stamp: float = 0.0, seq: int = 0) -> tuple[SonarScan, Pose2]:
    spread = np.linspace(-beam_width_rad / 2, beam_width_rad / 2, rays_per_beam)
    rays = (heading + np.asarray(RING_ANGLES)[:, None] + spread[None, :]).ravel()
    hits, _, _ = ray_cast(np.array([x, y]), rays, np.asarray(walls, dtype=float), max_range_m)
    nearest = hits.reshape(len(RING_ANGLES), rays_per_beam).min(axis=1)
    ranges = [float(r) for r in np.clip(nearest, MIN_RANGE_M, max_range_m)]
    scan = SonarScan(stamp=stamp, seq=seq, angles_rad=list(RING_ANGLES), ranges_m=ranges,
                     beam_width_rad=float(beam_width_rad), min_range_m=MIN_RANGE_M,
                     max_range_m=max_range_m)
    return scan, Pose2(x_m=x, y_m=y, heading_rad=heading)
