"""Explorer core: predicted and confirmed places, link confidence, loop closing, path following."""

from __future__ import annotations

import copy
import math
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import msgspec
import numpy as np

from messages.types import LocalizationBelief, Pose2, SonarScan
from services.explorer.controller import Command, clear_towards, open_directions, velocity_command
from services.explorer.planner import dijkstra, path_to, reachable
from sim.geometry import wrap_angle

NO_PLACE = -1
TRAVERSED, INFERRED, PREDICTED = "traversed", "inferred", "predicted"  # link kinds


@dataclass(frozen=True)
class ExplorerParams:
    """Parameters of the explorer core (defaults in code; deploy files only override)."""

    place_spacing_m: float = 1.0  # distance of a predicted place from the confirmed place it comes from
    directions: int = 16  # candidate directions of predicted places, evenly spaced from east (world frame):
    # with 8, a door between two places of a corridor lay in no direction of either, and its room stayed
    # unexplored
    open_distance_m: float = 1.5  # free length the sonar must show along a direction for it to be open
    open_half_width_m: float = 0.2  # half width of the corridor that must be seen free (robot radius)
    open_edge_distance_m: float = 1.0  # the corridor's edges must be seen free this far (its centre line further)
    sample_step_m: float = 0.1  # spacing of the points checked along a corridor by the free-space classifier
    min_place_separation_m: float = 0.8  # no place is predicted this close to an existing place
    merge_distance_m: float = 0.5  # predicted places this close to a newly confirmed place are removed
    inferred_link_max_m: float = 2.0  # links are inferred to confirmed places closer than this
    loop_closing_path_m: float = 3.0  # traversed path longer than this to a neighbour: go there directly
    confidence_initial: float = 0.5  # confidence of a new link
    confidence_rate: float = 0.5  # lambda of Eqs. 17-18
    confidence_min: float = 0.2  # a link is deleted when its confidence falls below this
    arrive_tolerance_m: float = 0.1  # the robot has reached a place within this distance of it
    on_the_way_m: float = 0.5  # a place this close to a leg's line, passed on the way, continues the leg
    leg_timeout_base_s: float = 20.0  # a leg fails after this ...
    leg_timeout_per_m_s: float = 20.0  # ... plus this per metre of its length
    blocked_timeout_s: float = 5.0  # a leg fails after the controller is blocked this long
    progress_timeout_s: float = 10.0  # a leg fails when the robot has come no nearer its end ...
    progress_m: float = 0.1  # ... by this much in that long (dithering at a door frame, neither blocked
    # nor stalled for long)
    max_interruptions: int = 3  # legs towards a predicted place that end at another place: deleted after this
    # many (the recognizer keeps putting the robot at a near-duplicate of the leg's start)
    back_to_start_m: float = 0.4  # after a failed leg, a robot this far from the leg's start goes back to
    # within half of it before the next leg (wedged beside a place, heading straight on for the next fails)
    max_held_failures: int = 4  # a link whose deletion would leave no predicted place within the robot's reach
    # (while some are left elsewhere) is kept through this many failures below confidence_min, each one a
    # request to the recognizer to relocalise; then Eq. 18 deletes it
    max_speed_mps: float = 0.3  # forward speed limit
    max_turn_radps: float = 1.0  # turn rate limit
    heading_gain: float = 1.5  # turn rate per radian of heading error, 1/s
    turn_in_place_rad: float = 0.8  # above this heading error the robot turns without moving
    stop_distance_m: float = 0.3  # an obstacle ahead closer than this stops the robot
    slow_distance_m: float = 0.8  # the robot slows down linearly below this frontal clearance
    avoid_distance_m: float = 0.6  # obstacles in the front half closer than this turn the robot away
    avoid_gain: float = 0.8  # turn rate per unit of (1 - range / avoid distance), rad/s
    front_half_angle_rad: float = 0.5  # half angle of the frontal sector
    stall_window_s: float = 2.0  # moving forward this long ...
    stall_distance_m: float = 0.03  # ... with less dead-reckoned progress than this is a stall
    stall_min_speed_mps: float = 0.05  # commands at least this fast count as moving forward
    recover_s: float = 1.5  # after a stall, back away from the nearest obstacle this long
    recover_speed_mps: float = 0.1  # backing speed while recovering
    recover_turn_radps: float = 0.6  # turn rate away from the nearest obstacle while recovering
    rear_clearance_m: float = 0.4  # no backing when the rear sector sees an obstacle closer than this


@dataclass(frozen=True)
class PlaceFix:
    """A localization from the place recognizer, with the time it refers to.

    ``place_id`` -1 means between places; the offset is robot minus place centre (world frame).
    """

    place_id: int
    offset_x_m: float
    offset_y_m: float
    stamp_s: float

    @classmethod
    def from_message(cls, msg: LocalizationBelief) -> PlaceFix:
        return cls(msg.place_id, msg.offset_x_m, msg.offset_y_m, msg.stamp)


# Events: the fields of the messages of the same name in messages.types (without stamp and seq).
@dataclass(frozen=True)
class PlacePredictedEvent:
    place_id: int
    x_m: float
    y_m: float
    parent_id: int


@dataclass(frozen=True)
class PlaceConfirmedEvent:
    place_id: int
    x_m: float
    y_m: float


