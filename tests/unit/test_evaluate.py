"""The map error's turn and scale about the first place, against a general least-squares solver."""

import math

import numpy as np
import pytest
from scipy.optimize import least_squares

from services.launch.evaluate import ate_m, similarity_about


def _reference(est: np.ndarray, tru: np.ndarray) -> tuple[float, float, float]:
    """Scale, turn and residual by iterating on (log size, turn) with scipy's nonlinear least squares."""
    e, t = est - est[0], tru - tru[0]

    def resid(p):
        k, th = math.exp(p[0]), p[1]
        c, s = math.cos(th), math.sin(th)
        return (k * e @ np.array([[c, s], [-s, c]]) - t).ravel()

    sol = least_squares(resid, [0.0, 0.0], xtol=1e-14, ftol=1e-14, gtol=1e-14)
    r = resid(sol.x).reshape(-1, 2)
    return math.exp(-sol.x[0]), -sol.x[1], float(np.sqrt(np.mean(np.sum(r**2, axis=1))))


@pytest.mark.parametrize("seed", range(4))
def test_turn_scale_and_residual_are_the_least_squares_ones(seed):
    rng = np.random.default_rng(seed)
    tru = rng.uniform(-20, 20, size=(60, 2)) + (5.0, -3.0)
    scale, turn = 1.0 + rng.uniform(-0.02, 0.02), math.radians(rng.uniform(-3, 3))
    c, s = math.cos(turn), math.sin(turn)
    est = scale * (tru - tru[0]) @ np.array([[c, s], [-s, c]]) + rng.normal(0, 0.1, size=tru.shape) + (1.0, 2.0)
    est[0] = (1.0, 2.0)
    ids = [7 + 3 * k for k in range(len(tru))]
    estimate, truth = dict(zip(ids, map(tuple, est))), dict(zip(ids, map(tuple, tru)))
    got = similarity_about(estimate, truth, ids[0])
    ref_scale, ref_turn, ref_res = _reference(est, tru)
    assert got.scale == pytest.approx(ref_scale, rel=1e-9)
    assert got.turn_rad == pytest.approx(ref_turn, abs=1e-9)
    assert got.residual_m == pytest.approx(ref_res, rel=1e-7)
    assert abs(got.scale - scale) < 0.01 and abs(got.turn_rad - turn) < math.radians(0.5)  # what was put in
    assert got.residual_m < ate_m(estimate, truth, ids[0])


def test_an_exact_similarity_leaves_nothing():
    tru = {0: (0.0, 0.0), 1: (3.0, 0.0), 2: (3.0, 4.0)}
    est = {0: (10.0, 10.0), 1: (10.0, 13.03), 2: (5.96, 13.03)}  # 1.01 times larger, turned +90 degrees
    got = similarity_about(est, tru, 0)
    assert got.scale == pytest.approx(1.01) and got.turn_rad == pytest.approx(math.pi / 2)
    assert got.residual_m == pytest.approx(0.0, abs=1e-12)


def test_nothing_to_compare():
    assert similarity_about({0: (0.0, 0.0)}, {0: (1.0, 1.0)}, 0) is None
    assert similarity_about({0: (0.0, 0.0), 1: (0.0, 0.0)}, {0: (1.0, 1.0), 1: (2.0, 1.0)}, 0) is None
    assert similarity_about({0: (0.0, 0.0), 1: (1.0, 0.0)}, {0: (1.0, 1.0), 2: (2.0, 1.0)}, 0) is None
    assert similarity_about({0: (0.0, 0.0), 1: (1.0, 0.0)}, {0: (1.0, 1.0), 1: (2.0, 1.0)}, 5) is None
