"""Measures of an in-process run against ground truth: recognition, offsets, link errors, map errors,
coverage (pure)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.launch.inprocess import RunRecord
from sim.world import World

CHI2_2DOF_95 = 5.991  # 95% quantile of the chi-square distribution with 2 degrees of freedom


@dataclass(frozen=True)
class MetricParams:
    """What counts as a revisit, a misrecognition and covered space."""

    revisit_radius_m: float = 0.3  # a revisit of a place starts when the robot truly comes this close to it
    leave_radius_m: float = 1.0  # ... after having been further than this since it was last there
    wrong_place_m: float = 1.0  # a localization at a place truly further than this is a misrecognition
    coverage_radius_m: float = 1.0  # free space this close to the true trajectory counts as visited
    coverage_cell_m: float = 0.15  # cell size of the ground-truth grid
    min_gap_m2: float = 2.0  # unvisited free regions at least this large are listed


def recognition(rec: RunRecord, params: MetricParams = MetricParams()) -> dict:
    """Revisits recognised as the right place, misrecognitions, and offset errors.

    A revisit of place ``j`` starts when the true robot position comes within ``revisit_radius_m`` of
    ``j``'s true centre (the true position at its confirmation) after having been further than
    ``leave_radius_m`` since the confirmation or the previous revisit; it lasts until the robot is
    further than ``leave_radius_m`` again. It is recognised when a scan of that window localises the
    robot at ``j``. Offset error: for every scan localised at a place, the distance between the
    filtered offset and the true offset (true position minus the place's true centre).
    """
    places = rec.places
    if not places or not rec.scans:
        return {"revisits": 0, "recognised": 0, "recognition_rate": float("nan"), "misrecognised_scans": 0,
                "localised_scans": 0, "offset_error_median_m": float("nan"),
                "offset_error_p90_m": float("nan"), "revisit_offset_error_median_m": float("nan")}
    ids = np.array(sorted(places))
    centres = np.array([places[i].true_xy for i in ids])
    born = np.array([places[i].tick for i in ids])
    index = {int(pid): k for k, pid in enumerate(ids)}
    true_xy = np.array([s.true_xy for s in rec.scans])
    ticks = np.array([s.tick for s in rec.scans])
    said = np.array([s.place_id for s in rec.scans])
    dist = np.hypot(true_xy[:, None, 0] - centres[None, :, 0], true_xy[:, None, 1] - centres[None, :, 1])

    revisits = recognised = 0
    in_revisit = np.zeros(len(rec.scans), dtype=bool)
    for k, pid in enumerate(ids):
        away, window = False, None  # window: None outside a revisit, else whether it was recognised
        for s in np.flatnonzero(ticks > born[k]):
            d = dist[s, k]
            if window is not None:
                if d > params.leave_radius_m:
                    revisits += 1
                    recognised += window
                    window, away = None, True
                    continue
                window = window or bool(said[s] == pid)
                in_revisit[s] = True
            elif d > params.leave_radius_m:
                away = True
            elif away and d <= params.revisit_radius_m:
                window = bool(said[s] == pid)
                in_revisit[s] = True
        if window is not None:
            revisits += 1
            recognised += window

    localised = np.flatnonzero([p in index for p in said])
    wrong = 0
    errors = []
    for s in localised:
        k = index[int(said[s])]
        if dist[s, k] > params.wrong_place_m:
            wrong += 1
            continue
        true_off = true_xy[s] - centres[k]
        errors.append((float(np.hypot(*(np.asarray(rec.scans[s].offset_xy) - true_off))), in_revisit[s]))
    err = np.array([e for e, _ in errors]) if errors else np.zeros(0)
    err_rev = np.array([e for e, r in errors if r]) if errors else np.zeros(0)
    return {
        "revisits": revisits,
        "recognised": recognised,
        "recognition_rate": recognised / revisits if revisits else float("nan"),
        "localised_scans": int(localised.size),
        "misrecognised_scans": wrong,
        "offset_error_median_m": float(np.median(err)) if err.size else float("nan"),
        "offset_error_p90_m": float(np.percentile(err, 90)) if err.size else float("nan"),
        "revisit_offset_error_median_m": float(np.median(err_rev)) if err_rev.size else float("nan"),
    }


def link_errors(rec: RunRecord, noise: tuple[float, float, float] | None = None) -> dict:
    """Errors of the measured links against the true displacements, under the covariance of Eq. 5.

    For each link (its latest, fused measurement) ``e = D - (c_to - c_from)`` with ``c`` the true
    centres, split into ``p`` along the measured direction and ``q`` across it. The noise parameters
    are the maximum-likelihood estimates of Eqs. 12-14 from these true errors (or ``noise`` when
    given); each link's normalised squared error ``NEES = e^T C^-1 e`` (Eq. 5 covariance) follows a
    chi-square distribution with 2 degrees of freedom when the model holds. Reported: the error
    sizes, the estimates, the NEES mean, the fraction within the 95% chi-square bound, and the NEES
    mean of the longer half of the links over that of the shorter half (near 1 when errors grow with
    the step count as Eq. 5 says; far from 1 when they do not).
    """
    links = list(rec.latest_links().values())
    if not links:
        return {"links": 0}
    c = {pid: np.asarray(p.true_xy) for pid, p in rec.places.items()}
    th = np.array([lk.theta_rad for lk in links])
    u = np.stack([np.cos(th), np.sin(th)], axis=1)
    v = np.stack([-np.sin(th), np.cos(th)], axis=1)
    meas = np.array([lk.d_m for lk in links])[:, None] * u
    true = np.array([c[lk.to_id] - c[lk.from_id] for lk in links])
    e = meas - true
    p = (e * u).sum(axis=1)
    q = (e * v).sum(axis=1)
    t = np.array([lk.steps for lk in links], dtype=float)
    delta = np.array([lk.mean_step_m for lk in links])
    if noise is None:
        s_dd = float(np.mean(p**2 / t))
        s_aa = float(np.mean(q**2 / (t * delta**2)))
        s_da = float(np.mean(p * q / (t * delta)))
    else:
        s_dd, s_aa, s_da = noise
    a = t * s_dd
    b = t * delta * s_da
    d = t * delta**2 * s_aa
    det = a * d - b * b
    nees = (d * p * p - 2 * b * p * q + a * q * q) / det
    order = np.argsort(t, kind="stable")
    half = len(links) // 2
    short, long_ = order[:half], order[half:]
    ratio = float(nees[long_].mean() / nees[short].mean()) if half else float("nan")
    err = np.hypot(p, q)
    return {
        "links": len(links),
        "fused_links": int(sum(lk.traversals > 1 for lk in links)),
        "link_error_median_m": float(np.median(err)),
        "link_error_rms_m": float(np.sqrt(np.mean(err**2))),
        "link_d_error_rms_m": float(np.sqrt(np.mean((np.hypot(*meas.T) - np.hypot(*true.T)) ** 2))),
        "link_theta_error_rms_rad": float(np.sqrt(np.mean(
            (np.angle(np.exp(1j * (th - np.arctan2(true[:, 1], true[:, 0]))))) ** 2))),
        "s_dd_m2": s_dd, "s_aa_rad2": s_aa, "s_da_m_rad": s_da,
        "nees_mean": float(nees.mean()),
        "nees_within_95": float(np.mean(nees <= CHI2_2DOF_95)),
        "nees_long_over_short": ratio,
    }


def _aligned_rms(est: np.ndarray, true: np.ndarray) -> float:
    """RMS distance between ``est`` and ``true`` (``(N, 2)``) after the best rigid 2-D alignment."""
    me, mt = est.mean(axis=0), true.mean(axis=0)
    u, _, vt = np.linalg.svd((est - me).T @ (true - mt))
    rot = (u @ vt).T
    if np.linalg.det(rot) < 0:
        vt[-1] *= -1
        rot = (u @ vt).T
    res = (est - me) @ rot.T - (true - mt)
    return float(np.sqrt((res**2).sum(axis=1).mean()))


def map_errors(rec: RunRecord) -> dict:
    """Error of the place coordinates against the places' true centres after the best rigid
    alignment (RMS): the explorer's coordinates at confirmation (dead reckoning corrected by the
    recognitions) and, when the relaxer ran, the final relaxed coordinates."""
    ids = sorted(rec.places)
    if len(ids) < 3:
        return {}
    true = np.array([rec.places[i].true_xy for i in ids])
    out = {"map_error_explorer_rms_m": _aligned_rms(np.array([rec.places[i].map_xy for i in ids]), true)}
    relaxed = [i for i in ids if i in rec.relaxed]
    if len(relaxed) >= 3:
        out["map_error_relaxed_rms_m"] = _aligned_rms(np.array([rec.relaxed[i] for i in relaxed]),
                                                      np.array([rec.places[i].true_xy for i in relaxed]))
    return out


def coverage(rec: RunRecord, world: World, params: MetricParams = MetricParams()) -> dict:
    """Fraction of the reachable free space of the ground truth within ``coverage_radius_m`` of the
    true trajectory, and the unvisited free regions of at least ``min_gap_m2``."""
    from scipy import ndimage

    g = world.truth_grid(params.coverage_cell_m)
    traj = np.asarray(rec.trajectory, dtype=float)
    res = g.resolution_m
    visited = np.zeros_like(g.reachable)
    rows = np.clip(((traj[:, 1] - g.origin_y_m) / res).astype(int), 0, visited.shape[0] - 1)
    cols = np.clip(((traj[:, 0] - g.origin_x_m) / res).astype(int), 0, visited.shape[1] - 1)
    visited[rows, cols] = True
    near = ndimage.distance_transform_edt(~visited) * res <= params.coverage_radius_m
    covered = near & g.reachable
    gaps = g.reachable & ~near
    labels, n = ndimage.label(gaps)
    areas = np.bincount(labels.ravel())[1:] * res * res if n else np.zeros(0)
    big = sorted((float(a) for a in areas if a >= params.min_gap_m2), reverse=True)
    return {
        "reachable_m2": float(g.reachable.sum() * res * res),
        "coverage": float(covered.sum() / max(g.reachable.sum(), 1)),
        "unvisited_regions": len(big),
        "largest_unvisited_m2": big[0] if big else 0.0,
    }


def measure(rec: RunRecord, world: World, params: MetricParams = MetricParams()) -> dict:
    """Every measure of a run, flat, for reports and tests."""
    out: dict = {
        "world": rec.world, "seed": rec.seed, "sim_time_s": rec.sim_time_s, "wall_time_s": rec.wall_time_s,
        "complete": rec.complete, "predicted_left": rec.predicted_left, "places": len(rec.places),
        "deleted_confirmed": len(rec.deleted_confirmed), "scans": len(rec.scans), "collisions": rec.collisions,
        "relocalisations": rec.relocalisations,
    }
    out.update(recognition(rec, params))
    out.update(link_errors(rec))
    if rec.noise is not None:
        relaxer = link_errors(rec, rec.noise)
        out["nees_mean_relaxer_noise"] = relaxer.get("nees_mean", float("nan"))
        out["nees_within_95_relaxer_noise"] = relaxer.get("nees_within_95", float("nan"))
    out.update(map_errors(rec))
    out.update(coverage(rec, world, params))
    out.update({f"time_{k}_s": v for k, v in rec.timings_s.items()})
    return out
