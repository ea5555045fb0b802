"""The compass's local deviation at every place, learned on-line from the wheels' heading."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import msgspec
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from sim.geometry import wrap_angle

_DEG = math.pi / 180.0


@dataclass(frozen=True)
class DeviationParams:
    """Parameters of :class:`DeviationMap`."""

    enabled: bool = True  # learn the deviations and correct the links' angles with them (docs/places.md)
    prior_std_rad: float = 4.0 * _DEG  # a place's deviation before any visit: zero, with this spread
    prior_huber_rad: float = 2.0 * _DEG  # beyond this the prior grows linearly (Huber): a disturbance
    # is rare and large where it is, and a Gaussian prior shrinks it and spreads noise over the rest
    prior_iterations: int = 2  # reweighting steps per solve, each from the last estimate's weights
    compass_std_rad: float = 2.0 * _DEG  # white noise of one compass reading
    wheel_std_rad_per_sqrt_m: float = 1.0 * _DEG  # heading error the calibrated wheels add per sqrt(metre)
    wheel_std_rad_per_sqrt_rad: float = 0.03  # ... and per sqrt(radian) turned (measured in whole runs:
    # 0.7-1.1 degrees a sqrt(metre) and 0.02 a sqrt(radian), docs/places.md)
    min_gap_m: float = 0.2  # path counted between two visits at least (the wheels' error within a place)
    max_gap_m: float = 10.0  # two visits further apart along the path than this are not compared
    scale_prior_std: float = 0.05  # the wheels' rotation scale is 1 within about this before calibration
    drift_prior_std_rad_per_m: float = 2.0 * _DEG  # their heading drift is 0 within about this
    calibration_gate_rad: float = 0.15  # a scan-to-scan sample further than this from the calibration is
    # left out of it (a slip, a disturbance's edge), once it rests on 50 samples
    max_turn_rad: float = 1.5  # a scan-to-scan turn larger than this is left out (wrapping is ambiguous)
    gate_sd: float = 4.0  # a pair of visits further than this many standard deviations from the
    # estimate (its own spread plus twice the prior's) is left out
    republish_rad: float = 1.0 * _DEG  # a link is published again when its correction moved this much
    visit_baseline: bool = True  # a pair of visits compares the deviations where its scans were, not at
    # the places' centres: scale its difference by how far apart the visits' mean positions lie along
    # the centres' displacement (a visit's scans sit on the side it came from or leaves to)
    min_baseline: float = 0.3  # that factor is held at least this (a pair of visits nearly at one spot)


class DeviationState(msgspec.Struct, frozen=True):
    """Everything a :class:`DeviationMap` knows, for checkpoints."""

    normal: tuple[float, float, float, float, float]  # sums of the calibration's least squares
    samples: int
    last: tuple[float, float, float] | None  # compass heading, wheel heading, path of the last scan
    wheel_rad: float  # calibrated wheel heading, unwrapped
    turned_rad: float  # sum of the wheels' |turns|
    visit: tuple[int, float, float, int, float, float, float, float] | None  # place, ref, sum, count,
    # first and last path, first and last turned
    previous: tuple[int, float, int, float, float] | None  # the last closed visit: place, mean, count,
    # path and turned a third of its span before its end (where its mean's wheel error is counted from)
    rejected: int
    edges: list[tuple[int, int, float, float]]  # a < b, sum of weights, sum of weight x (d_b - d_a)
    estimate: dict[int, float]
    visit_position: tuple[float, float, float, float, float] | None = None  # the open visit's place
    # centre and its sum of the robot's offsets from it, and the scans with an offset
    previous_position: tuple[float, float, float, float] | None = None  # the last closed visit's centre
    # and mean offset
    last_reading: tuple[float, float, float] | None = None  # compass heading, wheel heading, path of the
    # last reading the wheel heading was integrated to (a scan's or one between scans)
    visit_anchor: tuple[float, float, float, float] | None = None  # the open visit's last scan:
    # dead-reckoned position and offset from the place, to place the readings around it


class DeviationMap:
    """Per-place compass deviation: where the compass reads ``d`` more than the true heading.

    Notes
    -----
    A disturbed compass bends every link measured through the disturbance the same way; fusing
    traversals does not average it out. The wheels do not see it. Between two consecutive visits of
    places ``a`` and ``b`` the difference ``g = compass - wheels`` (averaged over each visit's
    readings: its scans' and those of the dead-reckoned poses between them, some five a scan)
    changes by ``d_b - d_a`` plus the wheels' heading error over the path in between. The wheels are
    calibrated on-line against the compass over scan-to-scan increments, ``dc = a dw + b dL`` by
    least squares (the wheels' increments are the precise regressor, the compass's noise is in
    ``dc``; a deviation hardly changes over 0.2 m), with priors ``a = 1``, ``b = 0`` that hold it while
    the robot has not turned; the wheel heading is integrated as ``a dw + b dL``. A visit's scans lie on
    the side of its place the robot came from or left to, so a pair sees ``k (d_b - d_a)``, ``k`` the
    visits' mean positions projected on the centres' displacement over its length (``visit_baseline``;
    the deviation taken as linear between the centres). The deviations minimise
    the weighted squares of every pair of consecutive visits (variance ``compass_std^2 (1/n_a +
    1/n_b)`` plus the wheels' error over the path and the turns between the two means, each counted
    from a third of its visit's span, where a random walk's mean has its error) and a prior per place
    centred on 0 (most of a building is undisturbed): ``N(0, prior_std^2)`` within ``prior_huber_rad``,
    growing linearly beyond (Huber), so that the few disturbed places are not shrunk towards 0 nor
    the others spread by them. One sparse solve per reweighting step, ``prior_iterations`` steps per
    closed visit from the last estimate's weights.
    A pair further than ``gate_sd`` from the current estimate is left out (counted in ``rejected``).
    A link's angle is corrected by the mean of its two places' deviations, the mean along the path
    for a deviation that is smooth over a metre.
    """

    def __init__(self, params: DeviationParams | None = None) -> None:
        self.params = params or DeviationParams()
        self._normal = np.zeros(5)  # sums of dw^2, dw dL, dL^2, dw dc, dL dc
        self._samples = 0
        self._last: tuple[float, float, float] | None = None
        self._wheel = 0.0
        self._turned = 0.0
        self._visit: list | None = None  # [place, ref, sum, count, first path, last path, first/last turned]
        self._previous: tuple[int, float, int, float, float] | None = None
        self._position: list[float] | None = None  # the open visit: centre x, y, offset sums x, y, count
        self._anchor: tuple[float, float, float, float] | None = None  # the open visit's last scan with a
        # position: dead-reckoned x, y and offset x, y, from which the readings between scans are placed
        self._previous_position: tuple[float, float, float, float] | None = None  # centre, mean offset
        self._last_reading: tuple[float, float, float] | None = None  # the wheels integrated to here
        self.rejected = 0  # pairs of visits left out by the gate
        self._edges: dict[tuple[int, int], list[float]] = {}
        self.estimate: dict[int, float] = {}  # place id -> deviation (rad); absent: 0

    # --- inputs -------------------------------------------------------------------------------

    def observe(self, place_id: int, compass_rad: float, wheel_rad: float, path_m: float,
                centre_xy: tuple[float, float] | None = None, offset_xy: tuple[float, float] | None = None,
                xy: tuple[float, float] | None = None,
                readings: Sequence[tuple[float, float, float, float, float]] = ()) -> bool:
        """One scan: the place the robot is at (negative: between places), the compass and the raw
        wheel headings and the path travelled; where the place's centre is in the map and the robot's
        offset from it, when known, and the dead-reckoned position ``xy``. ``readings`` are the
        ``(compass, wheel, path, x, y)`` of every dead-reckoned pose since the last scan, oldest first:
        all belong to the visit when the place is the last scan's, else their first half to the last
        scan's visit and the rest to this one's. Returns whether the estimate changed."""
        cal = self.calibration()  # it changes only with a scan's increment, after the readings
        taken = [(self._integrate(c, w, s, cal), s, self._turned, x, y) for c, w, s, x, y in readings]
        self._calibrate(compass_rad, wheel_rad, path_m, cal)
        g = float(wrap_angle(compass_rad - self._wheel))
        v = self._visit
        if v is not None and v[0] == place_id:
            for r in taken:
                self._add_reading(*r)
            self._add_reading(g, path_m, self._turned)
            self._add_position(centre_xy, offset_xy, xy)
            return False
        half = len(taken) // 2
        if v is not None:
            for r in taken[:half]:
                self._add_reading(*r)
        changed = self._close_visit()
        if place_id >= 0:
            first = taken[half:] + [(g, path_m, self._turned)]
            self._visit = [place_id, first[0][0], 0.0, 0, first[0][1], first[0][1], first[0][2], first[0][2]]
            self._add_position(centre_xy, offset_xy, xy)
            for r in first:
                self._add_reading(*r)
        return changed

    def remove_place(self, place_id: int) -> None:
        """Forget a deleted place."""
        self._edges = {k: e for k, e in self._edges.items() if place_id not in k}
        self.estimate.pop(place_id, None)
        if self._visit is not None and self._visit[0] == place_id:
            self._visit, self._position, self._anchor = None, None, None
        if self._previous is not None and self._previous[0] == place_id:
            self._previous, self._previous_position = None, None

    def deviation(self, place_id: int) -> float:
        """The estimated deviation at a place, 0 where nothing is known."""
        return self.estimate.get(place_id, 0.0)

    def calibration(self) -> tuple[float, float]:
        """``(a, b)``: a wheel increment ``dw`` over a path ``dL`` turned the robot by ``a dw + b dL``."""
        p = self.params
        la = 2.0 * (p.compass_std_rad / p.scale_prior_std) ** 2  # a compass difference holds two readings
        lb = 2.0 * (p.compass_std_rad / p.drift_prior_std_rad_per_m) ** 2
        s = self._normal
        m00, m01, m11 = s[0] + la, s[1], s[2] + lb
        r0, r1 = s[3] + la, s[4]
        det = m00 * m11 - m01 * m01
        return float((r0 * m11 - r1 * m01) / det), float((r1 * m00 - r0 * m01) / det)

    @property
    def edges(self) -> int:
        """Pairs of places compared so far."""
        return len(self._edges)

    # --- checkpoints --------------------------------------------------------------------------

    def snapshot(self) -> DeviationState:
        v = self._visit
        return DeviationState(
            normal=tuple(float(x) for x in self._normal), samples=self._samples, last=self._last,
            wheel_rad=self._wheel, turned_rad=self._turned,
            visit=None if v is None else (int(v[0]), v[1], v[2], int(v[3]), v[4], v[5], v[6], v[7]),
            previous=self._previous, rejected=self.rejected,
            edges=[(a, b, e[0], e[1]) for (a, b), e in self._edges.items()], estimate=dict(self.estimate),
            visit_position=None if self._position is None else tuple(self._position),
            previous_position=self._previous_position, last_reading=self._last_reading, visit_anchor=self._anchor)

    def restore_snapshot(self, state: DeviationState) -> None:
        self._normal = np.array(state.normal, dtype=float)
        self._samples, self._wheel, self._turned = state.samples, state.wheel_rad, state.turned_rad
        self.rejected = state.rejected
        self._last = None if state.last is None else tuple(state.last)
        self._visit = None if state.visit is None else list(state.visit)
        self._previous = None if state.previous is None else tuple(state.previous)
        self._edges = {(a, b): [w, wm] for a, b, w, wm in state.edges}
        self.estimate = {int(k): float(v) for k, v in state.estimate.items()}
        self._position = None if state.visit_position is None else list(state.visit_position)
        self._anchor = None if state.visit_anchor is None else tuple(state.visit_anchor)
        self._previous_position = state.previous_position
        self._last_reading = self._last if state.last_reading is None else tuple(state.last_reading)

    # --- internals ----------------------------------------------------------------------------

    def _integrate(self, compass_rad: float, wheel_rad: float, path_m: float, cal: tuple[float, float]) -> float:
        """The wheel heading, calibrated by ``cal`` (:meth:`calibration`), carried to a reading; returns
        the reading's ``compass - wheels``."""
        last, self._last_reading = self._last_reading, (compass_rad, wheel_rad, path_m)
        if last is None:
            self._wheel = compass_rad  # the first reading aligns the wheels with the compass
        else:
            dw = float(wrap_angle(wheel_rad - last[1]))
            self._wheel += cal[0] * dw + cal[1] * (path_m - last[2])
            self._turned += abs(dw)
        return float(wrap_angle(compass_rad - self._wheel))

    def _calibrate(self, compass_rad: float, wheel_rad: float, path_m: float, cal: tuple[float, float]) -> None:
        """Integrate the wheels to a scan, then add its increment from the last scan to the calibration."""
        p = self.params
        last, self._last = self._last, (compass_rad, wheel_rad, path_m)
        a, b = cal
        self._integrate(compass_rad, wheel_rad, path_m, cal)
        if last is None:
            return
        dc = float(wrap_angle(compass_rad - last[0]))
        dw = float(wrap_angle(wheel_rad - last[1]))
        dl = path_m - last[2]
        if abs(dw) > p.max_turn_rad or abs(dc) > p.max_turn_rad:
            return
        if self._samples >= 50 and abs(dc - a * dw - b * dl) > p.calibration_gate_rad:
            return
        self._normal += (dw * dw, dw * dl, dl * dl, dw * dc, dl * dc)
        self._samples += 1

    def _add_reading(self, g: float, path_m: float, turned: float,
                     x: float | None = None, y: float | None = None) -> None:
        """One reading into the open visit; a reading between scans with its position (``x``, ``y``)."""
        v = self._visit
        v[2] += float(wrap_angle(g - v[1]))
        v[3] += 1
        v[5], v[7] = path_m, turned
        q, at = self._position, self._anchor
        if x is not None and at is not None:  # placed from the visit's last scan
            q[2] += at[2] + x - at[0]
            q[3] += at[3] + y - at[1]
            q[4] += 1.0

    def _add_position(self, centre_xy: tuple[float, float] | None, offset_xy: tuple[float, float] | None,
                      xy: tuple[float, float] | None) -> None:
        """A scan's offset into the open visit's positions (the visit's place centre from its first);
        with its dead-reckoned position it places the readings that follow (and, for a new visit, those
        just before)."""
        if centre_xy is None or offset_xy is None:
            return
        q = self._position
        if q is None:
            q = self._position = [float(centre_xy[0]), float(centre_xy[1]), 0.0, 0.0, 0.0]
        q[2] += float(offset_xy[0])
        q[3] += float(offset_xy[1])
        q[4] += 1.0
        self._anchor = None if xy is None else (float(xy[0]), float(xy[1]), float(offset_xy[0]), float(offset_xy[1]))

    def _baseline(self, prev: tuple[float, float, float, float] | None,
                  position: tuple[float, float, float, float] | None) -> float:
        """How much of the deviations' difference between two consecutive visits' places their scans
        saw: the visits' mean positions (centre, mean offset) projected on the centres' displacement,
        over its length (linear deviation between the centres); 1 without positions."""
        p = self.params
        if not p.visit_baseline or prev is None or position is None:
            return 1.0
        c = np.subtract(position[:2], prev[:2])
        length2 = float(c @ c)
        if length2 < 1e-6:
            return 1.0
        seen = np.add(position[:2], position[2:]) - np.add(prev[:2], prev[2:])
        return max(float(seen @ c) / length2, p.min_baseline)

    def _close_visit(self) -> bool:
        v, self._visit = self._visit, None
        if v is None:
            return False
        q, self._position, self._anchor = self._position, None, None
        position = None if q is None else (q[0], q[1], q[2] / q[4], q[3] / q[4])
        place, mean, count = v[0], float(wrap_angle(v[1] + v[2] / v[3])), v[3]
        # the wheels' error in a visit's mean is their error a third of its span from either end
        # (the mean of a random walk): counted from there, the path and turns between two means
        path3, turned3 = (v[5] - v[4]) / 3.0, (v[7] - v[6]) / 3.0
        prev, self._previous = self._previous, (place, mean, count, v[5] - path3, v[7] - turned3)
        prev_position, self._previous_position = self._previous_position, position
        p = self.params
        if prev is None or prev[0] == place or v[4] - prev[3] > p.max_gap_m:
            return False
        k = self._baseline(prev_position, position)
        gap = max(v[4] + path3 - prev[3], p.min_gap_m)
        var = (p.compass_std_rad**2 * (1.0 / prev[2] + 1.0 / count) + p.wheel_std_rad_per_sqrt_m**2 * gap
               + p.wheel_std_rad_per_sqrt_rad**2 * max(v[6] + turned3 - prev[4], 0.0))
        a, b, diff = prev[0], place, float(wrap_angle(mean - prev[1]))
        if a > b:
            a, b, diff = b, a, -diff
        # the pair measures k (d_b - d_a): a row of weight k^2 / var for the difference diff / k
        if abs(diff - k * (self.deviation(b) - self.deviation(a))) > p.gate_sd * math.sqrt(
                var + 2.0 * (k * p.prior_std_rad) ** 2):
            self.rejected += 1
            return False
        e = self._edges.setdefault((a, b), [0.0, 0.0])
        e[0] += k * k / var
        e[1] += k * diff / var
        self._solve()
        return True

    def _solve(self) -> None:
        """The deviations of every compared place: ``(P + L^T W L) d = L^T W m`` (sparse), the prior's
        weights ``P`` reweighted (Huber) from the previous estimate, ``prior_iterations`` times."""
        p = self.params
        ids = sorted({i for k in self._edges for i in k})
        if not ids:
            self.estimate = {}
            return
        row = {pid: n for n, pid in enumerate(ids)}
        pairs = np.array([(row[a], row[b]) for a, b in self._edges], dtype=int).reshape(-1, 2)
        e = np.array(list(self._edges.values()), dtype=float).reshape(-1, 2)
        w, wm = e[:, 0], e[:, 1]
        n = len(ids)
        links = np.zeros(n)
        np.add.at(links, pairs[:, 0], w)
        np.add.at(links, pairs[:, 1], w)
        off = sp.coo_matrix((np.concatenate([-w, -w]), (np.concatenate([pairs[:, 0], pairs[:, 1]]),
                                                         np.concatenate([pairs[:, 1], pairs[:, 0]]))), shape=(n, n))
        off = off.tocsc()
        rhs = np.zeros(n)
        np.add.at(rhs, pairs[:, 1], wm)
        np.add.at(rhs, pairs[:, 0], -wm)
        d = np.array([self.estimate.get(pid, 0.0) for pid in ids])
        for _ in range(max(p.prior_iterations, 1)):
            prior = np.minimum(1.0, p.prior_huber_rad / np.maximum(np.abs(d), 1e-12)) / p.prior_std_rad**2
            d = np.atleast_1d(spla.spsolve((sp.diags(prior + links, format="csc") + off), rhs))
        self.estimate = {pid: float(x) for pid, x in zip(ids, d, strict=True)}
