"""What a service that continues a saved run asks the relaxer: the map, the scans, where the robot was."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import zenoh

from messages import topics
from messages.types import MapGraph, PlaceScan, ScanSet, SonarScan
from services.runtime.client import AliveWatcher, query
from services.runtime.errors import QueryFailed

log = logging.getLogger("relaxmap.runtime")

LATEST_SCANS = 50  # the robot's place is that of the latest of these scans whose place is in the map


class NoSavedMap(RuntimeError):
    """The relaxer holds nothing to continue (no place, or no scan taken at a place), or did not answer."""


@dataclass(frozen=True)
class SavedMap:
    """The relaxer's map as a continued run starts."""

    graph: MapGraph  # places (relaxed coordinates) and traversed links
    near: list[PlaceScan]  # every scan taken within ``near_m`` of its place's centre, oldest first
    latest: PlaceScan  # the robot's latest scan at a place of the map: where it was, by dead reckoning too


def fetch_saved_map(session: zenoh.Session, robot: str = topics.DEFAULT_ROBOT, *, near_m: float,
                    timeout_s: float = 60.0) -> SavedMap:
    """Wait for the relaxer, then ask it for the map and the scans a continued run needs.

    Raises
    ------
    NoSavedMap
        Saying why: the relaxer is not alive within ``timeout_s``, a query failed, or the map holds
        no place or no scan of one.
    """
    watcher = AliveWatcher(session, robot)
    try:
        if not watcher.wait_alive(["relaxer"], timeout_s):
            raise NoSavedMap(f"the relaxer is not alive after {timeout_s:g} s")
    finally:
        watcher.close()
    try:
        graph = query(session, topics.map_graph(robot), type_=MapGraph, timeout_s=timeout_s)
        near = query(session, topics.map_scans(robot), {"max_offset": near_m}, type_=ScanSet, timeout_s=timeout_s)
        recent = query(session, topics.map_scans(robot), {"latest": LATEST_SCANS}, type_=ScanSet,
                       timeout_s=timeout_s)
    except QueryFailed as e:
        raise NoSavedMap(str(e)) from e
    ids = {p.place_id for p in graph.places}
    if not ids:
        raise NoSavedMap("the relaxer's map holds no place")
    at_places = [s for s in recent.scans if s.place_id in ids]
    if not at_places:
        raise NoSavedMap(f"none of the latest {LATEST_SCANS} scans was taken at a place of the map")
    log.info("saved map: %d places, %d links, %d scans near their place; robot last at place %d",
             len(ids), len(graph.links), len(near.scans), at_places[-1].place_id)
    return SavedMap(graph=graph, near=[s for s in near.scans if s.place_id in ids], latest=at_places[-1])


def sonar_scan(scan: PlaceScan, *, seq: int = 0, min_range_m: float = 0.0) -> SonarScan:
    """A stored scan as the sonar message it was (the store keeps no minimum range)."""
    return SonarScan(stamp=scan.stamp, seq=seq, angles_rad=list(scan.angles_rad), ranges_m=list(scan.ranges_m),
                     beam_width_rad=scan.beam_width_rad, min_range_m=min_range_m, max_range_m=scan.max_range_m)
