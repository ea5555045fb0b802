"""Compass-mode relaxation (Figure 3, Appendix A), its exact sparse solve and the on-line cycle.

Strategy of the on-line cycle (measured by ``relaxmap bench relax``, see docs/relaxer.md): every
cycle runs one vectorised Gauss-Seidel sweep over all places (Figure 3 step 2, colour class by
colour class), then computes the energy and re-estimates the noise from the same three residual sums
(step 3). The graph keeps per-link quantities from which every noise-dependent array is a linear
combination, so a new noise estimate costs a few array products and no per-link inversions. When a
loop closure leaves the map far from equilibrium, the sweep steps shrink slowly; the cycle predicts
how many more sweeps convergence needs from the ratio of successive steps and, when that exceeds the
measured cost of one sparse factorisation expressed in sweeps, solves the quadratic energy exactly
instead (the simultaneous-equation solve the paper suggests in Section 7).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import msgspec
import numpy as np
import scipy.sparse as sp

from services.relaxer.graph import GraphError, MapGraph, _grown, colour_places
from services.relaxer.sparse import spd_solve

__all__ = [
    "CompassNoise", "CompassParams", "CompassRelaxer", "CompassResult", "CycleReport",
    "energy", "estimate_noise", "estimate_noise_reml", "information_coefficients", "link_information", "normal_equations",
    "relax", "solve_exact",
]


class CompassNoise(msgspec.Struct, frozen=True):
    """The three global noise parameters of Eq. 5 (per odometry step)."""

    s_dd_m2: float = 1.0  # variance of the distance travelled per step (m^2)
    s_aa_rad2: float = 1.0  # variance of the heading per step (rad^2)
    s_da_m_rad: float = 0.0  # covariance of distance and heading per step (m rad)


class CompassParams(msgspec.Struct, frozen=True):
    """Parameters of compass-mode relaxation and of the on-line cycle."""

    max_sweeps: int = 100_000  # sweeps (Figure 3 iterations) in one batch relaxation before giving up
    tol_energy_rel: float = 1e-12  # converged when a sweep lowers E (Eq. 7) by less than this fraction (0: off)
    tol_step_m: float = 1e-9  # ... or when a sweep moves no place by more than this (m)
    tol_noise_rel: float = 1e-6  # noise re-estimation has converged below this relative change
    estimate_noise: bool = True  # re-estimate S_dd, S_aa, S_da after each sweep (Eqs. 12-14)
    dof_correction: bool = True  # divide by the residual degrees of freedom, not by K (unbiased estimates)
    min_s_dd_m2: float = 1e-12  # floor of the re-estimated S_dd (m^2)
    min_s_aa_rad2: float = 1e-12  # floor of the re-estimated S_aa (rad^2)
    max_correlation: float = 0.99  # |S_da| is kept below this fraction of sqrt(S_dd S_aa)
    auto_min_step_m: float = 1e-3  # the auto strategy acts only on sweeps moving a place more than this (m)
    auto_target_step_m: float = 1e-6  # the sweep step (m) at which the auto strategy deems a map settled
    exact_cost_sweeps: float = 64.0  # cost of one exact solve in sweeps, at 1000 places (measured)
    exact_cost_growth: float = 0.07  # that cost grows as (places / 1000) ** this (measured)
    max_exact_noise_rounds: int = 50  # exact solves alternated with noise re-estimation, at most
    noise_refresh_rel: float = 1e-3  # adopt a new noise estimate once it differs by more than this (relative);
    # the sweep is rebuilt when the noise's shape (up to scale) moved by more than this
    class_chunk_places: int = 512  # places per sweep class: a change recompiles only its class (measured)


@dataclass(frozen=True)
class CompassResult:
    """Result of a compass-mode solve."""

    xy: np.ndarray  # (N, 2) coordinates by dense place index (m)
    ids: np.ndarray  # (N,) place ids
    energy: float  # Eq. 7 at ``xy`` under ``noise``
    iterations: int  # sweeps, or exact solves
    converged: bool
    method: str  # "relax", "exact" or "auto"
    noise: CompassNoise
    exact_solves: int = 0


@dataclass(frozen=True)
class CycleReport:
    """What one on-line cycle did."""

    energy: float  # Eq. 7 after the cycle's sweep, under the noise it used
    step_m: float  # largest move of a place in the sweep (m)
    exact: bool  # the auto strategy solved the energy exactly in this cycle
    noise: CompassNoise  # noise parameters for the next cycle


def information_coefficients(noise: CompassNoise) -> np.ndarray:
    """``(a, b, c, 1)`` such that each link information is ``basis @ coef`` (see ``link_geometry``).

    Notes
    -----
    Inverting Eq. 5: ``(a, b, c) = (S_aa, -S_da, S_dd) / (S_dd S_aa - S_da^2)``.
    """
    det = noise.s_dd_m2 * noise.s_aa_rad2 - noise.s_da_m_rad ** 2
    if not (noise.s_dd_m2 > 0 and noise.s_aa_rad2 > 0 and det > 0):
        raise ValueError(f"noise parameters are not a covariance: {noise}")
    return np.array([noise.s_aa_rad2 / det, -noise.s_da_m_rad / det, noise.s_dd_m2 / det, 1.0])


def link_information(graph: MapGraph, noise: CompassNoise) -> np.ndarray:
    """Per-link information ``C_ji^-1`` as ``(W_xx, W_xy, W_yy)``, shape (K, 3).

    Notes
    -----
    Eq. 5 for links without ``variance``; ``I / v`` for circular-noise links (Appendix A).
    """
    return graph.basis @ information_coefficients(noise)


def _residual_sums(graph: MapGraph, xy: np.ndarray, *, circular: bool = True) -> np.ndarray:
    """``(sum p~^2, sum p~ q~, sum q~^2, sum |e|^2 / v)`` with ``p~ = e.u/sqrt(T)``, ``q~ = e.u_perp/(sqrt(T) delta)``.

    ``circular=False`` says no link has a variance of its own (the last sum is 0 then).
    """
    e = np.take(xy, graph.dst, axis=0)  # np.take gathers rows about twice as fast as xy[index]
    e -= np.take(xy, graph.src, axis=0)
    e -= graph.disp
    p = np.einsum("ij,ij->i", e, graph.u_scaled)
    q = np.einsum("ij,ij->i", e, graph.v_scaled)
    c = graph.inv_var @ np.einsum("ij,ij->i", e, e) if circular else 0.0
    return np.array([p @ p, p @ q, q @ q, c])


def _energy_from_sums(sums: np.ndarray, coef: np.ndarray) -> float:
    return float(coef[0] * sums[0] + 2.0 * coef[1] * sums[1] + coef[2] * sums[2] + sums[3])


def energy(graph: MapGraph, xy: np.ndarray, noise: CompassNoise) -> float:
    """The energy of Eq. 7, ``sum over links (r_i - r_j - D_ji)^T C_ji^-1 (r_i - r_j - D_ji)``.

    Each link counts once. With ``p = e.u`` and ``q = e.u_perp`` it equals
    ``sum (a p^2/T + 2 b p q/(T delta) + c q^2/(T delta^2))`` plus ``|e|^2 / v`` for circular links.
    """
    return _energy_from_sums(_residual_sums(graph, np.asarray(xy, dtype=float)), information_coefficients(noise))


def _noise_from_sums(sums: np.ndarray, n_fig3: int, cycle_rank: int, n_links: int, previous: CompassNoise,
                     params: CompassParams) -> CompassNoise:
    if cycle_rank <= 0 or n_fig3 == 0 or not sums[0] + sums[2] > 0:
        return previous  # a tree (or no three-parameter link): every residual is zero
    den = n_fig3 * (cycle_rank / n_links) if params.dof_correction else float(n_fig3)
    s_dd = max(sums[0] / den, params.min_s_dd_m2)
    s_aa = max(sums[2] / den, params.min_s_aa_rad2)
    lim = params.max_correlation * math.sqrt(s_dd * s_aa)
    s_da = min(max(sums[1] / den, -lim), lim)
    return CompassNoise(float(s_dd), float(s_aa), float(s_da))


def estimate_noise(graph: MapGraph, xy: np.ndarray, previous: CompassNoise,
                   params: CompassParams = CompassParams()) -> CompassNoise:
    """Maximum-likelihood noise parameters from the current residuals (Eqs. 12-14).

    Parameters
    ----------
    graph : MapGraph
    xy : ndarray, shape (N, 2)
        Current coordinates.
    previous : CompassNoise
        Kept when the graph has no loop (every residual of a tree is zero).
    params : CompassParams
        Floors, the correlation bound and the degrees-of-freedom correction.

    Notes
    -----
    With ``e_ji = r_i - r_j - D_ji``, ``p = e.u`` and ``q = e.u_perp`` over the K links with the
    three-parameter model: ``S_dd = sum p^2/T / K`` (Eq. 12), ``S_aa = sum q^2/(T delta^2) / K``
    (Eq. 13), ``S_da = sum p q/(T delta) / K`` (Eq. 14). Residuals at the minimum have only
    ``2 (K_all - N + parts)`` degrees of freedom out of ``2 K_all``; with ``dof_correction`` the
    divisor ``K`` is scaled by that fraction, which removes the downward bias of the joint estimate
    (with a tree, nothing is estimated).
    """
    count, _ = graph.components()
    rank = graph.n_links - graph.n_places + count
    n_fig3 = int(graph.n_links - np.count_nonzero(graph.circular))
    return _noise_from_sums(_residual_sums(graph, np.asarray(xy, dtype=float)), n_fig3, rank, graph.n_links,
                            previous, params)


def _gauge(graph: MapGraph, pinned: int) -> np.ndarray:
    """Indices held fixed: ``pinned`` and, in every other part, its first place."""
    count, labels = graph.components()
    fixed = np.zeros(graph.n_places, dtype=bool)
    if graph.n_places:
        first = np.full(count, -1, dtype=np.int64)
        order = np.arange(graph.n_places)[::-1]
        first[labels[order]] = order  # the last write per label is its smallest index
        fixed[first] = True
        fixed[first[labels[pinned]]] = False
        fixed[pinned] = True
    return fixed


def normal_equations(graph: MapGraph, noise: CompassNoise) -> tuple[sp.csr_matrix, np.ndarray]:
    """The quadratic energy as ``E(x) = x^T H x - 2 g^T x + const`` over ``x = (x_0, y_0, x_1, ...)``.

    Notes
    -----
    Each link adds ``W`` to the diagonal blocks of both places and ``-W`` off the diagonal; the
    right-hand side gets ``+W D`` at its second place and ``-W D`` at its first (gradient of Eq. 7).
    """
    n = graph.n_places
    upper, g, _ = _reduced_system(graph, link_information(graph, noise), np.zeros(n, dtype=bool), np.zeros(2 * n))
    return sp.csr_matrix(upper + sp.triu(upper, 1).T), g


def _reduced_system(graph: MapGraph, w: np.ndarray, fixed: np.ndarray,
                    x: np.ndarray) -> tuple[sp.csc_matrix, np.ndarray, np.ndarray]:
    """The normal equations over the free places only: ``(upper triangle of H_ff, rhs, free variables)``.

    Notes
    -----
    Assembled straight from the links (the same sums as :func:`normal_equations`, rows and columns of
    the fixed places left out, their coordinates moved to the right-hand side), and only the upper
    triangle, which is all a symmetric factorisation reads: building the full ``H`` and slicing it
    cost as much as the factorisation itself at a thousand places.
    """
    n = graph.n_places
    index = np.full(n, -1, dtype=np.int64)
    free_places = np.flatnonzero(~fixed)
    index[free_places] = np.arange(len(free_places))
    i, j = graph.src, graph.dst
    fi, fj = index[i], index[j]
    wxx, wxy, wyy = w[:, 0], w[:, 1], w[:, 2]
    rows, cols, vals = [], [], []
    for f in (fi, fj):  # diagonal blocks: (x, x), (x, y), (y, y) of each free end
        m = f >= 0
        b = 2 * f[m]
        rows += [b, b, b + 1]
        cols += [b, b + 1, b + 1]
        vals += [wxx[m], wxy[m], wyy[m]]
    m = (fi >= 0) & (fj >= 0)  # off-diagonal blocks -W, in the upper triangle
    lo, hi = 2 * np.minimum(fi[m], fj[m]), 2 * np.maximum(fi[m], fj[m])
    rows += [lo, lo, lo + 1, lo + 1]
    cols += [hi, hi + 1, hi, hi + 1]
    vals += [-wxx[m], -wxy[m], -wxy[m], -wyy[m]]
    size = 2 * len(free_places)
    h = sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(size, size))
    # right-hand side: +W D at the second place, -W D at the first; a fixed neighbour adds +W x_fixed
    xy = x.reshape(-1, 2)
    dx, dy = graph.disp[:, 0], graph.disp[:, 1]
    at = np.concatenate([j, i])
    gx = np.concatenate([wxx * dx + wxy * dy, -(wxx * dx + wxy * dy)])
    gy = np.concatenate([wxy * dx + wyy * dy, -(wxy * dx + wyy * dy)])
    for a, b in ((i, j), (j, i)):  # a free, b fixed
        m = (index[a] >= 0) & (index[b] < 0)
        if m.any():
            bx, by = xy[b[m], 0], xy[b[m], 1]
            at = np.concatenate([at, a[m]])
            gx = np.concatenate([gx, wxx[m] * bx + wxy[m] * by])
            gy = np.concatenate([gy, wxy[m] * bx + wyy[m] * by])
    g = np.stack([np.bincount(at, gx, minlength=n), np.bincount(at, gy, minlength=n)], axis=1)
    free = np.repeat(~fixed, 2)
    return h, g[free_places].ravel(), free


def _exact_xy(graph: MapGraph, xy: np.ndarray, noise: CompassNoise, pinned: int,
              xi: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """Exact minimum; with ``xi`` (shape (m, K, 2) standard normal) also ``m`` posterior fluctuations.

    A fluctuation ``y = H^-1 J^T W^(1/2) xi`` has covariance ``H^-1``: the posterior covariance of
    the coordinates when the likelihood is ``exp(-E/2)``.
    """
    x = np.asarray(xy, dtype=float).reshape(-1).copy()
    y = None
    fixed = _gauge(graph, pinned)
    if not fixed.all():
        w = link_information(graph, noise)
        hff, rhs, free = _reduced_system(graph, w, fixed, x)
        if xi is None:
            x[free] = spd_solve(hff, rhs, upper=True)
        else:
            l11 = np.sqrt(w[:, 0])
            l21 = w[:, 1] / l11
            l22 = np.sqrt(np.maximum(w[:, 2] - l21 * l21, 0.0))
            lx = l11 * xi[..., 0]
            ly = l21 * xi[..., 0] + l22 * xi[..., 1]
            m = xi.shape[0]
            f = np.zeros((m, graph.n_places, 2))
            lxy = np.stack([lx, ly], axis=-1)
            for s in range(m):
                np.add.at(f[s], graph.dst, lxy[s])
                np.add.at(f[s], graph.src, -lxy[s])
            b = np.concatenate([rhs[:, None], f.reshape(m, -1)[:, free].T], axis=1)
            sol = spd_solve(hff, b, upper=True)
            x[free] = sol[:, 0]
            y = np.zeros((m, 2 * graph.n_places))
            y[:, free] = sol[:, 1:].T
            y = y.reshape(m, -1, 2)
    elif xi is not None:
        y = np.zeros((xi.shape[0], graph.n_places, 2))
    return x.reshape(-1, 2), y


def estimate_noise_reml(graph: MapGraph, xy0: np.ndarray, *, noise: CompassNoise = CompassNoise(),
                        rng: np.random.Generator, pinned: int = 0, samples: int = 16, max_rounds: int = 200,
                        tol_rel: float = 1e-4, params: CompassParams = CompassParams()
                        ) -> tuple[CompassNoise, np.ndarray, int]:
    """Noise parameters by restricted maximum likelihood (EM with exact posterior samples).

    Parameters
    ----------
    graph : MapGraph
    xy0 : ndarray, shape (N, 2)
        Initial coordinates (only the gauge places' values matter).
    noise : CompassNoise
        Starting point of the EM iteration.
    rng : numpy.random.Generator
        Draws the ``samples`` posterior fluctuations, reused in every round.
    samples : int
        Number of posterior samples for the E-step.
    max_rounds, tol_rel :
        EM stops when no parameter changes by more than ``tol_rel`` (relative) in a round.
    params : CompassParams
        Floors and the correlation bound.

    Returns
    -------
    noise : CompassNoise
    xy : ndarray, shape (N, 2)
        The exact minimum of Eq. 7 under ``noise``.
    rounds : int

    Notes
    -----
    Eqs. 12-14 applied to the residuals of the relaxed map estimate the noise jointly with the
    coordinates; that joint estimate is biased low and, when a map has fewer than ``2 (N - 1)``
    links, degenerate: the coordinates can absorb every across-track residual and drive ``S_aa`` to
    its floor. EM with the coordinates as hidden variables replaces the residual products of
    Eqs. 12-14 by their posterior expectations: ``S = (1/K) sum E[z z^T]`` with
    ``z = (p / sqrt(T), q / (sqrt(T) delta))``, the expectation being the product at the minimum plus
    the posterior covariance, estimated from exact samples of the Gaussian posterior. Its fixed point
    maximises the likelihood of the measurements with the coordinates integrated out (REML).
    """
    xy = _check(graph, xy0, pinned)
    circ = graph.circular
    n_fig3 = int(graph.n_links - np.count_nonzero(circ))
    if n_fig3 == 0 or graph.n_links - graph.n_places + graph.components()[0] <= 0:
        xy, _ = _exact_xy(graph, xy, noise, pinned)
        return noise, xy, 0
    xi = rng.standard_normal((samples, graph.n_links, 2))
    u, v = graph.u_scaled, graph.v_scaled

    def em(th: np.ndarray) -> np.ndarray:
        """One EM round on ``th = (S_dd, S_aa, S_da)``."""
        nz = CompassNoise(float(th[0]), float(th[1]), float(th[2]))
        x, y = _exact_xy(graph, xy, nz, pinned, xi)
        e = x[graph.dst] - x[graph.src] - graph.disp
        p = np.einsum("ij,ij->i", e, u)
        q = np.einsum("ij,ij->i", e, v)
        de = y[:, graph.dst] - y[:, graph.src]
        dp = np.einsum("sij,ij->si", de, u)
        dq = np.einsum("sij,ij->si", de, v)
        s_dd = max((p @ p + np.einsum("si,si->", dp, dp) / samples) / n_fig3, params.min_s_dd_m2)
        s_aa = max((q @ q + np.einsum("si,si->", dq, dq) / samples) / n_fig3, params.min_s_aa_rad2)
        lim = params.max_correlation * math.sqrt(s_dd * s_aa)
        s_da = min(max((p @ q + np.einsum("si,si->", dp, dq) / samples) / n_fig3, -lim), lim)
        return np.array([s_dd, s_aa, s_da])

    def valid(th: np.ndarray) -> bool:
        return bool(np.all(np.isfinite(th)) and th[0] > 0 and th[1] > 0
                    and abs(th[2]) < params.max_correlation * math.sqrt(th[0] * th[1]))

    # EM accelerated by squared extrapolation (SQUAREM, Varadhan and Roland 2008)
    th = np.array([noise.s_dd_m2, noise.s_aa_rad2, noise.s_da_m_rad])
    rounds = 0
    while rounds < max_rounds:
        scale = np.array([th[0], th[1], math.sqrt(th[0] * th[1])])
        th1 = em(th)
        th2 = em(th1)
        rounds += 2
        r = (th1 - th) / scale
        vv = (th2 - th1) / scale - r
        nv = float(np.linalg.norm(vv))
        alpha = -float(np.linalg.norm(r)) / nv if nv > 0 else -1.0
        alpha = min(alpha, -1.0)
        cand = th - scale * (2 * alpha * r - alpha * alpha * vv)
        new = th2
        if valid(cand):
            nxt = em(cand)
            rounds += 1
            if valid(nxt):
                new = nxt
        change = float(np.max(np.abs(new - th) / np.array([new[0], new[1], math.sqrt(new[0] * new[1])])))
        th = new
        if change <= tol_rel:
            break
    noise = CompassNoise(float(th[0]), float(th[1]), float(th[2]))
    xy, _ = _exact_xy(graph, xy, noise, pinned)
    return noise, xy, rounds


def _check(graph: MapGraph, xy: np.ndarray, pinned: int) -> np.ndarray:
    xy = np.array(xy, dtype=float, copy=True).reshape(-1, 2) if graph.n_places else np.zeros((0, 2))
    if xy.shape != (graph.n_places, 2):
        raise GraphError(f"coordinates have shape {xy.shape}, the graph has {graph.n_places} places")
    if not np.all(np.isfinite(xy)):
        raise GraphError("coordinates must be finite")
    if graph.n_places and not 0 <= pinned < graph.n_places:
        raise GraphError(f"pinned index {pinned} out of range")
    return xy


def solve_exact(graph: MapGraph, xy0: np.ndarray, *, noise: CompassNoise = CompassNoise(), pinned: int = 0,
                params: CompassParams = CompassParams()) -> CompassResult:
    """Minimise Eq. 7 exactly with one sparse factorisation (per noise estimate).

    Parameters
    ----------
    graph : MapGraph
    xy0 : ndarray, shape (N, 2)
        Initial coordinates: those of the pinned place (and of the first place of every other
        part of a disconnected graph) are kept.
    noise : CompassNoise
        Initial noise parameters.
    pinned : int
        Dense index of the place that fixes the gauge.
    params : CompassParams
        With ``estimate_noise``, solves alternate with Eqs. 12-14 until the noise settles.

    Notes
    -----
    Eq. 7 is quadratic: its minimum solves ``H x = g`` (see :func:`normal_equations`) with the gauge
    places removed.
    """
    xy = _check(graph, xy0, pinned)
    rounds = 0
    converged = True
    while True:
        xy = _exact_xy(graph, xy, noise, pinned)[0]
        rounds += 1
        if not params.estimate_noise:
            break
        new = estimate_noise(graph, xy, noise, params)
        change = _noise_change(noise, new)
        noise = new
        if change <= params.tol_noise_rel:
            xy = _exact_xy(graph, xy, noise, pinned)[0] if change > 0 else xy
            break
        if rounds >= params.max_exact_noise_rounds:
            converged = False
            break
    return CompassResult(xy=xy, ids=np.array(graph.ids), energy=energy(graph, xy, noise), iterations=rounds,
                         converged=converged, method="exact", noise=noise, exact_solves=rounds)


def _noise_change(a: CompassNoise, b: CompassNoise) -> float:
    scale = math.sqrt(b.s_dd_m2 * b.s_aa_rad2)
    return max(abs(a.s_dd_m2 - b.s_dd_m2) / b.s_dd_m2, abs(a.s_aa_rad2 - b.s_aa_rad2) / b.s_aa_rad2,
               abs(a.s_da_m_rad - b.s_da_m_rad) / scale)


def _shape_change(a: np.ndarray, b: np.ndarray, *, scale_matters: bool) -> float:
    """Largest difference of two information-coefficient vectors ``(a, b, c, 1)``, each divided by
    its ``a + c`` (relative difference of the last entry as well when ``scale_matters``)."""
    sa, sb = a[0] + a[2], b[0] + b[2]
    change = float(np.abs(a[:3] / sa - b[:3] / sb).max())
    return max(change, abs(sb / sa - 1.0)) if scale_matters else change


# ------------------------------------------------------------------------------- colour classes
class _ColourClass:
    """Places of one colour (no two linked) and the half-links that point at them.

    A half-link is one end of a link seen from its target place: ``(t, nb, k, sign)`` with ``t`` the
    target's position in this class, ``nb`` the neighbour's dense index, ``k`` the link slot and
    ``sign`` +1 when the target is the link's second place (``r_i = r_j + D``), -1 otherwise.
    """

    __slots__ = ("colour", "members", "n", "t", "nb", "k", "sign", "m", "version", "_built", "_numeric", "rows",
                 "cols", "mflat", "data", "const")

    def __init__(self, colour: int) -> None:
        self.colour = colour
        self._numeric = -1
        self.members = np.empty(16, dtype=np.int64)
        self.n = 0
        self.t = np.empty(16, dtype=np.int64)
        self.nb = np.empty(16, dtype=np.int64)
        self.k = np.empty(16, dtype=np.int64)
        self.sign = np.empty(16)
        self.m = 0
        self.version = 0
        self._built = -1
        self.rows = self.cols = self.mflat = self.data = self.const = None

    def push_hl(self, t: int, nb: int, k: int, sign: float) -> int:
        q = self.m
        if q >= self.t.shape[0]:
            self.t, self.nb, self.k, self.sign = (_grown(a, q + 1) for a in (self.t, self.nb, self.k, self.sign))
        self.t[q], self.nb[q], self.k[q], self.sign[q] = t, nb, k, sign
        self.m = q + 1
        self.version += 1
        return q

    def structure(self) -> None:
        """Index arrays of the class's 2x2-block sparse rows (rebuilt after structural changes)."""
        if self._built == self.version:
            return
        t, nb = self.t[: self.m], self.nb[: self.m]
        self.rows = (2 * t[:, None] + np.array([0, 0, 1, 1])).ravel()
        self.cols = (2 * nb[:, None] + np.array([0, 1, 0, 1])).ravel()
        self.mflat = (2 * self.members[: self.n, None] + np.array([0, 1])).ravel()
        self._built = self.version

    def compile(self, basis: np.ndarray, disp: np.ndarray, coef: np.ndarray) -> None:
        """Numeric arrays of the block update ``r = A^-1 (sum W r_nb + sum sign W D)`` for the class."""
        self.structure()
        self._numeric = self.version
        n, m = self.n, self.m
        t, k, sg = self.t[:m], self.k[:m], self.sign[:m]
        wk = basis[k] @ coef
        dk = disp[k]
        wd = np.stack([wk[:, 0] * dk[:, 0] + wk[:, 1] * dk[:, 1], wk[:, 1] * dk[:, 0] + wk[:, 2] * dk[:, 1]], axis=1)
        axx = np.bincount(t, wk[:, 0], n)
        axy = np.bincount(t, wk[:, 1], n)
        ayy = np.bincount(t, wk[:, 2], n)
        det = axx * ayy - axy * axy
        ia, ib, ic = ayy / det, -axy / det, axx / det
        wdk = wd * sg[:, None]
        hx = np.bincount(t, wdk[:, 0], n)
        hy = np.bincount(t, wdk[:, 1], n)
        self.const = np.stack([ia * hx + ib * hy, ib * hx + ic * hy], axis=1).ravel()
        at, bt, ct = ia[t], ib[t], ic[t]
        self.data = np.stack([at * wk[:, 0] + bt * wk[:, 1], at * wk[:, 1] + bt * wk[:, 2],
                              bt * wk[:, 0] + ct * wk[:, 1], bt * wk[:, 1] + ct * wk[:, 2]], axis=1).ravel()

    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.members, self.t, self.nb, self.k, self.sign)) + sum(
            a.nbytes for a in (self.rows, self.cols, self.mflat, self.data, self.const) if a is not None)