@dataclass(frozen=True)
class PlaceDeletedEvent:
    place_id: int
    reason: str


@dataclass(frozen=True)
class LinkInferredEvent:
    from_id: int
    to_id: int
    d_m: float


@dataclass(frozen=True)
class LinkConfidenceEvent:
    from_id: int
    to_id: int
    confidence: float


@dataclass(frozen=True)
class LinkDeletedEvent:
    from_id: int
    to_id: int
    reason: str


Event = (PlacePredictedEvent | PlaceConfirmedEvent | PlaceDeletedEvent | LinkInferredEvent
         | LinkConfidenceEvent | LinkDeletedEvent)


@dataclass(frozen=True)
class ExplorerStatus:
    """Fields of :class:`messages.types.ExplorationStatus`."""

    complete: bool
    confirmed: int
    predicted: int
    target_id: int


@dataclass(frozen=True)
class ExplorerOutput:
    """One step's result: events in order, the velocity command, the status, diagnostics."""

    events: tuple[Event, ...]
    command: Command
    status: ExplorerStatus
    diagnostics: dict[str, float] = field(default_factory=dict)


class Place(msgspec.Struct, array_like=True):
    """A place of the explorer's map; a predicted place keeps its offset from its parent.

    Places and links go into the checkpoint saved on every tick as arrays, not maps: half the bytes,
    and half the encoding time (0.12 ms instead of 0.23 ms for 380 places and 1570 links).
    """

    place_id: int
    x_m: float
    y_m: float
    confirmed: bool
    parent_id: int


class Link(msgspec.Struct, array_like=True):
    """A link between two places: traversed, inferred (planning only) or to a predicted place."""

    a: int
    b: int
    kind: str
    confidence: float


def confidence_after_traversal(confidence: float, rate: float) -> float:
    """Eq. 17: ``c' = lambda + (1 - lambda) c``.

    >>> confidence_after_traversal(0.5, 0.5)
    0.75
    """
    return rate + (1.0 - rate) * confidence


def confidence_after_failure(confidence: float, rate: float) -> float:
    """Eq. 18: ``c' = (1 - lambda) c``.

    >>> confidence_after_failure(0.5, 0.5)
    0.25
    """
    return (1.0 - rate) * confidence


def _key(a: int, b: int) -> tuple[int, int]:
    return (a, b) if a < b else (b, a)


class ExplorerState(msgspec.Struct, frozen=True):
    """Everything an :class:`Explorer` knows (its parameters aside), to go on after a restart."""

    places: list[Place]
    links: list[Link]
    robot_xy: tuple[float, float] | None
    current: int
    last_place: int
    leg: tuple[int, int] | None
    target: int
    loop_queue: list[tuple[int, int]]
    complete: bool
    next_id: int
    last_pose: Pose2 | None
    last_scan: SonarScan | None
    scan_heading: float
    moving: list[tuple[float, float, float]]
    recover_until: float
    recover_cmd: tuple[float, float]
    stalls: int
    leg_start_s: float
    blocked_since: float | None
    fix_after_s: float
    progress_best_m: float = math.inf
    progress_since_s: float = 0.0
    via: int = -1  # after a failed leg: the place the robot goes back to first (-1: none)
    interrupted: dict[int, int] = msgspec.field(default_factory=dict)  # predicted place -> legs ended elsewhere
    held: list[tuple[int, int, int]] = msgspec.field(default_factory=list)  # (a, b, failures held) per link
    relocalisations: int = 0  # relocalisation requests so far


