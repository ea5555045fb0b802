"""Moravec-Elfes occupancy from sonar: the cone model, for local grids and the global grid map."""

from __future__ import annotations

import math

import msgspec
import numpy as np


class SonarConeParams(msgspec.Struct, frozen=True, kw_only=True):
    """The inverse sensor model of one sonar beam."""

    logodds_occupied: float = 0.9  # added to cells on the echo arc
    logodds_empty: float = -0.4  # added to cells swept by the beam before the echo
    echo_thickness_m: float = 0.15  # radial thickness of the occupied arc
    free_range_m: float = 3.0  # a beam without echo sweeps cells empty up to this range only


def cone_update(dx: np.ndarray, dy: np.ndarray, heading_rad: float, angles_rad: np.ndarray,
                ranges_m: np.ndarray, *, beam_width_rad: float, max_range_m: float, cell_m: float,
                params: SonarConeParams) -> np.ndarray:
    """Log-odds increment of each cell from one scan.

    Parameters
    ----------
    dx, dy : numpy.ndarray
        Cell centres minus the sensor position (any shape, the same for both), metres.
    heading_rad : float
        Robot heading (world frame).
    angles_rad, ranges_m : numpy.ndarray
        Beam bearings relative to the heading, and measured ranges (``max_range_m``: no echo).

    Returns
    -------
    numpy.ndarray
        The increment, shaped like ``dx``.

    Notes
    -----
    Moravec-Elfes with a uniform cone: cells inside a beam's cone closer than ``r - thickness/2``
    get ``logodds_empty``; with an echo (``r < max_range``), cells within ``thickness/2`` of ``r``
    get ``logodds_occupied``. A beam without echo sweeps empty up to ``free_range_m`` (long sonar
    misses are often specular, so they say little far away). The sensor's own cell is empty.
    Vectorised over beams and cells.
    """
    dist = np.hypot(dx, dy)
    ranges = np.clip(np.asarray(ranges_m, dtype=float), 0.0, max_range_m)
    echo = ranges < max_range_m
    sweep = np.where(echo, ranges, np.minimum(ranges, params.free_range_m))
    beams = heading_rad + np.asarray(angles_rad, dtype=float)
    shape = (len(beams),) + (1,) * dist.ndim
    # |bearing - beam| <= width / 2 as the cell's vector dotted with the beam's direction against
    # dist cos(width / 2) (width < 2 pi): the same cells as arctan2 and wrapping, in a third of the time
    along = np.cos(beams).reshape(shape) * dx[None] + np.sin(beams).reshape(shape) * dy[None]
    in_cone = (along >= dist[None] * math.cos(beam_width_rad / 2.0)) | (dist[None] < cell_m / 2.0)
    half = params.echo_thickness_m / 2.0
    empty = in_cone & (dist[None] < sweep.reshape(shape) - half)
    occupied = in_cone & (np.abs(dist[None] - ranges.reshape(shape)) <= half) & echo.reshape(shape)
    return params.logodds_empty * empty.sum(axis=0) + params.logodds_occupied * occupied.sum(axis=0)


