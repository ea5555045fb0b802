"""Generated office-like compass maps with known noise, for tests and benchmarks."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.relaxer.compass import CompassNoise
from services.relaxer.graph import MapGraph

__all__ = ["OfficeMap", "office_map", "measure_link"]


@dataclass(frozen=True)
class OfficeMap:
    """A generated map in exploration order."""

    graph: MapGraph  # places in the order the robot confirmed them
    xy_true: np.ndarray  # (N, 2) true coordinates (m)
    xy_dead_reckoning: np.ndarray  # (N, 2) coordinates from chaining the exploration links (m)
    mean_step_m: float  # nominal delta_bar (each link's is its length over its step count)


def measure_link(rng: np.random.Generator, true_disp: np.ndarray, noise: CompassNoise, steps: np.ndarray,
                 mean_step_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Noisy ``(d, theta)`` of true displacements, with the link covariance of Eq. 5.

    The sum of ``T`` independent steps with distance and heading noise ``(S_dd, S_aa, S_da)`` errs by
    ``T [[S_dd, delta S_da], [delta S_da, delta^2 S_aa]]`` along and across the direction of travel.
    """
    true_disp = np.atleast_2d(true_disp)
    k = true_disp.shape[0]
    cov = np.array([[noise.s_dd_m2, noise.s_da_m_rad], [noise.s_da_m_rad, noise.s_aa_rad2]])
    z = rng.multivariate_normal(np.zeros(2), cov, size=k) * np.sqrt(steps)[:, None]
    along, across = z[:, 0], z[:, 1] * mean_step_m
    ang = np.arctan2(true_disp[:, 1], true_disp[:, 0])
    c, s = np.cos(ang), np.sin(ang)
    disp = true_disp + np.stack([c * along - s * across, s * along + c * across], axis=1)
    return np.hypot(disp[:, 0], disp[:, 1]), np.arctan2(disp[:, 1], disp[:, 0])


def office_map(n_places: int, *, rng: np.random.Generator, noise: CompassNoise = CompassNoise(4e-4, 9e-4, 1e-4),
               spacing_m: float = 1.0, row_spacing_m: float = 1.6, mean_step_m: float = 0.1, loop_probability: float = 0.37, diagonal_probability: float = 0.0,
               jitter_m: float = 0.25, width: int | None = None) -> OfficeMap:
    """An office-like lattice explored row by row, with loop-closing links to earlier neighbours.

    Places sit on a ``width``-wide lattice (``spacing_m`` along a row, ``row_spacing_m`` between rows),
    confirmed in a
    boustrophedon order (each place linked to the previous one); every other lattice neighbour pair
    gets a loop-closing link with ``loop_probability`` (0.37 gives the paper's 188 links per 137
    places); ``diagonal_probability`` adds links to the diagonal neighbours in the row before.
    Places are moved off the lattice by up to ``jitter_m`` so that links have varied
    directions and lengths; each link is measured with ``steps = round(length / mean_step)`` steps.
    """
    if n_places < 1:
        raise ValueError("need at least one place")
    w = width or max(2, int(round(np.sqrt(n_places))))
    idx = np.arange(n_places)
    row, col = idx // w, idx % w
    col = np.where(row % 2 == 0, col, w - 1 - col)
    xy_true = np.stack([col * spacing_m, row * row_spacing_m], axis=1).astype(float)
    xy_true += rng.uniform(-jitter_m, jitter_m, size=xy_true.shape)
    xy_true -= xy_true[0]
    lattice = {(int(r), int(c)): int(i) for i, (r, c) in enumerate(zip(row, col))}
    src = list(range(n_places - 1))
    dst = list(range(1, n_places))
    for i in range(n_places):
        r, c = int(row[i]), int(col[i])
        for rr, cc, prob in ((r - 1, c, loop_probability), (r - 1, c - 1, diagonal_probability),
                             (r - 1, c + 1, diagonal_probability)):
            j = lattice.get((rr, cc))
            if j is not None and j < i - 1 and prob > 0 and rng.random() < prob:
                src.append(j)
                dst.append(i)
    src_a, dst_a = np.array(src), np.array(dst)
    k = len(src)
    true_disp = xy_true[dst_a] - xy_true[src_a]
    steps = np.maximum(1.0, np.round(np.hypot(true_disp[:, 0], true_disp[:, 1]) / mean_step_m))
    ms = np.hypot(true_disp[:, 0], true_disp[:, 1]) / steps
    d, th = measure_link(rng, true_disp, noise, steps, ms)
    g = MapGraph(capacity=n_places)
    g.add_places(range(n_places))
    g.add_links(src_a, dst_a, d_m=d, theta_rad=th, steps=steps, mean_step_m=ms, variance_m2=np.full(k, np.nan))
    step = np.stack([d[: n_places - 1] * np.cos(th[: n_places - 1]), d[: n_places - 1] * np.sin(th[: n_places - 1])], 1)
    xy_dr = np.concatenate([xy_true[:1], xy_true[0] + np.cumsum(step, axis=0)])
    return OfficeMap(graph=g, xy_true=xy_true, xy_dead_reckoning=xy_dr, mean_step_m=mean_step_m)
