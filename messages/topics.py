"""Every key expression of relaxmap, built from the robot name: ``relaxmap/<robot>/<area>/<topic>``."""

from __future__ import annotations

ROOT = "relaxmap"
DEFAULT_ROBOT = "robot0"


def _key(robot: str, *parts: str) -> str:
    if not robot or any(c in robot for c in "/*$?#"):
        raise ValueError(f"bad robot name {robot!r}: must be non-empty, without / * $ ? #")
    return "/".join((ROOT, robot, *parts))


# sensors (sensor_sim)
def odometry(robot: str = DEFAULT_ROBOT) -> str:
    return _key(robot, "sensors", "odometry")


def compass(robot: str = DEFAULT_ROBOT) -> str:
    return _key(robot, "sensors", "compass")


def sonar(robot: str = DEFAULT_ROBOT) -> str:
    return _key(robot, "sensors", "sonar")


def truth_pose(robot: str = DEFAULT_ROBOT) -> str:
    return _key(robot, "truth", "pose")


# dead_reckoning
def dr_pose(robot: str = DEFAULT_ROBOT) -> str:
    return _key(robot, "dr", "pose")


# place_recognizer
def localization(robot: str = DEFAULT_ROBOT) -> str:
    return _key(robot, "places", "localization")


def recognizer_progress(robot: str = DEFAULT_ROBOT) -> str:
    return _key(robot, "places", "progress")


def links_measured(robot: str = DEFAULT_ROBOT) -> str:
    return _key(robot, "links", "measured")


# explorer
def places_predicted(robot: str = DEFAULT_ROBOT) -> str:
    return _key(robot, "places", "predicted")


def places_confirmed(robot: str = DEFAULT_ROBOT) -> str:
    return _key(robot, "places", "confirmed")


def places_deleted(robot: str = DEFAULT_ROBOT) -> str:
    return _key(robot, "places", "deleted")


def links_inferred(robot: str = DEFAULT_ROBOT) -> str:
    return _key(robot, "links", "inferred")


def links_confidence(robot: str = DEFAULT_ROBOT) -> str:
    return _key(robot, "links", "confidence")


def links_deleted(robot: str = DEFAULT_ROBOT) -> str:
    return _key(robot, "links", "deleted")


def cmd_velocity(robot: str = DEFAULT_ROBOT) -> str:
    return _key(robot, "cmd", "velocity")


def exploration_status(robot: str = DEFAULT_ROBOT) -> str:
    return _key(robot, "explore", "status")


# relaxer
def map_update(robot: str = DEFAULT_ROBOT) -> str:
    return _key(robot, "map", "update")


def map_graph(robot: str = DEFAULT_ROBOT) -> str:
    return _key(robot, "map", "graph")


def map_place(robot: str = DEFAULT_ROBOT, place_id: int | str = "*") -> str:
    return _key(robot, "map", "place", str(place_id))


def map_path(robot: str = DEFAULT_ROBOT) -> str:
    return _key(robot, "map", "path")


def map_grid(robot: str = DEFAULT_ROBOT) -> str:
    return _key(robot, "map", "grid")


def map_stats(robot: str = DEFAULT_ROBOT) -> str:
    return _key(robot, "map", "stats")


def map_scans(robot: str = DEFAULT_ROBOT) -> str:
    return _key(robot, "map", "scans")


# every service
def alive(robot: str = DEFAULT_ROBOT, service: str = "*") -> str:
    """Liveliness token of a service (``*`` for all)."""
    return _key(robot, "alive", service)


def health(robot: str = DEFAULT_ROBOT, service: str = "*") -> str:
    """Health queryable of a service (``*`` for all)."""
    return _key(robot, "health", service)


# The map's events: published with history (zenoh's advanced publisher) so that a service that starts
# late or restarts hears every one of them; this many are kept per topic.
MAP_EVENT_HISTORY = 1_000_000
MAP_EVENT_TOPICS = ("places_confirmed", "places_deleted", "links_measured", "links_deleted")


def all_topics(robot: str = DEFAULT_ROBOT) -> dict[str, str]:
    """Name -> key expression of every fixed topic (queryables included), for checks and tools."""
    fns = (
        odometry, compass, sonar, truth_pose, dr_pose, localization, recognizer_progress, links_measured,
        places_predicted, places_confirmed, places_deleted, links_inferred, links_confidence,
        links_deleted, cmd_velocity, exploration_status, map_update, map_graph, map_path,
        map_grid, map_stats, map_scans,
    )
    return {fn.__name__: fn(robot) for fn in fns}
