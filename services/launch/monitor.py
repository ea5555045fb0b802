"""What the launcher hears of a run: progress for the bar, and the ground truth for the summary."""

from __future__ import annotations

import bisect
import math
import threading
import time

import msgspec
import zenoh

from messages import topics
from messages.codec import DecodeError, codec
from messages.types import (
    DeadReckonedPose,
    ExplorationStatus,
    LinkDeleted,
    LinkInferred,
    LinkMeasured,
    LocalizationBelief,
    MapUpdate,
    PlaceConfirmed,
    PlaceDeleted,
    PlacePredicted,
    TruthPose,
)


def _latest_at(times: list[float], stamp: float) -> int:
    """Index of the latest of the sorted ``times`` at or before ``stamp`` (the first one if all are later)."""
    return min(max(bisect.bisect(times, stamp + 1e-9) - 1, 0), len(times) - 1)


def _pair(a: int, b: int) -> tuple[int, int]:
    return (a, b) if a <= b else (b, a)


class RobotState(msgspec.Struct, frozen=True, kw_only=True):
    """Where the robot was at the last dead-reckoned pose of a run: true and dead-reckoned."""

    stamp: float  # simulated time of that pose
    tick: int  # the simulator's tick of that time
    truth: tuple[float, float, float]  # true x_m, y_m, heading_rad at the same tick
    dr_xy: tuple[float, float]  # compass dead-reckoned position
    dr_raw: tuple[float, float, float]  # raw odometry pose
    steps: int  # odometry steps integrated
    path_length_m: float  # distance integrated
    fix: PlaceFixState | None = None  # the last localization at a place (None: none was heard)


class PlaceFixState(msgspec.Struct, frozen=True, kw_only=True):
    """The recognizer's last localization at a place, with the dead-reckoned position of its stamp: the
    robot's map position is the place's centre plus the offset, moved on by dead reckoning since."""

    stamp: float
    place_id: int
    offset_xy: tuple[float, float]  # robot minus place centre
    dr_xy: tuple[float, float]  # compass dead-reckoned position at ``stamp``


class SavedPlace(msgspec.Struct, frozen=True, kw_only=True):
    """A place of an earlier part: its true position and its coordinates when first confirmed."""

    place_id: int
    truth: tuple[float, float]
    dead_reckoning: tuple[float, float]


class MonitorState(msgspec.Struct, frozen=True, kw_only=True):
    """The monitor's counts at the end of a run, for the part that continues it (in run.json)."""

    sim_time_s: float
    max_place_id: int
    places: list[SavedPlace]
    deleted_places: list[int]
    measured: list[tuple[int, int]]
    inferred: list[tuple[int, int]]
    deleted_links: list[tuple[int, int]]
    robot: RobotState | None = None  # None: no dead-reckoned pose was heard


