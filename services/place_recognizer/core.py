"""Place recognizer core: local grids, histogram match, belief over places and link measurements."""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import msgspec
import numpy as np

from messages.types import DeadReckonedPose, SonarScan
from services.place_recognizer import belief as _belief
from services.place_recognizer.deviation import DeviationMap, DeviationParams, DeviationState
from services.place_recognizer.grid import PlacedScan, build_grid, classify, integrate_scan
from services.place_recognizer.histogram import Histograms, histograms, match_axis, match_error_variance
from sim.geometry import wrap_angle

NO_PLACE = -1  # place id of the "no known place" hypothesis and of "between places"


@dataclass(frozen=True)
class PlaceRecognizerParams:
    """Parameters of the place recognizer core (defaults in code; deploy files only override)."""

    cell_m: float = 0.15  # side of a local grid cell (Section 4.3)
    grid_half_width_m: float = 3.0  # a local grid spans +-this around its centre on each axis
    logodds_occupied: float = 0.9  # log-odds added to cells at an echo's range inside its cone
    logodds_empty: float = -0.4  # log-odds added to cells a beam passed through
    logodds_threshold: float = 0.2  # cells with |log-odds| below this count as unknown
    echo_thickness_m: float = 0.15  # radial thickness of the occupied arc of an echo
    max_shift_m: float = 1.5  # largest offset searched by the histogram match, per axis
    match_error_k_m2: float = 3e-3  # k of Eqs. 20-21 (the paper's 1 m^2 was for its own Match scale)
    min_match_spread: float = 0.02  # floor of M* - M-bar in Eqs. 20-21
    observation_window_m: float = 0.5  # scans over this much recent path build one observation grid
    observation_max_scans: int = 8  # at most this many scans in one observation grid
    signature_radius_m: float = 0.5  # scans within this of a new place's centre build its signature
    place_radius_m: float = 0.5  # the robot is at a place while its filtered offset is within this
    localized_probability: float = 0.5  # the best place must be at least this probable to count
    transition_std_m: float = 0.1  # width of the motion kernel on top of the position variance
    transition_var_per_m_m2: float = 0.02  # dead-reckoning position variance added per metre travelled
    uniform_transition: float = 1e-4  # fraction of belief mass spread per update near the robot (relocalisation)
    unknown_offset_var_m2: float = 0.25  # offset variance of mass arriving without a position
    relocalise_std_m: float = 1.5  # relocalisation mass goes to places within about this of the robot
    match_weights: tuple[float, float, float] = (1.0, 0.05, 0.05)  # weights of the occupied, empty and
    # unknown counts in Eq. 19 (equal in the paper): the many empty and unknown cells depend on where the
    # sonar looked from more than on the place, and would drown the walls
    match_axes: str = "min"  # a place's score from its x and y scores: "min" (both must fit) or "mean"
    match_sharpness: float = 12.0  # beta: likelihood exp(beta (M - 1)) of a match score M (fitted 25 to one
    # observation; a scan is in about three consecutive ones, docs/places.md, "A "none" of three tracks")
    repeat_scan_m: float = 0.15  # a scan taken within this of a scan counted in full ...
    repeat_scan_memory_s: float = 20.0  # ... in the last this many simulated seconds, whatever its heading
    # (a robot standing still, turning on the spot or rocking back and forth: its sonar ring sees the
    # same walls from the same spot) ...
    repeat_scan_weight: float = 0.2  # ... counts as this fraction of an observation (tempered likelihood):
    # taken as independent, 15 s of a stalled robot beside a look-alike moved the belief 7 m
    none_components: int = 3  # "no known place" is a mixture of at most this many Gaussians (1: one, the
    # moment match of all its mass, which moves the robot's own track with the look-alikes') ...
    none_gate_sd: float = 3.0  # ... each taking the mass that arrives within this many standard deviations
    new_place_match: float = 0.7  # virtual match score of the "no known place" hypothesis
    confirmed_probability: float = 0.95  # belief in a place at the moment it is confirmed
    settle_observations: int = 5  # observations at a revisited place before its link is measured (or on
    # leaving it): with 3, arrivals in open halls and empty rooms measured links with the offset still wrong
    link_fuse_gate_m: float = 1.0  # a later traversal further than this from the fused link is rejected
    max_hypotheses: int = 5  # hypotheses reported in the localization (most probable first)
    match_min_prior: float = 1e-12  # places less probable than this before the scan are not matched
    link_map_gate_m: float = 0.75  # a traversal further than this from the centres' displacement is rejected
    arrival_gate_m: float = 1.0  # an arrival further than this from where dead reckoning puts the robot
    arrival_gate_per_m: float = 0.05  # ... plus this per metre travelled since the last place is a jump
    relocalise_fraction: float = 0.5  # asked to relocalise (the explorer's legs keep failing), this fraction
    # of the belief's mass goes to the places near the robot ...
    relocalise_request_std_m: float = 2.0  # ... in proportion to a Gaussian of this width about its
    # expected position, and the arrival gate is off for ...
    relocalise_scans: int = 25  # ... this many scans, or until the belief settles at another place (relocalise)
    match_window_sd: float = 3.0  # a place is matched at shifts within this many standard deviations of
    # its predicted offset (0: at every shift)
    match_offset_max_sd_m: float = math.inf  # a match whose offset is less certain than this (sigma*,
    # Eqs. 20-21) leaves the offsets as predicted: along a plain corridor its best shift is where its scans'
    # coverage lines up with the signature's. Off by default: those pulls shorten the links about as much
    # as the wheels lengthen them (docs/places.md, "Links that repeat the map")
    deviation: DeviationParams = field(default_factory=DeviationParams)  # the compass's deviation per place

    def __post_init__(self) -> None:
        if self.match_axes not in ("min", "mean"):
            raise ValueError(f"match_axes must be 'min' or 'mean', not {self.match_axes!r}")
        if len(self.match_weights) != 3 or min(self.match_weights) < 0 or max(self.match_weights) <= 0:
            raise ValueError(f"match_weights must be three weights >= 0, not all 0: {self.match_weights!r}")
        if not 0.0 < self.repeat_scan_weight <= 1.0:
            raise ValueError(f"repeat_scan_weight must be in (0, 1], got {self.repeat_scan_weight!r}")
        if not self.match_offset_max_sd_m > 0.0:
            raise ValueError(f"match_offset_max_sd_m must be > 0 (inf: off), got {self.match_offset_max_sd_m!r}")


