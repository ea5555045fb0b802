"""SE(2) maths on arrays of poses ``(..., 3) = (x, y, theta)``: wrap, compose, inverse, between, logmap."""

from __future__ import annotations

import numpy as np

__all__ = ["between", "compose", "inverse", "logmap", "wrap"]


def wrap(a: np.ndarray) -> np.ndarray:
    """Angles wrapped to ``[-pi, pi)`` (the sign at exactly pi does not matter to any caller)."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a * b``: pose ``b`` given in the frame of ``a``, expressed in the frame ``a`` is given in."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([a[..., 0] + c * b[..., 0] - s * b[..., 1],
                     a[..., 1] + s * b[..., 0] + c * b[..., 1],
                     wrap(a[..., 2] + b[..., 2])], axis=-1)


def inverse(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([-c * a[..., 0] - s * a[..., 1], s * a[..., 0] - c * a[..., 1], wrap(-a[..., 2])], axis=-1)


def between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a^-1 * b``: pose ``b`` in the frame of ``a``.

    >>> between(np.array([1.0, 0.0, np.pi / 2]), np.array([1.0, 1.0, np.pi])).round(12).tolist()
    [1.0, 0.0, 1.570796326795]
    """
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap(b[..., 2] - a[..., 2])], axis=-1)


def half_cot_terms(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``alpha = (w/2) cot(w/2)`` and its derivative, with series near zero."""
    w = np.asarray(w, dtype=float)
    small = np.abs(w) < 1e-4
    ws = np.where(small, 1.0, w)
    half = 0.5 * ws
    t = np.tan(half)
    alpha = np.where(small, 1.0 - w * w / 12.0, half / t)
    dalpha = np.where(small, -w / 6.0, 0.5 / t - 0.25 * ws / np.sin(half) ** 2)
    return alpha, dalpha


def logmap(p: np.ndarray) -> np.ndarray:
    """Tangent vector ``(v_x, v_y, w)`` of a pose, the translation taken through ``V(w)^-1``.

    Notes
    -----
    ``V^-1 = [[alpha, w/2], [-w/2, alpha]]`` with ``alpha = (w/2) cot(w/2)``: GTSAM's
    ``Pose2::Logmap``, whose tangent is ordered ``(x, y, theta)``.

    >>> logmap(np.array([1.0, 0.0, 0.0])).tolist()
    [1.0, 0.0, 0.0]
    """
    p = np.asarray(p, dtype=float)
    w = wrap(p[..., 2])
    alpha, _ = half_cot_terms(w)
    hw = 0.5 * w
    return np.stack([alpha * p[..., 0] + hw * p[..., 1], -hw * p[..., 0] + alpha * p[..., 1], w], axis=-1)
