"""The relaxer on the bus: places and links in, one relaxation cycle per update, map updates out."""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from pathlib import Path

import msgspec
import numpy as np
import zenoh

from messages import topics
from messages.types import (
    LinkDeleted,
    LinkMeasured,
    LocalizationBelief,
    MapUpdate,
    PlaceConfirmed,
    PlaceDeleted,
    SonarScan,
    VelocityCommand,
)
from services.relaxer.online import CycleOutcome, OnlineMap, OnlineParams, UnknownPlace
from services.relaxer.store import MapStore, StoredScan
from services.runtime import Node, QueryError, QueryParams

log = logging.getLogger("relaxmap.relaxer")


class RelaxerParams(msgspec.Struct, frozen=True, kw_only=True):
    """Parameters of the relaxer node."""

    store_path: str = "relaxmap-map.sqlite"  # the SQLite file of the map (created if missing)
    seed: int = 0  # seed of the noise estimator's posterior samples
    min_belief_for_scan: float = 0.5  # a sonar scan is kept for the grid when localised this surely
    pairing_window: int = 32  # scans (and beliefs) kept while their partner of the same stamp is awaited
    max_grid_cells: int = 4_000_000  # a grid query that would need more cells is refused
    settle_after_s: float = 2.0  # wall time without a map event or a velocity command after which the map is
    # solved exactly: a pause, not the gap between two events (exact solves fed back that often make worse
    # maps, docs/relaxer.md), and never while a lockstep clock runs
    order_timeout_s: float = 0.5  # wall time an explorer event waits for the velocity command that names it
    online: OnlineParams = OnlineParams()


ExplorerEvent = PlaceConfirmed | PlaceDeleted | LinkDeleted
_KIND = {PlaceConfirmed: 0, PlaceDeleted: 1, LinkDeleted: 2}


class ExplorerEvents:
    """The explorer's map events, applied in the groups its velocity commands close.

    The explorer publishes the place confirmations and the place and link deletions of one step on
    three keys, then the step's velocity command, which names the latest seq of each
    (``confirmed_seq``, ``deleted_seq``, ``links_deleted_seq``); zenoh keeps the order of one key's
    messages, not across keys. Once a command has been heard, the events up to the seqs it names are
    applied together when all of them are in, so the map does not depend on the order they came in.
    Before the first command (a relaxer fed by something other than the explorer, or the explorer's
    first step) each event is applied as it comes; events that no command names within
    ``timeout_s`` of wall time (the explorer died, or is not driving a clock) are applied then, counted.
    """

    def __init__(self, timeout_s: float, clock=time.monotonic) -> None:
        self.timeout_s = timeout_s
        self._clock = clock
        self._waiting: list[tuple[ExplorerEvent, float]] = []  # heard, not yet applied, with the wall time
        self._due: deque[tuple[list[int], float]] = deque()  # seqs named by commands not yet applied
        self.heard = [-1, -1, -1]  # highest seq heard: confirmations, place deletions, link deletions
        self.applied = [-1, -1, -1]  # ... applied
        self._named = [-1, -1, -1]  # ... named by a command
        self.commands = False  # a command has been heard: events wait for theirs
        self.timeouts = 0

    def add(self, msg: ExplorerEvent) -> None:
        k = _KIND[type(msg)]
        self.heard[k] = max(self.heard[k], msg.seq)
        self._waiting.append((msg, self._clock()))

    def command(self, msg: VelocityCommand) -> None:
        named = [msg.confirmed_seq, msg.deleted_seq, msg.links_deleted_seq]
        self.commands = True
        if any(n > m for n, m in zip(named, self._named)):
            self._named = [max(n, m) for n, m in zip(named, self._named)]
            self._due.append((named, self._clock()))

    def ready(self) -> list[list[ExplorerEvent]]:
        """The groups of events to apply now, in order (each group relaxed by one cycle)."""
        out: list[list[ExplorerEvent]] = []
        if not self.commands:
            for m, _ in self._waiting:
                k = _KIND[type(m)]
                self.applied[k] = max(self.applied[k], m.seq)
                out.append([m])
            self._waiting = []
        for m, _ in self._waiting:
            if m.seq <= self.applied[_KIND[type(m)]]:
                out.append([m])  # heard again (history after a restart): at once
        self._waiting = [(m, t) for m, t in self._waiting if m.seq > self.applied[_KIND[type(m)]]]
        now = self._clock()
        while self._due:
            named, since = self._due[0]
            if any(h < n for h, n in zip(self.heard, named)) and now - since < self.timeout_s:
                break
            self.timeouts += any(h < n for h, n in zip(self.heard, named))
            self._due.popleft()
            out.append(self._take(named))
        if self._waiting and now - min(t for _, t in self._waiting) >= self.timeout_s:
            self.timeouts += 1  # named by no command in time
            out.append(self._take([max([self.applied[k]] + [m.seq for m, _ in self._waiting if _KIND[type(m)] == k])
                                   for k in range(3)]))
        return [g for g in out if g]

    def _take(self, named: list[int]) -> list[ExplorerEvent]:
        group = [m for m, _ in self._waiting if m.seq <= named[_KIND[type(m)]]]
        self._waiting = [(m, t) for m, t in self._waiting if m.seq > named[_KIND[type(m)]]]
        self.applied = [max(a, n) for a, n in zip(self.applied, named)]
        return group


