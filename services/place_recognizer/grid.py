"""Local occupancy grids from sonar scans (Moravec-Elfes log-odds update), aligned with world axes."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from messages.types import Pose2, SonarScan

OCCUPIED, EMPTY, UNKNOWN = 0, 1, 2  # cell labels, also the row order of a histogram


@dataclass(frozen=True)
class PlacedScan:
    """One sonar scan with the pose it was taken from (dead-reckoning frame).

    Attributes
    ----------
    x_m, y_m, heading_rad : float
        Pose of the robot when the scan was taken.
    angles_rad, ranges_m : numpy.ndarray
        Bearing of each transducer relative to the heading, and its range.
    beam_width_rad, min_range_m, max_range_m : float
        Full cone opening of each beam; ranges at ``max_range_m`` carry no echo.
    """

    x_m: float
    y_m: float
    heading_rad: float
    angles_rad: np.ndarray
    ranges_m: np.ndarray
    beam_width_rad: float
    min_range_m: float
    max_range_m: float

    @classmethod
    def from_message(cls, scan: SonarScan, pose: Pose2) -> PlacedScan:
        """Pair a :class:`messages.types.SonarScan` with the dead-reckoned pose it was taken at."""
        return cls(
            x_m=pose.x_m, y_m=pose.y_m, heading_rad=pose.heading_rad,
            angles_rad=np.asarray(scan.angles_rad, dtype=float),
            ranges_m=np.asarray(scan.ranges_m, dtype=float),
            beam_width_rad=scan.beam_width_rad, min_range_m=scan.min_range_m,
            max_range_m=scan.max_range_m,
        )


def grid_cells(half_width_m: float, cell_m: float) -> int:
    """Number of cells per axis of a local grid: odd, so that one cell sits on the centre."""
    return 2 * int(round(half_width_m / cell_m)) + 1


def empty_grid(half_width_m: float, cell_m: float) -> np.ndarray:
    """A local grid of log-odds, all zero (unknown); indexed ``[ix, iy]``."""
    n = grid_cells(half_width_m, cell_m)
    return np.zeros((n, n))


def integrate_scan(
    logodds: np.ndarray,
    centre_xy: tuple[float, float],
    scan: PlacedScan,
    *,
    cell_m: float,
    logodds_occupied: float,
    logodds_empty: float,
    echo_thickness_m: float,
) -> np.ndarray:
    """Add one scan to a local grid centred on ``centre_xy``; returns the new log-odds grid.

    Parameters
    ----------
    logodds : numpy.ndarray
        Square grid ``[ix, iy]``, cell ``(h, h)`` on ``centre_xy`` (``h = n // 2``).
    centre_xy : tuple of float
        World position of the grid centre.
    scan : PlacedScan
        The scan and its pose, in the same frame as ``centre_xy``.
    cell_m, logodds_occupied, logodds_empty, echo_thickness_m : float
        Cell side, log-odds increments, radial thickness of the occupied arc.

    Notes
    -----
    Moravec-Elfes with a uniform cone: for every beam with range ``r``, cells inside the cone
    (``|bearing - beam| <= width / 2``) closer than ``r - thickness / 2`` get ``logodds_empty``;
    if the beam has an echo (``r < max_range``), cells within ``thickness / 2`` of ``r`` get
    ``logodds_occupied``. The cell the sensor sits in is always swept empty. Vectorised over
    beams and cells.
    """
    n = logodds.shape[0]
    h = n // 2
    coords = (np.arange(n) - h) * cell_m
    dx = coords[:, None] + (centre_xy[0] - scan.x_m)  # [ix, iy] cell centre minus sensor position
    dy = coords[None, :] + (centre_xy[1] - scan.y_m)
    dist = np.hypot(dx, dy)
    ranges = np.clip(scan.ranges_m, 0.0, scan.max_range_m)
    beams = scan.heading_rad + np.asarray(scan.angles_rad)
    # |bearing - beam| <= width / 2 as cos(bearing - beam) >= cos(width / 2), i.e. the cell's vector
    # dotted with the beam's direction: a third of the time of arctan2 and wrapping (width < 2 pi)
    along = np.cos(beams)[:, None, None] * dx[None] + np.sin(beams)[:, None, None] * dy[None]
    in_cone = (along >= dist[None] * math.cos(scan.beam_width_rad / 2.0)) | (dist[None] < cell_m / 2.0)
    half = echo_thickness_m / 2.0
    r = ranges[:, None, None]
    empty = in_cone & (dist[None] < r - half)
    occupied = in_cone & (np.abs(dist[None] - r) <= half) & (r < scan.max_range_m)
    return logodds + logodds_empty * empty.sum(axis=0) + logodds_occupied * occupied.sum(axis=0)


def build_grid(
    scans: Sequence[PlacedScan],
    centre_xy: tuple[float, float],
    *,
    half_width_m: float,
    cell_m: float,
    logodds_occupied: float,
    logodds_empty: float,
    echo_thickness_m: float,
) -> np.ndarray:
    """A local log-odds grid centred on ``centre_xy`` from several scans (see :func:`integrate_scan`)."""
    grid = empty_grid(half_width_m, cell_m)
    for scan in scans:
        grid = integrate_scan(
            grid, centre_xy, scan, cell_m=cell_m, logodds_occupied=logodds_occupied,
            logodds_empty=logodds_empty, echo_thickness_m=echo_thickness_m,
        )
    return grid


def classify(logodds: np.ndarray, threshold: float) -> np.ndarray:
    """Cell labels: OCCUPIED above ``threshold``, EMPTY below ``-threshold``, UNKNOWN between."""
    labels = np.full(logodds.shape, UNKNOWN, dtype=np.int8)
    labels[logodds > threshold] = OCCUPIED
    labels[logodds < -threshold] = EMPTY
    return labels