class RunMonitor:
    """Subscribes to the run's progress topics; every field is safe to read from another thread.

    Ground truth is kept here, in the launcher, and never reaches a mapping service: the true pose
    history gives each confirmed place its true position (the robot's at the confirmation stamp).
    What a continued run needs of an earlier part (``saved_state``, ``restore``) is kept as well:
    the links measured and deleted, the places' true and first positions, the highest place id used,
    and where the robot was (true and dead-reckoned pose of the same tick).
    """

    def __init__(self, session: zenoh.Session, robot: str) -> None:
        self._lock = threading.Lock()
        self.started = time.monotonic()
        self.sim_time_s = 0.0
        self.last_update: MapUpdate | None = None
        self.status: ExplorationStatus | None = None
        self._truth_t: list[float] = []
        self._truth_pose: list[tuple[float, float, float]] = []
        self._truth_tick: list[int] = []
        self._last_dr: DeadReckonedPose | None = None
        self._dr_t: list[float] = []  # every compass dead-reckoned position, by stamp
        self._dr_xy: list[tuple[float, float]] = []
        self._last_fix: LocalizationBelief | None = None
        self.max_place_id = -1  # the highest place id heard of (predicted, confirmed or deleted)
        self._saved_truth: dict[int, tuple[float, float]] = {}  # places of earlier parts of the run
        self._saved_dr: dict[int, tuple[float, float]] = {}
        self.confirmed: dict[int, PlaceConfirmed] = {}
        self.deleted_places: set[int] = set()
        self.measured: set[tuple[int, int]] = set()
        self.inferred: set[tuple[int, int]] = set()
        self.deleted_links: set[tuple[int, int]] = set()  # deleted after their latest measurement
        self._measured_at: dict[tuple[int, int], float] = {}  # latest measurement's stamp, this part of the run
        self._deleted_at: dict[tuple[int, int], float] = {}  # latest deletion's stamp
        self.decode_errors = 0
        self._last_event = time.monotonic()  # when the last map event (place or link) was heard
        handlers = {
            topics.truth_pose(robot): (TruthPose, self._on_truth),
            topics.map_update(robot): (MapUpdate, self._on_update),
            topics.exploration_status(robot): (ExplorationStatus, self._on_status),
            topics.places_predicted(robot): (PlacePredicted, self._on_predicted),
            topics.places_confirmed(robot): (PlaceConfirmed, self._on_confirmed),
            topics.dr_pose(robot): (DeadReckonedPose, self._on_dr),
            topics.localization(robot): (LocalizationBelief, self._on_localization),
            topics.places_deleted(robot): (PlaceDeleted, self._on_place_deleted),
            topics.links_measured(robot): (LinkMeasured, self._on_measured),
            topics.links_inferred(robot): (LinkInferred, self._on_inferred),
            topics.links_deleted(robot): (LinkDeleted, self._on_link_deleted),
        }
        self._subs = [session.declare_subscriber(key, self._decoder(t, fn)) for key, (t, fn) in handlers.items()]

    def _decoder(self, type_, fn):
        dec = codec(type_)

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                msg = dec.decode(sample.payload.to_bytes())
            except DecodeError:
                with self._lock:
                    self.decode_errors += 1
                return
            with self._lock:
                fn(msg)

        return on_sample

    def _on_truth(self, msg: TruthPose) -> None:
        self.sim_time_s = max(self.sim_time_s, msg.stamp)
        i = bisect.bisect(self._truth_t, msg.stamp)
        self._truth_t.insert(i, msg.stamp)
        self._truth_pose.insert(i, (msg.pose.x_m, msg.pose.y_m, msg.pose.heading_rad))
        self._truth_tick.insert(i, msg.seq)

    def _on_dr(self, msg: DeadReckonedPose) -> None:
        if self._last_dr is None or msg.stamp >= self._last_dr.stamp:
            self._last_dr = msg
        i = bisect.bisect(self._dr_t, msg.stamp)
        self._dr_t.insert(i, msg.stamp)
        self._dr_xy.insert(i, (msg.compass.x_m, msg.compass.y_m))

    def _on_localization(self, msg: LocalizationBelief) -> None:
        if msg.place_id >= 0 and (self._last_fix is None or msg.stamp >= self._last_fix.stamp):
            self._last_fix = msg

    def _fix_state(self) -> PlaceFixState | None:
        """The last localization at a place, with the dead-reckoned position of its stamp (if kept)."""
        f = self._last_fix
        if f is None or f.place_id in self.deleted_places:
            return None
        if not self._dr_t:
            return None
        i = _latest_at(self._dr_t, f.stamp)
        if abs(self._dr_t[i] - f.stamp) >= 1e-6:
            return None
        return PlaceFixState(stamp=f.stamp, place_id=f.place_id, offset_xy=(f.offset_x_m, f.offset_y_m),
                             dr_xy=self._dr_xy[i])

    def _on_predicted(self, msg: PlacePredicted) -> None:
        self.max_place_id = max(self.max_place_id, msg.place_id)

    def _on_update(self, msg: MapUpdate) -> None:
        if self.last_update is None or msg.version >= self.last_update.version:
            self.last_update = msg

    def _on_status(self, msg: ExplorationStatus) -> None:
        self.status = msg

    def _on_confirmed(self, msg: PlaceConfirmed) -> None:
        self._last_event = time.monotonic()
        self.confirmed.setdefault(msg.place_id, msg)
        self.max_place_id = max(self.max_place_id, msg.place_id)

    def _on_place_deleted(self, msg: PlaceDeleted) -> None:
        self._last_event = time.monotonic()
        self.deleted_places.add(msg.place_id)
        self.max_place_id = max(self.max_place_id, msg.place_id)

    def _on_measured(self, msg: LinkMeasured) -> None:
        self._last_event = time.monotonic()
        pair = _pair(msg.from_id, msg.to_id)
        self.measured.add(pair)
        self._measured_at[pair] = max(msg.stamp, self._measured_at.get(pair, -math.inf))
        if self._measured_at[pair] > self._deleted_at.get(pair, -math.inf):
            self.deleted_links.discard(pair)  # measured again after its deletion: the map must hold it

    def _on_inferred(self, msg: LinkInferred) -> None:
        self.inferred.add(_pair(msg.from_id, msg.to_id))

    def _on_link_deleted(self, msg: LinkDeleted) -> None:
        self._last_event = time.monotonic()
        pair = _pair(msg.from_id, msg.to_id)
        self.inferred.discard(pair)
        self._deleted_at[pair] = max(msg.stamp, self._deleted_at.get(pair, -math.inf))
        if self._deleted_at[pair] >= self._measured_at.get(pair, -math.inf):
            self.deleted_links.add(pair)

    # -- views ------------------------------------------------------------------------------------
    def progress(self) -> dict[str, float]:
        with self._lock:
            up = self.last_update
            wall = time.monotonic() - self.started
            return {"sim_time_s": self.sim_time_s, "wall_time_s": wall,
                    "places": up.places if up else 0, "links": up.links if up else 0,
                    "energy": up.energy if up else float("nan"),
                    "rtf": self.sim_time_s / wall if wall > 0 else 0.0,
                    "complete": bool(self.status and self.status.complete)}

    def map_counts(self) -> tuple[int, int]:
        """Places confirmed and links measured, less those deleted: what the relaxer's map should hold."""
        with self._lock:
            places = set(self.confirmed) - self.deleted_places
            links = {p for p in self.measured - self.deleted_links if p[0] in places and p[1] in places}
            return len(places), len(links)

    def quiet_s(self) -> float:
        """Seconds since the last map event was heard."""
        with self._lock:
            return time.monotonic() - self._last_event

    def place_truth(self) -> dict[int, tuple[float, float]]:
        """True position of every confirmed place that was not deleted (earlier parts' included)."""
        with self._lock:
            out = {pid: xy for pid, xy in self._saved_truth.items() if pid not in self.deleted_places}
            for pid, msg in self.confirmed.items():
                if pid in self.deleted_places or not self._truth_t:
                    continue
                out[pid] = self._truth_pose[_latest_at(self._truth_t, msg.stamp)][:2]
            return out


    def place_dead_reckoning(self) -> dict[int, tuple[float, float]]:
        """Where compass dead reckoning alone put every confirmed place: the dead-reckoned position at
        its confirmation stamp (the map of dead reckoning, as ``grid_dead_reckoning.png`` draws it)."""
        with self._lock:
            out = {pid: xy for pid, xy in self._saved_dr.items() if pid not in self.deleted_places}
            for pid, msg in self.confirmed.items():
                if pid in self.deleted_places or not self._dr_t:
                    continue
                out[pid] = self._dr_xy[_latest_at(self._dr_t, msg.stamp)]
            return out

    def links_lost(self, in_map: set[tuple[int, int]]) -> set[tuple[int, int]]:
        """Measured links missing from ``in_map`` that were not deleted on purpose (nor their places)."""
        with self._lock:
            return {p for p in self.measured - in_map - self.deleted_links
                    if p[0] not in self.deleted_places and p[1] not in self.deleted_places}

    def saved_state(self) -> MonitorState:
        """What a continued run needs to go on counting (see ``restore``)."""
        truth, dr = self.place_truth(), self.place_dead_reckoning()
        with self._lock:
            robot = None
            if self._last_dr is not None and self._truth_t:
                d = self._last_dr
                i = _latest_at(self._truth_t, d.stamp)
                robot = RobotState(
                    stamp=d.stamp, tick=self._truth_tick[i], truth=self._truth_pose[i],
                    dr_xy=(d.compass.x_m, d.compass.y_m),
                    dr_raw=(d.raw.x_m, d.raw.y_m, d.raw.heading_rad), steps=d.steps, path_length_m=d.path_length_m,
                    fix=self._fix_state())
            return MonitorState(
                sim_time_s=self.sim_time_s, max_place_id=self.max_place_id,
                places=[SavedPlace(place_id=pid, truth=truth[pid], dead_reckoning=dr[pid])
                        for pid in sorted(truth) if pid in dr],
                deleted_places=sorted(self.deleted_places), measured=sorted(self.measured),
                inferred=sorted(self.inferred), deleted_links=sorted(self.deleted_links), robot=robot)

    def restore(self, state: MonitorState) -> None:
        """Go on from an earlier part of the run: its links, places and simulated time count."""
        with self._lock:
            self.sim_time_s = max(self.sim_time_s, state.sim_time_s)
            self.max_place_id = max(self.max_place_id, state.max_place_id)
            self._saved_truth.update((p.place_id, p.truth) for p in state.places)
            self._saved_dr.update((p.place_id, p.dead_reckoning) for p in state.places)
            self.deleted_places.update(state.deleted_places)
            self.measured.update(_pair(*p) for p in state.measured)
            self.inferred.update(_pair(*p) for p in state.inferred)
            self.deleted_links.update(_pair(*p) for p in state.deleted_links)

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