def run(session: zenoh.Session, params: RelaxerParams, *, robot: str = topics.DEFAULT_ROBOT,
        stop: threading.Event) -> None:
    store = MapStore(Path(params.store_path))
    stored = store.load()
    core = OnlineMap(params.online, stored, rng=np.random.default_rng(params.seed))
    core.load_scans(store.scans())
    if stored.places:
        log.info("resumed %d places, %d links, version %d from %s", len(stored.places), len(stored.links),
                 stored.version, params.store_path)
    scans: dict[int, SonarScan] = {}  # sonar scans awaiting their belief, by stamp in microseconds
    beliefs: dict[int, LocalizationBelief] = {}  # beliefs awaiting their scan
    last_event = [time.monotonic()]
    heard = {"link_seq": -1}  # the latest link taken in, named in every update with the explorer's events
    # applied: a recognizer or explorer following the map waits for the update that holds its input
    events = ExplorerEvents(params.order_timeout_s)
    with Node(session, "relaxer", robot=robot) as node:
        pub = node.publisher(topics.map_update(robot), MapUpdate)

        def apply(outcome: CycleOutcome, t0: float) -> None:
            last_event[0] = time.monotonic()
            store.commit(outcome.tx)
            if outcome.update is not None:
                c, d, ld = events.applied
                pub.put(msgspec.structs.replace(outcome.update, **heard, confirmed_seq=c, deleted_seq=d,
                                                links_deleted_seq=ld))
                core.cycle_ms.append((time.perf_counter() - t0) * 1e3)
            node.detail.update(places=core.relaxer.graph.n_places, links=len(core.links), version=core.version,
                               pending_links=len(core._pending), scans=len(core.scans),
                               order_timeouts=events.timeouts)

        def apply_events() -> None:
            for group in events.ready():
                t0 = time.perf_counter()
                apply(core.on_explorer_events(group, max(m.stamp for m in group)), t0)

        def on_event(msg: PlaceConfirmed | PlaceDeleted | LinkDeleted) -> None:
            if isinstance(msg, PlaceConfirmed):
                core.check_place(msg)  # a bad one is refused here, counted by the node
            events.add(msg)
            apply_events()

        def on_command(msg: VelocityCommand) -> None:
            last_event[0] = time.monotonic()  # the clock runs: no settling
            events.command(msg)
            apply_events()

        def on_measured(msg: LinkMeasured) -> None:
            t0 = time.perf_counter()
            heard["link_seq"] = max(heard["link_seq"], msg.seq)
            apply(core.on_link_measured(msg), t0)

        def at_minimum() -> None:
            """Bring the map to its minimum if a sweep left it short (one exact solve, one update)."""
            t0 = time.perf_counter()
            outcome = core.settle()
            if outcome is not None:
                apply(outcome, t0)

        def settle() -> None:
            """Idle for ``settle_after_s``: the map at rest is its minimum. Also applies explorer events
            whose command is overdue."""
            apply_events()
            if time.monotonic() - last_event[0] >= params.settle_after_s:
                at_minimum()

        # a scan and the belief of the same stamp (the recognizer's, which carries the scan's
        # dead-reckoned pose) make one stored scan, in whichever order they come
        def on_belief(msg: LocalizationBelief) -> None:
            scan = scans.pop(round(msg.stamp * 1e6), None)
            if scan is None:
                wait(beliefs, msg)
            else:
                keep_scan(scan, msg)

        def on_sonar(msg: SonarScan) -> None:
            belief = beliefs.pop(round(msg.stamp * 1e6), None)
            if belief is None:
                wait(scans, msg)
            else:
                keep_scan(msg, belief)

        def wait(waiting: dict, msg: SonarScan | LocalizationBelief) -> None:
            waiting[round(msg.stamp * 1e6)] = msg
            while len(waiting) > params.pairing_window:
                del waiting[min(waiting)]  # its partner never came (a scan the recognizer could not pair)

        def keep_scan(msg: SonarScan, belief: LocalizationBelief) -> None:
            """Keep the scan for the grid, with the place it was taken at and the offset from it."""
            if belief.pose is None:
                return
            pose = belief.pose
            if belief.place_id >= 0 and belief.probability >= params.min_belief_for_scan:
                place = (belief.place_id, belief.offset_x_m, belief.offset_y_m)  # the recognizer's offset
            else:
                place = core.anchor(pose.x_m, pose.y_m)  # the nearest place, offset by dead reckoning
            if place is None:
                return
            scan = StoredScan(msg.stamp, *place, pose.x_m, pose.y_m, pose.heading_rad, msg.angles_rad, msg.ranges_m,
                              msg.beam_width_rad, msg.max_range_m)
            store.commit(core.add_scan(scan))

        # -- queries --------------------------------------------------------------------------------
        def q_graph(_key: str, _p: QueryParams):
            at_minimum()  # the map asked for whole (written at a run's end) is the minimum, whatever the timing
            return core.graph()

        def q_place(key: str, _p: QueryParams):
            raw = key.rsplit("/", 1)[-1]
            try:
                pid = int(raw)
            except ValueError:
                raise QueryError(f"place id must be an integer, got {raw[:40]!r}") from None
            try:
                return core.place(pid)
            except UnknownPlace as e:
                raise QueryError(e.args[0]) from None

        def q_path(_key: str, p: QueryParams):
            a, b = p.int("from"), p.int("to")
            try:
                path = core.path(a, b)
            except UnknownPlace as e:
                raise QueryError(e.args[0]) from None
            if path is None:
                raise QueryError(f"no path from place {a} to place {b}: they are in unconnected parts")
            return path

        def q_grid(_key: str, p: QueryParams):
            res = p.float("resolution", params.online.grid_resolution_m, min_value=0.02, max_value=5.0)
            frame = p.str("frame", "relaxed", choices=("relaxed", "dead_reckoning"))
            try:
                return core.grid(res, frame, max_cells=params.max_grid_cells)
            except ValueError as e:
                raise QueryError(str(e)) from None

        def q_stats(_key: str, _p: QueryParams):
            return core.stats()

        def q_scans(_key: str, p: QueryParams):
            place = p.int("place", min_value=0) if "place" in p else None
            max_offset = p.float("max_offset", min_value=0.0) if "max_offset" in p else None
            latest = p.int("latest", min_value=0) if "latest" in p else None
            try:
                return core.scan_set(place_id=place, max_offset_m=max_offset, latest=latest)
            except UnknownPlace as e:
                raise QueryError(e.args[0]) from None

        # the map's events with history: a relaxer that starts late or restarts hears all of them
        node.subscribe(topics.places_confirmed(robot), PlaceConfirmed, on_event, history=True)
        node.subscribe(topics.links_measured(robot), LinkMeasured, on_measured, history=True)
        node.subscribe(topics.places_deleted(robot), PlaceDeleted, on_event, history=True)
        node.subscribe(topics.links_deleted(robot), LinkDeleted, on_event, history=True)
        node.subscribe(topics.cmd_velocity(robot), VelocityCommand, on_command)
        node.subscribe(topics.localization(robot), LocalizationBelief, on_belief)
        node.subscribe(topics.sonar(robot), SonarScan, on_sonar)
        node.queryable(topics.map_graph(robot), q_graph)
        node.queryable(topics.map_place(robot, "*"), q_place)
        node.queryable(topics.map_path(robot), q_path, params=("from", "to"))
        node.queryable(topics.map_grid(robot), q_grid, params=("resolution", "frame"))
        node.queryable(topics.map_stats(robot), q_stats)
        node.queryable(topics.map_scans(robot), q_scans, params=("place", "max_offset", "latest"))
        node.spin(stop, tick=settle)
    store.close()
