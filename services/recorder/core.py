"""Recorder core: the map, poses, sonar rays and belief as plain arrays ready to be drawn."""

from __future__ import annotations

import itertools
import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field

import msgspec
import numpy as np

from messages.types import (
    LinkDeleted,
    LinkInferred,
    LinkMeasured,
    LocalizationBelief,
    MapUpdate,
    OccupancyGrid,
    PlaceConfirmed,
    PlaceDeleted,
    PlacePredicted,
    Pose2,
    SonarScan,
)

POSE_SOURCES = ("truth", "compass", "raw")  # true pose, compass dead reckoning, raw odometry
UNKNOWN_CELL = 255  # OccupancyGrid.cells value of an unknown cell
UNKNOWN_GREY = 128  # grey level an unknown cell is drawn with


class RecorderParams(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Parameters of the recorder (defaults in code; deploy files and flags only override)."""

    trail_points: int = 1000  # at most this many points per pose trail; the oldest are dropped
    trail_spacing_m: float = 0.05  # a trail gets a new point once the pose moved this far from the last
    trail_period_s: float = 5.0  # each trail is logged at most once per this many simulated seconds
    live_period_s: float = 0.5  # poses, sonar rays and the belief: at most once per this, simulated s
    # (logging the three poses every 0.1 s and the trails every 1 s took over half the recorder's CPU)
    map_period_s: float = 1.0  # places and links changed by other events than a map update: logged at most
    # once per this many simulated s (the last change of each period, at its time); every map update is logged
    grid_every_versions: int = 10  # ask for the occupancy grid every this many map versions ...
    grid_period_s: float = 30.0  # ... or when this many simulated seconds passed since the last ask
    grid_resolution_m: float = 0.0  # resolution asked of map/grid; 0 leaves it to the relaxer
    grid_timeout_s: float = 2.0  # a grid query without a reply after this many wall seconds failed
    sonar_pose: str = "truth"  # the pose sonar rays are drawn from: "truth", "compass" or "raw"
    arrow_length_m: float = 0.4  # length of the arrow that shows a pose's heading
    # The Rerun SDK holds memory for every chunk it sends (rerun-io/rerun#12623): it sends what was
    # logged every this many wall seconds (or once this many bytes wait), as few large chunks.
    flush_period_s: float = 5.0
    viewer_flush_period_s: float = 1.0  # ... with a viewer attached, which would otherwise lag behind
    flush_bytes: int = 64 << 20

    def __post_init__(self) -> None:
        if self.sonar_pose not in POSE_SOURCES:
            raise ValueError(f"sonar_pose must be one of {', '.join(POSE_SOURCES)}, got {self.sonar_pose!r}")
        if self.trail_points < 2:
            raise ValueError(f"trail_points must be at least 2, got {self.trail_points}")
        if self.grid_every_versions < 1:
            raise ValueError(f"grid_every_versions must be at least 1, got {self.grid_every_versions}")
        for name in ("trail_spacing_m", "trail_period_s", "live_period_s", "map_period_s", "grid_period_s",
                     "grid_resolution_m"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be at least 0, got {getattr(self, name)}")
        if not self.flush_period_s > 0 or not self.viewer_flush_period_s > 0 or self.flush_bytes < 1:
            raise ValueError("flush_period_s, viewer_flush_period_s and flush_bytes must be positive, got "
                             f"{self.flush_period_s}, {self.viewer_flush_period_s}, {self.flush_bytes}")
        if not self.grid_timeout_s > 0 or not self.arrow_length_m > 0:
            raise ValueError("grid_timeout_s and arrow_length_m must be positive")


@dataclass(frozen=True)
class Style:
    """How each kind of thing is drawn: RGBA colours, radii and widths in screen points."""

    confirmed_color: tuple[int, int, int, int] = (30, 110, 230, 255)
    confirmed_radius_pt: float = 6.0
    predicted_color: tuple[int, int, int, int] = (240, 150, 30, 200)
    predicted_radius_pt: float = 4.0
    traversed_color: tuple[int, int, int, int] = (30, 110, 230, 255)
    traversed_width_pt: float = 2.5  # line width, not radius
    inferred_color: tuple[int, int, int, int] = (240, 150, 30, 160)
    inferred_width_pt: float = 1.0
    pose_colors: tuple[tuple[int, int, int, int], ...] = (
        (20, 170, 60, 255),  # truth
        (200, 40, 160, 255),  # compass dead reckoning
        (150, 150, 150, 255),  # raw odometry
    )
    pose_width_pt: float = 2.0
    trail_width_pt: float = 1.0
    echo_color: tuple[int, int, int, int] = (230, 40, 40, 180)
    no_echo_color: tuple[int, int, int, int] = (160, 160, 160, 90)
    ray_width_pt: float = 0.75
    echo_radius_pt: float = 2.5
    belief_color: tuple[int, int, int, int] = (20, 200, 200, 255)
    belief_radius_pt: float = 12.0  # radius of a hypothesis of probability 1 (scales with sqrt(p))

    def pose_color(self, source: str) -> tuple[int, int, int, int]:
        return self.pose_colors[POSE_SOURCES.index(source)]


STYLE = Style()


# --- views: what the node draws ----------------------------------------------------------------------


@dataclass(frozen=True)
class PlacesView:
    """Places to draw: ids with positions (N, 2), metres, world frame, sorted by id."""

    confirmed_ids: np.ndarray
    confirmed_xy: np.ndarray
    predicted_ids: np.ndarray
    predicted_xy: np.ndarray


@dataclass(frozen=True)
class LinksView:
    """Links to draw as segments (N, 2, 2): ``[[x1, y1], [x2, y2]]`` with their ``(from, to)`` ids."""

    traversed_ids: np.ndarray  # (N, 2) int
    traversed: np.ndarray  # (N, 2, 2) float
    inferred_ids: np.ndarray
    inferred: np.ndarray


@dataclass(frozen=True)
class SonarRays:
    """One scan in the world frame: each ray from ``origin`` to ``ends[i]``; ``echo[i]`` if it hit."""

    origin: np.ndarray  # (2,)
    ends: np.ndarray  # (N, 2)
    echo: np.ndarray  # (N,) bool

    @property
    def segments(self) -> np.ndarray:
        """(N, 2, 2): every ray as a segment from the sensor to its end."""
        return np.stack([np.broadcast_to(self.origin, self.ends.shape), self.ends], axis=1)


@dataclass(frozen=True)
class BeliefView:
    """The localization belief on the map.

    ``estimate_xy`` is the believed position (place centre plus filtered offset) and ``sigma_m`` its
    standard deviation per axis; both are None between places or when the place is not on the map.
    """

    place_id: int
    probability: float
    estimate_xy: np.ndarray | None
    sigma_m: float | None
    hypothesis_ids: np.ndarray  # hypotheses whose place is on the map, most probable first
    hypothesis_xy: np.ndarray  # (K, 2)
    hypothesis_p: np.ndarray  # (K,)


@dataclass(frozen=True)
class GridImage:
    """The occupancy grid as a grey image, row 0 at ``origin`` (the lowest y), column 0 the lowest x."""

    grey: np.ndarray  # (height, width) uint8: 255 free, 0 occupied, 128 unknown
    origin_xy: tuple[float, float]
    resolution_m: float
    version: int


def _link_key(a: int, b: int) -> tuple[int, int]:
    """Links are drawn undirected: a traversal ``b -> a`` is the same line as ``a -> b``."""
    return (a, b) if a <= b else (b, a)


def _segments(links: Mapping[tuple[int, int], object], ids: np.ndarray,
              xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The links whose both places are among ``ids`` (sorted), sorted by key, and their segments."""
    keys = np.fromiter(itertools.chain.from_iterable(links), dtype=np.int64, count=2 * len(links)).reshape(-1, 2)
    keys = keys[np.lexsort((keys[:, 1], keys[:, 0]))]
    rows = np.searchsorted(ids, keys).clip(max=max(ids.size - 1, 0))
    drawn = (ids[rows] == keys).all(axis=1) if ids.size else np.zeros(len(keys), dtype=bool)
    return keys[drawn], xy[rows[drawn]].reshape(-1, 2, 2)


@dataclass
class _Trail:
    points: deque[tuple[float, float]]
    logged_stamp: float | None = None  # simulated time the trail was last logged at


@dataclass
class RecorderState:
    """What the recorder knows of the map and the robot; fed with bus messages, one at a time."""

    params: RecorderParams = field(default_factory=RecorderParams)
    initial: dict[int, tuple[float, float]] = field(default_factory=dict)  # confirmed, as first reported
    relaxed: dict[int, tuple[float, float]] = field(default_factory=dict)  # from MapUpdate
    predicted: dict[int, PlacePredicted] = field(default_factory=dict)
    traversed: dict[tuple[int, int], LinkMeasured] = field(default_factory=dict)
    inferred: dict[tuple[int, int], LinkInferred] = field(default_factory=dict)
    poses: dict[str, Pose2] = field(default_factory=dict)
    version: int = -1  # latest map version seen
    map_logged: float | None = None  # when the places and links were last logged (see map_due)
    _trails: dict[str, _Trail] = field(default_factory=dict)
    _live_stamp: dict[str, float] = field(default_factory=dict)
    _grid_version: int | None = None  # map version of the last grid request
    _grid_stamp: float | None = None

    # -- places -------------------------------------------------------------------------------------
    def place_confirmed(self, msg: PlaceConfirmed) -> None:
        self.initial[msg.place_id] = (msg.x_m, msg.y_m)
        self.predicted.pop(msg.place_id, None)

    def place_predicted(self, msg: PlacePredicted) -> None:
        """A prediction for a place that is already confirmed is ignored (confirmation wins)."""
        if msg.place_id not in self.initial and msg.place_id not in self.relaxed:
            self.predicted[msg.place_id] = msg

    def place_deleted(self, msg: PlaceDeleted) -> None:
        """The place and every link that touches it disappear."""
        pid = msg.place_id
        for table in (self.initial, self.relaxed, self.predicted):
            table.pop(pid, None)
        for links in (self.traversed, self.inferred):
            for key in [k for k in links if pid in k]:
                del links[key]

    def map_update(self, msg: MapUpdate) -> None:
        """Relaxed coordinates replace the initial ones of the places they cover.

        A place the relaxer moved but whose confirmation was not seen (a recorder started late) is
        taken as confirmed at its relaxed position.
        """
        self.version = max(self.version, msg.version)
        for p in msg.changed:
            self.relaxed[p.place_id] = (p.x_m, p.y_m)
            self.initial.setdefault(p.place_id, (p.x_m, p.y_m))
            self.predicted.pop(p.place_id, None)

    def position(self, place_id: int) -> tuple[float, float] | None:
        """Where a place is drawn: relaxed, else as confirmed, else as predicted; None if unknown.

        A predicted place is moved with its parent: its dead-reckoning position plus the shift that
        relaxation gave the parent, so that it stays where it was predicted relative to the map.
        """
        if place_id in self.relaxed:
            return self.relaxed[place_id]
        if place_id in self.initial:
            return self.initial[place_id]
        pred = self.predicted.get(place_id)
        if pred is None:
            return None
        parent = pred.parent_id
        if parent in self.relaxed and parent in self.initial:
            (rx, ry), (ix, iy) = self.relaxed[parent], self.initial[parent]
            return (pred.x_m + rx - ix, pred.y_m + ry - iy)
        return (pred.x_m, pred.y_m)

    def _table(self) -> tuple[np.ndarray, np.ndarray, int]:
        """Every place on the map: sorted ids (confirmed first, then predicted), their positions (N, 2),
        and how many are confirmed. Built with arrays: a map of 400 places and 2000 links is drawn
        about once per simulated second, and dicts of tuples cost 8 ms a time."""
        confirmed = sorted(self.initial.keys() | self.relaxed.keys())
        predicted = sorted(self.predicted.keys() - set(confirmed))
        xy = [self.position(pid) for pid in confirmed]
        xy += [self.position(pid) for pid in predicted]
        return (np.array(confirmed + predicted, dtype=np.int64),
                np.array(xy, dtype=np.float64).reshape(-1, 2), len(confirmed))

    def places(self) -> PlacesView:
        ids, xy, n = self._table()
        return PlacesView(confirmed_ids=ids[:n], confirmed_xy=xy[:n], predicted_ids=ids[n:], predicted_xy=xy[n:])

    # -- links --------------------------------------------------------------------------------------
    def link_measured(self, msg: LinkMeasured) -> None:
        """A traversed link; it replaces an inferred one between the same places."""
        key = _link_key(msg.from_id, msg.to_id)
        self.traversed[key] = msg
        self.inferred.pop(key, None)

    def link_inferred(self, msg: LinkInferred) -> None:
        """An inferred link between places already joined by a traversed one is ignored."""
        key = _link_key(msg.from_id, msg.to_id)
        if key not in self.traversed:
            self.inferred[key] = msg

    def link_deleted(self, msg: LinkDeleted) -> None:
        key = _link_key(msg.from_id, msg.to_id)
        held = self.traversed.get(key)
        if held is not None and held.stamp > msg.stamp:
            return  # a deletion heard again after the link was measured anew
        self.traversed.pop(key, None)
        self.inferred.pop(key, None)

    def links(self, places: PlacesView | None = None) -> LinksView:
        """Segments of the links whose both places are on the map (others wait for their places);
        ``places``, the :meth:`places` of the same moment, saves building them again."""
        places = places if places is not None else self.places()
        ids = np.concatenate([places.confirmed_ids, places.predicted_ids])
        xy = np.concatenate([places.confirmed_xy, places.predicted_xy])
        order = np.argsort(ids, kind="stable")
        ids, xy = ids[order], xy[order]
        t_ids, t_segs = _segments(self.traversed, ids, xy)
        i_ids, i_segs = _segments(self.inferred, ids, xy)
        return LinksView(traversed_ids=t_ids, traversed=t_segs, inferred_ids=i_ids, inferred=i_segs)

    # -- poses --------------------------------------------------------------------------------------
    def pose(self, source: str, pose: Pose2) -> None:
        """The latest pose of ``source`` (one of POSE_SOURCES); extends its bounded trail."""
        if source not in POSE_SOURCES:
            raise ValueError(f"unknown pose source {source!r}")
        self.poses[source] = pose
        trail = self._trails.get(source)
        if trail is None:
            trail = self._trails[source] = _Trail(deque(maxlen=self.params.trail_points))
        p = (pose.x_m, pose.y_m)
        if not trail.points or math.dist(trail.points[-1], p) >= self.params.trail_spacing_m:
            trail.points.append(p)

    def trail(self, source: str) -> np.ndarray:
        """(N, 2) positions of ``source``'s trail, oldest first, N <= params.trail_points."""
        trail = self._trails.get(source)
        return np.array(trail.points if trail else [], dtype=np.float64).reshape(-1, 2)

    def trail_due(self, source: str, stamp: float) -> bool:
        """True (and remembered) when ``source``'s trail should be logged at ``stamp``."""
        trail = self._trails.get(source)
        if trail is None:
            return False
        if not _due(trail.logged_stamp, stamp, self.params.trail_period_s):
            return False
        trail.logged_stamp = stamp
        return True

    def live_due(self, what: str, stamp: float) -> bool:
        """True (and remembered) when ``what`` (a pose source, "sonar", "belief") should be logged now."""
        if not _due(self._live_stamp.get(what), stamp, self.params.live_period_s):
            return False
        self._live_stamp[what] = stamp
        return True

    def arrow(self, source: str) -> tuple[np.ndarray, np.ndarray] | None:
        """Origin (2,) and vector (2,) of the arrow that shows ``source``'s pose, None before any."""
        pose = self.poses.get(source)
        if pose is None:
            return None
        length = self.params.arrow_length_m
        return (np.array([pose.x_m, pose.y_m]),
                np.array([length * math.cos(pose.heading_rad), length * math.sin(pose.heading_rad)]))

    # -- sonar and belief ---------------------------------------------------------------------------
    def sonar_rays(self, scan: SonarScan) -> SonarRays | None:
        """The scan's rays in the world frame, from the latest ``params.sonar_pose`` pose.

        Ray ``i`` leaves the pose at bearing ``heading + angles_rad[i]`` and ends at ``ranges_m[i]``;
        a range at (or beyond) ``max_range_m`` is no echo. None until that pose is known.
        """
        pose = self.poses.get(self.params.sonar_pose)
        if pose is None:
            return None
        angles = np.asarray(scan.angles_rad, dtype=np.float64)
        ranges = np.asarray(scan.ranges_m, dtype=np.float64)
        if angles.shape != ranges.shape:
            raise ValueError(f"sonar scan with {angles.size} angles and {ranges.size} ranges")
        bearing = pose.heading_rad + angles
        reach = np.minimum(ranges, scan.max_range_m)
        ends = np.column_stack([pose.x_m + reach * np.cos(bearing), pose.y_m + reach * np.sin(bearing)])
        return SonarRays(origin=np.array([pose.x_m, pose.y_m]), ends=ends, echo=ranges < scan.max_range_m)

    def belief(self, msg: LocalizationBelief) -> BeliefView:
        estimate = sigma = None
        centre = self.position(msg.place_id) if msg.place_id >= 0 else None
        if centre is not None:
            estimate = np.array([centre[0] + msg.offset_x_m, centre[1] + msg.offset_y_m])
            sigma = math.sqrt(max(msg.offset_var_m2, 0.0))
        hyps = [(h.place_id, xy, h.probability) for h in msg.hypotheses
                if h.place_id >= 0 and (xy := self.position(h.place_id)) is not None]
        return BeliefView(
            place_id=msg.place_id, probability=msg.probability, estimate_xy=estimate, sigma_m=sigma,
            hypothesis_ids=np.array([h[0] for h in hyps], dtype=np.int64),
            hypothesis_xy=np.array([h[1] for h in hyps], dtype=np.float64).reshape(-1, 2),
            hypothesis_p=np.array([h[2] for h in hyps], dtype=np.float64),
        )

    def map_due(self, stamp: float) -> bool:
        """True when a change of the places and links at ``stamp`` may be logged at once: ``map_period_s``
        after they were last logged (``map_logged``), or the first time."""
        return _due(self.map_logged, stamp, self.params.map_period_s)

    # -- the occupancy grid -------------------------------------------------------------------------
    def grid_due(self, version: int, stamp: float) -> bool:
        """True (and remembered) when the grid should be asked for after map ``version`` at ``stamp``:
        the first time, every ``grid_every_versions`` versions, or ``grid_period_s`` after the last ask.
        """
        p = self.params
        due = (self._grid_version is None
               or version - self._grid_version >= p.grid_every_versions
               or version < self._grid_version  # a new run started
               or _due(self._grid_stamp, stamp, p.grid_period_s))
        if due:
            self._grid_version, self._grid_stamp = version, stamp
        return due


def _due(last: float | None, stamp: float, period_s: float) -> bool:
    """Rate limit on simulated time; a clock that went back (a new run) makes it due at once."""
    return last is None or stamp - last >= period_s or stamp < last


def grid_image(grid: OccupancyGrid) -> GridImage:
    """The grid as grey levels: free white, occupied black, unknown mid grey.

    Occupancy ``o`` in 0..100 percent becomes ``255 - round(2.55 o)``; 255 (unknown) becomes 128;
    other values above 100 are treated as occupied.

    Raises
    ------
    ValueError
        When ``cells`` does not hold ``width * height`` bytes.
    """
    if grid.width < 0 or grid.height < 0 or len(grid.cells) != grid.width * grid.height:
        raise ValueError(f"occupancy grid of {grid.width} x {grid.height} cells with {len(grid.cells)} bytes")
    cells = np.frombuffer(grid.cells, dtype=np.uint8).reshape(grid.height, grid.width)
    occ = np.minimum(cells, 100).astype(np.float64)
    grey = (255.0 - np.rint(occ * 2.55)).astype(np.uint8)
    grey[cells == UNKNOWN_CELL] = UNKNOWN_GREY
    return GridImage(grey=grey, origin_xy=(grid.origin_x_m, grid.origin_y_m), resolution_m=grid.resolution_m,
                     version=grid.version)
