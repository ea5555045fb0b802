"""Angles, SE(2), distances and ray casting against analytic answers and a scalar reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from sim.geometry import (
    circular_mean,
    point_segment_distance,
    ray_cast,
    se2_compose,
    se2_inverse,
    segment_segment_distance,
    segments_cross,
    wrap_angle,
)

MAX = 6.5
finite = st.floats(min_value=-1e3, max_value=1e3, allow_nan=False)


@given(finite)
def test_wrap_angle_range_and_equivalence(a):
    w = wrap_angle(a)
    assert -math.pi < w <= math.pi
    assert math.isclose(math.cos(w), math.cos(a), abs_tol=1e-9)
    assert math.isclose(math.sin(w), math.sin(a), abs_tol=1e-9)
    arr = wrap_angle(np.array([a, a + 2 * math.pi]))
    assert np.all((arr > -math.pi) & (arr <= math.pi))
    assert np.allclose(np.cos(arr), math.cos(a), atol=1e-9)


def test_wrap_angle_edges():
    assert wrap_angle(math.pi) == math.pi
    assert wrap_angle(-math.pi) == math.pi
    assert wrap_angle(np.array([-math.pi]))[0] == math.pi
    assert circular_mean(math.pi - 0.1, -math.pi + 0.1) == pytest.approx(math.pi)
    assert circular_mean(0.2, 0.4) == pytest.approx(0.3)


@given(finite, finite, st.floats(-10, 10), finite, finite, st.floats(-10, 10))
def test_se2_inverse_and_compose(x, y, h, u, v, g):
    a, b = (x, y, h), (u, v, g)
    ident = se2_compose(a, se2_inverse(a))
    assert ident[0] == pytest.approx(0.0, abs=1e-6) and ident[1] == pytest.approx(0.0, abs=1e-6)
    assert math.cos(ident[2]) == pytest.approx(1.0)
    back = se2_compose(se2_inverse(a), se2_compose(a, b))
    assert back[0] == pytest.approx(u, abs=1e-6) and back[1] == pytest.approx(v, abs=1e-6)


# -- ray casting: analytic cases ----------------------------------------------------------------------

CORRIDOR = np.array([[-20.0, -1.0, 20.0, -1.0], [-20.0, 1.0, 20.0, 1.0]])  # 2 m wide, along x


def test_corridor_distances():
    ang = np.radians([90.0, -90.0, 45.0, 135.0, 30.0, 0.0, 180.0])
    ranges, wall, cos_inc = ray_cast(np.array([0.0, 0.0]), ang, CORRIDOR, MAX)
    expect = [1.0, 1.0, math.sqrt(2), math.sqrt(2), 2.0, MAX, MAX]
    assert ranges == pytest.approx(expect)
    assert list(wall) == [1, 0, 1, 1, 1, -1, -1]
    assert cos_inc[:4] == pytest.approx([1.0, 1.0, math.cos(math.pi / 4), math.cos(math.pi / 4)])
    assert cos_inc[4] == pytest.approx(math.cos(math.radians(60)))
    assert cos_inc[5] == 0.0


def test_corridor_off_centre_and_many_origins():
    origins = np.array([[0.0, 0.5], [3.0, -0.25], [-7.0, 0.0]])
    ranges, _, _ = ray_cast(origins, np.radians([90.0, -90.0, 60.0]), CORRIDOR, MAX)
    assert ranges == pytest.approx([0.5, 0.75, 1.0 / math.sin(math.radians(60))])


def test_corner():
    walls = np.array([[2.0, -5.0, 2.0, 3.0], [-5.0, 3.0, 2.0, 3.0]])  # an inside corner at (2, 3)
    ang = np.array([math.atan2(3, 2), math.radians(30), math.radians(80), math.radians(-45), math.radians(200)])
    ranges, wall, _ = ray_cast(np.zeros(2), ang, walls, MAX)
    assert ranges[0] == pytest.approx(math.sqrt(13))
    assert ranges[1] == pytest.approx(2.0 / math.cos(math.radians(30)))
    assert ranges[2] == pytest.approx(3.0 / math.sin(math.radians(80)))
    assert ranges[3] == pytest.approx(2.0 * math.sqrt(2))
    assert ranges[4] == MAX and wall[4] == -1
    assert wall[1] == 0 and wall[2] == 1


def test_beam_missing_a_thin_wall_end():
    # a thin wall ending at (1, 0.5); a farther wall behind it at x = 4
    walls = np.array([[1.0, -1.0, 1.0, 0.5], [4.0, -10.0, 4.0, 10.0]])
    just_over = math.atan2(0.5 + 1e-3, 1.0)
    just_under = math.atan2(0.5 - 1e-3, 1.0)
    ranges, wall, _ = ray_cast(np.zeros(2), np.array([just_under, just_over]), walls, MAX)
    assert wall[0] == 0 and ranges[0] == pytest.approx(math.hypot(1.0, 0.499))
    assert wall[1] == 1 and ranges[1] == pytest.approx(4.0 / math.cos(just_over))
    # with no wall behind, the ray past the end sees nothing at all
    ranges, wall, _ = ray_cast(np.zeros(2), np.array([just_over]), walls[:1], MAX)
    assert ranges[0] == MAX and wall[0] == -1


def test_max_range_and_behind():
    walls = np.array([[10.0, -1.0, 10.0, 1.0], [-2.0, -1.0, -2.0, 1.0]])
    ranges, wall, _ = ray_cast(np.zeros(2), np.array([0.0]), walls, MAX)
    assert ranges[0] == MAX and wall[0] == -1  # beyond range; the wall behind never counts
    ranges, _, _ = ray_cast(np.zeros(2), np.array([0.0]), walls, 12.0)
    assert ranges[0] == pytest.approx(10.0)


def test_no_walls_and_no_rays():
    ranges, wall, cos_inc = ray_cast(np.zeros(2), np.array([0.0, 1.0]), np.zeros((0, 4)), MAX)
    assert list(ranges) == [MAX, MAX] and list(wall) == [-1, -1]
    assert ray_cast(np.zeros(2), np.zeros(0), CORRIDOR, MAX)[0].shape == (0,)


def _scalar_cast(o, a, walls, max_range):
    best = max_range
    d = (math.cos(a), math.sin(a))
    for x1, y1, x2, y2 in walls:
        e = (x2 - x1, y2 - y1)
        den = d[0] * e[1] - d[1] * e[0]
        if abs(den) < 1e-12:
            continue
        w = (x1 - o[0], y1 - o[1])
        t = (w[0] * e[1] - w[1] * e[0]) / den
        u = (w[0] * d[1] - w[1] * d[0]) / den
        if t >= 0 and 0 <= u <= 1:
            best = min(best, t)
    return best


def test_matches_scalar_reference_on_random_walls():
    rng = np.random.default_rng(3)
    walls = rng.uniform(-8, 8, size=(60, 4))
    origins = rng.uniform(-5, 5, size=(200, 2))
    angles = rng.uniform(-math.pi, math.pi, size=200)
    ranges, _, _ = ray_cast(origins, angles, walls, MAX)
    expect = [_scalar_cast(o, a, walls, MAX) for o, a in zip(origins, angles, strict=True)]
    assert ranges == pytest.approx(expect, abs=1e-9)


# -- distances -----------------------------------------------------------------------------------------


def test_point_segment_distance():
    seg = np.array([[0.0, 0.0, 2.0, 0.0], [5.0, 5.0, 5.0, 5.0]])  # the second is degenerate (a point)
    d = point_segment_distance(np.array([[1.0, 1.0], [-3.0, 4.0], [3.0, 0.0]]), seg)
    assert d[:, 0] == pytest.approx([1.0, 5.0, 1.0])
    assert d[0, 1] == pytest.approx(math.hypot(4, 4))


def test_segment_segment_distance_and_crossing():
    walls = np.array([[0.0, -1.0, 0.0, 1.0],   # crossed
                      [2.0, 1.0, 3.0, 1.0],    # 1 m above the segment's end
                      [-1.0, 0.5, 1.0, 0.5],   # crossed (x = 0 is inside)
                      [0.5, 0.2, 0.5, 3.0]])   # its end is 0.2 m above the segment's middle
    seg = np.array([-1.0, 0.0, 2.0, 0.0])
    assert list(segments_cross(seg, walls)) == [True, False, False, False]
    d = segment_segment_distance(seg, walls)
    assert d == pytest.approx([0.0, 1.0, 0.5, 0.2])
    assert segment_segment_distance(seg, np.zeros((0, 4))).shape == (0,)