class CompassRelaxer:
    """On-line compass-mode relaxation: a map graph, its coordinates and noise, changed place by place.

    The graph, the initial coordinates and the parameters come in separately; afterwards every change
    goes through this object (:meth:`add_place`, :meth:`add_link`, :meth:`remove_link`,
    :meth:`remove_place`), which keeps the graph colouring and the per-colour sweep arrays up to date
    in O(degree) per change. :meth:`cycle` is one on-line cycle (Figure 3 steps 2-3, plus the auto
    strategy); :meth:`relax` runs cycles to convergence.

    Parameters
    ----------
    graph : MapGraph
        Taken over (not copied): change it only through this object from now on.
    xy : ndarray, shape (N, 2)
        Initial coordinates by dense index.
    noise : CompassNoise
        Initial noise parameters (Figure 3 step 1).
    pinned_id : int or None
        Id of the place that never moves (gauge); default the place at index 0.
    params : CompassParams

    Examples
    --------
    >>> g = MapGraph()
    >>> _ = g.add_places([0, 1, 2])
    >>> _ = g.add_link(0, 1, d_m=1.0, theta_rad=0.0, steps=10, mean_step_m=0.1)
    >>> _ = g.add_link(1, 2, d_m=1.0, theta_rad=np.pi / 2, steps=10, mean_step_m=0.1)
    >>> _ = g.add_link(0, 2, d_m=1.5, theta_rad=np.pi / 4, steps=15, mean_step_m=0.1)
    >>> r = CompassRelaxer(g, np.zeros((3, 2)), noise=CompassNoise(0.01, 0.01, 0.0),
    ...                    params=CompassParams(estimate_noise=False))
    >>> res = r.relax()
    >>> bool(res.converged), res.xy.round(3).tolist()
    (True, [[0.0, 0.0], [1.024, 0.0], [1.024, 1.024]])
    """

    def __init__(self, graph: MapGraph, xy: np.ndarray, *, noise: CompassNoise = CompassNoise(),
                 pinned_id: int | None = None, params: CompassParams = CompassParams()) -> None:
        self.graph = graph
        self.params = params
        n = graph.n_places
        xy = np.asarray(xy, dtype=float).reshape(-1, 2) if n else np.zeros((0, 2))
        if xy.shape != (n, 2) or not np.all(np.isfinite(xy)):
            raise GraphError(f"need finite coordinates of shape ({n}, 2), got {xy.shape}")
        self._xy = np.empty((max(2 * n, 16), 2))
        self._xy[:n] = xy
        self._pinned_id: int | None = None
        if pinned_id is not None:
            graph.index_of(pinned_id)
            self._pinned_id = int(pinned_id)
        elif n:
            self._pinned_id = int(graph.ids[0])
        self.noise = noise
        self._coef = information_coefficients(noise)
        self._sweep_coef = self._coef  # the coefficients the compiled sweep arrays were built with
        self._numeric_dirty = True
        self._n_circular = int(np.count_nonzero(graph.circular))
        self._parts_dirty = True
        self._parts = 0
        self._uf: np.ndarray = np.empty(0, dtype=np.int64)
        self._last_step = math.nan
        self.cycles = 0
        self.exact_solves = 0
        self._bulk_build()

    # ------------------------------------------------------------------------------ properties
    @property
    def xy(self) -> np.ndarray:
        """Current coordinates by dense place index (a copy)."""
        return self._xy[: self.graph.n_places].copy()

    @property
    def pinned_index(self) -> int:
        return -1 if self._pinned_id is None else self.graph.index_of(self._pinned_id)

    @property
    def n_colours(self) -> int:
        return len({c.colour for c in self._classes if c.n})

    def position(self, place_id: int) -> np.ndarray:
        return self._xy[self.graph.index_of(place_id)].copy()

    def set_xy(self, xy: np.ndarray) -> None:
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        if xy.shape != (self.graph.n_places, 2) or not np.all(np.isfinite(xy)):
            raise GraphError(f"need finite coordinates of shape ({self.graph.n_places}, 2)")
        self._xy[: self.graph.n_places] = xy

    def set_noise(self, noise: CompassNoise) -> None:
        self._adopt_noise(noise, tolerance=1e-12)  # a shape differing only by rounding keeps the sweep

    def _adopt_noise(self, noise: CompassNoise, *, tolerance: float) -> None:
        """Take ``noise`` for the energy and the estimates; rebuild the sweep only if its shape moved.

        Notes
        -----
        The block update of Eq. 9 is unchanged when every link information is multiplied by one
        constant, so the sweep depends on the noise only up to scale while no link has a circular
        variance of its own. The sweep arrays are rebuilt when that shape differs from the one they
        were built with by more than ``tolerance`` (any change, with circular links, past scale too).
        """
        self.noise = noise
        self._coef = information_coefficients(noise)
        if _shape_change(self._sweep_coef, self._coef, scale_matters=self._n_circular > 0) > tolerance:
            self._sweep_coef = self._coef
            self._numeric_dirty = True

    def nbytes(self) -> int:
        """Bytes of numpy arrays held (graph, coordinates, sweep arrays; capacity included)."""
        return self.graph.nbytes() + self._xy.nbytes + self._colour.nbytes + self._pos.nbytes + \
            self._hlpos.nbytes + self._uf.nbytes + sum(c.nbytes() for c in self._classes)

    # ---------------------------------------------------------------------------- construction
    def _bulk_build(self) -> None:
        g = self.graph
        n, k = g.n_places, g.n_links
        cap_n, cap_k = max(2 * n, 16), max(2 * k, 16)
        self._colour = np.full(cap_n, -1, dtype=np.int64)
        self._pos = np.full(cap_n, -1, dtype=np.int64)
        self._hlpos = np.full((cap_k, 2), -1, dtype=np.int64)
        self._classes: list[_ColourClass] = []
        src, dst = g.src, g.dst
        deg = np.bincount(src, minlength=n) + np.bincount(dst, minlength=n)
        active = deg > 0
        pin = self.pinned_index
        if pin >= 0:
            active[pin] = False
        colour = colour_places(n, src, dst, active)
        slot = self._colour[:n]
        self._open: dict[int, int] = {}  # colour -> index of its class that still has room
        chunk = max(1, self.params.class_chunk_places)
        for c in range(int(colour.max(initial=-1)) + 1):
            mem_all = np.flatnonzero(colour == c)
            for start in range(0, len(mem_all), chunk):
                mem = mem_all[start: start + chunk]
                cls = _ColourClass(c)
                cls.members = _grown(cls.members, len(mem))
                cls.members[: len(mem)] = mem
                cls.n = len(mem)
                self._pos[mem] = np.arange(len(mem))
                slot[mem] = len(self._classes)
                self._open[c] = len(self._classes)
                self._classes.append(cls)
        ncls = len(self._classes)
        # half-links: end 0 targets src (sign -1), end 1 targets dst (sign +1)
        for end, tgt, nbr, sign in ((0, src, dst, -1.0), (1, dst, src, 1.0)):
            ct = slot[tgt] if k else np.zeros(0, dtype=np.int64)
            for c in range(ncls):
                sel = np.flatnonzero(ct == c)
                cls = self._classes[c]
                q0 = cls.m
                m = len(sel)
                for name in ("t", "nb", "k", "sign"):
                    setattr(cls, name, _grown(getattr(cls, name), q0 + m))
                cls.t[q0: q0 + m] = self._pos[tgt[sel]]
                cls.nb[q0: q0 + m] = nbr[sel]
                cls.k[q0: q0 + m] = sel
                cls.sign[q0: q0 + m] = sign
                cls.m = q0 + m
                cls.version += 1
                self._hlpos[sel, end] = np.arange(q0, q0 + m)
        self._numeric_dirty = True

    def _colour_of(self, i: int) -> int:
        c = int(self._colour[i])
        return self._classes[c].colour if c >= 0 else -1

    def _free_colour(self, i: int) -> int:
        g = self.graph
        used = set()
        for s in g.link_slots_of(i):
            j = int(g._dst[s]) if g._src[s] == i else int(g._src[s])
            used.add(self._colour_of(j))
        c = 0
        while c in used:
            c += 1
        return c

    # ----------------------------------------------------------------------- class maintenance
    def _join(self, i: int, colour: int) -> None:
        """Put place ``i`` (with links) into a class of ``colour`` with all its half-links."""
        g = self.graph
        c = self._open.get(colour, -1)
        if c < 0 or self._classes[c].n >= self.params.class_chunk_places:
            c = len(self._classes)
            self._classes.append(_ColourClass(colour))
            self._open[colour] = c
        cls = self._classes[c]
        p = cls.n
        cls.members = _grown(cls.members, p + 1)
        cls.members[p] = i
        cls.n = p + 1
        self._colour[i] = c
        self._pos[i] = p
        for s in g.link_slots_of(i):
            end = 0 if g._src[s] == i else 1
            nb = int(g._dst[s]) if end == 0 else int(g._src[s])
            self._hlpos[s, end] = cls.push_hl(p, nb, s, 1.0 if end else -1.0)
        cls.version += 1

    def _drop_hl(self, cls: _ColourClass, q: int) -> None:
        last = cls.m - 1
        if q != last:
            cls.t[q], cls.nb[q], cls.k[q], cls.sign[q] = cls.t[last], cls.nb[last], cls.k[last], cls.sign[last]
            self._hlpos[cls.k[q], 1 if cls.sign[q] > 0 else 0] = q
        cls.m = last
        cls.version += 1

    def _leave(self, i: int) -> None:
        """Take place ``i`` and its half-links out of its colour class."""
        c = int(self._colour[i])
        if c < 0:
            return
        g = self.graph
        cls = self._classes[c]
        for s in g.link_slots_of(i):
            end = 0 if g._src[s] == i else 1
            q = int(self._hlpos[s, end])
            if q >= 0:
                self._drop_hl(cls, q)
                self._hlpos[s, end] = -1
        p = int(self._pos[i])
        last = cls.n - 1
        if p != last:
            moved = int(cls.members[last])
            cls.members[p] = moved
            self._pos[moved] = p
            for s in g.link_slots_of(moved):
                end = 0 if g._src[s] == moved else 1
                q = int(self._hlpos[s, end])
                if q >= 0:
                    cls.t[q] = p
        cls.n = last
        cls.version += 1
        self._colour[i] = -1
        self._pos[i] = -1

    def _ensure_capacity(self) -> None:
        g = self.graph
        n, k = g.n_places, g.n_links
        if n > self._xy.shape[0]:
            self._xy = _grown(self._xy, n)
        if n > self._colour.shape[0]:
            old = self._colour.shape[0]
            self._colour = _grown(self._colour, n)
            self._pos = _grown(self._pos, n)
            self._colour[old:] = -1
            self._pos[old:] = -1
        if k > self._hlpos.shape[0]:
            old = self._hlpos.shape[0]
            self._hlpos = _grown(self._hlpos, k)
            self._hlpos[old:] = -1

    # ------------------------------------------------------------------------ on-line changes
    def add_place(self, place_id: int, xy: tuple[float, float] | np.ndarray) -> int:
        """Add a place at ``xy`` (e.g. its dead-reckoning position); return its dense index."""
        xy = np.asarray(xy, dtype=float).reshape(2)
        if not np.all(np.isfinite(xy)):
            raise GraphError(f"place {place_id}: coordinates must be finite")
        i = self.graph.add_place(place_id)
        self._ensure_capacity()
        self._xy[i] = xy
        self._colour[i] = -1
        self._pos[i] = -1
        if self._pinned_id is None:
            self._pinned_id = int(place_id)
        if not self._parts_dirty:
            self._uf = _grown(self._uf, i + 1)
            self._uf[i] = i
            self._parts += 1
        return i

    def add_link(self, from_id: int, to_id: int, *, d_m: float, theta_rad: float, steps: int = 1,
                 mean_step_m: float = 1.0, variance_m2: float | None = None) -> int:
        """Add a traversed link (see :meth:`MapGraph.add_link`); return its slot."""
        g = self.graph
        s = g.add_link(from_id, to_id, d_m=d_m, theta_rad=theta_rad, steps=steps, mean_step_m=mean_step_m,
                       variance_m2=variance_m2)
        self._ensure_capacity()
        self._hlpos[s] = -1
        if variance_m2 is not None:
            self._n_circular += 1
            if self._n_circular == 1 and self._sweep_coef is not self._coef:  # scale matters from now on
                self._sweep_coef = self._coef
                self._numeric_dirty = True
        i, j = int(g._src[s]), int(g._dst[s])
        pin = self.pinned_index
        for end, tgt, nb in ((0, i, j), (1, j, i)):
            if tgt == pin:
                continue
            c = int(self._colour[tgt])
            if c < 0:
                self._join(tgt, self._free_colour(tgt))
            else:
                cls = self._classes[c]
                self._hlpos[s, end] = cls.push_hl(int(self._pos[tgt]), nb, s, 1.0 if end else -1.0)
        if self._colour_of(i) >= 0 and self._colour_of(i) == self._colour_of(j):
            move = i if g.degree(i) <= g.degree(j) else j
            self._leave(move)
            self._join(move, self._free_colour(move))
        if not self._parts_dirty:
            ri, rj = self._find(i), self._find(j)
            if ri != rj:
                self._uf[ri] = rj
                self._parts -= 1
        return s

    def remove_link(self, a_id: int, b_id: int) -> None:
        """Remove the link between two places (e.g. its confidence fell below the threshold)."""
        self._remove_link_slot(self.graph.link_slot(a_id, b_id))

    def _remove_link_slot(self, s: int) -> None:
        g = self.graph
        i, j = int(g._src[s]), int(g._dst[s])
        if np.isfinite(g._variance[s]):
            self._n_circular -= 1
        for end in (0, 1):
            q = int(self._hlpos[s, end])
            if q >= 0:
                tgt = i if end == 0 else j
                self._drop_hl(self._classes[int(self._colour[tgt])], q)
                self._hlpos[s, end] = -1
        _, last = g.remove_link_slot(s)
        if last != s:
            for end in (0, 1):
                q = int(self._hlpos[last, end])
                self._hlpos[s, end] = q
                if q >= 0:
                    tgt = int(g._src[s]) if end == 0 else int(g._dst[s])
                    cls = self._classes[int(self._colour[tgt])]
                    cls.k[q] = s
                    cls.version += 1
            self._hlpos[last] = -1
        for p in (i, j):
            if g.degree(p) == 0 and self._colour[p] >= 0:
                self._leave(p)
        self._parts_dirty = True

    def remove_place(self, place_id: int) -> None:
        """Remove a place and its links (e.g. no path reaches it any more)."""
        g = self.graph
        i = g.index_of(place_id)
        if self._pinned_id == int(place_id):
            raise GraphError(f"place {place_id} is pinned; pin another place first")
        while g.degree(i):
            self._remove_link_slot(g.link_slots_of(i)[0])
            i = g.index_of(place_id)
        self._leave(i)
        last = g.n_places - 1
        if i != last:
            # the last place moves into index i: fix references to it
            c = int(self._colour[last])
            if c >= 0:
                self._classes[c].members[int(self._pos[last])] = i
                self._classes[c].version += 1
            for s in g.link_slots_of(last):
                end_other = 1 if g._src[s] == last else 0  # the half-link whose neighbour is `last`
                other = int(g._dst[s]) if end_other == 1 else int(g._src[s])
                q = int(self._hlpos[s, end_other])
                if q >= 0:
                    cls = self._classes[int(self._colour[other])]
                    cls.nb[q] = i
                    cls.version += 1
            self._colour[i], self._pos[i] = self._colour[last], self._pos[last]
            self._xy[i] = self._xy[last]
        g.remove_place(place_id)
        self._colour[last] = -1
        self._pos[last] = -1
        self._parts_dirty = True

    def pin(self, place_id: int) -> None:
        """Make ``place_id`` the place that never moves."""
        new = self.graph.index_of(place_id)
        old = self.pinned_index
        self._pinned_id = int(place_id)
        if old >= 0 and old != new and self.graph.degree(old):
            self._join(old, self._free_colour(old))
        self._leave(new)

    # --------------------------------------------------------------------------------- parts
    def _find(self, i: int) -> int:
        uf = self._uf
        root = i
        while uf[root] != root:
            root = int(uf[root])
        while uf[i] != root:
            uf[i], i = root, int(uf[i])
        return root

    def n_parts(self) -> int:
        """Number of connected parts (union-find on additions; recomputed after removals)."""
        if self._parts_dirty:
            g = self.graph
            count, labels = g.components()
            self._uf = np.empty(max(2 * g.n_places, 16), dtype=np.int64)
            n = g.n_places
            roots = np.full(count, -1, dtype=np.int64)
            roots[labels[::-1]] = np.arange(n)[::-1]
            self._uf[:n] = roots[labels]
            self._parts = count
            self._parts_dirty = False
        return self._parts

    # ------------------------------------------------------------------------------ numerics
    def _compile(self) -> None:
        """Refresh the numeric arrays of the classes a change touched (all of them after a noise change)."""
        g = self.graph
        basis, disp = g._basis[: g.n_links], g._disp[: g.n_links]
        for cls in self._classes:
            if cls.n and (self._numeric_dirty or cls._numeric != cls.version):
                cls.compile(basis, disp, self._sweep_coef)
        self._numeric_dirty = False

    def sweep(self, *, track_step: bool = True) -> float:
        """One Gauss-Seidel sweep over all places (Figure 3 step 2); return the largest move (m).

        Notes
        -----
        Places of one colour share no link, so updating a whole colour class at once is exactly
        Gauss-Seidel: each place moves to the information-weighted mean of its neighbours' proposals,
        ``r_i = (sum_j C_ji^-1)^-1 sum_j C_ji^-1 (r_j + D_ji)`` (Eq. 9; Eq. 29 for circular links),
        seeing the newest coordinates of the other classes. Each block update minimises Eq. 7 over
        one place, so the energy never increases (Eqs. 15-16).
        """
        self._compile()
        xf = self._xy[: self.graph.n_places].reshape(-1)
        step = 0.0
        for cls in self._classes:
            if not cls.n:
                continue
            y = np.bincount(cls.rows, cls.data * xf[cls.cols], 2 * cls.n)
            y += cls.const
            if track_step:
                step = max(step, float(np.abs(y - xf[cls.mflat]).max()))
            xf[cls.mflat] = y
        return step

    def _sums(self) -> np.ndarray:
        return _residual_sums(self.graph, self._xy[: self.graph.n_places], circular=self._n_circular > 0)

    def energy(self) -> float:
        """Eq. 7 at the current coordinates and noise."""
        return _energy_from_sums(self._sums(), self._coef)

    def _reestimate(self, sums: np.ndarray) -> CompassNoise:
        g = self.graph
        rank = g.n_links - g.n_places + self.n_parts()
        return _noise_from_sums(sums, g.n_links - self._n_circular, rank, g.n_links, self.noise, self.params)

    def solve_exact(self) -> None:
        """Move every place to the exact minimum of Eq. 7 under the current noise."""
        g = self.graph
        if g.n_places:
            self._xy[: g.n_places] = _exact_xy(g, self._xy[: g.n_places], self.noise, self.pinned_index)[0]
        self.exact_solves += 1
        self._last_step = math.nan

    def exact_cost_in_sweeps(self) -> float:
        """Cost of one exact solve in units of one sweep, from the measured model in the parameters."""
        n = max(self.graph.n_places, 1)
        return self.params.exact_cost_sweeps * (n / 1000.0) ** self.params.exact_cost_growth

    def _wants_exact(self, step: float) -> bool:
        p = self.params
        prev = self._last_step
        self._last_step = step
        if not step > p.auto_min_step_m or not prev > p.auto_min_step_m:
            return False  # settled, or a new disturbance: watch how the next sweep shrinks it
        rho = step / prev
        if rho >= 1.0:
            return False  # still growing (changes keep coming): no prediction yet
        remaining = math.log(p.auto_target_step_m / step) / math.log(rho)
        return remaining > self.exact_cost_in_sweeps()

    def cycle(self, *, auto: bool = True) -> CycleReport:
        """One on-line cycle: a sweep, the energy, noise re-estimation and the auto strategy.

        Notes
        -----
        Figure 3 steps 2 and 3, run once per cycle of the mapping process (Section 3.2). With
        ``auto``, a map left far from equilibrium (a sweep step above ``auto_min_step_m`` whose
        decay predicts more remaining sweeps than an exact solve costs) is solved exactly.
        """
        step = self.sweep(track_step=True)
        exact = False
        if auto and self._wants_exact(step):
            self.solve_exact()
            exact = True
        sums = self._sums()
        e = _energy_from_sums(sums, self._coef)
        if self.params.estimate_noise:
            new = self._reestimate(sums)
            if _noise_change(self.noise, new) > self.params.noise_refresh_rel:
                self._adopt_noise(new, tolerance=self.params.noise_refresh_rel)
        self.cycles += 1
        return CycleReport(energy=e, step_m=step, exact=exact, noise=self.noise)

    def relax(self, *, method: str = "relax", max_sweeps: int | None = None) -> CompassResult:
        """Run Figure 3 to convergence (``relax``), the exact solve (``exact``) or cycles with the auto
        strategy (``auto``); return the result."""
        p = self.params
        g = self.graph
        if method == "exact":
            res = solve_exact(g, self.xy, noise=self.noise, pinned=max(self.pinned_index, 0), params=p)
            self._xy[: g.n_places] = res.xy
            self.set_noise(res.noise)
            return res
        if method not in ("relax", "auto"):
            raise ValueError(f"unknown method {method!r}")
        limit = p.max_sweeps if max_sweeps is None else max_sweeps
        e_prev = math.inf
        converged = False
        sweeps = 0
        exact0 = self.exact_solves
        self._last_step = math.nan
        while sweeps < limit:
            noise_before = self.noise
            rep = self.cycle(auto=method == "auto")
            sweeps += 1
            noise_settled = _noise_change(noise_before, self.noise) <= p.tol_noise_rel
            small = rep.step_m <= p.tol_step_m or (
                p.tol_energy_rel > 0 and (e_prev - rep.energy) <= p.tol_energy_rel * rep.energy)
            e_prev = rep.energy
            if small and noise_settled:
                converged = True
                break
        xy = self.xy
        return CompassResult(xy=xy, ids=np.array(g.ids), energy=_energy_from_sums(self._sums(), self._coef),
                             iterations=sweeps, converged=converged, method=method, noise=self.noise,
                             exact_solves=self.exact_solves - exact0)


def relax(graph: MapGraph, xy0: np.ndarray, *, noise: CompassNoise = CompassNoise(), pinned: int = 0,
          method: str = "relax", params: CompassParams = CompassParams()) -> CompassResult:
    """Optimise a compass-mode map (batch): Figure 3 sweeps, the exact solve, or the auto strategy.

    Parameters
    ----------
    graph : MapGraph
        Not modified.
    xy0 : ndarray, shape (N, 2)
        Initial coordinates.
    noise : CompassNoise
        Initial noise parameters.
    pinned : int
        Dense index of the place that never moves.
    method : {"relax", "exact", "auto"}
    params : CompassParams

    Notes
    -----
    ``relax`` repeats Figure 3 steps 2-3 (Eqs. 9-14) until a sweep lowers the energy (Eq. 7) by less
    than ``tol_energy_rel`` of it (or moves no place more than ``tol_step_m``) and the noise settles.
    """
    xy = _check(graph, xy0, pinned)
    if method == "exact":
        return solve_exact(graph, xy, noise=noise, pinned=pinned, params=params)
    g = graph.copy()
    pid = int(g.ids[pinned]) if g.n_places else None
    return CompassRelaxer(g, xy, noise=noise, pinned_id=pid, params=params).relax(method=method)
