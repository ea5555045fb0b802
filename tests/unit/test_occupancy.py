"""The Moravec-Elfes cone model and the growing global grid, against hand-placed walls."""

from __future__ import annotations

import math

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


def test_cone_update_is_the_rule_cell_by_cell():
    """Every cell of a scan's window against the rule evaluated one cell and one beam at a time, by bearing."""
    rng = np.random.default_rng(7)
    params = SonarConeParams()
    width, max_range = np.deg2rad(25), 5.0
    angles = np.deg2rad(np.arange(16) * 22.5)
    xs = (np.arange(-40, 40) + 0.5) * CELL + 0.03
    ys = (np.arange(-40, 40) + 0.5) * CELL - 0.07
    dx, dy = np.meshgrid(xs, ys)
    for heading in (0.0, 0.3, -2.9, np.pi):
        ranges = rng.uniform(0.3, 5.5, 16).clip(max=max_range)
        inc = cone_update(dx, dy, heading, angles, ranges, beam_width_rad=width, max_range_m=max_range,
                          cell_m=CELL, params=params)
        want = np.zeros_like(dx)
        half = params.echo_thickness_m / 2
        for (i, j), x in np.ndenumerate(dx):
            y = dy[i, j]
            dist = math.hypot(x, y)
            for a, r in zip(angles, ranges):
                off = math.remainder(math.atan2(y, x) - heading - a, 2 * math.pi)
                if not (abs(off) <= width / 2 or dist < CELL / 2):
                    continue
                echo = r < max_range
                if dist < (r if echo else min(r, params.free_range_m)) - half:
                    want[i, j] += params.logodds_empty
                if echo and abs(dist - r) <= half:
                    want[i, j] += params.logodds_occupied
        np.testing.assert_allclose(inc, want, atol=1e-9)


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


def test_composed_grids_equal_scans_integrated_at_the_shifted_positions():
    from services.common.occupancy import compose

    angles = np.deg2rad(np.arange(16) * 22.5)
    rng = np.random.default_rng(3)
    whole = GlobalGrid(CELL)
    parts = []
    for shift in [(0.0, 0.0), (3.0, 0.45), (-1.5, 2.1)]:  # whole cells: 20, 3, -10, 14
        part = GlobalGrid(CELL)
        for _ in range(3):
            off = rng.uniform(-0.5, 0.5, 2)
            ranges = rng.uniform(0.5, 6.5, 16)
            part.integrate(*off, 0.3, angles, ranges, beam_width_rad=0.44, max_range_m=6.5)
            whole.integrate(off[0] + shift[0], off[1] + shift[1], 0.3, angles, ranges, beam_width_rad=0.44,
                            max_range_m=6.5)
        parts.append((part, *shift))
    got = compose(parts, CELL)

    def cells(g):  # {(row, col) in world cell indices: log-odds} of the non-zero cells
        r0, c0 = np.round(g.origin[::-1] / CELL).astype(int)
        rows, cols = np.nonzero(g.logodds)
        return {(r + r0, c + c0): g.logodds[r, c] for r, c in zip(rows, cols)}

    a, b = cells(got), cells(whole)
    assert len(a) > 500 and set(a) == set(b)
    assert all(np.isclose(a[k], b[k]) for k in a)
