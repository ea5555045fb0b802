"""The belief over places: motion prior, match likelihood and the offset filter (Eqs. 22-23)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.place_recognizer import belief as B

MOTION = dict(transition_std_m=0.1, transition_var_per_m_m2=0.02, place_radius_m=0.5,
              uniform_transition=0.0, unknown_offset_var_m2=0.25)


def _one_place(offset=(0.0, 0.0), var=(0.0, 0.0)):
    b = B.add_place(B.Belief.empty(), 7, (2.0, 1.0), probability=1.0)
    return B.Belief(ids=b.ids, centres=b.centres, probs=b.probs, offsets=np.array([offset], float),
                    offset_vars=np.array([var], float), none_prob=0.0, none_xy=np.zeros(2), none_var_m2=0.0)


def test_standing_still_at_a_place_keeps_the_mass():
    b = B.predict(_one_place(), np.zeros(2), **MOTION)
    # kernel 1 for the place, exp(-R^2 / (2 s^2)) = exp(-0.25 / 0.02) for "none"
    k_none = math.exp(-0.25 / 0.02)
    assert b.probs[0] == pytest.approx(1.0 / (1.0 + k_none))
    assert b.none_prob == pytest.approx(k_none / (1.0 + k_none))
    np.testing.assert_allclose(b.offsets[0], [0.0, 0.0], atol=1e-12)


def test_moving_within_a_place_moves_the_offset_by_dead_reckoning():
    b = B.predict(_one_place(offset=(0.1, 0.0), var=(0.01, 0.01)), np.array([0.2, 0.0]), **MOTION)
    # r' = r + D (Eq. 22's prior), variance grows by q |D| = 0.004
    np.testing.assert_allclose(b.offsets[0], [0.3, 0.0], atol=1e-9)
    np.testing.assert_allclose(b.offset_vars[0], [0.014, 0.014], atol=1e-9)


def test_moving_to_a_neighbour_carries_the_mass_and_offset():
    b = B.add_place(B.Belief.empty(), 0, (0.0, 0.0), probability=1.0)
    b = B.add_place(b, 1, (1.0, 0.0), probability=0.0)
    b = B.Belief(ids=b.ids, centres=b.centres, probs=np.array([1.0, 0.0]), offsets=b.offsets,
                 offset_vars=b.offset_vars, none_prob=0.0, none_xy=np.zeros(2), none_var_m2=0.0)
    moved = B.predict(b, np.array([0.95, 0.0]), **MOTION)
    s2 = 0.02 * 0.95 + 0.1**2  # kernel variance: q |D| + transition_std^2
    k = [math.exp(-(0.95**2) / (2 * s2)), math.exp(-(0.05**2) / (2 * s2)), math.exp(-(0.5**2) / (2 * s2))]
    assert moved.probs[1] == pytest.approx(k[1] / sum(k))
    assert moved.probs[1] > 0.98
    np.testing.assert_allclose(moved.offsets[1], [-0.05, 0.0], atol=1e-6)


def test_far_from_every_place_the_mass_goes_to_none():
    moved = B.predict(_one_place(), np.array([3.0, 0.0]), **MOTION)
    assert moved.none_prob > 0.99
    np.testing.assert_allclose(moved.none_xy, [5.0, 1.0])


def test_relocalisation_mass_goes_to_places_near_the_robot_not_across_the_building():
    """The relocalising fraction is weighted by exp(-|c_j - m|^2 / (2 s_r^2)) around the expected robot
    position m; with an infinite s_r it is spread evenly over every place and "none"."""
    b = B.add_place(B.Belief.empty(), 0, (0.0, 0.0), probability=1.0)
    for pid, xy in ((1, (1.5, 0.0)), (2, (10.0, 0.0))):
        b = B.add_place(b, pid, xy, probability=0.0)
    b = B.Belief(ids=b.ids, centres=b.centres, probs=np.array([1.0, 0.0, 0.0]), offsets=b.offsets,
                 offset_vars=b.offset_vars, none_prob=0.0, none_xy=np.zeros(2), none_var_m2=0.0)
    eps = 1e-3
    even = B.predict(b, np.zeros(2), **{**MOTION, "uniform_transition": eps})
    # place 2 is 10 m away: only the even spread reaches it
    assert even.probs[2] == pytest.approx(eps / 4, rel=1e-6)
    local = B.predict(b, np.zeros(2), **{**MOTION, "uniform_transition": eps, "relocalise_std_m": 2.0})
    g = np.array([1.0, math.exp(-1.5**2 / 8.0), math.exp(-100.0 / 8.0), 1.0])
    assert local.probs[2] == pytest.approx(eps * g[2] / g.sum(), rel=1e-6)
    assert local.probs[2] < 1e-8 and local.probs[1] > even.probs[1]
    assert local.probs.sum() + local.none_prob == pytest.approx(1.0)
    # what arrives without a position has the unknown offset variance
    assert local.offset_vars[2] == pytest.approx([0.25, 0.25])


def test_correct_offset_filter_eqs_22_23():
    b = _one_place(offset=(0.2, -0.1), var=(0.04, 0.01))
    out = B.correct(b, np.array([0.95]), np.array([[0.5, -0.1]]), np.array([[0.04, 0.03]]),
                    match_sharpness=40.0, new_place_match=0.9)
    # x: r = 0.2 + 0.04/0.08 (0.5 - 0.2) = 0.35, 1/s^2 = 1/0.04 + 1/0.04 -> 0.02
    # y: r = -0.1 (observation agrees), s^2 = 1/(1/0.01 + 1/0.03) = 0.0075
    np.testing.assert_allclose(out.offsets[0], [0.35, -0.1])
    np.testing.assert_allclose(out.offset_vars[0], [0.02, 0.0075])


def test_likelihood_ratio_from_match_scores():
    b = B.add_place(B.Belief.empty(), 0, (0.0, 0.0), probability=0.5)
    b = B.add_place(b, 1, (5.0, 0.0), probability=0.5)
    b = B.Belief(ids=b.ids, centres=b.centres, probs=np.array([0.4, 0.4]), offsets=b.offsets,
                 offset_vars=b.offset_vars, none_prob=0.2, none_xy=np.zeros(2), none_var_m2=0.0)
    out = B.correct(b, np.array([1.0, 0.9]), np.zeros((2, 2)), np.ones((2, 2)),
                    match_sharpness=40.0, new_place_match=0.95)
    assert out.probs[0] / out.probs[1] == pytest.approx(math.exp(4.0))
    # none: prior 0.2 (half of a place's), virtual score 0.95
    assert out.none_prob / out.probs[0] == pytest.approx(0.5 * math.exp(-2.0))
    # a place without a signature (NaN) gets the none likelihood
    out2 = B.correct(b, np.array([np.nan, 0.9]), np.zeros((2, 2)), np.ones((2, 2)),
                     match_sharpness=40.0, new_place_match=0.95)
    assert out2.probs[0] / out2.none_prob == pytest.approx(2.0)


@settings(max_examples=50, deadline=None)
@given(
    xs=st.lists(st.floats(-40, 40), min_size=1, max_size=6),
    dx=st.floats(-2, 2), dy=st.floats(-2, 2),
    eps=st.floats(0.0, 0.1),
    reloc=st.sampled_from([math.inf, 0.5, 2.0]),
    seed=st.integers(0, 2**31 - 1),
)
def test_predict_and_correct_keep_a_distribution(xs, dx, dy, eps, reloc, seed):
    rng = np.random.default_rng(seed)
    b = B.Belief.empty()
    for i, x in enumerate(xs):
        # some places hold no mass at all (as far ones do once the kernel has underflowed)
        b = B.add_place(b, i, (x, rng.uniform(-5, 5)), probability=float(rng.choice([0.0, rng.uniform(0.1, 0.9)])))
    b = B.predict(b, np.array([dx, dy]), **{**MOTION, "uniform_transition": eps, "relocalise_std_m": reloc})
    assert b.probs.sum() + b.none_prob == pytest.approx(1.0)
    assert (b.offset_vars >= 0).all() and np.isfinite(b.offsets).all() and np.isfinite(b.offset_vars).all()
    b = B.correct(b, rng.uniform(0, 1, len(xs)), rng.normal(size=(len(xs), 2)), np.full((len(xs), 2), 0.1),
                  match_sharpness=40.0, new_place_match=0.9)
    assert b.probs.sum() + b.none_prob == pytest.approx(1.0)
    assert (b.probs >= 0).all() and b.none_prob >= 0


def test_remove_and_move_places():
    b = B.add_place(B.Belief.empty(), 0, (0.0, 0.0), probability=0.5)
    b = B.add_place(b, 1, (1.0, 0.0), probability=0.5)  # probs 0.25, 0.5, none 0.25
    r = B.remove_place(b, 1)
    assert r.ids.tolist() == [0]
    assert r.probs[0] == pytest.approx(0.5) and r.none_prob == pytest.approx(0.5)
    m = B.move_places(b, {1: (3.0, 4.0)})
    np.testing.assert_allclose(m.centres, [[0.0, 0.0], [3.0, 4.0]])


def test_negligible_hypotheses_are_not_moved_as_sources():
    """Moving only the hypotheses at least ``min_source_probability`` probable gives the belief of moving
    them all, to within the mass left out, and places that held next to nothing keep what arrives."""
    rng = np.random.default_rng(11)
    n = 60
    centres = rng.uniform(0.0, 30.0, size=(n, 2))
    probs = np.full(n, 1e-16)
    probs[[3, 17, 40]] = [0.6, 0.25, 0.1]
    b = B.Belief(ids=np.arange(n), centres=centres, probs=probs, offsets=rng.normal(0.0, 0.1, (n, 2)),
                 offset_vars=np.full((n, 2), 0.01), none_prob=1.0 - probs.sum(), none_xy=centres[3] + 0.4,
                 none_var_m2=0.05)
    motion = {**MOTION, "uniform_transition": 1e-4}
    every = B.predict(b, np.array([0.7, -0.2]), relocalise_std_m=1.5, min_source_probability=0.0, **motion)
    some = B.predict(b, np.array([0.7, -0.2]), relocalise_std_m=1.5, **motion)
    np.testing.assert_allclose(some.probs, every.probs, atol=1e-12)
    assert some.none_prob == pytest.approx(every.none_prob, abs=1e-12)
    big = every.probs > 1e-6
    np.testing.assert_allclose(some.offsets[big], every.offsets[big], atol=1e-9)
    np.testing.assert_allclose(some.none_xy, every.none_xy, atol=1e-9)


def _corridor(probs):
    """Places 0-5 on a line 1 m apart, the robot at their centres with the given masses."""
    n = 6
    return B.Belief(ids=np.arange(n), centres=np.c_[np.arange(n, dtype=float), np.zeros(n)],
                    probs=np.asarray(probs, float), offsets=np.zeros((n, 2)), offset_vars=np.full((n, 2), 0.01),
                    none_prob=0.0, none_xy=np.zeros(2), none_var_m2=0.0)


def test_none_as_a_mixture_keeps_each_track():
    """Leaving a corridor of look-alike places, the robot is at place 2 (0.8) or at its neighbours.
    Merged into one Gaussian, "none" sits between them, wider than any, and brings the robot back
    nearer place 3; as a mixture each track keeps its own position and comes back to its place."""
    b = _corridor([0.0, 0.05, 0.8, 0.15, 0.0, 0.0])
    north, south = np.array([0.0, 1.0]), np.array([0.0, -1.0])
    merged = B.predict(b, north, **MOTION)
    mixed = B.predict(b, north, **MOTION, none_components=3)
    for out in (merged, mixed):
        assert out.none_prob > 0.99
        assert out.probs.sum() + out.none_prob == pytest.approx(1.0)
    # the kernel variance 0.01 + 0.02 + 0.1^2 = 0.04 a source: 1 m is 3.5 sd of two, beyond the gate
    parts = mixed.none_mixture()
    np.testing.assert_allclose(parts[:, 0], [0.8, 0.15, 0.05], atol=1e-3)
    np.testing.assert_allclose(parts[:, 1:3], [[2.0, 1.0], [3.0, 1.0], [1.0, 1.0]], atol=1e-9)
    np.testing.assert_allclose(parts[:, 3], 0.03)
    np.testing.assert_allclose(mixed.none_xy, [2.0, 1.0], atol=1e-9)
    assert merged.none_mixture().shape == (1, 4)
    assert merged.none_xy[0] == pytest.approx(2.0 + 0.15 - 0.05, abs=1e-3)
    back_merged = B.predict(merged, south, **MOTION)
    back_mixed = B.predict(mixed, south, **MOTION, none_components=3)
    # back where it left: as a mixture, places 1-3 hold 0.05 : 0.8 : 0.15 again, each with its own
    # track (offset about 0); merged, every hypothesis has the robot at x = 2.1, place 2 holds 0.64
    # and place 3 0.049 with an offset of -0.9 m
    assert back_mixed.probs[2] > 0.7 and back_merged.probs[2] < 0.65
    assert back_mixed.probs[2] / back_mixed.probs[3] == pytest.approx(0.8 / 0.15, rel=1e-2)
    assert back_mixed.probs[1] / back_mixed.probs[3] == pytest.approx(0.05 / 0.15, rel=1e-2)
    np.testing.assert_allclose(back_mixed.offsets[1:4, 0], 0.0, atol=0.01)
    np.testing.assert_allclose(back_merged.offsets[1:4, 0], [1.1, 0.1, -0.9], atol=0.01)


def test_a_mixture_of_one_is_the_moment_match_bit_for_bit():
    b = _corridor([0.1, 0.2, 0.3, 0.2, 0.1, 0.1])
    one = B.predict(b, np.array([0.3, 2.0]), **MOTION)
    again = B.predict(b, np.array([0.3, 2.0]), **MOTION, none_components=1, none_gate_sd=0.1)
    assert np.array_equal(one.none_xy, again.none_xy) and one.none_var_m2 == again.none_var_m2
    assert np.array_equal(one.probs, again.probs)


def test_reduce_merges_what_is_left_into_the_nearest_component():
    w = np.array([0.5, 0.1, 0.3, 0.1])
    xy = np.array([[0.0, 0.0], [0.1, 0.0], [3.0, 0.0], [3.2, 0.0]])
    var = np.full((4, 2), 0.01)
    # gate 0.5 sd: every source is its own seed until two are taken; the rest join the nearest
    out = B._reduce(w, xy, var, 2, 0.5)
    np.testing.assert_allclose(out[:, 0], [0.6, 0.4])
    np.testing.assert_allclose(out[:, 1], [0.1 / 6, 3.05])
    np.testing.assert_allclose(out[0, 3], 0.01 + (0.5 * (0.1 / 6) ** 2 + 0.1 * (0.1 - 0.1 / 6) ** 2) / 0.6 / 2)
