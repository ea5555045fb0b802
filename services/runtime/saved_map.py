"""What a service that continues a saved run asks the relaxer: the map, the scans, where the robot was."""

from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass

import zenoh

from messages import topics
from messages.types import MapGraph, PlaceScan, ScanSet, SonarScan
from services.runtime.client import AliveWatcher, query
from services.runtime.errors import QueryFailed
from services.runtime.service import finite_float, nonnegative_int

log = logging.getLogger("relaxmap.runtime")

LATEST_SCANS = 50  # the robot's place is that of the latest of these scans whose place is in the map


class NoSavedMap(RuntimeError):
    """The relaxer holds nothing to continue (no place, or no scan taken at a place), or did not answer."""


@dataclass(frozen=True)
class RobotAt:
    """Where the robot was: at a place, with its offset from the centre (robot minus centre), and its
    dead-reckoned position then; later dead-reckoned poses move it on from there."""

    place_id: int
    offset_xy: tuple[float, float]
    dr_xy: tuple[float, float]


@dataclass(frozen=True)
class SavedMap:
    """The relaxer's map as a continued run starts."""

    graph: MapGraph  # places (relaxed coordinates) and traversed links
    near: list[PlaceScan]  # every scan taken within ``near_m`` of its place's centre, oldest first
    latest: PlaceScan  # the robot's latest scan at a place of the map (its heading, its ranges)
    robot: RobotAt  # where the robot was


def fetch_saved_map(session: zenoh.Session, robot: str = topics.DEFAULT_ROBOT, *, near_m: float,
                    at: RobotAt | None = None, timeout_s: float = 600.0) -> SavedMap:
    """Wait for the relaxer, then ask it for the map and the scans a continued run needs.

    The robot is ``at`` (the recognizer's last localization, as the launcher heard it) when its place
    is in the map; else where the latest scan at a place puts it (a scan the relaxer kept with the
    place nearest by dead reckoning, when the recognizer was not sure: the poorer guess).

    A relaxer resuming a large map takes a while to come alive (it re-integrates every stored scan
    into its grids): ``timeout_s`` allows for it.

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
    latest = at_places[-1]
    if at is None or at.place_id not in ids:
        if at is not None:
            log.warning("saved map: the robot's place %d is not in the map: placing it by the latest scan",
                        at.place_id)
        at = RobotAt(place_id=latest.place_id, offset_xy=(latest.offset_x_m, latest.offset_y_m),
                     dr_xy=(latest.dr_x_m, latest.dr_y_m))
    log.info("saved map: %d places, %d links, %d scans near their place; robot last at place %d",
             len(ids), len(graph.links), len(near.scans), at.place_id)
    return SavedMap(graph=graph, near=[s for s in near.scans if s.place_id in ids], latest=latest, robot=at)


def add_resume_arguments(parser: argparse.ArgumentParser) -> None:
    """``--resume`` and where the robot was (``--resume-place --resume-offset --resume-dr``)."""
    parser.add_argument("--resume", action="store_true",
                        help="continue the map the relaxer holds (asked over the bus before the start)")
    parser.add_argument("--resume-place", type=nonnegative_int, default=None, metavar="ID",
                        help="with --resume: the place the robot was last localised at")
    parser.add_argument("--resume-offset", type=finite_float, nargs=2, default=(0.0, 0.0), metavar=("X", "Y"),
                        help="... its offset from the place's centre then (robot minus centre)")
    parser.add_argument("--resume-dr", type=finite_float, nargs=2, default=None, metavar=("X", "Y"),
                        help="... and its dead-reckoned position then")


def robot_at_from_args(args: argparse.Namespace) -> RobotAt | None:
    """``RobotAt`` from ``--resume-place --resume-offset --resume-dr`` (None unless place and position are given)."""
    if args.resume_place is None or args.resume_dr is None:
        return None
    return RobotAt(place_id=args.resume_place, offset_xy=tuple(args.resume_offset), dr_xy=tuple(args.resume_dr))


def sonar_scan(scan: PlaceScan, *, seq: int = 0, min_range_m: float = 0.0) -> SonarScan:
    """A stored scan as the sonar message it was (the store keeps no minimum range)."""
    return SonarScan(stamp=scan.stamp, seq=seq, angles_rad=list(scan.angles_rad), ranges_m=list(scan.ranges_m),
                     beam_width_rad=scan.beam_width_rad, min_range_m=min_range_m, max_range_m=scan.max_range_m)
