"""Compass-mode relaxation against an independent dense solve of Eq. 7."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from services.relaxer.compass import (
    CompassNoise,
    CompassParams,
    CompassRelaxer,
    energy,
    estimate_noise,
    estimate_noise_reml,
    relax,
    solve_exact,
)
from services.relaxer.graph import GraphError, MapGraph
from services.relaxer.synthetic import office_map

FIXED = CompassParams(estimate_noise=False, tol_energy_rel=0.0, tol_step_m=1e-12, max_sweeps=200_000)


# ---------------------------------------------------------------- independent reference (dense)
def _cov(link, noise):
    """Eq. 5 (or Appendix A) written out directly: R C_local R^T."""
    _, _, d, th, steps, ms, var = link
    if var is not None:
        return var * np.eye(2)
    r = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    c_local = steps * np.array([[noise.s_dd_m2, ms * noise.s_da_m_rad], [ms * noise.s_da_m_rad, ms * ms * noise.s_aa_rad2]])
    return r @ c_local @ r.T


def _dense_energy(n, links, noise, xy):
    e_tot = 0.0
    for link in links:
        a, b, d, th = link[:4]
        e = xy[b] - xy[a] - d * np.array([math.cos(th), math.sin(th)])
        e_tot += e @ np.linalg.solve(_cov(link, noise), e)
    return e_tot


def _dense_minimum(n, links, noise, xy0, pinned):
    h = np.zeros((2 * n, 2 * n))
    g = np.zeros(2 * n)
    for link in links:
        a, b, d, th = link[:4]
        w = np.linalg.inv(_cov(link, noise))
        dd = d * np.array([math.cos(th), math.sin(th)])
        for p, sp_ in ((a, -1.0), (b, 1.0)):
            g[2 * p: 2 * p + 2] += sp_ * w @ dd
            for q, sq in ((a, -1.0), (b, 1.0)):
                h[2 * p: 2 * p + 2, 2 * q: 2 * q + 2] += sp_ * sq * w
    free = np.ones(2 * n, dtype=bool)
    free[2 * pinned: 2 * pinned + 2] = False
    x = np.asarray(xy0, dtype=float).reshape(-1).copy()
    x[free] = np.linalg.solve(h[np.ix_(free, free)], g[free] - h[np.ix_(free, ~free)] @ x[~free])
    return x.reshape(-1, 2)


def _build(n, links):
    g = MapGraph()
    g.add_places(range(n))
    for a, b, d, th, steps, ms, var in links:
        g.add_link(a, b, d_m=d, theta_rad=th, steps=steps, mean_step_m=ms, variance_m2=var)
    return g


@st.composite
def compass_problems(draw, max_places=12):
    n = draw(st.integers(2, max_places))
    pairs = set()
    edges = []
    for i in range(1, n):
        j = draw(st.integers(0, i - 1))
        edges.append((j, i) if draw(st.booleans()) else (i, j))
        pairs.add((min(i, j), max(i, j)))
    for _ in range(draw(st.integers(0, n))):
        a, b = draw(st.integers(0, n - 1)), draw(st.integers(0, n - 1))
        if a != b and (min(a, b), max(a, b)) not in pairs:
            pairs.add((min(a, b), max(a, b)))
            edges.append((a, b))
    links = []
    for a, b in edges:
        d = draw(st.floats(0.2, 3.0))
        th = draw(st.floats(-math.pi, math.pi))
        steps = draw(st.integers(1, 30))
        ms = draw(st.floats(0.1, 0.3))
        var = draw(st.one_of(st.none(), st.floats(0.01, 0.2)))
        links.append((a, b, d, th, steps, ms, var))
    # noise of a realistic size: per-step variances within two orders of magnitude of each other
    s_dd = draw(st.floats(1e-3, 2e-2))
    s_aa = draw(st.floats(5e-2, 5e-1))
    corr = draw(st.floats(-0.7, 0.7))
    noise = CompassNoise(s_dd, s_aa, corr * math.sqrt(s_dd * s_aa))
    xy0 = np.array(draw(st.lists(st.floats(-10, 10), min_size=2 * n, max_size=2 * n))).reshape(n, 2)
    pinned = draw(st.integers(0, n - 1))
    return n, links, noise, xy0, pinned


SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@SETTINGS
@given(compass_problems())
def test_every_sweep_leaves_energy_no_higher(problem):
    n, links, noise, xy0, pinned = problem
    g = _build(n, links)
    r = CompassRelaxer(g, xy0, noise=noise, pinned_id=pinned, params=FIXED)
    e_prev = _dense_energy(n, links, noise, xy0)
    assert energy(g, xy0, noise) == pytest.approx(e_prev, rel=1e-9)
    for _ in range(25):
        r.sweep()
        e = _dense_energy(n, links, noise, r.xy)
        assert e <= e_prev * (1 + 1e-10) + 1e-12
        e_prev = e


@SETTINGS
@given(compass_problems())
def test_sweeps_converge_to_the_exact_minimum(problem):
    n, links, noise, xy0, pinned = problem
    g = _build(n, links)
    ref = _dense_minimum(n, links, noise, xy0, pinned)
    ex = solve_exact(g, xy0, noise=noise, pinned=pinned, params=FIXED)
    np.testing.assert_allclose(ex.xy, ref, atol=1e-8)
    res = relax(g, xy0, noise=noise, pinned=pinned, params=FIXED)
    assert res.converged
    np.testing.assert_allclose(res.xy, ref, atol=1e-6)
    assert np.array_equal(res.xy[pinned], xy0[pinned])
    assert res.energy == pytest.approx(_dense_energy(n, links, noise, ref), rel=1e-6, abs=1e-9)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(compass_problems(max_places=10))
def test_exact_solve_without_qdldl_reaches_the_same_minimum(problem):
    # SuperLU in symmetric mode, given the upper triangle the qdldl path factorises
    import services.relaxer.sparse as sparse

    n, links, noise, xy0, pinned = problem
    g = _build(n, links)
    ref = _dense_minimum(n, links, noise, xy0, pinned)
    saved = sparse._qdldl
    sparse._qdldl = None
    try:
        ex = solve_exact(g, xy0, noise=noise, pinned=pinned, params=FIXED)
    finally:
        sparse._qdldl = saved
    np.testing.assert_allclose(ex.xy, ref, atol=1e-8)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(compass_problems(max_places=8), st.floats(-50, 50), st.floats(-50, 50))
def test_pinned_place_never_moves_and_translation_does_not_change_the_result(problem, tx, ty):
    n, links, noise, xy0, pinned = problem
    g = _build(n, links)
    base = relax(g, xy0, noise=noise, pinned=pinned, params=FIXED)
    assert np.array_equal(base.xy[pinned], xy0[pinned])
    moved = xy0 + np.array([tx, ty])
    # translating the others only: the same minimum
    others = xy0.copy()
    mask = np.arange(n) != pinned
    others[mask] = moved[mask]
    res = relax(g, others, noise=noise, pinned=pinned, params=FIXED)
    np.testing.assert_allclose(res.xy, base.xy, atol=1e-6)
    # translating everything: the result moves with it
    res = relax(g, moved, noise=noise, pinned=pinned, params=FIXED)
    np.testing.assert_allclose(res.xy - np.array([tx, ty]), base.xy, atol=1e-6)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2**31 - 1))
def test_online_changes_keep_sweeps_exact(seed):
    """Random additions and removals through the on-line engine, then relax: the dense minimum."""
    rng = np.random.default_rng(seed)
    noise = CompassNoise(0.01, 0.02, 0.003)
    g = MapGraph(capacity=1)
    small_classes = msgspec.structs.replace(FIXED, class_chunk_places=int(rng.integers(2, 6)))
    r = CompassRelaxer(g, np.zeros((0, 2)), noise=noise, params=small_classes)
    next_id = 0
    for _ in range(rng.integers(10, 60)):
        op = rng.random()
        ids = g.ids.tolist()
        if op < 0.35 or len(ids) < 2:
            r.add_place(next_id, rng.uniform(-5, 5, 2))
            next_id += 1
        elif op < 0.8:
            a, b = rng.choice(ids, 2, replace=False)
            if not g.has_link(a, b):
                var = float(rng.uniform(0.1, 1)) if rng.random() < 0.3 else None
                r.add_link(int(a), int(b), d_m=float(rng.uniform(0.5, 2)), theta_rad=float(rng.uniform(-3, 3)),
                           steps=int(rng.integers(1, 20)), mean_step_m=0.1, variance_m2=var)
        elif op < 0.92 and g.n_links:
            s = int(rng.integers(g.n_links))
            r.remove_link(int(g.ids[g.src[s]]), int(g.ids[g.dst[s]]))
        else:
            victim = int(rng.choice(ids))
            if victim != int(g.ids[r.pinned_index]):
                r.remove_place(victim)
        _check_invariants(r)
    if g.n_links == 0:
        return
    # reference: the dense minimum of each part containing a link, on a fresh copy of the graph
    res = r.relax()
    ex = solve_exact(g, r.xy, noise=noise, pinned=r.pinned_index, params=FIXED)
    np.testing.assert_allclose(res.xy, ex.xy, atol=1e-6)
    count, labels = g.components()
    if count == 1:
        links = [(int(g.src[k]), int(g.dst[k]), float(g.d_m[k]), float(g.theta_rad[k]), float(g.steps[k]),
                  float(g.mean_step_m[k]), None if math.isnan(g.variance_m2[k]) else float(g.variance_m2[k]))
                 for k in range(g.n_links)]
        ref = _dense_minimum(g.n_places, links, noise, r.xy, r.pinned_index)
        np.testing.assert_allclose(res.xy, ref, atol=1e-6)


def _check_invariants(r: CompassRelaxer) -> None:
    g = r.graph
    pin = r.pinned_index
    seen = {}
    for c, cls in enumerate(r._classes):
        for p in range(cls.n):
            i = int(cls.members[p])
            assert i not in seen
            seen[i] = c
            assert r._colour[i] == c and r._pos[i] == p
        for q in range(cls.m):
            k, sign = int(cls.k[q]), cls.sign[q]
            tgt = int(g.dst[k]) if sign > 0 else int(g.src[k])
            nb = int(g.src[k]) if sign > 0 else int(g.dst[k])
            assert int(cls.members[cls.t[q]]) == tgt and int(cls.nb[q]) == nb
            assert r._hlpos[k, 1 if sign > 0 else 0] == q
    for i in range(g.n_places):
        assert (i in seen) == (g.degree(i) > 0 and i != pin)
    for k in range(g.n_links):
        a, b = int(g.src[k]), int(g.dst[k])
        assert not (a in seen and b in seen and seen[a] == seen[b])


def test_figure3_with_noise_estimation_reaches_the_fixed_point_of_exact_solves():
    # more than 2 (N - 1) links: the joint estimate of Eqs. 12-14 is not degenerate
    om = office_map(60, rng=np.random.default_rng(3), loop_probability=0.9, diagonal_probability=0.6)
    start = CompassNoise(1e-3, 1e-3, 0.0)
    res = relax(om.graph, om.xy_dead_reckoning, noise=start,
                params=CompassParams(tol_energy_rel=0.0, tol_step_m=1e-12, tol_noise_rel=1e-12, noise_refresh_rel=0.0,
                                     max_sweeps=30_000))
    ex = solve_exact(om.graph, om.xy_dead_reckoning, noise=start,
                     params=CompassParams(tol_noise_rel=1e-9, noise_refresh_rel=0.0, max_exact_noise_rounds=2000))
    assert ex.converged
    np.testing.assert_allclose(res.xy, ex.xy, atol=1e-5)
    for a, b in zip(msgspec_tuple(res.noise), msgspec_tuple(ex.noise)):
        assert a == pytest.approx(b, rel=1e-3)
    # the coordinates minimise Eq. 7 under the noise, which is Eqs. 12-14 at the coordinates
    again = estimate_noise(om.graph, ex.xy, ex.noise)
    assert again.s_dd_m2 == pytest.approx(ex.noise.s_dd_m2, rel=1e-6)
    assert again.s_aa_rad2 == pytest.approx(ex.noise.s_aa_rad2, rel=1e-6)


def msgspec_tuple(noise: CompassNoise) -> tuple[float, float, float]:
    return noise.s_dd_m2, noise.s_aa_rad2, noise.s_da_m_rad


def test_noise_estimation_keeps_previous_values_on_a_tree_and_respects_floors():
    g = MapGraph()
    g.add_places(range(4))
    for a in range(3):
        g.add_link(a, a + 1, d_m=1.0, theta_rad=0.3 * a, steps=10, mean_step_m=0.1)
    prev = CompassNoise(0.3, 0.2, 0.01)
    xy = np.cumsum(np.r_[[[0, 0]], np.random.default_rng(0).normal(size=(3, 2))], axis=0)
    assert estimate_noise(g, xy, prev) == prev
    g.remove_link(1, 2)
    g.remove_link(2, 3)
    g.add_link(1, 2, d_m=1.0, theta_rad=0.0, steps=10, mean_step_m=0.1)
    g.add_link(2, 3, d_m=1.0, theta_rad=0.0, steps=10, mean_step_m=0.1)
    g.add_link(0, 3, d_m=3.3, theta_rad=0.0, steps=30, mean_step_m=0.1)
    g.remove_link(0, 1)
    g.add_link(0, 1, d_m=1.0, theta_rad=0.0, steps=10, mean_step_m=0.1)
    xy = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.0]])  # no across-track residual at all
    est = estimate_noise(g, xy, prev, CompassParams(min_s_aa_rad2=1e-6))
    assert est.s_aa_rad2 == 1e-6
    assert abs(est.s_da_m_rad) <= 0.99 * math.sqrt(est.s_dd_m2 * est.s_aa_rad2)


def test_reml_noise_estimates_within_ten_percent_of_the_truth():
    truth = CompassNoise(4e-4, 9e-4, 3e-4)
    om = office_map(3000, rng=np.random.default_rng(11), noise=truth, loop_probability=0.9,
                    diagonal_probability=0.5)
    est, xy, rounds = estimate_noise_reml(om.graph, om.xy_dead_reckoning, noise=CompassNoise(1e-3, 1e-3, 0.0),
                                          rng=np.random.default_rng(5), samples=32)
    assert est.s_dd_m2 == pytest.approx(truth.s_dd_m2, rel=0.10)
    assert est.s_aa_rad2 == pytest.approx(truth.s_aa_rad2, rel=0.10)
    assert est.s_da_m_rad == pytest.approx(truth.s_da_m_rad, rel=0.10)
    # and the map is better than dead reckoning
    err = np.sqrt(np.mean(np.sum((xy - om.xy_true) ** 2, axis=1)))
    err_dr = np.sqrt(np.mean(np.sum((om.xy_dead_reckoning - om.xy_true) ** 2, axis=1)))
    assert err < 0.5 * err_dr


def test_auto_strategy_solves_a_big_loop_exactly():
    """A long corridor loop closed at the end: sweeps crawl, the auto cycle switches to the exact solve."""
    rng = np.random.default_rng(2)
    n = 400
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    true = 30.0 * np.stack([np.cos(ang), np.sin(ang)], 1)
    g = MapGraph()
    g.add_places(range(n))
    r = CompassRelaxer(g, true.copy(), noise=CompassNoise(1e-3, 1e-3, 0.0),
                       params=CompassParams(estimate_noise=False))
    for k in range(n):
        a, b = k, (k + 1) % n
        dd = true[b] - true[a] + rng.normal(0, 0.05, 2) + np.array([0.02, 0.0])  # biased: a large loop error
        r.add_link(a, b, d_m=float(np.hypot(*dd)), theta_rad=float(np.arctan2(dd[1], dd[0])), steps=10,
                   mean_step_m=0.1)
    exact_seen = False
    for _ in range(12):
        exact_seen |= r.cycle().exact
    assert exact_seen
    ref = solve_exact(g, r.xy, noise=r.noise, params=FIXED)
    np.testing.assert_allclose(r.xy, ref.xy, atol=1e-6)
    # without the auto strategy the same cycles are far from it
    r2 = CompassRelaxer(g.copy(), true.copy(), noise=CompassNoise(1e-3, 1e-3, 0.0),
                        params=CompassParams(estimate_noise=False))
    for _ in range(12):
        r2.cycle(auto=False)
    assert np.abs(r2.xy - ref.xy).max() > 0.1


def test_disconnected_map_gets_a_gauge_per_part():
    g = MapGraph()
    g.add_places(range(5))
    g.add_link(0, 1, d_m=1.0, theta_rad=0.0, steps=10, mean_step_m=0.1)
    g.add_link(2, 3, d_m=1.0, theta_rad=1.0, steps=10, mean_step_m=0.1)
    xy0 = np.array([[0, 0], [5, 5], [7, 7], [1, 1], [3, 3]], dtype=float)
    res = solve_exact(g, xy0, noise=CompassNoise(0.01, 0.01, 0), params=FIXED)
    np.testing.assert_allclose(res.xy[[0, 2, 4]], xy0[[0, 2, 4]])  # pinned, first of part, isolated place
    np.testing.assert_allclose(res.xy[1], [1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(res.xy[3], xy0[2] + [math.cos(1.0), math.sin(1.0)], atol=1e-12)
    rel = relax(g, xy0, noise=CompassNoise(0.01, 0.01, 0), params=FIXED)
    assert energy(g, rel.xy, CompassNoise(0.01, 0.01, 0)) < 1e-12


def test_graph_rejects_bad_links_and_places():
    g = MapGraph()
    g.add_places([1, 2])
    with pytest.raises(GraphError, match="duplicate place id 1"):
        g.add_place(1)
    with pytest.raises(GraphError, match="no place with id 3"):
        g.add_link(1, 3, d_m=1.0, theta_rad=0.0)
    with pytest.raises(GraphError, match="itself"):
        g.add_link(1, 1, d_m=1.0, theta_rad=0.0)
    with pytest.raises(GraphError, match="mean_step"):
        g.add_link(1, 2, d_m=1.0, theta_rad=0.0, steps=10, mean_step_m=0.0)
    g.add_link(1, 2, d_m=1.0, theta_rad=0.0)
    with pytest.raises(GraphError, match="duplicate link"):
        g.add_link(2, 1, d_m=1.0, theta_rad=0.0)


def test_graph_grows_and_shrinks_consistently():
    rng = np.random.default_rng(4)
    g = MapGraph(capacity=1)
    model_places: set[int] = set()
    model_links: dict[tuple[int, int], float] = {}
    for step in range(2000):
        op = rng.random()
        if op < 0.4 or len(model_places) < 2:
            g.add_place(step)
            model_places.add(step)
        elif op < 0.75:
            a, b = rng.choice(sorted(model_places), 2, replace=False)
            key = (min(a, b), max(a, b))
            if key not in model_links:
                g.add_link(int(a), int(b), d_m=float(step), theta_rad=0.0)
                model_links[key] = float(step)
        elif op < 0.9 and model_links:
            key = list(model_links)[rng.integers(len(model_links))]
            g.remove_link(*key)
            del model_links[key]
        else:
            victim = int(rng.choice(sorted(model_places)))
            g.remove_place(victim)
            model_places.discard(victim)
            model_links = {k: v for k, v in model_links.items() if victim not in k}
    assert set(g.ids.tolist()) == model_places
    assert all(g.index_of(p) < g.n_places for p in model_places)
    got = {(min(int(g.ids[a]), int(g.ids[b])), max(int(g.ids[a]), int(g.ids[b]))): float(d)
           for a, b, d in zip(g.src, g.dst, g.d_m)}
    assert got == model_links
    assert sum(g.degree(i) for i in range(g.n_places)) == 2 * g.n_links


@pytest.mark.parametrize("with_circular", [False, True])
def test_new_noise_rebuilds_the_sweep_unless_only_its_scale_changed(with_circular):
    """Eq. 9 is unchanged when every information is multiplied by one constant: after a noise change
    the engine's sweeps equal those of an engine built afresh with the new noise, whether or not it
    rebuilt its arrays."""
    om = office_map(60, rng=np.random.default_rng(5))
    g = om.graph
    if with_circular:
        g.remove_link(int(g.ids[g.src[3]]), int(g.ids[g.dst[3]]))
        g.add_link(int(g.ids[0]), int(g.ids[5]), d_m=5.0, theta_rad=0.1, steps=50, mean_step_m=0.1,
                   variance_m2=0.05)
    noise = CompassNoise(4e-4, 9e-4, 1e-4)
    for new in (CompassNoise(3 * 4e-4, 3 * 9e-4, 3 * 1e-4), CompassNoise(4e-4, 2e-3, -1e-4)):
        r = CompassRelaxer(g.copy(), om.xy_dead_reckoning, noise=noise, params=FIXED)
        r.sweep()
        r.set_noise(new)
        fresh = CompassRelaxer(g.copy(), r.xy, noise=new, params=FIXED)
        for _ in range(5):
            r.sweep()
            fresh.sweep()
        np.testing.assert_allclose(r.xy, fresh.xy, rtol=0, atol=1e-12)
        assert r.energy() == pytest.approx(fresh.energy(), rel=1e-12)
