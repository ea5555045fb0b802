"""How good a map is: error of place coordinates against ground truth (pure)."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np


def place_errors_m(estimate: Mapping[int, tuple[float, float]], truth: Mapping[int, tuple[float, float]],
                   first_id: int) -> dict[int, float]:
    """Position error of each place in both maps, after removing the translation of ``first_id``.

    Both maps are shifted so that place ``first_id`` is at its true position (its own error is then
    zero); no rotation is removed: with a compass, both frames share north.

    Returns
    -------
    dict
        Place id to error in metres; empty when no place is in both maps or ``first_id`` is in neither.

    Examples
    --------
    >>> place_errors_m({0: (1.0, 1.0), 1: (2.0, 1.0)}, {0: (0.0, 0.0), 1: (1.0, 1.0)}, 0)
    {0: 0.0, 1: 1.0}
    """
    ids = sorted(set(estimate) & set(truth))
    if not ids or first_id not in estimate or first_id not in truth:
        return {}
    est = np.array([estimate[i] for i in ids], dtype=float)
    tru = np.array([truth[i] for i in ids], dtype=float)
    shift = np.asarray(truth[first_id], dtype=float) - np.asarray(estimate[first_id], dtype=float)
    err = np.hypot(*(est + shift - tru).T)
    return {i: float(e) for i, e in zip(ids, err, strict=True)}


def ate_m(estimate: Mapping[int, tuple[float, float]], truth: Mapping[int, tuple[float, float]],
          first_id: int) -> float:
    """RMS of :func:`place_errors_m`: the error of the whole map; NaN when no place can be compared.

    Examples
    --------
    >>> ate_m({0: (1.0, 1.0), 1: (2.0, 1.0)}, {0: (0.0, 0.0), 1: (1.0, 1.0)}, 0)
    0.7071067811865476
    """
    err = np.array(list(place_errors_m(estimate, truth, first_id).values()))
    return float(np.sqrt(np.mean(err**2))) if err.size else float("nan")