@dataclass(frozen=True)
class Localization:
    """The belief as published (fields of :class:`messages.types.LocalizationBelief`).

    ``place_id`` is the place the robot is at, or -1 between places; ``probability`` and the
    offset (robot minus centre, world frame) belong to the most probable place hypothesis even when
    ``place_id`` is -1. ``hypotheses`` lists ``(place_id, probability)`` most probable first, -1
    standing for "no known place".
    """

    place_id: int
    probability: float
    offset_x_m: float
    offset_y_m: float
    offset_var_m2: float
    hypotheses: tuple[tuple[int, float], ...]


@dataclass(frozen=True)
class LinkEstimate:
    """A link measurement (fields of :class:`messages.types.LinkMeasured`), fused over traversals."""

    from_id: int
    to_id: int
    d_m: float
    theta_rad: float
    steps: int
    mean_step_m: float
    traversals: int


@dataclass(frozen=True)
class RecognizerOutput:
    """What one call returns: the localization, links measured now, diagnostics."""

    localization: Localization
    links: tuple[LinkEstimate, ...] = ()
    diagnostics: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class _Mark:
    """Where the robot was (dead reckoning and step record) with its offset from a place."""

    place_id: int
    dr_xy: tuple[float, float]
    steps: int
    path_length_m: float
    offset_xy: tuple[float, float]


@dataclass
class _Pending:
    """A traversal that has arrived and waits for the arrival offset to settle."""

    departure: _Mark
    to_id: int
    arrival_dr_xy: tuple[float, float]
    arrival_steps: int
    arrival_path_m: float
    observations: int


@dataclass
class PlaceSignature:
    """A place's stored local grid (centred on the place, dead-reckoning frame) and its histograms."""

    logodds: np.ndarray
    hist: Histograms
    anchor_dr_xy: tuple[float, float]


@dataclass
class _SignatureStack:
    """Every signature's x and y histograms in one array each (row ``row[place_id]``): stacking them
    anew for every scan cost as much as matching them."""

    row: dict[int, int]
    x: np.ndarray  # (places, 3, n)
    y: np.ndarray

    @classmethod
    def of(cls, signatures: Mapping[int, PlaceSignature]) -> _SignatureStack:
        pids = list(signatures)
        return cls({pid: k for k, pid in enumerate(pids)}, np.stack([signatures[i].hist.x for i in pids]),
                   np.stack([signatures[i].hist.y for i in pids]))


@dataclass
class LinkAccumulator:
    """The traversals of one link fused by the rule of :class:`PlaceRecognizer` (weights ``1 / T``).

    Kept in the direction of the first traversal; :meth:`add` negates reverse traversals.

    Examples
    --------
    >>> acc = LinkAccumulator.first(0, 1, np.array([1.0, 0.0]), steps=20, mean_step_m=0.05)
    >>> acc.add(1, 0, np.array([-1.3, 0.0]), steps=10, mean_step_m=0.1, gate_m=1.0)
    True
    >>> e = acc.estimate()
    >>> round(e.d_m, 3), e.steps, round(e.mean_step_m, 4), e.traversals
    (1.2, 7, 0.0833, 2)
    """

    from_id: int
    to_id: int
    sum_w: float  # sum of 1 / T_k
    sum_wd: tuple[float, float]  # sum of D_k / T_k (two floats, not an array: the checkpoint saved with
    # every scan encodes every accumulator, and an array costs the encoder a hook call)
    sum_wstep: float  # sum of mean_step_k / T_k
    traversals: int
    applied_rad: float = 0.0  # the deviation correction of the last published estimate
    corrected: bool = False  # the sums are corrected already (a restored map): later traversals are
    # corrected as they come, and the fused link is not corrected again

    @classmethod
    def first(cls, from_id: int, to_id: int, disp: np.ndarray, *, steps: int, mean_step_m: float) -> LinkAccumulator:
        """The link's first traversal: displacement ``disp`` from ``from_id`` to ``to_id``."""
        w = 1.0 / steps
        return cls(from_id, to_id, w, (w * float(disp[0]), w * float(disp[1])), w * mean_step_m, 1)

    def add(self, from_id: int, to_id: int, disp: np.ndarray, *, steps: int, mean_step_m: float,
            gate_m: float) -> bool:
        """Fuse a later traversal; ``False`` (and nothing changes) when it is further than ``gate_m``."""
        dx, dy = float(disp[0]), float(disp[1])
        if (from_id, to_id) != (self.from_id, self.to_id):
            dx, dy = -dx, -dy
        if np.hypot(dx - self.sum_wd[0] / self.sum_w, dy - self.sum_wd[1] / self.sum_w) > gate_m:
            return False
        w = 1.0 / steps
        self.sum_w += w
        self.sum_wd = (self.sum_wd[0] + w * dx, self.sum_wd[1] + w * dy)
        self.sum_wstep += w * mean_step_m
        self.traversals += 1
        return True

    def estimate(self, rotate_rad: float = 0.0) -> LinkEstimate:
        """The fused measurement, its angle less ``rotate_rad``."""
        dx, dy = self.sum_wd[0] / self.sum_w, self.sum_wd[1] / self.sum_w
        return LinkEstimate(
            from_id=self.from_id, to_id=self.to_id, d_m=float(np.hypot(dx, dy)),
            theta_rad=float(wrap_angle(np.arctan2(dy, dx) - rotate_rad)), steps=max(1, int(round(1.0 / self.sum_w))),
            mean_step_m=float(self.sum_wstep / self.sum_w), traversals=self.traversals,
        )


