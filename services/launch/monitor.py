"""What the launcher hears of a run: progress for the bar, and the ground truth for the summary."""

from __future__ import annotations

import bisect
import threading
import time

import zenoh

from messages import topics
from messages.codec import DecodeError, codec
from messages.types import (
    ExplorationStatus,
    LinkDeleted,
    LinkInferred,
    LinkMeasured,
    MapUpdate,
    PlaceConfirmed,
    PlaceDeleted,
    TruthPose,
)


def _pair(a: int, b: int) -> tuple[int, int]:
    return (a, b) if a <= b else (b, a)


class RunMonitor:
    """Subscribes to the run's progress topics; every field is safe to read from another thread.

    Ground truth is kept here, in the launcher, and never reaches a mapping service: the true pose
    history gives each confirmed place its true position (the robot's at the confirmation stamp).
    """

    def __init__(self, session: zenoh.Session, robot: str) -> None:
        self._lock = threading.Lock()
        self.started = time.monotonic()
        self.sim_time_s = 0.0
        self.last_update: MapUpdate | None = None
        self.status: ExplorationStatus | None = None
        self._truth_t: list[float] = []
        self._truth_xy: list[tuple[float, float]] = []
        self.confirmed: dict[int, PlaceConfirmed] = {}
        self.deleted_places: set[int] = set()
        self.measured: set[tuple[int, int]] = set()
        self.inferred: set[tuple[int, int]] = set()
        self.deleted_links: set[tuple[int, int]] = set()
        self.decode_errors = 0
        self._last_event = time.monotonic()  # when the last map event (place or link) was heard
        handlers = {
            topics.truth_pose(robot): (TruthPose, self._on_truth),
            topics.map_update(robot): (MapUpdate, self._on_update),
            topics.exploration_status(robot): (ExplorationStatus, self._on_status),
            topics.places_confirmed(robot): (PlaceConfirmed, self._on_confirmed),
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
        self._truth_xy.insert(i, (msg.pose.x_m, msg.pose.y_m))

    def _on_update(self, msg: MapUpdate) -> None:
        if self.last_update is None or msg.version >= self.last_update.version:
            self.last_update = msg

    def _on_status(self, msg: ExplorationStatus) -> None:
        self.status = msg

    def _on_confirmed(self, msg: PlaceConfirmed) -> None:
        self._last_event = time.monotonic()
        self.confirmed.setdefault(msg.place_id, msg)

    def _on_place_deleted(self, msg: PlaceDeleted) -> None:
        self._last_event = time.monotonic()
        self.deleted_places.add(msg.place_id)

    def _on_measured(self, msg: LinkMeasured) -> None:
        self._last_event = time.monotonic()
        self.measured.add(_pair(msg.from_id, msg.to_id))

    def _on_inferred(self, msg: LinkInferred) -> None:
        self.inferred.add(_pair(msg.from_id, msg.to_id))

    def _on_link_deleted(self, msg: LinkDeleted) -> None:
        self._last_event = time.monotonic()
        self.inferred.discard(_pair(msg.from_id, msg.to_id))
        self.deleted_links.add(_pair(msg.from_id, msg.to_id))

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
        """True position of every confirmed place that was not deleted."""
        with self._lock:
            out = {}
            for pid, msg in self.confirmed.items():
                if pid in self.deleted_places or not self._truth_t:
                    continue
                i = min(max(bisect.bisect(self._truth_t, msg.stamp) - 1, 0), len(self._truth_t) - 1)
                out[pid] = self._truth_xy[i]
            return out

    def place_dead_reckoning(self) -> dict[int, tuple[float, float]]:
        """Coordinates of every confirmed place as first confirmed (compass dead reckoning)."""
        with self._lock:
            return {pid: (m.x_m, m.y_m) for pid, m in self.confirmed.items() if pid not in self.deleted_places}

    def links_lost(self, in_map: set[tuple[int, int]]) -> set[tuple[int, int]]:
        """Measured links missing from ``in_map`` that were not deleted on purpose (nor their places)."""
        with self._lock:
            return {p for p in self.measured - in_map - self.deleted_links
                    if p[0] not in self.deleted_places and p[1] not in self.deleted_places}

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
