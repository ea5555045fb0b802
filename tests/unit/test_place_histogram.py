"""Local grids, histograms and the histogram match of the place recognizer."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.place_recognizer.grid import (
    EMPTY,
    OCCUPIED,
    UNKNOWN,
    PlacedScan,
    build_grid,
    classify,
    integrate_scan,
)
from services.place_recognizer.histogram import histograms, match_axis, match_error_variance
from tests.unit._sonar_rooms import box, scan_at

CELL = 0.15
GRID = dict(half_width_m=3.0, cell_m=CELL, logodds_occupied=0.9, logodds_empty=-0.4, echo_thickness_m=0.15)


def _room_hist(x, y, walls, headings=(0.0, 0.2)):
    scans = [PlacedScan.from_message(*scan_at(x, y, h, walls)) for h in headings]
    return histograms(classify(build_grid(scans, (x, y), **GRID), 0.2))


def _shift_grid(labels: np.ndarray, k: int, axis: int) -> np.ndarray:
    """out[j] = labels[j + k] along ``axis``; cells shifted in from outside are unknown."""
    out = np.full_like(labels, UNKNOWN)
    n = labels.shape[axis]
    src = [slice(None)] * 2
    dst = [slice(None)] * 2
    if k >= 0:
        src[axis], dst[axis] = slice(k, n), slice(0, n - k)
    else:
        src[axis], dst[axis] = slice(0, n + k), slice(-k, n)
    out[tuple(dst)] = labels[tuple(src)]
    return out


def test_histograms_count_labels_per_column_and_row():
    labels = np.array([[OCCUPIED, EMPTY, UNKNOWN],
                       [EMPTY, EMPTY, OCCUPIED],
                       [UNKNOWN, UNKNOWN, UNKNOWN]])  # [ix, iy]
    h = histograms(labels)
    np.testing.assert_array_equal(h.x, [[1, 1, 0], [1, 2, 0], [1, 0, 3]])
    np.testing.assert_array_equal(h.y, [[1, 0, 1], [1, 2, 0], [1, 1, 2]])


def test_match_scores_hand_computed():
    # two elements, each a column of 2 cells: a = [(O1,E1,U0), (O0,E0,U2)], b = [(O0,E2,U0), (O1,E1,U0)]
    a = np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 2.0]])
    b = np.array([[0.0, 1.0], [2.0, 1.0], [0.0, 0.0]])
    m = match_axis(a, b, 1)
    # s=-1: a1 vs b0: 0+0+0 = 0 over w=2 -> 0
    # s= 0: a0 vs b0: 0+1+0, a1 vs b1: 0+0+0 -> 1/4
    # s=+1: a0 vs b1: 1+1+0 = 2 over w=2 -> 1
    np.testing.assert_allclose(m.scores, [0.0, 0.25, 1.0])
    assert int(m.best_shift) == 1
    assert float(m.best_score) == pytest.approx(1.0)
    assert float(m.mean_score) == pytest.approx(1.25 / 3)


def test_match_error_variance_eqs_20_21():
    # k / (M* - M-bar)^2 = 1 / 0.25^2 = 16; flat match floored at the minimum spread
    assert float(match_error_variance(np.array(0.75), np.array(0.5), k_m2=1.0, min_spread=0.01)) == pytest.approx(16.0)
    assert float(match_error_variance(np.array(0.5), np.array(0.5), k_m2=1e-3, min_spread=0.02)) == pytest.approx(2.5)


@settings(max_examples=40, deadline=None)
@given(k=st.integers(-8, 8), axis=st.integers(0, 1), seed=st.integers(0, 2**31 - 1))
def test_grid_matched_with_itself_shifted_by_k_cells(k, axis, seed):
    rng = np.random.default_rng(seed)
    labels = rng.integers(0, 3, size=(41, 41)).astype(np.int8)
    stored = histograms(labels)
    observed = histograms(_shift_grid(labels, k, axis))
    max_shift = 10
    mx = match_axis(observed.x, stored.x, max_shift)
    my = match_axis(observed.y, stored.y, max_shift)
    shifted, other = (mx, my) if axis == 0 else (my, mx)
    assert int(shifted.best_shift) * CELL == pytest.approx(k * CELL)
    assert float(shifted.scores[k + max_shift]) == pytest.approx(1.0)
    assert float(shifted.best_score) == pytest.approx(1.0)
    # the other axis' histogram changed (cells replaced by unknown) but is still best unshifted
    assert int(other.best_shift) == 0 or k == 0


@settings(max_examples=20, deadline=None)
@given(k=st.integers(-10, 10), seed=st.integers(0, 2**31 - 1))
def test_rolled_histograms_match_at_the_roll(k, seed):
    rng = np.random.default_rng(seed)
    labels = rng.integers(0, 3, size=(41, 41)).astype(np.int8)
    stored = histograms(labels).x
    m = match_axis(np.roll(stored, -k, axis=1), stored, 10)
    assert int(m.best_shift) == k
    assert float(m.scores[k + 10]) == pytest.approx(1.0)


def test_match_is_vectorised_over_many_stored():
    rng = np.random.default_rng(3)
    hs = [histograms(rng.integers(0, 3, size=(21, 21)).astype(np.int8)).x for _ in range(4)]
    many = match_axis(hs[2], np.stack(hs), 5)
    for i, h in enumerate(hs):
        one = match_axis(hs[2], h, 5)
        np.testing.assert_allclose(many.scores[i], one.scores)
    assert int(np.argmax(many.best_score)) == 2


def test_moravec_elfes_single_beam():
    # one beam straight along +x, 20 deg wide, echo at 1.5 m; grid centred on the sensor
    scan = PlacedScan(x_m=0.0, y_m=0.0, heading_rad=0.0, angles_rad=np.array([0.0]),
                      ranges_m=np.array([1.5]), beam_width_rad=np.deg2rad(20.0), min_range_m=0.1,
                      max_range_m=5.0)
    grid = integrate_scan(np.zeros((41, 41)), (0.0, 0.0), scan, cell_m=CELL, logodds_occupied=0.9,
                          logodds_empty=-0.4, echo_thickness_m=0.15)
    h = 20
    assert grid[h, h] == pytest.approx(-0.4)  # the sensor's own cell
    assert grid[h + 5, h] == pytest.approx(-0.4)  # 0.75 m ahead: swept
    assert grid[h + 10, h] == pytest.approx(0.9)  # 1.5 m ahead: the echo
    assert grid[h + 12, h] == 0.0  # behind the echo: unknown
    assert grid[h, h + 5] == 0.0  # outside the cone: unknown
    assert grid[h - 5, h] == 0.0  # behind the sensor: unknown
    no_echo = PlacedScan(**{**scan.__dict__, "ranges_m": np.array([5.0])})
    g2 = integrate_scan(np.zeros((41, 41)), (0.0, 0.0), no_echo, cell_m=CELL, logodds_occupied=0.9,
                        logodds_empty=-0.4, echo_thickness_m=0.15)
    assert (g2 <= 0.0).all() and g2[h + 19, h] == pytest.approx(-0.4)



def _integrate_cell_by_cell(centre, scan: PlacedScan, n: int) -> np.ndarray:
    """Moravec-Elfes as the docstring states it, one cell and one beam at a time with bearings."""
    grid = np.zeros((n, n))
    h = n // 2
    for ix in range(n):
        for iy in range(n):
            dx = (ix - h) * CELL + centre[0] - scan.x_m
            dy = (iy - h) * CELL + centre[1] - scan.y_m
            dist = float(np.hypot(dx, dy))
            for angle, rng in zip(scan.angles_rad, np.clip(scan.ranges_m, 0.0, scan.max_range_m)):
                off = (np.arctan2(dy, dx) - scan.heading_rad - angle + np.pi) % (2 * np.pi) - np.pi
                if not (abs(off) <= scan.beam_width_rad / 2 or dist < CELL / 2):
                    continue
                if dist < rng - 0.075:
                    grid[ix, iy] += -0.4
                if abs(dist - rng) <= 0.075 and rng < scan.max_range_m:
                    grid[ix, iy] += 0.9
    return grid


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_vectorised_grid_update_is_the_cell_by_cell_rule(seed):
    rng = np.random.default_rng(seed)
    scan = PlacedScan(x_m=rng.uniform(-0.4, 0.4), y_m=rng.uniform(-0.4, 0.4), heading_rad=rng.uniform(-np.pi, np.pi),
                      angles_rad=np.linspace(-np.pi, np.pi, 16, endpoint=False), ranges_m=rng.uniform(0.2, 6.0, 16),
                      beam_width_rad=np.deg2rad(rng.uniform(10.0, 40.0)), min_range_m=0.1, max_range_m=5.0)
    centre = (rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2))
    got = integrate_scan(np.zeros((21, 21)), centre, scan, cell_m=CELL, logodds_occupied=0.9,
                         logodds_empty=-0.4, echo_thickness_m=0.15)
    np.testing.assert_allclose(got, _integrate_cell_by_cell(centre, scan, 21), atol=1e-12)

ROOM = box(0, 0, 4, 3) + [(2, 0, 2, 1.2)]
OTHER_ROOM = box(0, 0, 2.5, 5)


def test_scan_match_finds_the_offset_from_the_place_centre():
    stored = _room_hist(1.0, 1.5, ROOM)
    observed = _room_hist(1.45, 1.2, ROOM)  # robot 0.45 m east, 0.30 m south of the centre
    mx, my = match_axis(observed.x, stored.x, 10), match_axis(observed.y, stored.y, 10)
    assert int(mx.best_shift) * CELL == pytest.approx(0.45)
    assert int(my.best_shift) * CELL == pytest.approx(-0.30)


def test_two_different_rooms_score_lower_than_a_room_with_itself():
    a = _room_hist(1.0, 1.5, ROOM)
    a_again = _room_hist(1.0, 1.5, ROOM, headings=(0.1, 0.3))
    b = _room_hist(1.0, 1.5, OTHER_ROOM)

    def score(o, s):
        return 0.5 * (float(match_axis(o.x, s.x, 10).best_score) + float(match_axis(o.y, s.y, 10).best_score))

    assert score(a, a) == pytest.approx(1.0)
    assert score(b, a) < score(a_again, a) - 0.05
    assert score(a, b) < score(a_again, a) - 0.05


def test_weighted_match():
    """Weights scale each label's counts: equal weights are Eq. 19, and a weighted match is Eq. 19 of the
    scaled histograms (a histogram with itself still scores 1 at its shift)."""
    rng = np.random.default_rng(5)
    a = histograms(rng.integers(0, 3, size=(31, 31)).astype(np.int8)).x
    b = histograms(rng.integers(0, 3, size=(31, 31)).astype(np.int8)).x
    np.testing.assert_allclose(match_axis(a, b, 6, (1.0, 1.0, 1.0)).scores, match_axis(a, b, 6).scores)
    w = np.array([1.0, 0.05, 0.05])[:, None]
    np.testing.assert_allclose(match_axis(a, b, 6, (1.0, 0.05, 0.05)).scores, match_axis(a * w, b * w, 6).scores)
    m = match_axis(np.roll(a, -2, axis=1), a, 6, (1.0, 0.05, 0.05))
    assert int(m.best_shift) == 2 and float(m.best_score) == pytest.approx(1.0)
    # a weight of zero leaves that label out: histograms that differ only there score 1
    c = a.copy()
    c[2] = rng.permutation(c[2])
    assert float(match_axis(c, a, 0, (1.0, 1.0, 0.0)).best_score) == pytest.approx(
        float(match_axis(c[:2], a[:2], 0).best_score))


def test_weighting_the_walls_separates_two_rooms_further():
    """The default weights (walls first) widen the gap between a room seen again from other headings and
    another room, relative to Eq. 19's equal weights."""
    a = _room_hist(1.0, 1.5, ROOM)
    a_again = _room_hist(1.0, 1.5, ROOM, headings=(0.1, 0.3))
    b = _room_hist(1.0, 1.5, OTHER_ROOM)

    def score(o, s, w):
        return min(float(match_axis(o.x, s.x, 10, w).best_score), float(match_axis(o.y, s.y, 10, w).best_score))

    gap = {w: score(a_again, a, w) - score(b, a, w) for w in ((1.0, 1.0, 1.0), (1.0, 0.05, 0.05))}
    assert gap[(1.0, 0.05, 0.05)] > gap[(1.0, 1.0, 1.0)] > 0.0
