"""Pose mode (Appendix B, no compass): SE(2) pose graphs, Gauss-Newton / Levenberg-Marquardt and relaxation.

The objective is GTSAM's for ``BetweenFactor<Pose2>``: ``0.5 * sum e^T Info e`` with
``e = Logmap(Z^-1 * (X_i^-1 * X_j))``, tangent ordered ``(x, y, theta)``. Jacobians are exact and
vectorised; the normal equations are assembled into a sparse matrix whose pattern is computed once
and factorised with QDLDL (sparse LDL^T, AMD ordering, symbolic analysis kept across iterations) or,
without it, SuperLU (symmetric mode, one fill-reducing ordering reused across iterations).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import msgspec
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from services.relaxer.graph import GraphError, colour_places
from services.relaxer.se2 import half_cot_terms, wrap
from services.relaxer.sparse import SolveError

try:  # sparse LDL^T (pip wheel); SuperLU in symmetric mode otherwise
    import qdldl as _qdldl
except ImportError:
    _qdldl = None

__all__ = ["PoseGraph", "PoseParams", "PoseResult", "objective", "odometry_initialisation", "optimize", "residuals",
           "residuals_and_jacobians"]


@dataclass(frozen=True)
class PoseGraph:
    """Poses with ids and relative-pose edges (the measurement of ``j`` in the frame of ``i``)."""

    ids: np.ndarray  # (N,) vertex ids by dense index
    i: np.ndarray  # (K,) dense index of each edge's first pose
    j: np.ndarray  # (K,) dense index of each edge's second pose
    z: np.ndarray  # (K, 3) measured relative pose (x, y, theta) of j in the frame of i (m, m, rad)
    info: np.ndarray  # (K, 3, 3) information matrix in (x, y, theta) order

    @property
    def n_poses(self) -> int:
        return len(self.ids)

    @property
    def n_edges(self) -> int:
        return len(self.i)

    def components(self) -> tuple[int, np.ndarray]:
        from scipy.sparse.csgraph import connected_components

        n = self.n_poses
        adj = sp.coo_matrix((np.ones(self.n_edges), (self.i, self.j)), shape=(n, n))
        count, labels = connected_components(adj, directed=False)
        return int(count), labels

    def gauge(self) -> np.ndarray:
        """Poses held fixed: the first pose (lowest index) of every connected part."""
        count, labels = self.components()
        first = np.full(count, -1, dtype=np.int64)
        order = np.arange(self.n_poses)[::-1]
        first[labels[order]] = order
        fixed = np.zeros(self.n_poses, dtype=bool)
        fixed[first] = True
        return fixed


class PoseParams(msgspec.Struct, frozen=True):
    """Parameters of the pose-graph solvers."""

    max_iters: int = 100  # GN/LM iterations (or relaxation sweeps) before giving up
    tol_rel: float = 1e-10  # converged when an iteration lowers the objective by less than this fraction
    tol_abs: float = 1e-12  # ... or by less than this (objective units)
    lambda_initial: float = 1e-5  # LM: initial damping added to the diagonal (GTSAM's default)
    lambda_factor: float = 10.0  # LM: damping multiplier on rejection, divisor on success
    lambda_max: float = 1e10  # LM: give up when the damping grows past this
    relax_tol_step: float = 1e-10  # relaxation: converged when no coordinate moves more than this


@dataclass(frozen=True)
class PoseResult:
    """Result of a pose-graph solve."""

    poses: np.ndarray  # (N, 3) optimised poses (x, y, theta) by dense index
    objective: float  # 0.5 * sum e^T Info e at ``poses``
    initial_objective: float
    iterations: int
    converged: bool
    method: str  # "gn", "lm" or "relax"


def residuals(graph: PoseGraph, poses: np.ndarray) -> np.ndarray:
    """``e_k = Logmap(Z_k^-1 X_i^-1 X_j)``, shape (K, 3)."""
    return residuals_and_jacobians(graph, poses, jacobians=False)[0]


def residuals_and_jacobians(graph: PoseGraph, poses: np.ndarray, *, jacobians: bool = True,
                            edges: np.ndarray | None = None):
    """Residuals and their exact Jacobians with respect to ``(x, y, theta)`` of both poses.

    Returns
    -------
    e : ndarray, shape (K, 3)
    ji, jj : ndarray, shape (K, 3, 3) or None

    Notes
    -----
    With ``t_d = R(th_i + th_z)^T (t_j - t_i) - R(th_z)^T t_z`` and ``w = wrap(th_j - th_i - th_z)``:
    ``e = (V(w)^-1 t_d, w)``, ``V^-1 = [[alpha, w/2], [-w/2, alpha]]``,
    ``d e_t / d t_j = V^-1 R(th_i + th_z)^T = -d e_t / d t_i``,
    ``d e_t / d th_j = V'^-1 t_d``, ``d e_t / d th_i = -V^-1 J (t_d + R(th_z)^T t_z) - V'^-1 t_d``
    with ``J`` the 90-degree rotation, and ``d w / d th_j = 1 = -d w / d th_i``. This is Appendix B's
    proposal ``r'_ji = r_j + F_ji`` (Eqs. 30-31) written as a residual.
    """
    sel = slice(None) if edges is None else edges
    i, j, z = graph.i[sel], graph.j[sel], graph.z[sel]
    pi, pj = poses[i], poses[j]
    a = pi[:, 2] + z[:, 2]
    ca, sa = np.cos(a), np.sin(a)
    cz, sz = np.cos(z[:, 2]), np.sin(z[:, 2])
    dx, dy = pj[:, 0] - pi[:, 0], pj[:, 1] - pi[:, 1]
    # R(th_z)^T t_z
    zx, zy = cz * z[:, 0] + sz * z[:, 1], -sz * z[:, 0] + cz * z[:, 1]
    rx, ry = ca * dx + sa * dy, -sa * dx + ca * dy  # R(th_i + th_z)^T (t_j - t_i)
    tx, ty = rx - zx, ry - zy
    w = wrap(pj[:, 2] - pi[:, 2] - z[:, 2])
    alpha, dalpha = half_cot_terms(w)
    hw = 0.5 * w
    e = np.stack([alpha * tx + hw * ty, -hw * tx + alpha * ty, w], axis=1)
    if not jacobians:
        return e, None, None
    k = len(w)
    jj = np.zeros((k, 3, 3))
    # V^-1 R^T with R^T = [[ca, sa], [-sa, ca]]
    jj[:, 0, 0] = alpha * ca - hw * sa
    jj[:, 0, 1] = alpha * sa + hw * ca
    jj[:, 1, 0] = -hw * ca - alpha * sa
    jj[:, 1, 1] = -hw * sa + alpha * ca
    # V'^-1 t_d, V'^-1 = [[dalpha, 1/2], [-1/2, dalpha]]
    vx, vy = dalpha * tx + 0.5 * ty, -0.5 * tx + dalpha * ty
    jj[:, 0, 2] = vx
    jj[:, 1, 2] = vy
    jj[:, 2, 2] = 1.0
    ji = -jj
    # -V^-1 J r  with r = t_d + R(th_z)^T t_z = (rx, ry), J r = (-ry, rx)
    jrx, jry = -ry, rx
    ji[:, 0, 2] = -(alpha * jrx + hw * jry) - vx
    ji[:, 1, 2] = -(-hw * jrx + alpha * jry) - vy
    ji[:, 2, 2] = -1.0
    return e, ji, jj


def objective(graph: PoseGraph, poses: np.ndarray) -> float:
    """GTSAM's objective ``0.5 * sum e^T Info e``."""
    e = residuals(graph, np.asarray(poses, dtype=float))
    return 0.5 * float(np.einsum("ki,kij,kj->", e, graph.info, e))


