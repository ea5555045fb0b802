"""Pose mode against GTSAM, run in the test on the same initial values."""

from __future__ import annotations


import numpy as np
import pytest

from services.relaxer.g2o import read_g2o
from services.relaxer.pose import PoseGraph, PoseParams, objective, optimize, residuals, residuals_and_jacobians
from services.relaxer.se2 import between, compose, inverse, logmap

gtsam = pytest.importorskip("gtsam")

from tests.conftest import DATASETS  # noqa: E402 (after the gtsam check where there is one)


def _dataset(name: str):
    path = DATASETS / f"{name}.g2o"
    if not path.exists():
        pytest.skip(f"data set {path} not found (set RELAXMAP_DATASETS)")
    return read_g2o(path)


def gtsam_optimum(graph: PoseGraph, poses: np.ndarray) -> tuple[float, float, np.ndarray]:
    """GTSAM LM from ``poses``, pose 0 held by a tight prior: (initial, final objective, poses)."""
    fg = gtsam.NonlinearFactorGraph()
    for k in range(graph.n_edges):
        fg.add(gtsam.BetweenFactorPose2(int(graph.i[k]), int(graph.j[k]), gtsam.Pose2(*graph.z[k]),
                                        gtsam.noiseModel.Gaussian.Information(graph.info[k])))
    n_between = fg.size()
    fg.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*poses[0]), gtsam.noiseModel.Isotropic.Sigma(3, 1e-8)))
    values = gtsam.Values()
    for k, p in enumerate(poses):
        values.insert(k, gtsam.Pose2(*p))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(0.0)
    params.setMaxIterations(500)
    result = gtsam.LevenbergMarquardtOptimizer(fg, values, params).optimize()
    f0 = sum(fg.at(k).error(values) for k in range(n_between))
    f1 = sum(fg.at(k).error(result) for k in range(n_between))
    out = np.array([[result.atPose2(k).x(), result.atPose2(k).y(), result.atPose2(k).theta()]
                    for k in range(len(poses))])
    return f0, f1, out


def _check_dataset(name: str) -> None:
    data = _dataset(name)
    f0, f_ref, _ = gtsam_optimum(data.graph, data.poses)
    for method in ("lm", "gn"):
        res = optimize(data.graph, data.poses, method=method)
        assert res.initial_objective == pytest.approx(f0, rel=1e-9)
        assert res.converged
        assert abs(res.objective - f_ref) <= 1e-6 * f_ref, (method, res.objective, f_ref)


@pytest.mark.parametrize("name", ["intel", "CSAIL", "MIT", "manhattan", "kitti_00", "kitti_05"])
def test_reaches_gtsam_optimum(name):
    _check_dataset(name)


@pytest.mark.slow
def test_reaches_gtsam_optimum_city10000():
    _check_dataset("city10000")


def _random_graph(rng, n=30, extra=20):
    i = list(range(n - 1)) + list(rng.integers(0, n, extra))
    j = list(range(1, n)) + list(rng.integers(0, n, extra))
    keep = [a != b for a, b in zip(i, j)]
    i = np.array(i)[keep]
    j = np.array(j)[keep]
    k = len(i)
    z = np.column_stack([rng.normal(1, 0.3, k), rng.normal(0, 0.3, k), rng.uniform(-3, 3, k)])
    a = rng.normal(size=(k, 3, 3))
    info = a @ a.transpose(0, 2, 1) + np.eye(3)
    return PoseGraph(ids=np.arange(n), i=i, j=j, z=z, info=info)


def test_residuals_match_gtsam_between_factor():
    rng = np.random.default_rng(0)
    g = _random_graph(rng)
    poses = np.column_stack([rng.normal(0, 5, (g.n_poses, 2)), rng.uniform(-3, 3, g.n_poses)])
    e = residuals(g, poses)
    values = gtsam.Values()
    for k, p in enumerate(poses):
        values.insert(k, gtsam.Pose2(*p))
    for k in range(g.n_edges):
        f = gtsam.BetweenFactorPose2(int(g.i[k]), int(g.j[k]), gtsam.Pose2(*g.z[k]),
                                     gtsam.noiseModel.Gaussian.Information(g.info[k]))
        np.testing.assert_allclose(e[k], f.unwhitenedError(values), atol=1e-9)
        assert 0.5 * e[k] @ g.info[k] @ e[k] == pytest.approx(f.error(values), rel=1e-9)


