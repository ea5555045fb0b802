"""Occupancy histograms of a local grid (Figure 8) and their match over all shifts (Eqs. 19-21)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from services.place_recognizer.grid import EMPTY, OCCUPIED, UNKNOWN


@dataclass(frozen=True)
class Histograms:
    """The x and y histograms of a local grid.

    Attributes
    ----------
    x : numpy.ndarray
        Shape ``(3, n)``: rows OCCUPIED, EMPTY, UNKNOWN; column ``ix`` counts the cells of grid
        column ``ix`` (all ``iy``) with that label.
    y : numpy.ndarray
        Shape ``(3, n)``, likewise per grid row ``iy``.
    """

    x: np.ndarray
    y: np.ndarray


@dataclass(frozen=True)
class AxisMatch:
    """Result of matching one axis' histograms over all shifts.

    Attributes
    ----------
    scores : numpy.ndarray
        ``Match`` (Eq. 19) at each shift ``-max_shift..max_shift`` (last axis), in ``[0, 1]``.
    best_shift : numpy.ndarray
        Integer shift (cells) of the best score; ties go to the smallest ``|shift|``.
    best_score : numpy.ndarray
        ``M*``, the best score.
    mean_score : numpy.ndarray
        ``M-bar``, the mean score over all shifts.
    """

    scores: np.ndarray
    best_shift: np.ndarray
    best_score: np.ndarray
    mean_score: np.ndarray


def histograms(labels: np.ndarray) -> Histograms:
    """Reduce a labelled grid ``[ix, iy]`` to its x and y histograms (Figure 8)."""
    x = np.stack([(labels == c).sum(axis=1) for c in (OCCUPIED, EMPTY, UNKNOWN)]).astype(float)
    y = np.stack([(labels == c).sum(axis=0) for c in (OCCUPIED, EMPTY, UNKNOWN)]).astype(float)
    return Histograms(x=x, y=y)


def match_axis(observed: np.ndarray, stored: np.ndarray, max_shift: int,
               weights: tuple[float, float, float] | None = None) -> AxisMatch:
    """Match an observed histogram against stored ones over every shift (Eq. 19).

    Parameters
    ----------
    observed : numpy.ndarray
        Shape ``(3, n)``.
    stored : numpy.ndarray
        Shape ``(..., 3, n)``: one or many stored histograms (e.g. one per place).
    max_shift : int
        Shifts ``s`` in ``-max_shift..max_shift`` cells are tried.
    weights : tuple of float, optional
        Weights of the occupied, empty and unknown counts; ``None`` is Eq. 19's equal weights.

    Returns
    -------
    AxisMatch
        Arrays with the leading shape of ``stored``.

    Notes
    -----
    At shift ``s`` observed element ``j`` is compared with stored element ``j + s``:

        Match(s) = (1 / w(s)) sum_j [min(O^o_j, O^s_{j+s}) + min(E^o_j, E^s_{j+s}) + min(U^o_j, U^s_{j+s})]

    over the elements ``j`` where both exist, with ``w(s) = sum_j max(n^o_j, n^s_{j+s})`` (``n`` the
    cell count of an element), so ``0 <= Match <= 1`` and ``Match = 1`` exactly when the overlapping
    elements are identical. With ``weights`` each label's counts are scaled by its weight first (in
    the minima and in ``n``). If the observation grid is centred at the robot ``p`` and the stored one
    at the place centre ``c``, the best ``s`` is ``(p - c) / cell``: the robot's offset from the
    place centre in cells. All shifts and all stored histograms are evaluated at once through a
    sliding window over the stored histograms padded with ``max_shift`` missing elements each side.

    Examples
    --------
    >>> a = np.array([[0., 1., 0., 0.], [1., 0., 1., 1.], [0., 0., 0., 0.]])
    >>> m = match_axis(np.roll(a, -1, axis=1), a, 2)
    >>> int(m.best_shift), float(m.best_score)
    (1, 1.0)
    """
    observed = np.asarray(observed, dtype=float)
    stored = np.asarray(stored, dtype=float)
    if weights is not None:
        w = np.asarray(weights, dtype=float)[:, None]
        observed, stored = observed * w, stored * w
    n = observed.shape[-1]
    pad = [(0, 0)] * (stored.ndim - 1) + [(max_shift, max_shift)]
    padded = np.pad(stored, pad)  # missing elements are zero: they add nothing to the minima
    windows = sliding_window_view(padded, n, axis=-1)  # (..., 3, 2S+1, n): element j + s
    j_plus_s = np.arange(n)[None, :] + np.arange(-max_shift, max_shift + 1)[:, None]
    valid = (j_plus_s >= 0) & (j_plus_s < n)  # (2S+1, n): where stored element j + s exists
    num = np.minimum(observed[:, None, :], windows).sum(axis=(-3, -1))
    totals_obs = observed.sum(axis=0)  # (n,)
    totals_st = windows.sum(axis=-3)  # (..., 2S+1, n)
    den = np.where(valid, np.maximum(totals_obs, totals_st), 0.0).sum(axis=-1)
    scores = np.divide(num, den, out=np.zeros_like(num), where=den > 0)
    shifts = np.arange(-max_shift, max_shift + 1)
    # the best score, ties broken towards the smallest |shift|
    order = np.argsort(np.abs(shifts), kind="stable")
    best_in_order = np.argmax(scores[..., order], axis=-1)
    best_idx = order[best_in_order]
    best_score = np.take_along_axis(scores, best_idx[..., None], axis=-1)[..., 0]
    return AxisMatch(scores=scores, best_shift=shifts[best_idx], best_score=best_score,
                     mean_score=scores.mean(axis=-1))


def match_error_variance(best_score: np.ndarray, mean_score: np.ndarray, *, k_m2: float,
                         min_spread: float) -> np.ndarray:
    """Error heuristic of the match offset (Eqs. 20-21), m^2.

    ``sigma^2 = k / (M* - M-bar)^2``; the spread ``M* - M-bar`` is floored at ``min_spread`` so a
    flat match (nothing to lock onto) gives a large but finite variance.

    Examples
    --------
    >>> float(match_error_variance(np.array(0.9), np.array(0.4), k_m2=1.0, min_spread=1e-3))
    4.0
    """
    spread = np.maximum(np.asarray(best_score) - np.asarray(mean_score), min_spread)
    return k_m2 / spread**2