class GlobalGrid:
    """A world-aligned log-odds grid that grows to fit the scans integrated into it.

    Cell ``[row, col]`` has its centre at ``(origin_x + (col + 0.5) * cell, origin_y + (row + 0.5) * cell)``.
    Each scan touches only the window of cells its beams can reach.
    """

    def __init__(self, cell_m: float, params: SonarConeParams = SonarConeParams()) -> None:
        self.cell_m = cell_m
        self.params = params
        self.origin = np.zeros(2)
        self.logodds = np.zeros((0, 0))

    def _ensure(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """Grow the grid (in whole cells) so that it covers [lo, hi]."""
        c = self.cell_m
        if self.logodds.size == 0:
            self.origin = np.floor(lo / c) * c
            rows, cols = (np.ceil((hi - self.origin) / c).astype(int) + 1)[::-1]
            self.logodds = np.zeros((rows, cols))
            return
        top = self.origin + np.array(self.logodds.shape[::-1]) * c
        new_lo = np.minimum(self.origin, np.floor(lo / c) * c)
        new_hi = np.maximum(top, np.ceil(hi / c) * c)
        if np.allclose(new_lo, self.origin) and np.allclose(new_hi, top):
            return
        cols, rows = np.round((new_hi - new_lo) / c).astype(int)
        off_c, off_r = np.round((self.origin - new_lo) / c).astype(int)
        grown = np.zeros((rows, cols))
        grown[off_r:off_r + self.logodds.shape[0], off_c:off_c + self.logodds.shape[1]] = self.logodds
        self.origin, self.logodds = new_lo, grown

    def integrate(self, x_m: float, y_m: float, heading_rad: float, angles_rad: np.ndarray, ranges_m: np.ndarray,
                  *, beam_width_rad: float, max_range_m: float) -> None:
        """Add one scan taken at ``(x_m, y_m, heading_rad)``."""
        ranges = np.asarray(ranges_m, dtype=float)
        echo = ranges < max_range_m
        reach = float(np.max(np.where(echo, ranges, np.minimum(ranges, self.params.free_range_m)), initial=0.0))
        reach += self.params.echo_thickness_m + self.cell_m
        centre = np.array([x_m, y_m])
        self._ensure(centre - reach, centre + reach)
        c = self.cell_m
        c0, r0 = np.floor((centre - reach - self.origin) / c).astype(int)
        c1, r1 = np.ceil((centre + reach - self.origin) / c).astype(int)
        r0, c0 = max(r0, 0), max(c0, 0)
        r1, c1 = min(r1, self.logodds.shape[0]), min(c1, self.logodds.shape[1])
        xs = self.origin[0] + (np.arange(c0, c1) + 0.5) * c - x_m
        ys = self.origin[1] + (np.arange(r0, r1) + 0.5) * c - y_m
        dx, dy = np.meshgrid(xs, ys)  # [row, col]
        self.logodds[r0:r1, c0:c1] += cone_update(dx, dy, heading_rad, angles_rad, ranges,
                                                  beam_width_rad=beam_width_rad, max_range_m=max_range_m,
                                                  cell_m=c, params=self.params)

    def occupancy_percent(self) -> np.ndarray:
        """Cells as bytes: 0-100 occupancy probability in percent, 255 where nothing was seen."""
        p = 1.0 / (1.0 + np.exp(-self.logodds))
        out = np.round(p * 100.0).astype(np.uint8)
        out[self.logodds == 0.0] = 255
        return out


def compose(parts: list[tuple[GlobalGrid, float, float]], cell_m: float) -> GlobalGrid:
    """One grid from several, each shifted by ``(dx, dy)`` metres (rounded to whole cells) and added.

    Log-odds add, so this equals integrating every part's scans at the shifted positions, up to half
    a cell of rounding. Parts must share ``cell_m``.
    """
    out = GlobalGrid(cell_m, parts[0][0].params if parts else SonarConeParams())
    placed = []
    for g, dx, dy in parts:
        if g.logodds.size == 0:
            continue
        if g.cell_m != cell_m:
            raise ValueError(f"grid of {g.cell_m} m cells composed at {cell_m} m")
        origin = g.origin + np.round(np.array([dx, dy]) / cell_m) * cell_m
        placed.append((g, origin))
    if not placed:
        return out
    lo = np.min([o for _, o in placed], axis=0)
    hi = np.max([o + np.array(g.logodds.shape[::-1]) * cell_m for g, o in placed], axis=0)
    cols, rows = np.round((hi - lo) / cell_m).astype(int)
    out.origin, out.logodds = lo, np.zeros((rows, cols))
    for g, origin in placed:
        c0, r0 = np.round((origin - lo) / cell_m).astype(int)
        out.logodds[r0:r0 + g.logodds.shape[0], c0:c0 + g.logodds.shape[1]] += g.logodds
    return out
