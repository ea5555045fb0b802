"""The relaxer on the bus: places and links in, one relaxation cycle per update, map updates out."""

from __future__ import annotations

import logging
import threading
import time
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
    settle_after_s: float = 2.0  # wall time without a map event after which the map is solved exactly: a
    # pause, not the gap between two events (exact solves fed back that often make worse maps, docs/relaxer.md)
    online: OnlineParams = OnlineParams()


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
    heard = {"link_seq": -1, "confirmed_seq": -1}  # the latest link and place confirmation taken in, named in
    # every update: a recognizer or explorer following the map waits for the update that holds its input
    with Node(session, "relaxer", robot=robot) as node:
        pub = node.publisher(topics.map_update(robot), MapUpdate)

        def apply(outcome: CycleOutcome, t0: float) -> None:
            last_event[0] = time.monotonic()
            store.commit(outcome.tx)
            if outcome.update is not None:
                pub.put(msgspec.structs.replace(outcome.update, **heard))
                core.cycle_ms.append((time.perf_counter() - t0) * 1e3)
            node.detail.update(places=core.relaxer.graph.n_places, links=len(core.links), version=core.version,
                               pending_links=len(core._pending), scans=len(core.scans))

        def on_confirmed(msg: PlaceConfirmed) -> None:
            t0 = time.perf_counter()
            heard["confirmed_seq"] = max(heard["confirmed_seq"], msg.seq)
            apply(core.on_place_confirmed(msg), t0)

        def on_measured(msg: LinkMeasured) -> None:
            t0 = time.perf_counter()
            heard["link_seq"] = max(heard["link_seq"], msg.seq)
            apply(core.on_link_measured(msg), t0)

        def on_place_deleted(msg: PlaceDeleted) -> None:
            t0 = time.perf_counter()
            apply(core.on_place_deleted(msg.place_id, msg.stamp), t0)

        def on_link_deleted(msg: LinkDeleted) -> None:
            t0 = time.perf_counter()
            apply(core.on_link_deleted(msg.from_id, msg.to_id, msg.stamp), t0)

        def at_minimum() -> None:
            """Bring the map to its minimum if a sweep left it short (one exact solve, one update)."""
            t0 = time.perf_counter()
            outcome = core.settle()
            if outcome is not None:
                apply(outcome, t0)

        def settle() -> None:
            """Idle for ``settle_after_s``: the map at rest is its minimum."""
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
        node.subscribe(topics.places_confirmed(robot), PlaceConfirmed, on_confirmed, history=True)
        node.subscribe(topics.links_measured(robot), LinkMeasured, on_measured, history=True)
        node.subscribe(topics.places_deleted(robot), PlaceDeleted, on_place_deleted, history=True)
        node.subscribe(topics.links_deleted(robot), LinkDeleted, on_link_deleted, history=True)
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