def test_jacobians_match_finite_differences():
    rng = np.random.default_rng(1)
    g = _random_graph(rng)
    poses = np.column_stack([rng.normal(0, 5, (g.n_poses, 2)), rng.uniform(-3, 3, g.n_poses)])
    poses[:3, 2] = [0.0, 1e-7, np.pi - 1e-3]
    _, ji, jj = residuals_and_jacobians(g, poses)
    h = 1e-6
    for c in range(3):
        for jac, end in ((ji, g.i), (jj, g.j)):
            for k in range(g.n_edges):
                p1, p2 = poses.copy(), poses.copy()
                p1[end[k], c] += h
                p2[end[k], c] -= h
                num = (residuals(g, p1)[k] - residuals(g, p2)[k]) / (2 * h)
                num[2] = (num[2] + np.pi / h) % (2 * np.pi / h) - np.pi / h  # no wrap jumps
                np.testing.assert_allclose(jac[k, :, c], num, atol=1e-5)


def test_se2_maths_against_gtsam():
    rng = np.random.default_rng(2)
    for _ in range(20):
        a = np.r_[rng.normal(0, 3, 2), rng.uniform(-3, 3)]
        b = np.r_[rng.normal(0, 3, 2), rng.uniform(-3, 3)]
        ga, gb = gtsam.Pose2(*a), gtsam.Pose2(*b)
        c = ga.compose(gb)
        np.testing.assert_allclose(compose(a, b), [c.x(), c.y(), c.theta()], atol=1e-12)
        d = ga.between(gb)
        np.testing.assert_allclose(between(a, b), [d.x(), d.y(), d.theta()], atol=1e-12)
        iv = ga.inverse()
        np.testing.assert_allclose(inverse(a), [iv.x(), iv.y(), iv.theta()], atol=1e-12)
        np.testing.assert_allclose(logmap(b), gtsam.Pose2.Logmap(gb), atol=1e-12)


def test_appendix_b_relaxation_converges_to_the_batch_optimum():
    rng = np.random.default_rng(3)
    n = 15
    truth = np.column_stack([np.cumsum(rng.normal(0.5, 0.2, (n, 2)), axis=0), rng.uniform(-3, 3, n)])
    i = np.r_[np.arange(n - 1), rng.integers(0, n, 30)]
    j = np.r_[np.arange(1, n), rng.integers(0, n, 30)]
    keep = i != j
    i, j = i[keep], j[keep]
    z = between(truth[i], truth[j]) + rng.normal(0, 0.02, (len(i), 3))
    info = np.tile(np.diag([100.0, 100.0, 400.0]), (len(i), 1, 1))
    g = PoseGraph(ids=np.arange(n), i=i, j=j, z=z, info=info)
    lm = optimize(g, truth, method="lm")
    start = lm.poses + np.column_stack([rng.normal(0, 0.1, (n, 2)), rng.normal(0, 0.05, n)])
    start[0] = lm.poses[0]
    seen = []
    res = optimize(g, start, method="relax", params=PoseParams(max_iters=20000, tol_rel=0.0, relax_tol_step=1e-12),
                   callback=lambda it, f: seen.append(f) and False)
    assert res.converged
    assert res.objective == pytest.approx(lm.objective, rel=1e-8)
    np.testing.assert_allclose(res.poses, lm.poses, atol=1e-6)
    assert all(b <= a * (1 + 1e-6) for a, b in zip(seen[5:], seen[6:]))


def test_disconnected_pose_graph_holds_the_first_pose_of_each_part():
    rng = np.random.default_rng(4)
    g1 = _random_graph(rng, n=10, extra=5)
    g2 = _random_graph(rng, n=8, extra=4)
    g = PoseGraph(ids=np.arange(18), i=np.r_[g1.i, g2.i + 10], j=np.r_[g1.j, g2.j + 10],
                  z=np.r_[g1.z, g2.z], info=np.r_[g1.info, g2.info])
    poses = np.column_stack([rng.normal(0, 5, (18, 2)), rng.uniform(-3, 3, 18)])
    res = optimize(g, poses)
    np.testing.assert_array_equal(res.poses[[0, 10]], poses[[0, 10]])
    r1 = optimize(g1, poses[:10])
    r2 = optimize(g2, poses[10:])
    assert res.objective == pytest.approx(r1.objective + r2.objective, rel=1e-8)


def test_superlu_path_reaches_the_same_optimum(monkeypatch):
    import services.relaxer.pose as pose

    data = _dataset("CSAIL")
    with_ldl = optimize(data.graph, data.poses)
    monkeypatch.setattr(pose, "_qdldl", None)
    without = optimize(data.graph, data.poses)
    assert without.objective == pytest.approx(with_ldl.objective, rel=1e-9)