class RecognizerState(msgspec.Struct, frozen=True):
    """What a :class:`PlaceRecognizer` knows besides its places' signatures, to go on after a restart."""

    belief: _belief.Belief
    current: int
    first_visit: int
    scans: list[tuple[PlacedScan, float]]
    last_xy: tuple[float, float] | None
    inside: _Mark | None
    departure: _Mark | None
    pending: _Pending | None
    links: list[LinkAccumulator]
    rejected_traversals: int
    signature_ids: list[int]  # the places whose signatures go with this state
    rejected_arrivals: int = 0
    deviation: DeviationState | None = None
    relocalisations: int = 0
    suspect: int = -1  # see PlaceRecognizer.relocalise
    unanchored: int = 0
    deviation_place: int = NO_PLACE  # the last place a scan found the robot at
    full_scans: list[tuple[float, float, float]] = []  # see PlaceRecognizer._scan_weight


class PlaceRecognizer:
    """Recognises places from sonar and measures the links between them.

    Call :meth:`step` with each sonar scan and the dead-reckoned pose it was taken at; call
    :meth:`add_place` when the explorer confirms a place (the robot is there now),
    :meth:`remove_place` when a place is deleted and :meth:`move_places` with relaxed coordinates.

    Notes
    -----
    Observation: the scans of the last ``observation_window_m`` of path, placed by dead reckoning,
    build a local grid centred on the robot, reduced to x and y histograms; each place's stored
    histograms are matched against them over all shifts (Eq. 19, with the labels weighted by
    ``match_weights``). The best shifts times the cell size are the offsets ``r*`` (robot minus
    centre) and Eqs. 20-21 their variances. The score of a place is the lower of its x and y best
    scores (``match_axes``). The belief is the hidden-Markov filter of
    :mod:`services.place_recognizer.belief`. The robot is *at* place ``j`` when ``j`` is the most
    probable hypothesis, with probability at least ``localized_probability`` and a filtered offset
    no longer than ``place_radius_m``; otherwise it is between places (-1).

    Link measurement (Eqs. 24-27): leaving place ``i`` (last mark inside it: dead-reckoned position
    ``p_i``, offset ``r_i``) and arriving at ``j`` (``p_j``) measures
    ``D = r_i + (p_j - p_i) - r_j``, ``d = |D|``, ``theta = atan2(D_y, D_x)``; the mean step
    ``delta-bar`` is the path length over the odometry steps between the two marks, and ``T`` the
    larger of those steps and ``round(d / delta-bar)`` (the marks lie inside the places, so the steps
    between them miss part of the centre-to-centre distance that Eq. 5 accounts for). At a new place ``r_j = 0`` exactly (its centre is where the
    robot stands), so the link is measured at once; at a known place ``r_j`` is taken after
    ``settle_observations`` filtered observations (or on leaving), moved back to the arrival by dead
    reckoning.

    Fusing rule for later traversals: each traversal ``k`` is weighted by ``1 / T_k`` (its
    variance grows with its step count, Eq. 5); the link's displacement is the weighted mean
    ``sum(D_k / T_k) / sum(1 / T_k)`` (reverse traversals enter negated), its step count the
    equivalent ``round(1 / sum(1 / T_k))`` (so the relaxer sees the fused, smaller covariance), its
    mean step the weighted mean of the mean steps, and ``traversals`` counts them. A traversal
    further than ``link_fuse_gate_m`` from the fused displacement is rejected as a misrecognition.

    Map gate: a traversal whose displacement ``D`` differs from that of the two places' current
    centres (the explorer's, or the relaxed ones) by more than ``link_map_gate_m`` is rejected as a
    misrecognition before it is fused (counted in ``rejected_traversals``). The belief itself follows
    those centres, so a recognition that contradicts them by metres is a jump to a look-alike place;
    a missing link costs the relaxer far less than a wrong one.

    Arrival gate: the robot arrives at a place only where dead reckoning from the last place it was at
    (that place's centre, its offset there, and the dead-reckoned travel since) puts it, within
    ``arrival_gate_m`` plus ``arrival_gate_per_m`` per metre travelled; a recognition further away is a
    jump to a look-alike (counted in ``rejected_arrivals``) and the robot stays between places.
    """

    def __init__(self, params: PlaceRecognizerParams | None = None) -> None:
        self.params = params or PlaceRecognizerParams()
        self.belief = _belief.Belief.empty()
        self.current = NO_PLACE
        self._signatures: dict[int, PlaceSignature] = {}
        self._stack: _SignatureStack | None = None  # the signatures' histograms as arrays, for match
        self._first_visit: int = NO_PLACE  # the new place whose signature still grows
        self._scans: deque[tuple[PlacedScan, float]] = deque()
        self._last_xy: tuple[float, float] | None = None
        self._deviation_place = NO_PLACE  # the last place a scan found the robot at: between places
        # the compass's deviation there turns the dead-reckoned motion into the map's frame
        self._full_scans: deque[tuple[float, float, float]] = deque()  # (x, y, stamp) of the scans counted in full
        self._inside: _Mark | None = None
        self._departure: _Mark | None = None
        self._pending: _Pending | None = None
        self._links: dict[frozenset[int], LinkAccumulator] = {}
        self.rejected_traversals = 0  # traversals refused by the fusing gate
        self.rejected_arrivals = 0  # recognitions refused as jumps (arrival gate)
        self.relocalisations = 0  # requests to relocalise taken (see relocalise)
        self._suspect = NO_PLACE  # after relocalise: the place the robot was believed at ...
        self._unanchored = 0  # ... and the scans left without the arrival gate
        self._restored_at: tuple[int, tuple[float, float], tuple[float, float]] | None = None  # see restore
        self.deviations = DeviationMap(self.params.deviation)

    # --- inputs -------------------------------------------------------------------------------

    def step(self, dr: DeadReckonedPose, scan: SonarScan,
             between: Sequence[DeadReckonedPose] = ()) -> RecognizerOutput:
        """One observation: a sonar scan and the dead-reckoned pose it was taken at.

        Parameters
        ----------
        dr : messages.types.DeadReckonedPose
            Its ``compass`` pose places the scan; ``steps`` and ``path_length_m`` give ``T`` and the
            mean step of link measurements.
        scan : messages.types.SonarScan
        between : sequence of messages.types.DeadReckonedPose
            The poses since the last scan, oldest first: their compass readings go into the visits'
            means of the deviation map.

        Returns
        -------
        RecognizerOutput
            Localization, the links measured by this observation (usually none), diagnostics
            (``best_score``, ``none_prob``, ``places``).
        """
        p = self.params
        placed = PlacedScan.from_message(scan, dr.compass)
        xy = (dr.compass.x_m, dr.compass.y_m)
        self._depart_from_restored(dr)
        self._remember_scan(placed, dr.path_length_m)
        if self._last_xy is None:
            self.belief = _belief.Belief.empty(xy) if self.belief.ids.size == 0 else self.belief
        self._move_belief_to(xy)
        scores, offsets, variances = self.match(xy)
        variances = np.where(variances > p.match_offset_max_sd_m**2, np.inf, variances)
        self.belief = _belief.correct(self.belief, scores, offsets, variances,
                                      match_sharpness=p.match_sharpness * self._scan_weight(dr),
                                      new_place_match=p.new_place_match)
        if self._first_visit == self.current and self.current != NO_PLACE:
            self._grow_signature(self.current, placed)
        links = self._track(dr)
        if self.current != NO_PLACE:
            self._deviation_place = self.current
        if p.deviation.enabled and self.deviations.observe(
                self.current, dr.compass.heading_rad, dr.raw.heading_rad, dr.path_length_m,
                *self._centre_and_offset(self.current), xy=xy,
                readings=[(b.compass.heading_rad, b.raw.heading_rad, b.path_length_m, b.compass.x_m, b.compass.y_m)
                          for b in between]):
            links = links + self._recorrected({(lk.from_id, lk.to_id) for lk in links})
        valid = scores[~np.isnan(scores)]
        diag = {"best_score": float(valid.max()) if valid.size else float("nan"),
                "none_prob": self.belief.none_prob, "places": float(self.belief.ids.size),
                "rejected_traversals": float(self.rejected_traversals),
                "rejected_arrivals": float(self.rejected_arrivals)}
        return RecognizerOutput(localization=self.localization(), links=links, diagnostics=diag)

    def _scan_weight(self, dr: DeadReckonedPose) -> float:
        """How much of an observation this scan is: ``repeat_scan_weight`` when it was taken within
        ``repeat_scan_m`` of a scan counted in full in the last ``repeat_scan_memory_s`` (the robot has
        not moved on: its sonar sees the same echoes again, and counting them as independent evidence
        multiplies a look-alike's small edge scan after scan), else 1 (and it is remembered)."""
        p = self.params
        x, y, t = dr.compass.x_m, dr.compass.y_m, dr.stamp
        full = self._full_scans
        while full and t - full[0][2] > p.repeat_scan_memory_s:
            full.popleft()
        if any(math.hypot(x - fx, y - fy) < p.repeat_scan_m for fx, fy, _ in full):
            return p.repeat_scan_weight
        full.append((x, y, t))
        return 1.0

    def relocalise(self) -> None:
        """The explorer's legs keep failing from where the belief puts the robot: the belief may be wrong.

        ``relocalise_fraction`` of its mass goes to the places within about ``relocalise_request_std_m``
        of the robot (:func:`services.place_recognizer.belief.spread`), which the next scans then
        match. For the next ``relocalise_scans`` scans, or until the belief settles at another place,
        the arrival gate is off (anchored at a place the robot is not at, it refuses the right ones),
        and no link is measured from or to the place the robot was believed at: its offsets there are
        suspect.
        """
        p = self.params
        self.belief = _belief.spread(self.belief, p.relocalise_fraction, std_m=p.relocalise_request_std_m,
                                     unknown_offset_var_m2=p.unknown_offset_var_m2)
        mark = self._inside if self._inside is not None else self._departure
        self._suspect = self.current if self.current != NO_PLACE else (NO_PLACE if mark is None else mark.place_id)
        self._unanchored = p.relocalise_scans
        if self._pending is not None and self._suspect in (self._pending.to_id, self._pending.departure.place_id):
            self._pending = None
        self.relocalisations += 1

    def add_place(self, place_id: int, x_m: float, y_m: float, dr: DeadReckonedPose) -> RecognizerOutput:
        """A place confirmed by the explorer at the robot's position; stores its signature.

        The signature is the grid of the recent scans taken within ``signature_radius_m`` of the
        robot, centred on it; it keeps growing with the scans taken at the place until the robot
        first leaves it. If the robot had left another place, the link to the new one is measured
        now (the offset at the new place is zero by definition).
        """
        p = self.params
        self._depart_from_restored(dr)
        xy = (dr.compass.x_m, dr.compass.y_m)
        near = [s for s, _ in self._scans if np.hypot(s.x_m - xy[0], s.y_m - xy[1]) <= p.signature_radius_m]
        grid, hist = self._local_grid(near, xy)
        self._signatures[place_id] = PlaceSignature(grid, hist, xy)
        self._stack = None
        if place_id in set(self.belief.ids.tolist()):
            self.belief = _belief.remove_place(self.belief, place_id)
        if self._last_xy is None:
            self._last_xy = xy
            self.belief = _belief.Belief.empty(xy)
        # the belief describes the robot at the last scan: move it to the confirmation first, or the
        # new place's zero offset would be dated at that scan and every later offset would be ahead
        # by the distance travelled in between
        self._move_belief_to(xy)
        self.belief = _belief.add_place(self.belief, place_id, (x_m, y_m), probability=p.confirmed_probability)
        self._first_visit = place_id
        links = self._arrive_or_leave(place_id, dr, settled_now=True)
        return RecognizerOutput(localization=self.localization(), links=links,
                                diagnostics={"places": float(self.belief.ids.size)})

    def restore(self, places: Mapping[int, tuple[float, float]], links: Iterable[LinkEstimate],
                scans: Mapping[int, Sequence[PlacedScan]], *, at_place: int,
                offset_xy: tuple[float, float], dr_xy: tuple[float, float]) -> None:
        """Continue a saved map: its places, fused links and signatures, and where the robot is.

        Parameters
        ----------
        places : mapping
            Place id to centre (the relaxed coordinates).
        links : iterable of LinkEstimate
            The map's fused measurements; later traversals are fused into them.
        scans : mapping
            Place id to the scans taken at it, each placed at its offset from the place's centre
            (frame of the centre at the origin): they build the place's signature.
        at_place, offset_xy, dr_xy : int, tuple, tuple
            The place the robot was last at, its offset from the centre, and its dead-reckoned
            position then; later poses move the belief on from there.

        Notes
        -----
        A signature is rebuilt from the scans within ``signature_radius_m`` of the centre (or, when
        none is, from the nearest one), as :meth:`add_place` builds it from the scans around a new
        place. A link's accumulator is rebuilt from its fused measurement: ``T`` steps weigh ``1 / T``.
        The belief starts with ``confirmed_probability`` at ``at_place`` (at ``offset_xy``), the
        rest on "none"; the robot is between places until an observation says where it is. It left
        ``at_place`` as far as links go: the first other place it reaches, or the first new one, is
        linked from ``at_place`` (the offset moved on by dead reckoning to the first pose after the
        restore), so the continued map joins the saved one.
        """
        if self.belief.ids.size:
            raise ValueError("restore needs a recognizer without places")
        p = self.params
        ids = sorted(places)
        for pid in ids:
            placed = list(scans.get(pid, ()))
            if not placed:
                continue
            near = [s for s in placed if np.hypot(s.x_m, s.y_m) <= p.signature_radius_m]
            near = near or [min(placed, key=lambda s: np.hypot(s.x_m, s.y_m))]
            grid, hist = self._local_grid(near, (0.0, 0.0))
            self._signatures[pid] = PlaceSignature(grid, hist, (0.0, 0.0))
            self._stack = None
        for lk in links:
            if lk.from_id in places and lk.to_id in places:
                w = 1.0 / max(lk.steps, 1)
                disp = (w * (lk.d_m * float(np.cos(lk.theta_rad))), w * (lk.d_m * float(np.sin(lk.theta_rad))))
                self._links[frozenset((lk.from_id, lk.to_id))] = LinkAccumulator(
                    lk.from_id, lk.to_id, w, disp, w * lk.mean_step_m, lk.traversals, corrected=True)
        n = len(ids)
        probs = np.zeros(n)
        offsets = np.zeros((n, 2))
        none_prob = 1.0
        if at_place in places:
            row = ids.index(at_place)
            probs[row], none_prob = p.confirmed_probability, 1.0 - p.confirmed_probability
            offsets[row] = offset_xy
        self.belief = _belief.Belief(
            ids=np.array(ids, dtype=int), centres=np.array([places[i] for i in ids], dtype=float).reshape(-1, 2),
            probs=probs, offsets=offsets, offset_vars=np.zeros((n, 2)), none_prob=none_prob,
            none_xy=np.asarray(dr_xy, dtype=float), none_var_m2=0.0)
        self._last_xy = (float(dr_xy[0]), float(dr_xy[1]))
        self.current = NO_PLACE
        self._first_visit = NO_PLACE
        self._restored_at = None
        if at_place in places:
            self._restored_at = (at_place, (float(offset_xy[0]), float(offset_xy[1])), self._last_xy)

    def remove_place(self, place_id: int) -> None:
        """Forget a deleted place: its belief mass, signature and links."""
        if place_id in set(self.belief.ids.tolist()):
            self.belief = _belief.remove_place(self.belief, place_id)
        self._signatures.pop(place_id, None)
        self._stack = None
        self._links = {k: v for k, v in self._links.items() if place_id not in k}
        self.deviations.remove_place(place_id)
        if self.current == place_id:
            self.current, self._inside = NO_PLACE, None
        if self._departure is not None and self._departure.place_id == place_id:
            self._departure = None
        if self._pending is not None and place_id in (self._pending.to_id, self._pending.departure.place_id):
            self._pending = None
        if self._first_visit == place_id:
            self._first_visit = NO_PLACE

    def move_places(self, centres: Mapping[int, tuple[float, float]]) -> None:
        """New coordinates of places (e.g. relaxed); offsets are relative and stay."""
        self.belief = _belief.move_places(self.belief, dict(centres))

    # --- checkpoints --------------------------------------------------------------------------

    def snapshot(self) -> RecognizerState:
        """The state without the signatures (see :meth:`signatures`); it shares the recognizer's arrays
        and link accumulators, so it is to be encoded before the next call."""
        return RecognizerState(
            belief=self.belief, current=self.current, first_visit=self._first_visit, scans=list(self._scans),
            last_xy=self._last_xy, inside=self._inside, departure=self._departure,
            pending=None if self._pending is None else _Pending(**vars(self._pending)),
            links=list(self._links.values()),
            rejected_traversals=self.rejected_traversals, signature_ids=list(self._signatures),
            rejected_arrivals=self.rejected_arrivals, deviation=self.deviations.snapshot(),
            relocalisations=self.relocalisations, suspect=self._suspect, unanchored=self._unanchored,
            deviation_place=self._deviation_place, full_scans=list(self._full_scans))

    def signatures(self) -> dict[int, PlaceSignature]:
        """Each place's signature; a signature's ``logodds`` is a new array whenever it has grown."""
        return dict(self._signatures)

    def restore_snapshot(self, state: RecognizerState, signatures: Mapping[int, PlaceSignature]) -> None:
        """Take up a :meth:`snapshot` and the signatures of its places."""
        missing = [i for i in state.signature_ids if i not in signatures]
        if missing:
            raise ValueError(f"signatures of places {missing} are missing")
        self.belief, self.current, self._first_visit = state.belief, state.current, state.first_visit
        self._signatures = {i: signatures[i] for i in state.signature_ids}
        self._stack = None
        self._scans = deque((scan, path) for scan, path in state.scans)
        self._last_xy = None if state.last_xy is None else tuple(state.last_xy)
        self._inside, self._departure, self._pending = state.inside, state.departure, state.pending
        self._links = {frozenset((a.from_id, a.to_id)): a for a in state.links}
        self.rejected_traversals = state.rejected_traversals
        self.rejected_arrivals = state.rejected_arrivals
        self.relocalisations = state.relocalisations
        self._suspect, self._unanchored = state.suspect, state.unanchored
        self._deviation_place = state.deviation_place
        self._full_scans = deque(tuple(f) for f in state.full_scans)
        self.deviations = DeviationMap(self.params.deviation)
        if state.deviation is not None:
            self.deviations.restore_snapshot(state.deviation)

    # --- queries ------------------------------------------------------------------------------

    def signature(self, place_id: int) -> Histograms:
        """The stored histograms of a place."""
        return self._signatures[place_id].hist

    def link(self, a: int, b: int) -> LinkEstimate | None:
        """The fused measurement of the link between two places, in its first direction."""
        acc = self._links.get(frozenset((a, b)))
        return None if acc is None else acc.estimate()

    def localization(self) -> Localization:
        """The current belief as published."""
        b, p = self.belief, self.params
        entries = [(int(i), float(q)) for i, q in zip(b.ids, b.probs, strict=True)] + [(NO_PLACE, b.none_prob)]
        entries.sort(key=lambda e: -e[1])
        if b.ids.size:
            row = int(np.argmax(b.probs))
            off, var = b.offsets[row], float(b.offset_vars[row].mean())
            prob = float(b.probs[row])
        else:
            off, var, prob = np.zeros(2), 0.0, 0.0
        return Localization(place_id=self.current, probability=prob, offset_x_m=float(off[0]),
                            offset_y_m=float(off[1]), offset_var_m2=var,
                            hypotheses=tuple(entries[: p.max_hypotheses]))

    def match(self, xy: tuple[float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Match the observation grid at ``xy`` (recent scans) against the signatures of the places
        whose prior probability is at least ``match_min_prior`` (the others stay unmatched, NaN: the
        cost of a scan then grows with the places near the robot, not with the map).

        Returns
        -------
        scores : numpy.ndarray
            ``(P,)`` in belief order, the lower (or the mean, ``match_axes``) of the x and y best
            scores; NaN without signature.
        offsets, variances : numpy.ndarray
            ``(P, 2)``: ``r*`` (best shift times cell size, Section 4.3) and ``sigma*^2`` (Eqs. 20-21).
        """
        p = self.params
        P = self.belief.ids.size
        scores = np.full(P, np.nan)
        offsets = np.zeros((P, 2))
        variances = np.full((P, 2), np.inf)
        if not self._signatures or not self._scans:
            return scores, offsets, variances
        if self._stack is None:
            self._stack = _SignatureStack.of(self._signatures)
        pairs = [(int(r), k) for r in np.flatnonzero(self.belief.probs >= p.match_min_prior)
                 if (k := self._stack.row.get(int(self.belief.ids[r]))) is not None]
        if not pairs:
            return scores, offsets, variances
        rows, sel = [r for r, _ in pairs], [k for _, k in pairs]
        _, obs = self._local_grid([s for s, _ in self._scans], xy)
        sx, sy = self._stack.x[sel], self._stack.y[sel]
        max_shift = int(round(p.max_shift_m / p.cell_m))
        w = p.match_weights
        mx, my = match_axis(obs.x, sx, max_shift, w), match_axis(obs.y, sy, max_shift, w)
        best = [self._plausible_best(m, rows, axis, max_shift) for axis, m in enumerate((mx, my))]
        if p.match_axes == "min":
            scores[rows] = np.minimum(best[0][1], best[1][1])
        else:  # "mean"
            scores[rows] = 0.5 * (best[0][1] + best[1][1])
        offsets[rows] = np.stack([best[0][0], best[1][0]], axis=1) * p.cell_m
        variances[rows] = np.stack([
            match_error_variance(best[0][1], mx.mean_score, k_m2=p.match_error_k_m2, min_spread=p.min_match_spread),
            match_error_variance(best[1][1], my.mean_score, k_m2=p.match_error_k_m2, min_spread=p.min_match_spread),
        ], axis=1)
        return scores, offsets, variances

    def _plausible_best(self, m, rows: list[int], axis: int, max_shift: int) -> tuple[np.ndarray, np.ndarray]:
        """Best shift and score of each matched place among the shifts its prior makes plausible.

        A hypothesis "the robot is at place j" says where at ``j`` it is (the predicted offset and its
        variance): a better score at a shift the robot cannot be at (another stretch of a corridor that
        looks the same) is not evidence for ``j``. Shifts within ``match_window_sd`` standard deviations
        (prior variance plus the rounding of whole cells) of the predicted offset count; the one
        nearest the prediction always does. Of equal best scores, the shift nearest the prediction wins.
        """
        p = self.params
        shifts = np.arange(-max_shift, max_shift + 1)
        if p.match_window_sd <= 0:
            return m.best_shift, m.best_score
        pred = self.belief.offsets[rows, axis] / p.cell_m  # cells
        sd = np.sqrt(self.belief.offset_vars[rows, axis] + p.cell_m**2 / 12.0) / p.cell_m
        dist = np.abs(shifts[None, :] - pred[:, None])
        allowed = (dist <= p.match_window_sd * sd[:, None]) | (dist == dist.min(axis=1, keepdims=True))
        masked = np.where(allowed, m.scores, -np.inf)
        # ties to the shift nearest the prediction: along a stretch that looks the same (a corridor, an
        # empty room) the scores are flat, and ties to the smallest |shift| pulled the offset to the centre
        idx = np.argmin(np.where(masked >= masked.max(axis=1, keepdims=True), dist, np.inf), axis=1)
        return shifts[idx], masked[np.arange(len(rows)), idx]

    # --- internals ----------------------------------------------------------------------------

    def _local_grid(self, scans: Sequence[PlacedScan], centre: tuple[float, float]) -> tuple[np.ndarray, Histograms]:
        """The local occupancy grid of ``scans`` centred on ``centre``, and its histograms."""
        p = self.params
        grid = build_grid(scans, centre, half_width_m=p.grid_half_width_m, cell_m=p.cell_m,
                          logodds_occupied=p.logodds_occupied, logodds_empty=p.logodds_empty,
                          echo_thickness_m=p.echo_thickness_m)
        return grid, histograms(classify(grid, p.logodds_threshold))

    def _move_belief_to(self, xy: tuple[float, float]) -> None:
        """Move the belief by the dead-reckoned displacement since the last pose it was moved to, turned
        by the compass's deviation where the robot is or last was: the map's links are corrected for
        it, the compass's dead reckoning is not, and a displacement through a disturbance would
        otherwise miss the next place by the deviation times its length (docs/places.md, *The robot's
        motion in the map's frame*)."""
        p = self.params
        move = np.zeros(2) if self._last_xy is None else np.subtract(xy, self._last_xy)
        self._last_xy = xy
        here = self.current if self.current != NO_PLACE else self._deviation_place
        if p.deviation.enabled and here != NO_PLACE:
            move = _rotated(move, -self.deviations.deviation(here))
        self.belief = _belief.predict(
            self.belief, move, transition_std_m=p.transition_std_m,
            transition_var_per_m_m2=p.transition_var_per_m_m2, place_radius_m=p.place_radius_m,
            uniform_transition=p.uniform_transition, unknown_offset_var_m2=p.unknown_offset_var_m2,
            relocalise_std_m=p.relocalise_std_m, none_components=p.none_components, none_gate_sd=p.none_gate_sd,
        )

    def _depart_from_restored(self, dr: DeadReckonedPose) -> None:
        """The first pose after :meth:`restore`: the robot has left the place it was saved at."""
        if self._restored_at is None:
            return
        pid, offset, xy0 = self._restored_at
        self._restored_at = None
        if self.current == NO_PLACE and self._departure is None and np.any(self.belief.ids == pid):
            xy = (dr.compass.x_m, dr.compass.y_m)
            moved = (offset[0] + xy[0] - xy0[0], offset[1] + xy[1] - xy0[1])
            self._departure = _Mark(pid, xy, dr.steps, dr.path_length_m, moved)

    def _remember_scan(self, scan: PlacedScan, path_m: float) -> None:
        p = self.params
        self._scans.append((scan, path_m))
        while len(self._scans) > 1 and (
            len(self._scans) > p.observation_max_scans or path_m - self._scans[0][1] > p.observation_window_m
        ):
            self._scans.popleft()

    def _grow_signature(self, place_id: int, scan: PlacedScan) -> None:
        p = self.params
        sig = self._signatures.get(place_id)
        if sig is None or np.hypot(scan.x_m - sig.anchor_dr_xy[0], scan.y_m - sig.anchor_dr_xy[1]) > p.signature_radius_m:
            return
        sig.logodds = integrate_scan(sig.logodds, sig.anchor_dr_xy, scan, cell_m=p.cell_m,
                                     logodds_occupied=p.logodds_occupied, logodds_empty=p.logodds_empty,
                                     echo_thickness_m=p.echo_thickness_m)
        sig.hist = histograms(classify(sig.logodds, p.logodds_threshold))
        if self._stack is not None and place_id in self._stack.row:
            k = self._stack.row[place_id]
            self._stack.x[k], self._stack.y[k] = sig.hist.x, sig.hist.y

    def _centre_and_offset(self, place_id: int) -> tuple[tuple[float, float] | None, tuple[float, float] | None]:
        """The place's centre in the recognizer's map and the robot's filtered offset from it."""
        if place_id == NO_PLACE:
            return None, None
        try:
            row = self.belief.index(place_id)
        except KeyError:
            return None, None
        c, o = self.belief.centres[row], self.belief.offsets[row]
        return (float(c[0]), float(c[1])), (float(o[0]), float(o[1]))

    def _at_place(self) -> int:
        b, p = self.belief, self.params
        if b.ids.size == 0:
            return NO_PLACE
        row = int(np.argmax(b.probs))
        if b.probs[row] < max(p.localized_probability, b.none_prob):
            return NO_PLACE
        if np.hypot(*b.offsets[row]) > p.place_radius_m:
            return NO_PLACE
        return int(b.ids[row])

    def _mark(self, place_id: int, dr: DeadReckonedPose) -> _Mark:
        row = self.belief.index(place_id)
        return _Mark(place_id, (dr.compass.x_m, dr.compass.y_m), dr.steps, dr.path_length_m,
                     (float(self.belief.offsets[row, 0]), float(self.belief.offsets[row, 1])))

    def _track(self, dr: DeadReckonedPose) -> tuple[LinkEstimate, ...]:
        new = self._at_place()
        if self._unanchored > 0:  # relocalising: no gate; settled elsewhere, the gate is back from there
            self._unanchored -= 1
            if new not in (NO_PLACE, self._suspect):
                self._unanchored = 0  # (_arrive_or_leave drops the link from the suspect place)
            elif self._unanchored == 0:
                self._suspect = NO_PLACE  # the belief stayed: its place is trusted again
        elif new not in (NO_PLACE, self.current) and not self._plausible_arrival(new, dr):
            self.rejected_arrivals += 1
            new = NO_PLACE
        return self._arrive_or_leave(new, dr, settled_now=False)

    def _plausible_arrival(self, place_id: int, dr: DeadReckonedPose) -> bool:
        """Whether the belief's position at ``place_id`` lies near where dead reckoning from the last
        place puts the robot: within ``arrival_gate_m`` plus ``arrival_gate_per_m`` per metre travelled."""
        b, p = self.belief, self.params
        mark = self._inside if self._inside is not None else self._departure
        if mark is None:
            return True
        try:
            last, new = b.index(mark.place_id), b.index(place_id)
        except KeyError:
            return True
        predicted = b.centres[last] + mark.offset_xy + np.subtract((dr.compass.x_m, dr.compass.y_m), mark.dr_xy)
        claimed = b.centres[new] + b.offsets[new]
        gate = p.arrival_gate_m + p.arrival_gate_per_m * max(0.0, dr.path_length_m - mark.path_length_m)
        return bool(np.hypot(*(claimed - predicted)) <= gate)

    def _arrive_or_leave(self, new: int, dr: DeadReckonedPose, *, settled_now: bool) -> tuple[LinkEstimate, ...]:
        links: list[LinkEstimate] = []
        if new != self.current:
            if self.current != NO_PLACE:
                if self._pending is not None and self._pending.to_id == self.current and self._inside is not None:
                    links += self._finish(self._pending, self._inside)
                self._departure = self._inside
                if self._first_visit == self.current:
                    self._first_visit = NO_PLACE
            self._pending = None
            if self._suspect != NO_PLACE and self._departure is not None and self._suspect in (
                    self._departure.place_id, new):
                self._departure = None  # relocalising (relocalise): no link from or to the suspect place
            if new not in (NO_PLACE, self._suspect):
                self._suspect = NO_PLACE
            if new != NO_PLACE and self._departure is not None and self._departure.place_id != new:
                self._pending = _Pending(self._departure, new, (dr.compass.x_m, dr.compass.y_m), dr.steps,
                                         dr.path_length_m, 0)
                self._departure = None
            elif new != NO_PLACE:
                self._departure = None
            self.current = new
        if self.current != NO_PLACE:
            self._inside = self._mark(self.current, dr)
            pend = self._pending
            if pend is not None and pend.to_id == self.current:
                pend.observations += 1
                if settled_now or pend.observations >= self.params.settle_observations:
                    links += self._finish(pend, self._inside)
                    self._pending = None
        return tuple(links)

    def _finish(self, pend: _Pending, at: _Mark) -> list[LinkEstimate]:
        """Measure the pending link with the offset at ``at`` moved back to the arrival (Eqs. 24-27)."""
        dep = pend.departure
        r_to_arrival = np.subtract(at.offset_xy, np.subtract(at.dr_xy, pend.arrival_dr_xy))
        disp = np.asarray(dep.offset_xy) + np.subtract(pend.arrival_dr_xy, dep.dr_xy) - r_to_arrival
        gap_steps = pend.arrival_steps - dep.steps
        path = pend.arrival_path_m - dep.path_length_m
        d = float(np.hypot(*disp))
        mean_step = path / gap_steps if gap_steps >= 1 and path > 0.0 else max(d, 1e-6)
        # the marks are inside the places: count the steps of the whole centre-to-centre distance
        steps = max(1, gap_steps, int(round(d / mean_step)))
        if not self._agrees_with_map(dep.place_id, pend.to_id, disp):
            self.rejected_traversals += 1
            return []
        est = self._fuse(dep.place_id, pend.to_id, disp, steps, mean_step)
        return [] if est is None else [est]

    def _agrees_with_map(self, a: int, b: int, disp: np.ndarray) -> bool:
        """Whether a traversal ``a -> b`` lies within ``link_map_gate_m`` of the places' centres."""
        try:
            ca, cb = self.belief.centres[self.belief.index(a)], self.belief.centres[self.belief.index(b)]
        except KeyError:
            return True
        return bool(np.hypot(*(np.asarray(disp) - (cb - ca))) <= self.params.link_map_gate_m)

    def _fuse(self, a: int, b: int, disp: np.ndarray, steps: int, mean_step: float) -> LinkEstimate | None:
        key = frozenset((a, b))
        acc = self._links.get(key)
        if acc is None:
            acc = self._links[key] = LinkAccumulator.first(a, b, disp, steps=steps, mean_step_m=mean_step)
            return self._published(acc)
        if acc.corrected:  # a restored link: this traversal is corrected alone
            disp = _rotated(disp, -self._correction(a, b))
        if not acc.add(a, b, disp, steps=steps, mean_step_m=mean_step, gate_m=self.params.link_fuse_gate_m):
            self.rejected_traversals += 1
            return None
        return self._published(acc)

    def _correction(self, a: int, b: int) -> float:
        """The angle by which the compass turned a link between ``a`` and ``b``: the mean of the places'
        deviations (0 while ``deviation.enabled`` is off)."""
        if not self.params.deviation.enabled:
            return 0.0
        return 0.5 * (self.deviations.deviation(a) + self.deviations.deviation(b))

    def _published(self, acc: LinkAccumulator) -> LinkEstimate:
        """The estimate to publish, corrected for the deviation (a restored link is corrected already)."""
        if acc.corrected:
            return acc.estimate()
        acc.applied_rad = self._correction(acc.from_id, acc.to_id)
        return acc.estimate(acc.applied_rad)

    def _recorrected(self, skip: set[tuple[int, int]]) -> tuple[LinkEstimate, ...]:
        """The links whose correction moved by ``deviation.republish_rad`` or more since they were
        published, published again (the same traversals, the angle corrected anew)."""
        tol = self.params.deviation.republish_rad
        return tuple(self._published(acc) for acc in self._links.values()
                     if not acc.corrected and (acc.from_id, acc.to_id) not in skip
                     and abs(self._correction(acc.from_id, acc.to_id) - acc.applied_rad) >= tol)


def _rotated(v: np.ndarray, angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])
