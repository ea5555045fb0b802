"""How good a map is: error of place coordinates against ground truth (pure)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

Coordinates = Mapping[int, tuple[float, float]]


def _in_both(estimate: Coordinates, truth: Coordinates,
             first_id: int) -> tuple[list[int], np.ndarray, np.ndarray] | None:
    """The places of both maps (ids, estimated and true coordinates, rows in id order); None when there
    is none or ``first_id`` is missing from either map."""
    ids = sorted(set(estimate) & set(truth))
    if not ids or first_id not in estimate or first_id not in truth:
        return None
    return ids, np.array([estimate[i] for i in ids], dtype=float), np.array([truth[i] for i in ids], dtype=float)


def place_errors_m(estimate: Coordinates, truth: Coordinates, first_id: int) -> dict[int, float]:
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
    both = _in_both(estimate, truth, first_id)
    if both is None:
        return {}
    ids, est, tru = both
    shift = np.asarray(truth[first_id], dtype=float) - np.asarray(estimate[first_id], dtype=float)
    err = np.hypot(*(est + shift - tru).T)
    return {i: float(e) for i, e in zip(ids, err, strict=True)}


def ate_m(estimate: Coordinates, truth: Coordinates, first_id: int) -> float:
    """RMS of :func:`place_errors_m`: the error of the whole map; NaN when no place can be compared.

    Examples
    --------
    >>> ate_m({0: (1.0, 1.0), 1: (2.0, 1.0)}, {0: (0.0, 0.0), 1: (1.0, 1.0)}, 0)
    0.7071067811865476
    """
    err = np.array(list(place_errors_m(estimate, truth, first_id).values()))
    return float(np.sqrt(np.mean(err**2))) if err.size else float("nan")


@dataclass(frozen=True)
class Similarity:
    """The turn and the size of a whole map about its first place, and the error left without them."""

    scale: float  # the map's size over the truth's (above 1: the map is too large)
    turn_rad: float  # the map's rotation from the truth's frame, counter-clockwise
    residual_m: float  # RMS error of the places once the map is turned back and rescaled about the first place


def similarity_about(estimate: Coordinates, truth: Coordinates, first_id: int) -> Similarity | None:
    """The least-squares turn and scale of ``estimate`` against ``truth`` about place ``first_id``.

    With the first place at the origin of both maps and places as complex numbers ``e`` and ``t``,
    the factor ``a`` minimising ``sum |a e - t|^2`` is ``(e^H t) / (e^H e)``: the map is ``1/|a|``
    times the true size and turned by ``-arg a``. A map scaled by its odometry's distance error, or
    turned by a compass bias, shows it here; what is left in ``residual_m`` are the links' own errors.
    None when fewer than two places can be compared or they all sit on the first.

    Examples
    --------
    >>> s = similarity_about({0: (0.0, 0.0), 1: (0.0, 2.0)}, {0: (1.0, 1.0), 1: (2.0, 1.0)}, 0)
    >>> round(s.scale, 6), round(float(np.degrees(s.turn_rad)), 6), round(s.residual_m, 6)
    (2.0, 90.0, 0.0)
    """
    both = _in_both(estimate, truth, first_id)
    if both is None or len(both[0]) < 2:
        return None
    _, est, tru = both
    est = est - np.asarray(estimate[first_id], dtype=float)
    tru = tru - np.asarray(truth[first_id], dtype=float)
    ze, zt = est[:, 0] + 1j * est[:, 1], tru[:, 0] + 1j * tru[:, 1]
    norm = float(np.vdot(ze, ze).real)
    if norm == 0.0 or not np.any(zt):
        return None
    a = np.vdot(ze, zt) / norm
    return Similarity(scale=float(1.0 / abs(a)), turn_rad=float(-np.angle(a)),
                      residual_m=float(np.sqrt(np.mean(np.abs(a * ze - zt) ** 2))))