class Explorer:
    """Explores by going to the nearest predicted place (Section 4.2).

    Call :meth:`step` on every control tick with the time, the robot's dead-reckoned pose, the latest
    sonar scan (or ``None``) and the place recognizer's localization *on the tick it arrived*
    (``None`` otherwise); :meth:`move_places` takes relaxed coordinates.

    Notes
    -----
    Position: the robot's map position is the last localized place centre plus its offset, moved by
    the dead-reckoned displacement since. The first step confirms place 0 where the robot stands.

    Rules (Section 4.2, Eqs. 17-18):

    - *Prediction*: around each newly confirmed place, a place is predicted ``place_spacing_m`` away
      in each of ``directions`` world directions that the sonar shows open
      (:func:`services.explorer.controller.clear_towards` with ``open_distance_m``), unless a place is
      already within ``min_place_separation_m``.
    - *Target*: the nearest predicted place by the shortest path over all links (Dijkstra, weight
      length / confidence); the robot follows the path one leg (link) at a time.
    - *Confirmation*: the leg towards a predicted place, from its nearest confirmed place, succeeds
      when the robot comes within ``arrive_tolerance_m`` of it, i.e. it could travel the 1 m; the
      place is confirmed at the robot's position (dead reckoning relative to the last place). The
      leg fails when the controller stays blocked for ``blocked_timeout_s``, when the robot comes no
      nearer the leg's end by ``progress_m`` in ``progress_timeout_s``, or when the leg outlasts
      ``leg_timeout_base_s + leg_timeout_per_m_s * length``: the predicted place is deleted.
      Arriving at a confirmed place within ``on_the_way_m`` of a leg's line towards a confirmed place
      (and nearer its end) counts as a traversal to it, and the leg goes on from there.
      Arriving at a known confirmed place instead ends the leg; a predicted target within
      ``merge_distance_m`` of that place is deleted as a duplicate.
    - *Inferred links* from a newly confirmed place to confirmed places within
      ``inferred_link_max_m`` whose direction the sonar shows clear (planning only).
    - *Loop closing*: for each such neighbour, if the shortest path over traversed links only is
      longer than ``loop_closing_path_m`` (or none exists), the robot later travels that inferred
      link directly, before any further exploration.
    - *Confidence*: a new link starts at ``confidence_initial``; a traversal sets
      ``c = lambda + (1 - lambda) c`` (Eq. 17); a failed traversal (timeout, blocked, or arrival at a
      different place than the leg's end) sets ``c = (1 - lambda) c`` (Eq. 18); below
      ``confidence_min`` the link is deleted, then every predicted place no path from the robot's last
      place reaches is deleted, and every confirmed one left without a traversed or inferred link.
      The last link of the place a leg starts from is kept, however low: legs that fail from every
      link of the robot's place mean the robot is stuck or lost, and deleting them would prune the
      whole map beyond it and end the exploration. A link whose deletion would leave no predicted
      place within the robot's reach, while some are left elsewhere, is kept through
      ``max_held_failures`` failures below ``confidence_min``. Every failure below it of a leg from
      the robot's place asks the recognizer to relocalise (:attr:`relocalisations`, carried by the
      velocity command). After a failed leg, a robot more than
      ``back_to_start_m`` from the leg's start goes back to it before heading for the next leg's end.
      A predicted place is deleted once ``max_interruptions`` legs towards it have ended at another
      place (the recognizer putting the robot at a near-duplicate of the leg's start, for ever).
    - *End*: exploration is complete when no predicted place and no loop-closing leg is left.
    """

    def __init__(self, params: ExplorerParams | None = None) -> None:
        self.params = params or ExplorerParams()
        self.places: dict[int, Place] = {}
        self.links: dict[tuple[int, int], Link] = {}
        self.robot_xy: tuple[float, float] | None = None
        self.current = NO_PLACE  # the confirmed place the robot is at, -1 between places
        self.last_place = NO_PLACE  # the confirmed place the robot was at last
        self.leg: tuple[int, int] | None = None
        self.target = NO_PLACE  # final place of the current plan
        self.loop_queue: list[tuple[int, int]] = []  # inferred links to travel directly
        self.complete = False
        self._next_id = 0
        self._last_pose: Pose2 | None = None
        self._last_scan: SonarScan | None = None
        self._scan_heading = 0.0  # compass heading the last scan was taken at
        self._moving: deque[tuple[float, float, float]] = deque()  # (time, x, y) while commanding forward
        self._recover_until = -math.inf
        self._recover_cmd = (0.0, 0.0)
        self.stalls = 0  # stalls met (robot pressed against an obstacle the sonar missed)
        self._leg_start_s = 0.0
        self._blocked_since: float | None = None
        self._progress_best_m = math.inf  # nearest the robot has come to the leg's end ...
        self._progress_since_s = 0.0  # ... first reached at this time
        self._via = NO_PLACE  # after a failed leg: the place to go back to before the leg's end
        self._interrupted: dict[int, int] = {}  # predicted place -> legs towards it that ended at another place
        self._held: dict[tuple[int, int], int] = {}  # link -> failures below confidence_min it was kept through
        self.relocalisations = 0  # requests to the recognizer to relocalise, so far (see _failed)
        self._fix_after_s = -math.inf  # localizations older than this are stale (before a confirmation)
        self._counts: tuple[int, int, int, int] | None = None  # places, links, confirmed, traversed or inferred

    def snapshot(self) -> ExplorerState:
        """The explorer's state, for :meth:`restore_snapshot`. Its places and links are the explorer's own
        (copying them cost a millisecond a tick at 2000 links), so it is to be encoded before the next call."""
        return ExplorerState(
            places=list(self.places.values()), links=list(self.links.values()), robot_xy=self.robot_xy,
            current=self.current, last_place=self.last_place, leg=self.leg, target=self.target,
            loop_queue=list(self.loop_queue), complete=self.complete, next_id=self._next_id,
            last_pose=self._last_pose, last_scan=self._last_scan, scan_heading=self._scan_heading,
            moving=list(self._moving), recover_until=self._recover_until, recover_cmd=self._recover_cmd,
            stalls=self.stalls, leg_start_s=self._leg_start_s, blocked_since=self._blocked_since,
            fix_after_s=self._fix_after_s, progress_best_m=self._progress_best_m,
            progress_since_s=self._progress_since_s, via=self._via, interrupted=dict(self._interrupted),
            held=[(a, b, n) for (a, b), n in self._held.items()], relocalisations=self.relocalisations)

    def restore_snapshot(self, state: ExplorerState) -> None:
        """Take up the state of :meth:`snapshot` (of an explorer with the same parameters)."""
        self._counts = None
        self.places = {q.place_id: copy.copy(q) for q in state.places}
        self.links = {_key(lk.a, lk.b): copy.copy(lk) for lk in state.links}
        self.robot_xy = tuple(state.robot_xy) if state.robot_xy is not None else None
        self.current, self.last_place = state.current, state.last_place
        self.leg = tuple(state.leg) if state.leg is not None else None
        self.target, self.loop_queue, self.complete = state.target, [tuple(q) for q in state.loop_queue], state.complete
        self._next_id, self._last_pose, self._last_scan = state.next_id, state.last_pose, state.last_scan
        self._scan_heading, self._moving = state.scan_heading, deque(tuple(m) for m in state.moving)
        self._recover_until, self._recover_cmd = state.recover_until, tuple(state.recover_cmd)
        self.stalls, self._leg_start_s = state.stalls, state.leg_start_s
        self._blocked_since, self._fix_after_s = state.blocked_since, state.fix_after_s
        self._progress_best_m, self._progress_since_s = state.progress_best_m, state.progress_since_s
        self._via = state.via
        self._interrupted = dict(state.interrupted)
        self._held = {_key(a, b): n for a, b, n in state.held}
        self.relocalisations = state.relocalisations

    # --- inputs -------------------------------------------------------------------------------

    def step(self, now_s: float, pose: Pose2, scan: SonarScan | None = None,
             fix: PlaceFix | None = None) -> ExplorerOutput:
        """One control tick.

        Parameters
        ----------
        now_s : float
            Simulated time, seconds.
        pose : messages.types.Pose2
            Dead-reckoned pose (compass heading).
        scan : messages.types.SonarScan or None
            The latest sonar scan, if a new one arrived.
        fix : PlaceFix or None
            The latest localization, only on the tick it arrived.

        Returns
        -------
        ExplorerOutput
        """
        events: list[Event] = []
        if self._last_pose is None or self.robot_xy is None:
            self.robot_xy = (pose.x_m, pose.y_m)
        else:
            self.robot_xy = (self.robot_xy[0] + pose.x_m - self._last_pose.x_m,
                             self.robot_xy[1] + pose.y_m - self._last_pose.y_m)
        self._last_pose = pose
        if scan is not None:
            self._last_scan = scan
            self._scan_heading = pose.heading_rad
        if not any(p.confirmed for p in self.places.values()):
            if self._last_scan is None:
                return self._output(events, now_s, pose)
            events += self._confirm_here(self._new_id(), NO_PLACE, now_s)
        if fix is not None and fix.stamp_s >= self._fix_after_s:
            events += self._on_fix(fix, now_s)
        if self.leg is not None:
            events += self._progress(now_s)
        if self.leg is None and not self.complete:
            events += self._plan(now_s)
        return self._output(events, now_s, pose)

    def move_places(self, centres: Mapping[int, tuple[float, float]]) -> None:
        """New coordinates of confirmed places (e.g. relaxed); predicted places follow their parent."""
        shift = (0.0, 0.0)
        for pid, (x, y) in centres.items():
            p = self.places.get(pid)
            if p is None or not p.confirmed:
                continue
            dx, dy = x - p.x_m, y - p.y_m
            if pid == self.last_place:
                shift = (dx, dy)
            p.x_m, p.y_m = x, y
            for q in self.places.values():
                if not q.confirmed and q.parent_id == pid:
                    q.x_m, q.y_m = q.x_m + dx, q.y_m + dy
        if self.robot_xy is not None:
            self.robot_xy = (self.robot_xy[0] + shift[0], self.robot_xy[1] + shift[1])

    def restore(self, places: Mapping[int, tuple[float, float]], links: Iterable[tuple[int, int, int]],
                scans: Mapping[int, tuple[float, SonarScan]], *, at_place: int, robot_xy: tuple[float, float],
                pose: Pose2, scan: SonarScan | None = None, next_place_id: int = 0) -> list[Event]:
        """Continue a saved exploration: its confirmed places and traversed links, and a fresh set of
        predicted places; returns the prediction events.

        Parameters
        ----------
        places : mapping
            Confirmed place id to its coordinates (the relaxed ones).
        links : iterable of (int, int, int)
            Traversed links ``(a, b, traversals)``; a link's confidence is the initial one raised by
            Eq. 17 once per traversal after the first.
        scans : mapping
            Place id to ``(compass heading, scan)`` of a scan taken at the place: places are predicted
            around it as around a newly confirmed place (directions it shows open, no place near).
        at_place : int
            The place the robot was at last: plans start from it.
        robot_xy, pose : tuple, messages.types.Pose2
            The robot's map position and the dead-reckoned pose it had there; later poses move it on.
        scan : messages.types.SonarScan or None
            The robot's latest scan (taken at ``pose``'s heading), for the controller.
        next_place_id : int
            New places get ids from here (and above every id of ``places``): ids are never reused.
        """
        if self.places:
            raise ValueError("restore needs an explorer without places")
        if at_place not in places:
            raise ValueError(f"the robot's place {at_place} is not among the {len(places)} places")
        p = self.params
        self._counts = None
        for pid, (x, y) in sorted(places.items()):
            self.places[pid] = Place(pid, float(x), float(y), True, NO_PLACE)
        for a, b, traversals in links:
            if a == b or a not in places or b not in places:
                continue
            confidence = p.confidence_initial
            for _ in range(max(traversals, 1) - 1):
                confidence = confidence_after_traversal(confidence, p.confidence_rate)
            self.links[_key(a, b)] = Link(*_key(a, b), TRAVERSED, confidence)
        self._next_id = max(next_place_id, max(places) + 1)
        events: list[Event] = []
        for pid in sorted(scans):
            if pid in self.places:
                events += self._predict_around(pid, *scans[pid])
        self.current, self.last_place = NO_PLACE, at_place
        self.robot_xy = (float(robot_xy[0]), float(robot_xy[1]))
        self._last_pose = pose
        if scan is not None:
            self._last_scan, self._scan_heading = scan, pose.heading_rad
        return events

    # --- queries ------------------------------------------------------------------------------

    def graph(self, kinds: tuple[str, ...] = (TRAVERSED, INFERRED, PREDICTED), *,
              by_confidence: bool = True) -> dict[int, dict[int, float]]:
        """Adjacency over links of the given kinds, weight length (divided by confidence)."""
        g: dict[int, dict[int, float]] = {pid: {} for pid in self.places}
        for (a, b), link in self.links.items():
            if link.kind in kinds:
                w = self.distance(a, b) / (link.confidence if by_confidence else 1.0)
                g[a][b] = w
                g[b][a] = w
        return g

    def distance(self, a: int, b: int) -> float:
        pa, pb = self.places[a], self.places[b]
        return math.hypot(pb.x_m - pa.x_m, pb.y_m - pa.y_m)

    def distance_to(self, pid: int) -> float:
        """The robot's distance from place ``pid``."""
        assert self.robot_xy is not None
        q = self.places[pid]
        return math.hypot(q.x_m - self.robot_xy[0], q.y_m - self.robot_xy[1])

    def shortest_path(self, a: int, b: int) -> list[int]:
        """Planned path from ``a`` to ``b`` over all links; empty when none."""
        _, prev = dijkstra(self.graph(), a)
        return path_to(prev, a, b)

    # --- rules --------------------------------------------------------------------------------

    def _new_id(self) -> int:
        pid = self._next_id
        self._next_id += 1
        return pid

    def _on_fix(self, fix: PlaceFix, now_s: float) -> list[Event]:
        place = self.places.get(fix.place_id)
        if fix.place_id == NO_PLACE:
            self.current = NO_PLACE
            return []
        if place is None or not place.confirmed:
            return []
        self.robot_xy = (place.x_m + fix.offset_x_m, place.y_m + fix.offset_y_m)
        if fix.place_id == self.current:
            return []
        return self._arrive(fix.place_id, now_s)

    def _progress(self, now_s: float) -> list[Event]:
        assert self.leg is not None and self.robot_xy is not None
        frm, to = self.leg
        target = self.places[to]
        # progress counted towards the place gone back to first, when there is one
        dist = self.distance_to(to if self._via == NO_PLACE else self._via)
        near = dist <= self.params.arrive_tolerance_m and self._via == NO_PLACE
        if near and not target.confirmed:
            return self._confirm_here(to, frm, now_s)
        if near and to != self.current:
            return self._arrive(to, now_s)
        p = self.params
        timeout = p.leg_timeout_base_s + p.leg_timeout_per_m_s * self.distance(frm, to)
        if now_s - self._leg_start_s > timeout:
            return self._fail_leg(now_s, "timeout")
        if self._blocked_since is not None and now_s - self._blocked_since >= p.blocked_timeout_s:
            return self._fail_leg(now_s, "blocked")
        if dist <= self._progress_best_m - p.progress_m:
            self._progress_best_m, self._progress_since_s = dist, now_s
        elif now_s - self._progress_since_s > p.progress_timeout_s:
            return self._fail_leg(now_s, "no progress")
        return []

    def _arrive(self, k: int, now_s: float) -> list[Event]:
        """The robot is at confirmed place ``k`` (recognised, or reached the leg's end)."""
        events: list[Event] = []
        if k != self._via:
            self._via = NO_PLACE
        prev = self.last_place
        if self.leg is not None:
            frm, to = self.leg
            if k == frm and k == prev:
                self.current = k
                return events
            if k == to:
                events += self._traversed(prev if prev != NO_PLACE else frm, k)
                if self.loop_queue and self.loop_queue[0] == (frm, to):
                    self.loop_queue.pop(0)
            elif (self.places[to].confirmed and k != frm and _key(k, to) in self.links
                  and self._on_the_way(frm, to, k)):
                # an intermediate place: the traversal so far counts, the leg goes on from here, along
                # the link k - to (a leg with no link under it has nothing to fail, Eq. 18, and was
                # taken again and again)
                if prev != NO_PLACE and prev != k and prev in self.places:
                    events += self._traversed(prev, k)
                if self.loop_queue and self.loop_queue[0] == (frm, to):
                    self.loop_queue[0] = (k, to)
                self._start_leg((k, to), self.target, now_s)
                self.current = self.last_place = k
                return events + self._prune()
            else:
                if self.places[to].confirmed and k != frm:
                    events += self._failed(frm, to, "reached another place")
                elif not self.places[to].confirmed and self.distance(to, k) < self.params.merge_distance_m:
                    events += self._delete_place(to, f"coincides with place {k}")
                elif not self.places[to].confirmed and k != frm:
                    n = self._interrupted[to] = self._interrupted.get(to, 0) + 1
                    if n >= self.params.max_interruptions:
                        events += self._delete_place(to, f"{n} legs towards it ended at other places, "
                                                         f"the last at place {k}")
                if prev != NO_PLACE and prev != k and prev in self.places:
                    events += self._traversed(prev, k)
            self.leg = None
        elif prev != NO_PLACE and prev != k and prev in self.places:
            events += self._traversed(prev, k)
        self.current = self.last_place = k
        events += self._prune()
        return events

    def _on_the_way(self, frm: int, to: int, k: int) -> bool:
        """Whether place ``k`` lies on the straight leg ``frm -> to``, nearer ``to`` than ``frm`` is."""
        a, b, c = self.places[frm], self.places[to], self.places[k]
        ex, ey = b.x_m - a.x_m, b.y_m - a.y_m
        length2 = ex * ex + ey * ey
        if length2 == 0.0 or self.distance(k, to) >= self.distance(frm, to):
            return False
        t = min(max(((c.x_m - a.x_m) * ex + (c.y_m - a.y_m) * ey) / length2, 0.0), 1.0)
        off = math.hypot(a.x_m + t * ex - c.x_m, a.y_m + t * ey - c.y_m)
        return off <= self.params.on_the_way_m

    def _traversed(self, a: int, b: int) -> list[Event]:
        """A traversal of ``a -> b``: a new link at the initial confidence, or Eq. 17."""
        if a == b or a not in self.places or b not in self.places:
            return []
        p = self.params
        link = self.links.get(_key(a, b))
        if link is None or link.kind == PREDICTED:
            link = Link(*_key(a, b), TRAVERSED, p.confidence_initial)
            self.links[_key(a, b)] = link
        else:
            link.kind = TRAVERSED
            link.confidence = confidence_after_traversal(link.confidence, p.confidence_rate)
        self._held.pop(_key(a, b), None)  # travelled after all: its failures were the belief's
        return [LinkConfidenceEvent(a, b, link.confidence)]

    def _failed(self, a: int, b: int, reason: str, *, robot_at: int = NO_PLACE) -> list[Event]:
        """A failed traversal of ``a -> b`` (Eq. 18); deletes the link below the threshold.

        A leg from ``robot_at``, the place the robot is still at, that leaves its link below the
        threshold asks the recognizer to relocalise (:attr:`relocalisations`): legs that keep failing
        from where the belief puts the robot are what a wrong belief looks like to the explorer (in
        whole explorations of manchester-corridors the robot was 1.2-2.9 m from that place at 21 of 34
        deletions). Two exceptions to the deletion: the last link of ``robot_at`` is kept however often
        it fails (the rest of the map would be pruned as cut off from the robot); and a link whose
        deletion would leave every predicted place out of the robot's reach, some being left elsewhere,
        is kept through ``max_held_failures`` failures below the threshold (the prune would end the
        exploration), time for the relocalisation to put the robot where it is."""
        p = self.params
        key = _key(a, b)
        link = self.links.get(key)
        if link is None:
            return []
        link.confidence = confidence_after_failure(link.confidence, p.confidence_rate)
        events: list[Event] = [LinkConfidenceEvent(a, b, link.confidence)]
        below = link.confidence < p.confidence_min
        if robot_at != NO_PLACE:
            self.relocalisations += below
            if not any(robot_at in k and k != key and other.kind != PREDICTED for k, other in self.links.items()):
                return events
        if not below:
            return events
        if robot_at != NO_PLACE and self._cuts_off(robot_at, key):
            held = self._held[key] = self._held.get(key, 0) + 1
            if held <= p.max_held_failures:
                return events
        self._held.pop(key, None)
        del self.links[key]
        events.append(LinkDeletedEvent(a, b, f"confidence {link.confidence:.3f} below "
                                              f"{p.confidence_min} ({reason})"))
        self.loop_queue = [q for q in self.loop_queue if _key(*q) != key]
        return events

    def _cuts_off(self, robot_at: int, key: tuple[int, int]) -> bool:
        """Whether, without link ``key``, no predicted place is reachable from ``robot_at`` while some
        predicted place is left."""
        predicted = {pid for pid, q in self.places.items() if not q.confirmed}
        if not predicted:
            return False
        graph = self.graph()
        a, b = key
        graph[a].pop(b, None)
        graph[b].pop(a, None)
        return not predicted & reachable(graph, robot_at)

    def _fail_leg(self, now_s: float, reason: str) -> list[Event]:
        assert self.leg is not None
        frm, to = self.leg
        self.leg = None
        self._blocked_since = None
        if self.loop_queue and self.loop_queue[0] == (frm, to):
            self.loop_queue.pop(0)
        if frm in self.places and self.distance_to(frm) > self.params.back_to_start_m:
            self._via = frm
        if not self.places[to].confirmed:
            return self._delete_place(to, f"cannot travel {self.params.place_spacing_m} m towards it ({reason})")
        return self._failed(frm, to, reason, robot_at=frm) + self._prune()

    def _delete_place(self, pid: int, reason: str) -> list[Event]:
        events: list[Event] = []
        for key in [k for k in self.links if pid in k]:
            link = self.links.pop(key)
            if link.kind != PREDICTED:
                events.append(LinkDeletedEvent(link.a, link.b, f"place {pid} deleted"))
        del self.places[pid]
        self.loop_queue = [q for q in self.loop_queue if pid not in q]
        if self._via == pid:
            self._via = NO_PLACE
        self._interrupted.pop(pid, None)
        self._held = {k: n for k, n in self._held.items() if pid not in k}
        if self.leg is not None and pid in self.leg:
            self.leg = None
        events.append(PlaceDeletedEvent(pid, reason))
        return events

    def _prune(self) -> list[Event]:
        """Delete the places no path from the robot's last place reaches: predicted ones, and confirmed
        ones left without any traversed or inferred link (a confirmed part cut off by one deleted link
        stays in the map: recognising a place of it joins it again)."""
        if self.last_place == NO_PLACE:
            return []
        seen = reachable(self.graph(), self.last_place)
        linked = {pid for key, link in self.links.items() if link.kind != PREDICTED for pid in key}
        events: list[Event] = []
        for pid in sorted(set(self.places) - seen):
            if pid in self.places and (not self.places[pid].confirmed or pid not in linked):
                events += self._delete_place(pid, "no path reaches it")
        return events

    def _confirm_here(self, pid: int, frm: int, now_s: float) -> list[Event]:
        """Confirm place ``pid`` at the robot's position; predict, infer links, check loops."""
        assert self.robot_xy is not None
        p = self.params
        x, y = self.robot_xy
        place = self.places.get(pid)
        if place is None:
            place = self.places[pid] = Place(pid, x, y, True, frm)
        place.x_m, place.y_m, place.confirmed = x, y, True
        events: list[Event] = [PlaceConfirmedEvent(pid, x, y)]
        self._via = NO_PLACE
        self._interrupted.pop(pid, None)
        if frm != NO_PLACE:
            events += self._traversed(frm, pid)
        for q in [q for q in self.places.values() if not q.confirmed]:
            if math.hypot(q.x_m - x, q.y_m - y) < p.merge_distance_m:
                events += self._delete_place(q.place_id, f"merged into place {pid}")
        self.leg = None
        self.current = self.last_place = pid
        self._fix_after_s = now_s
        scan = self._last_scan
        if scan is not None and self._last_pose is not None:
            heading = self._scan_heading
            events += self._predict_around(pid, heading, scan)
            traversed = self.graph((TRAVERSED,), by_confidence=False)
            dist_traversed, _ = dijkstra(traversed, pid)
            for q in sorted(self.places.values(), key=lambda o: o.place_id):
                if not q.confirmed or q.place_id == pid or _key(pid, q.place_id) in self.links:
                    continue
                d = self.distance(pid, q.place_id)
                if d >= p.inferred_link_max_m:
                    continue
                direction = math.atan2(q.y_m - y, q.x_m - x)
                if not clear_towards(heading, scan, direction, max(d - p.arrive_tolerance_m, 0.0),
                                     half_width_m=p.open_half_width_m, sample_step_m=p.sample_step_m):
                    continue
                self.links[_key(pid, q.place_id)] = Link(*_key(pid, q.place_id), INFERRED, p.confidence_initial)
                events.append(LinkInferredEvent(pid, q.place_id, d))
                if dist_traversed.get(q.place_id, math.inf) > p.loop_closing_path_m:
                    self.loop_queue.append((pid, q.place_id))
        return events

    def _predict_around(self, pid: int, heading: float, scan: SonarScan) -> list[Event]:
        """Predict places around confirmed place ``pid`` in the directions ``scan`` (taken at compass
        ``heading``) shows open, unless a place is already near."""
        p = self.params
        x, y = self.places[pid].x_m, self.places[pid].y_m
        events: list[Event] = []
        for direction in open_directions(heading, scan, directions=p.directions, length_m=p.open_distance_m,
                                         half_width_m=p.open_half_width_m, sample_step_m=p.sample_step_m,
                                         edge_length_m=p.open_edge_distance_m):
            cx, cy = x + p.place_spacing_m * math.cos(direction), y + p.place_spacing_m * math.sin(direction)
            if any(math.hypot(o.x_m - cx, o.y_m - cy) < p.min_place_separation_m for o in self.places.values()):
                continue
            new = self._new_id()
            self.places[new] = Place(new, cx, cy, False, pid)
            self.links[_key(pid, new)] = Link(*_key(pid, new), PREDICTED, p.confidence_initial)
            events.append(PlacePredictedEvent(new, cx, cy, pid))
        return events

    def _plan(self, now_s: float) -> list[Event]:
        """Choose the next leg: a pending loop-closing link first, else towards the nearest predicted place."""
        source = self.last_place
        graph = self.graph()
        dist, prev = dijkstra(graph, source)
        while self.loop_queue:
            a, b = self.loop_queue[0]
            if _key(a, b) not in self.links or a not in self.places or b not in self.places:
                self.loop_queue.pop(0)
                continue
            if a == source:
                self._start_leg((a, b), b, now_s)
                return []
            path = path_to(prev, source, a)
            if len(path) < 2:
                self.loop_queue.pop(0)
                continue
            self._start_leg((path[0], path[1]), b, now_s)
            return []
        predicted = [pid for pid, p in self.places.items() if not p.confirmed and pid in dist]
        if not predicted:
            events = self._prune()
            self.complete = not any(not p.confirmed for p in self.places.values())
            self.target = NO_PLACE
            return events
        goal = min(predicted, key=lambda pid: (dist[pid], pid))
        path = path_to(prev, source, goal)
        self._start_leg((path[0], path[1]), goal, now_s)
        return []

    def _start_leg(self, leg: tuple[int, int], target: int, now_s: float) -> None:
        self.leg = leg
        self.target = target
        self._leg_start_s = now_s
        self._blocked_since = None
        self._progress_best_m, self._progress_since_s = math.inf, now_s

    def _output(self, events: list[Event], now_s: float, pose: Pose2) -> ExplorerOutput:
        p = self.params
        # (a deleted place is no longer gone back to: _delete_place clears it)
        if self._via != NO_PLACE and self.distance_to(self._via) <= 0.5 * p.back_to_start_m:
            self._via = NO_PLACE
            if self.leg is not None:  # the leg's end from here: its progress counted afresh
                self._progress_best_m, self._progress_since_s = math.inf, now_s
        if self.leg is not None and self.robot_xy is not None:
            goal = self.places[self.leg[1] if self._via == NO_PLACE else self._via]
            scan = self._scan_in_heading(pose.heading_rad)
            cmd = velocity_command(
                self.robot_xy[0], self.robot_xy[1], pose.heading_rad, goal.x_m, goal.y_m, scan,
                max_speed_mps=p.max_speed_mps, max_turn_radps=p.max_turn_radps, heading_gain=p.heading_gain,
                turn_in_place_rad=p.turn_in_place_rad, stop_distance_m=p.stop_distance_m,
                slow_distance_m=p.slow_distance_m, avoid_distance_m=p.avoid_distance_m,
                avoid_gain=p.avoid_gain, front_half_angle_rad=p.front_half_angle_rad,
            )
            if cmd.blocked:
                self._blocked_since = now_s if self._blocked_since is None else self._blocked_since
            else:
                self._blocked_since = None
            cmd = self._unstall(now_s, pose, cmd, scan)
        else:
            cmd = Command(0.0, 0.0, False, math.inf)
            self._moving.clear()
        counts = self._counts
        if events or counts is None or counts[:2] != (len(self.places), len(self.links)):
            # counted again only when something changed: every change of a step comes with an event
            counts = self._counts = (len(self.places), len(self.links),
                                     sum(1 for q in self.places.values() if q.confirmed),
                                     sum(1 for k in self.links.values() if k.kind != PREDICTED))
        confirmed = counts[2]
        status = ExplorerStatus(complete=self.complete, confirmed=confirmed,
                                predicted=len(self.places) - confirmed,
                                target_id=self.target if self.leg is not None else NO_PLACE)
        diag = {"links": float(counts[3]),
                "loop_queue": float(len(self.loop_queue)), "leg_age_s": now_s - self._leg_start_s
                if self.leg is not None else 0.0, "stalls": float(self.stalls)}
        return ExplorerOutput(events=tuple(events), command=cmd, status=status, diagnostics=diag)

    def _scan_in_heading(self, heading_rad: float) -> SonarScan | None:
        """The last scan with its bearings turned to the current heading (it was taken at another)."""
        scan = self._last_scan
        turn = wrap_angle(self._scan_heading - heading_rad)
        if scan is None or turn == 0.0:
            return scan
        return msgspec.structs.replace(scan, angles_rad=[a + turn for a in scan.angles_rad])

    def _unstall(self, now_s: float, pose: Pose2, cmd: Command, scan: SonarScan | None) -> Command:
        """Back away from an obstacle the sonar missed when forward commands make no progress.

        A stall: for ``stall_window_s`` every command asked at least ``stall_min_speed_mps`` forward
        and dead reckoning moved less than ``stall_distance_m``. The robot then backs off at
        ``recover_speed_mps`` (unless the rear sector is closer than ``rear_clearance_m``) while
        turning away from the side of the nearest echo, for ``recover_s``.
        """
        p = self.params
        if now_s < self._recover_until:
            return Command(self._recover_cmd[0], self._recover_cmd[1], cmd.blocked, cmd.front_clearance_m)
        if cmd.v_mps < p.stall_min_speed_mps:
            self._moving.clear()
            return cmd
        self._moving.append((now_s, pose.x_m, pose.y_m))
        t0, x0, y0 = self._moving[0]
        while len(self._moving) > 1 and now_s - self._moving[1][0] >= p.stall_window_s:
            self._moving.popleft()
            t0, x0, y0 = self._moving[0]
        if now_s - t0 < p.stall_window_s or math.hypot(pose.x_m - x0, pose.y_m - y0) >= p.stall_distance_m:
            return cmd
        self.stalls += 1
        self._moving.clear()
        v, w = -p.recover_speed_mps, 0.0
        if scan is not None and len(scan.ranges_m):
            angles = wrap_angle(np.asarray(scan.angles_rad, dtype=float))
            ranges = np.asarray(scan.ranges_m, dtype=float)
            nearest = float(angles[int(np.argmin(ranges))])
            w = -p.recover_turn_radps if nearest > 0 else p.recover_turn_radps
            rear = np.abs(angles) > 2.0 * math.pi / 3.0
            if rear.any() and float(ranges[rear].min()) < p.rear_clearance_m:
                v = 0.0
        self._recover_until = now_s + p.recover_s
        self._recover_cmd = (v, w)
        return Command(v, w, cmd.blocked, cmd.front_clearance_m)
