"""The Moravec-Elfes cone model and the growing global grid, against hand-placed walls."""

from __future__ import annotations

import numpy as np

from services.common.occupancy import GlobalGrid, SonarConeParams, cone_update

CELL = 0.15


def _cell_of(grid: GlobalGrid, x: float, y: float) -> tuple[int, int]:
    col, row = np.floor((np.array([x, y]) - grid.origin) / grid.cell_m).astype(int)
    return row, col


def test_single_beam_marks_free_then_occupied():
    xs = np.arange(0.0, 3.0, 0.05)
    inc = cone_update(xs, np.zeros_like(xs), 0.0, np.array([0.0]), np.array([2.0]), beam_width_rad=0.3,
                      max_range_m=6.5, cell_m=CELL, params=SonarConeParams(echo_thickness_m=0.2))
    assert np.all(inc[xs < 1.89] < 0)
    assert np.all(inc[(xs > 1.91) & (xs < 2.09)] > 0)
    assert np.all(inc[xs > 2.11] == 0)


def test_beam_without_echo_sweeps_free_only_to_free_range():
    xs = np.arange(0.0, 6.0, 0.05)
    p = SonarConeParams(free_range_m=2.5)
    inc = cone_update(xs, np.zeros_like(xs), 0.0, np.array([0.0]), np.array([6.5]), beam_width_rad=0.3,
                      max_range_m=6.5, cell_m=CELL, params=p)
    assert np.all(inc[xs < 2.4] < 0) and np.all(inc[xs > 2.5] == 0)


def test_global_grid_sees_a_wall_from_two_poses_and_grows():
    grid = GlobalGrid(CELL)
    angles = np.deg2rad(np.arange(16) * 22.5)
    # a wall at y = 2 seen from below: the upward beam (90 deg) echoes at 2 - y
    for x in (0.0, 4.0):
        ranges = np.full(16, 6.5)
        ranges[4] = 2.0
        grid.integrate(x, 0.0, 0.0, angles, ranges, beam_width_rad=np.deg2rad(25), max_range_m=6.5)
    occ = grid.occupancy_percent()
    for x in (0.0, 4.0):
        assert occ[_cell_of(grid, x, 2.0)] > 60
        assert occ[_cell_of(grid, x, 1.0)] < 50
    assert occ[_cell_of(grid, 2.0, 2.7)] == 255  # beyond the free range of the diagonal beams
    assert grid.origin[0] <= -3.0 and grid.origin[0] + grid.logodds.shape[1] * CELL >= 7.0
