"""Planar geometry shared by the simulator and the services: angles, SE(2), distances, ray casting."""

from __future__ import annotations

import math

import numpy as np

TWO_PI = 2.0 * math.pi
_PARALLEL_EPS = 1e-12  # |d x e| below this: ray and wall are parallel (no single crossing)


def wrap_angle(a):
    """Wrap an angle (scalar or array) into (-pi, pi].

    Examples
    --------
    >>> round(wrap_angle(3 * math.pi / 2), 6)
    -1.570796
    >>> float(wrap_angle(math.pi)) == math.pi
    True
    """
    if isinstance(a, np.ndarray):
        w = np.remainder(a + math.pi, TWO_PI) - math.pi
        return np.where(w <= -math.pi, w + TWO_PI, w)
    w = math.remainder(a, TWO_PI)  # in [-pi, pi]
    return math.pi if w <= -math.pi else w


def circular_mean(a: float, b: float) -> float:
    """Mean of two angles along the shorter arc between them, wrapped into (-pi, pi]."""
    return wrap_angle(a + 0.5 * wrap_angle(b - a))


def se2_compose(a: tuple[float, float, float], b: tuple[float, float, float]) -> tuple[float, float, float]:
    """``a ⊕ b``: pose ``b`` expressed in the frame of ``a``, moved into the frame ``a`` lives in."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], wrap_angle(a[2] + b[2]))


def se2_inverse(a: tuple[float, float, float]) -> tuple[float, float, float]:
    """The pose ``a^-1`` with ``a ⊕ a^-1 = identity``."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (-c * a[0] - s * a[1], s * a[0] - c * a[1], wrap_angle(-a[2]))


def point_segment_distance(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Euclidean distance of every point to every segment.

    Parameters
    ----------
    points : (P, 2) array
    segments : (N, 4) array of ``x1, y1, x2, y2``

    Returns
    -------
    (P, N) array of distances.
    """
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    s = np.asarray(segments, dtype=float).reshape(-1, 4)
    ax, ay = s[:, 0], s[:, 1]
    ex, ey = s[:, 2] - ax, s[:, 3] - ay
    len2 = ex * ex + ey * ey
    wx = p[:, 0:1] - ax
    wy = p[:, 1:2] - ay
    # a degenerate segment (a point) has ex = ey = 0, hence t = 0: the distance to that point
    t = np.clip((wx * ex + wy * ey) / np.where(len2 > 0.0, len2, 1.0), 0.0, 1.0)
    return np.hypot(wx - t * ex, wy - t * ey)


def segments_cross(seg: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Whether segment ``seg`` (4,) touches or crosses each of ``segments`` (N, 4); (N,) bool."""
    seg = np.asarray(seg, dtype=float)
    s = np.asarray(segments, dtype=float).reshape(-1, 4)
    p = seg[:2]
    d = seg[2:] - p
    q = s[:, :2]
    e = s[:, 2:] - q
    w = q - p
    denom = d[0] * e[:, 1] - d[1] * e[:, 0]
    t_num = w[:, 0] * e[:, 1] - w[:, 1] * e[:, 0]
    u_num = w[:, 0] * d[1] - w[:, 1] * d[0]
    nz = np.abs(denom) > _PARALLEL_EPS
    safe = np.where(nz, denom, 1.0)
    t = t_num / safe
    u = u_num / safe
    return nz & (t >= 0.0) & (t <= 1.0) & (u >= 0.0) & (u <= 1.0)


def segment_segment_distance(seg: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Shortest distance between segment ``seg`` (4,) and each of ``segments`` (N, 4); (N,) array.

    Zero where they cross; otherwise the smallest of the four endpoint-to-segment distances.
    """
    seg = np.asarray(seg, dtype=float)
    s = np.asarray(segments, dtype=float).reshape(-1, 4)
    if s.shape[0] == 0:
        return np.zeros(0)
    ends = seg.reshape(2, 2)
    d_ends = point_segment_distance(ends, s).min(axis=0)  # seg's endpoints to every segment
    d_back = np.minimum(point_segment_distance(s[:, :2], seg[None, :])[:, 0],
                        point_segment_distance(s[:, 2:], seg[None, :])[:, 0])
    dist = np.minimum(d_ends, d_back)
    return np.where(segments_cross(seg, s), 0.0, dist)


def ray_cast(origins: np.ndarray, angles: np.ndarray, walls: np.ndarray,
             max_range_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cast rays against wall segments, all rays against all walls at once.

    Parameters
    ----------
    origins : (2,) or (R, 2) array
        Start of each ray (one origin shared by every ray, or one per ray).
    angles : (R,) array
        Direction of each ray, radians, world frame.
    walls : (N, 4) array of ``x1, y1, x2, y2``
    max_range_m : float
        Rays that hit nothing nearer report this range.

    Returns
    -------
    ranges : (R,) array
        Distance to the nearest wall along each ray, ``max_range_m`` where none is nearer.
    wall : (R,) int array
        Index of the wall hit, -1 for none.
    cos_incidence : (R,) array
        Cosine of the angle between the ray and the wall's normal (1: head on, 0: grazing);
        0 where nothing was hit.

    Notes
    -----
    A ray ``o + t d`` (``|d| = 1``) meets a wall ``p + u e`` where ``t = (w x e) / (d x e)`` and
    ``u = (w x d) / (d x e)`` with ``w = p - o``; a hit needs ``t >= 0`` and ``0 <= u <= 1``.
    ``|d x e| / |e|`` is the cosine of the incidence angle.
    """
    ang = np.asarray(angles, dtype=float).reshape(-1)
    o = np.asarray(origins, dtype=float)
    o = np.broadcast_to(o.reshape(-1, 2), (ang.shape[0], 2))
    w = np.asarray(walls, dtype=float).reshape(-1, 4)
    r = ang.shape[0]
    if w.shape[0] == 0 or r == 0:
        return np.full(r, float(max_range_m)), np.full(r, -1, dtype=np.int64), np.zeros(r)
    dx = np.cos(ang)[:, None]
    dy = np.sin(ang)[:, None]
    ex = (w[:, 2] - w[:, 0])[None, :]
    ey = (w[:, 3] - w[:, 1])[None, :]
    wx = w[None, :, 0] - o[:, 0:1]
    wy = w[None, :, 1] - o[:, 1:2]
    denom = dx * ey - dy * ex  # (R, N)
    nz = np.abs(denom) > _PARALLEL_EPS
    safe = np.where(nz, denom, 1.0)
    t = (wx * ey - wy * ex) / safe
    u = (wx * dy - wy * dx) / safe
    hit = nz & (t >= 0.0) & (u >= 0.0) & (u <= 1.0) & (t < max_range_m)
    t = np.where(hit, t, np.inf)
    idx = np.argmin(t, axis=1)
    rows = np.arange(r)
    best = t[rows, idx]
    found = np.isfinite(best)
    ranges = np.where(found, best, float(max_range_m))
    wall = np.where(found, idx, -1)
    length = np.hypot(ex[0, idx], ey[0, idx])
    cos_inc = np.where(found, np.abs(denom[rows, idx]) / np.where(length > 0, length, 1.0), 0.0)
    return ranges, wall, cos_inc