class _Normal:
    """Sparse normal equations over the free poses with a pattern fixed once."""

    def __init__(self, graph: PoseGraph, fixed: np.ndarray) -> None:
        n = graph.n_poses
        free_idx = np.full(n, -1, dtype=np.int64)
        free = np.flatnonzero(~fixed)
        free_idx[free] = np.arange(len(free))
        self.n_free = 3 * len(free)
        self.free_idx = free_idx
        fi, fj = free_idx[graph.i], free_idx[graph.j]
        r3 = np.arange(3)
        rows, cols, keep = [], [], []
        for a, b in ((fi, fi), (fi, fj), (fj, fi), (fj, fj)):
            rr = (3 * a[:, None, None] + r3[None, :, None]) * np.ones((1, 1, 3), dtype=np.int64)
            cc = (3 * b[:, None, None] + r3[None, None, :]) * np.ones((1, 3, 1), dtype=np.int64)
            ok = np.repeat(((a >= 0) & (b >= 0))[:, None], 9, axis=1).reshape(-1, 3, 3)
            rows.append(rr)
            cols.append(cc)
            keep.append(ok)
        rows_a = np.stack(rows, axis=1).reshape(-1)  # (K, 4 blocks, 3, 3)
        cols_a = np.stack(cols, axis=1).reshape(-1)
        self.keep = np.stack(keep, axis=1).reshape(-1)
        key = rows_a[self.keep] * max(self.n_free, 1) + cols_a[self.keep]
        uniq, self.inv = np.unique(key, return_inverse=True)
        urow, ucol = uniq // max(self.n_free, 1), uniq % max(self.n_free, 1)
        self.indices = ucol.astype(np.int32)
        self.indptr = np.searchsorted(urow, np.arange(self.n_free + 1)).astype(np.int32)
        self.nnz = len(uniq)
        self.diag_pos = np.flatnonzero(urow == ucol)
        self.perm: np.ndarray | None = None
        self._ldl = None

    def assemble(self, graph: PoseGraph, e: np.ndarray, ji: np.ndarray, jj: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """CSR data of ``H = J^T Info J`` and the gradient ``g = J^T Info e`` over free variables."""
        oi = np.einsum("kab,kbc->kac", graph.info, ji)
        oj = np.einsum("kab,kbc->kac", graph.info, jj)
        hii = np.einsum("kba,kbc->kac", ji, oi)
        hij = np.einsum("kba,kbc->kac", ji, oj)
        hjj = np.einsum("kba,kbc->kac", jj, oj)
        blocks = np.stack([hii, hij, hij.transpose(0, 2, 1), hjj], axis=1).reshape(-1)
        data = np.bincount(self.inv, blocks[self.keep], self.nnz)
        oe = np.einsum("kab,kb->ka", graph.info, e)
        gi = np.einsum("kba,kb->ka", ji, oe)
        gj = np.einsum("kba,kb->ka", jj, oe)
        g = np.zeros(self.n_free)
        fi, fj = self.free_idx[graph.i], self.free_idx[graph.j]
        for f, gg in ((fi, gi), (fj, gj)):
            ok = f >= 0
            idx = (3 * f[ok, None] + np.arange(3)).reshape(-1)
            g += np.bincount(idx, gg[ok].reshape(-1), self.n_free)
        return data, g

    def solve(self, data: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        h = sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n_free, self.n_free))
        if _qdldl is not None:
            # sparse LDL^T with an AMD ordering; the symbolic analysis is kept across iterations
            try:
                if self._ldl is None:
                    self._ldl = _qdldl.Solver(h.tocsc())
                else:
                    self._ldl.update(h.tocsc())
                x = self._ldl.solve(rhs)
            except (ValueError, RuntimeError) as exc:
                raise SolveError(f"singular normal equations ({exc})") from None
            if not np.all(np.isfinite(x)):
                raise SolveError("normal equations are singular or badly conditioned")
            return x
        if self.perm is None:
            lu = self._factor(h.tocsc(), "MMD_AT_PLUS_A")
            self.perm = np.argsort(lu.perm_c)
            return lu.solve(rhs)
        p = self.perm
        hp = h[p][:, p].tocsc()
        x = np.empty_like(rhs)
        x[p] = self._factor(hp, "NATURAL").solve(rhs[p])
        return x

    @staticmethod
    def _factor(h: sp.csc_matrix, permc: str):
        try:
            return splu(h, permc_spec=permc, diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        except RuntimeError as exc:
            raise SolveError(f"singular normal equations ({exc})") from None


def _check_poses(graph: PoseGraph, poses0: np.ndarray) -> np.ndarray:
    poses = np.array(poses0, dtype=float, copy=True)
    if poses.shape != (graph.n_poses, 3):
        raise GraphError(f"poses have shape {poses.shape}, the graph has {graph.n_poses} poses")
    if not np.all(np.isfinite(poses)):
        raise GraphError("poses must be finite")
    return poses


def _gauss_newton(graph: PoseGraph, poses: np.ndarray, params: PoseParams, damped: bool,
                  callback: Callable[[int, float], bool] | None) -> tuple[np.ndarray, float, int, bool]:
    fixed = graph.gauge()
    normal = _Normal(graph, fixed)
    free = np.flatnonzero(~fixed)
    e, ji, jj = residuals_and_jacobians(graph, poses)
    f = 0.5 * float(np.einsum("ki,kij,kj->", e, graph.info, e))
    lam = params.lambda_initial
    it = 0
    converged = False
    if normal.n_free == 0:
        return poses, f, 0, True
    while it < params.max_iters:
        data, g = normal.assemble(graph, e, ji, jj)
        while True:
            d = data.copy()
            if damped:
                d[normal.diag_pos] += lam
            try:
                step = normal.solve(d, -g)
                ok = np.all(np.isfinite(step))
            except SolveError:
                if not damped:
                    raise
                ok = False
            if ok:
                trial = poses.copy()
                trial[free] += step.reshape(-1, 3)
                trial[free, 2] = wrap(trial[free, 2])
                e_t, ji_t, jj_t = residuals_and_jacobians(graph, trial)
                f_t = 0.5 * float(np.einsum("ki,kij,kj->", e_t, graph.info, e_t))
            if not damped or (ok and f_t <= f):
                break
            lam *= params.lambda_factor
            if lam > params.lambda_max:
                return poses, f, it, converged
        it += 1
        decrease = f - f_t
        poses, e, ji, jj, f = trial, e_t, ji_t, jj_t, f_t
        if damped:
            lam = max(lam / params.lambda_factor, 1e-12)
        if callback is not None and callback(it, f):
            break
        if abs(decrease) <= params.tol_abs or abs(decrease) <= params.tol_rel * f:
            converged = True
            break
    return poses, f, it, converged


def _relax(graph: PoseGraph, poses: np.ndarray, params: PoseParams,
           callback: Callable[[int, float], bool] | None) -> tuple[np.ndarray, float, int, bool]:
    """Appendix B: Gauss-Seidel over poses, one colour class at a time."""
    fixed = graph.gauge()
    n = graph.n_poses
    colour = colour_places(n, graph.i, graph.j, ~fixed)
    classes = []
    for c in range(int(colour.max(initial=-1)) + 1):
        members = np.flatnonzero(colour == c)
        pos = np.full(n, -1, dtype=np.int64)
        pos[members] = np.arange(len(members))
        ei = np.flatnonzero(colour[graph.i] == c)
        ej = np.flatnonzero(colour[graph.j] == c)
        edges = np.concatenate([ei, ej])
        target = np.concatenate([pos[graph.i[ei]], pos[graph.j[ej]]])
        first = np.concatenate([np.ones(len(ei), bool), np.zeros(len(ej), bool)])
        classes.append((members, edges, target, first))
    it = 0
    converged = False
    f = objective(graph, poses)
    while it < params.max_iters:
        step_max = 0.0
        for members, edges, target, first in classes:
            e, ji, jj = residuals_and_jacobians(graph, poses, edges=edges)
            jac = np.where(first[:, None, None], ji, jj)
            oj = np.einsum("kab,kbc->kac", graph.info[edges], jac)
            a = np.einsum("kba,kbc->kac", jac, oj)
            b = np.einsum("kba,kb->ka", oj, e)
            m = len(members)
            amat = np.zeros((m, 3, 3))
            np.add.at(amat, target, a)
            bvec = np.zeros((m, 3))
            np.add.at(bvec, target, b)
            delta = -np.linalg.solve(amat, bvec[..., None])[..., 0]
            poses[members] += delta
            poses[members, 2] = wrap(poses[members, 2])
            step_max = max(step_max, float(np.abs(delta).max(initial=0.0)))
        it += 1
        f_new = objective(graph, poses)
        small = step_max <= params.relax_tol_step or abs(f - f_new) <= params.tol_rel * f_new
        f = f_new
        if callback is not None and callback(it, f):
            break
        if small:
            converged = True
            break
    return poses, f, it, converged


def optimize(graph: PoseGraph, poses0: np.ndarray, *, method: str = "lm", params: PoseParams = PoseParams(),
             callback: Callable[[int, float], bool] | None = None) -> PoseResult:
    """Minimise GTSAM's pose-graph objective from ``poses0``.

    Parameters
    ----------
    graph : PoseGraph
    poses0 : ndarray, shape (N, 3)
        Initial poses; the first pose of every connected part stays where it is (gauge).
    method : {"lm", "gn", "relax", "auto"}
        Levenberg-Marquardt (``auto`` too), Gauss-Newton, or the relaxation of Appendix B.
    params : PoseParams
    callback : callable, optional
        ``callback(iteration, objective) -> bool`` after each iteration; returning True stops.

    Notes
    -----
    GN solves ``J^T Info J dx = -J^T Info e`` each iteration; LM adds ``lambda I`` and accepts a step
    only when the objective does not increase. The relaxation moves one colour class of poses at a
    time, each pose to the information-weighted mean of its neighbours' proposals (Eqs. 30-31,
    linearised exactly), and converges to a nearby local minimum.
    """
    poses = _check_poses(graph, poses0)
    f0 = objective(graph, poses)
    if method in ("lm", "auto"):
        poses, f, it, conv = _gauss_newton(graph, poses, params, True, callback)
    elif method == "gn":
        poses, f, it, conv = _gauss_newton(graph, poses, params, False, callback)
    elif method == "relax":
        poses, f, it, conv = _relax(graph, poses, params, callback)
    else:
        raise ValueError(f"unknown method {method!r}")
    return PoseResult(poses=poses, objective=f, initial_objective=f0, iterations=it, converged=conv,
                      method="lm" if method == "auto" else method)


def odometry_initialisation(graph: PoseGraph, known: np.ndarray | None = None,
                            poses: np.ndarray | None = None) -> np.ndarray:
    """Poses by composing edges from known poses (a part with none starts from its first pose at the origin).

    Sequential edges ``id -> id + 1`` are used first, then any edge from an initialised pose
    (breadth first), so every pose connected to a known one gets a value.
    """
    n = graph.n_poses
    out = np.zeros((n, 3)) if poses is None else np.array(poses, dtype=float)
    have = np.zeros(n, dtype=bool) if known is None else np.array(known, dtype=bool)
    count, labels = graph.components()
    for part in np.setdiff1d(np.arange(count), labels[have]).tolist():
        first = int(np.flatnonzero(labels == part)[0])  # a part with no known pose starts at the origin
        out[first] = 0.0
        have[first] = True
    ids = graph.ids
    seq = ids[graph.j] == ids[graph.i] + 1
    order = np.concatenate([np.flatnonzero(seq)[np.argsort(ids[graph.i[seq]], kind="stable")],
                            np.flatnonzero(~seq)])
    zl = graph.z.tolist()
    changed = True
    while changed:
        changed = False
        for k in order.tolist():
            a, b = int(graph.i[k]), int(graph.j[k])
            if have[a] and not have[b]:
                out[b] = _compose1(out[a], zl[k])
                have[b] = True
                changed = True
            elif have[b] and not have[a]:
                out[a] = _compose1(out[b], _inverse1(zl[k]))
                have[a] = True
                changed = True
        if have.all():
            break
    if not have.all():
        missing = int(ids[np.flatnonzero(~have)[0]])
        raise GraphError(f"pose {missing} has no initial value and no edge path from one that has")
    return out


def _compose1(a, b) -> tuple[float, float, float]:
    c, s = math.cos(a[2]), math.sin(a[2])
    t = a[2] + b[2]
    return a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], math.atan2(math.sin(t), math.cos(t))


def _inverse1(a) -> tuple[float, float, float]:
    c, s = math.cos(a[2]), math.sin(a[2])
    return -c * a[0] - s * a[1], s * a[0] - c * a[1], -a[2]
