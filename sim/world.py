"""The ground-truth world: walls, start pose, magnetic disturbances; loaded from JSON or a ROS map pair."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from sim.geometry import point_segment_distance, segment_segment_distance

ROBOT_RADIUS_M = 0.25  # radius of the simulated robot's disc
WALL_HALF_THICKNESS_M = 0.05  # a point this close to a wall line is inside the wall
BUILTIN_DIR = "worlds"  # package data directory of sim/ holding the built-in worlds
_CELL_M = 1.0  # cell size of the spatial index of walls


class WorldError(ValueError):
    """A world file is missing or malformed; the message names the file and the problem."""


@dataclass(frozen=True)
class MagneticDisturbance:
    """A region where the compass is deflected: ``deviation_deg`` at the centre, fading to 0 at ``radius_m``."""

    x_m: float
    y_m: float
    radius_m: float
    deviation_deg: float


@dataclass(frozen=True)
class Raster:
    """An occupancy raster: ``occupied[row, col]``, row 0 at ``origin_y_m`` (south), rotated by ``yaw_rad``."""

    occupied: np.ndarray  # (rows, cols) bool
    resolution_m: float
    origin_x_m: float
    origin_y_m: float
    yaw_rad: float = 0.0

    def cells_of(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Row and column of each point (may fall outside the raster)."""
        p = np.asarray(points, dtype=float).reshape(-1, 2)
        dx = p[:, 0] - self.origin_x_m
        dy = p[:, 1] - self.origin_y_m
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        lx, ly = c * dx + s * dy, -s * dx + c * dy
        return (np.floor(ly / self.resolution_m).astype(np.int64),
                np.floor(lx / self.resolution_m).astype(np.int64))

    def occupied_at(self, points: np.ndarray) -> np.ndarray:
        rows, cols = self.cells_of(points)
        h, w = self.occupied.shape
        inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
        out = np.zeros(rows.shape, dtype=bool)
        out[inside] = self.occupied[rows[inside], cols[inside]]
        return out


@dataclass(frozen=True)
class TruthGrid:
    """The world rasterised: which cells a wall crosses, and which free cells the robot can reach."""

    occupied: np.ndarray  # (rows, cols) bool: a wall crosses the cell
    reachable: np.ndarray  # (rows, cols) bool: free and connected to the start cell
    resolution_m: float
    origin_x_m: float  # world coordinates of the corner of cell (0, 0); rows grow with y
    origin_y_m: float


@dataclass(frozen=True, eq=False)
class World:
    """A simulated environment. Walls are segments ``x1, y1, x2, y2`` in metres.

    Use :func:`load_world` to build one from a name or file; the constructor trusts its inputs.
    """

    name: str
    walls: np.ndarray  # (N, 4) float, read-only
    start: tuple[float, float, float]  # x_m, y_m, heading_rad
    magnetic_disturbances: tuple[MagneticDisturbance, ...] = ()
    routes: dict[str, np.ndarray] = field(default_factory=dict)  # name -> (K, 2) waypoints, metres
    source: str = "<memory>"
    raster: Raster | None = None  # set for worlds loaded from an occupancy map
    _index: dict = field(default_factory=dict, init=False, repr=False, compare=False)  # walls_near cache

    # -- extent --------------------------------------------------------------------------------------
    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``xmin, ymin, xmax, ymax`` of the walls."""
        w = self.walls
        return (float(min(w[:, 0].min(), w[:, 2].min())), float(min(w[:, 1].min(), w[:, 3].min())),
                float(max(w[:, 0].max(), w[:, 2].max())), float(max(w[:, 1].max(), w[:, 3].max())))

    @property
    def size_m(self) -> tuple[float, float]:
        xmin, ymin, xmax, ymax = self.bounds
        return xmax - xmin, ymax - ymin

    # -- spatial queries -----------------------------------------------------------------------------
    def walls_near(self, x: float, y: float, margin_m: float) -> np.ndarray:
        """Every wall that may lie within ``margin_m`` of any point of the 1 m cell holding ``(x, y)``.

        A superset (bounding boxes), cached per cell and margin: cheap enough to call every step.
        """
        key = (math.floor(x / _CELL_M), math.floor(y / _CELL_M), margin_m)
        found = self._index.get(key)
        if found is None:
            x0, y0 = key[0] * _CELL_M - margin_m, key[1] * _CELL_M - margin_m
            x1, y1 = x0 + _CELL_M + 2 * margin_m, y0 + _CELL_M + 2 * margin_m
            w = self.walls
            keep = ((np.minimum(w[:, 0], w[:, 2]) <= x1) & (np.maximum(w[:, 0], w[:, 2]) >= x0)
                    & (np.minimum(w[:, 1], w[:, 3]) <= y1) & (np.maximum(w[:, 1], w[:, 3]) >= y0))
            found = np.ascontiguousarray(w[keep])
            found.flags.writeable = False
            self._index[key] = found
        return found

    def clearance(self, x: float, y: float) -> float:
        """Distance from ``(x, y)`` to the nearest wall."""
        return float(point_segment_distance(np.array([[x, y]]), self.walls).min())

    def occupied(self, points: np.ndarray, *, margin_m: float = 0.0) -> np.ndarray:
        """Whether each point (P, 2) lies in a wall (within its half thickness plus ``margin_m``),
        in an occupied cell of the source map, or outside the bounds; (P,) bool."""
        p = np.asarray(points, dtype=float).reshape(-1, 2)
        xmin, ymin, xmax, ymax = self.bounds
        out = (p[:, 0] < xmin) | (p[:, 0] > xmax) | (p[:, 1] < ymin) | (p[:, 1] > ymax)
        for start in range(0, p.shape[0], 4096):  # bounded memory: (4096, N) distances at a time
            chunk = p[start:start + 4096]
            d = point_segment_distance(chunk, self.walls).min(axis=1)
            out[start:start + 4096] |= d <= WALL_HALF_THICKNESS_M + margin_m
        if self.raster is not None:
            out |= self.raster.occupied_at(p)
        return out

    def segment_free(self, x0: float, y0: float, x1: float, y1: float, *,
                     radius_m: float = ROBOT_RADIUS_M) -> bool:
        """Whether a disc of ``radius_m`` can move straight from ``(x0, y0)`` to ``(x1, y1)`` without
        touching a wall (the explorer's confirmation test)."""
        seg = np.array([x0, y0, x1, y1], dtype=float)
        lo_x, hi_x = min(x0, x1) - radius_m, max(x0, x1) + radius_m
        lo_y, hi_y = min(y0, y1) - radius_m, max(y0, y1) + radius_m
        w = self.walls
        keep = ((np.minimum(w[:, 0], w[:, 2]) <= hi_x) & (np.maximum(w[:, 0], w[:, 2]) >= lo_x)
                & (np.minimum(w[:, 1], w[:, 3]) <= hi_y) & (np.maximum(w[:, 1], w[:, 3]) >= lo_y))
        near = w[keep]
        if near.shape[0] and segment_segment_distance(seg, near).min() < radius_m:
            return False
        if self.raster is not None:
            n = max(2, int(math.hypot(x1 - x0, y1 - y0) / (0.5 * self.raster.resolution_m)) + 1)
            pts = np.column_stack((np.linspace(x0, x1, n), np.linspace(y0, y1, n)))
            if self.raster.occupied_at(pts).any():
                return False
        return True

    def truth_grid(self, resolution_m: float = 0.15) -> TruthGrid:
        """Rasterise the walls and flood-fill the free space reachable from the start (4-connected)."""
        from scipy import ndimage

        if not resolution_m > 0:
            raise ValueError(f"resolution_m must be positive, got {resolution_m}")
        xmin, ymin, xmax, ymax = self.bounds
        cols = int(math.ceil((xmax - xmin) / resolution_m)) + 1
        rows = int(math.ceil((ymax - ymin) / resolution_m)) + 1
        occ = np.zeros((rows, cols), dtype=bool)
        w = self.walls
        length = np.hypot(w[:, 2] - w[:, 0], w[:, 3] - w[:, 1])
        n = np.maximum(2, np.ceil(length / (0.25 * resolution_m)).astype(np.int64) + 1)
        seg = np.repeat(np.arange(w.shape[0]), n)
        first = np.repeat(np.cumsum(n) - n, n)
        t = (np.arange(seg.shape[0]) - first) / (n[seg] - 1)
        px = w[seg, 0] + t * (w[seg, 2] - w[seg, 0])
        py = w[seg, 1] + t * (w[seg, 3] - w[seg, 1])
        ci = np.clip(((px - xmin) / resolution_m).astype(np.int64), 0, cols - 1)
        ri = np.clip(((py - ymin) / resolution_m).astype(np.int64), 0, rows - 1)
        occ[ri, ci] = True
        if self.raster is not None:
            yy, xx = np.mgrid[0:rows, 0:cols]
            centres = np.column_stack(((xx.ravel() + 0.5) * resolution_m + xmin,
                                       (yy.ravel() + 0.5) * resolution_m + ymin))
            occ |= self.raster.occupied_at(centres).reshape(rows, cols)
        labels, _ = ndimage.label(~occ)
        sr = min(max(int((self.start[1] - ymin) / resolution_m), 0), rows - 1)
        sc = min(max(int((self.start[0] - xmin) / resolution_m), 0), cols - 1)
        lab = labels[sr, sc]
        reachable = (labels == lab) if lab > 0 else np.zeros_like(occ)
        return TruthGrid(occupied=occ, reachable=reachable, resolution_m=resolution_m,
                         origin_x_m=xmin, origin_y_m=ymin)


# -- occupancy rasters to walls ----------------------------------------------------------------------


def raster_walls(occupied: np.ndarray, resolution_m: float, origin_x_m: float = 0.0,
                 origin_y_m: float = 0.0, yaw_rad: float = 0.0) -> np.ndarray:
    """The outline of the occupied cells as wall segments, collinear cell edges merged.

    ``occupied[row, col]`` with row 0 at ``origin_y_m``; cells outside the raster count as free,
    so occupied cells on its border are closed off too. Returns an (N, 4) array.
    """
    occ = np.pad(np.asarray(occupied, dtype=bool), 1)
    segs = []
    # horizontal edges: between padded rows r-1 and r, i.e. at y = (r - 1) * res
    h = occ[1:, :] != occ[:-1, :]  # (rows+1, cols+2)
    segs.append(_runs(h, resolution_m, horizontal=True))
    v = (occ[:, 1:] != occ[:, :-1]).T  # (cols+1, rows+2): at x = (c - 1) * res
    segs.append(_runs(v, resolution_m, horizontal=False))
    walls = np.concatenate(segs, axis=0)
    if yaw_rad:
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        x1, y1, x2, y2 = walls.T
        walls = np.column_stack((c * x1 - s * y1, s * x1 + c * y1, c * x2 - s * y2, s * x2 + c * y2))
    walls[:, [0, 2]] += origin_x_m
    walls[:, [1, 3]] += origin_y_m
    return walls


def _runs(edge: np.ndarray, res: float, *, horizontal: bool) -> np.ndarray:
    """Runs of True along axis 1 of ``edge`` (line index, padded position) as segments."""
    e = np.pad(edge, ((0, 0), (1, 1))).astype(np.int8)
    d = np.diff(e, axis=1)
    sl, sp = np.nonzero(d == 1)  # run starts at padded position sp (edge index sp)
    el, ep = np.nonzero(d == -1)  # run ends before position ep
    # positions in ``edge`` carry one cell of padding: cell index = position - 1
    line = sl.astype(float) * res
    a = (sp - 1).astype(float) * res
    b = (ep - 1).astype(float) * res
    if horizontal:
        return np.column_stack((a, line, b, line))
    return np.column_stack((line, a, line, b))


# -- loading -----------------------------------------------------------------------------------------


def builtin_worlds() -> list[str]:
    """Names of the built-in worlds, sorted."""
    folder = resources.files("sim").joinpath(BUILTIN_DIR)
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".json"))


def builtin_path(name: str) -> Path:
    return Path(str(resources.files("sim").joinpath(BUILTIN_DIR, f"{name}.json")))


def load_world(spec: str | Path) -> World:
    """A world from a built-in name, a JSON world file, or a ROS map_server ``.yaml``.

    Raises
    ------
    WorldError
        When the world is unknown, the file unreadable, or its content malformed; the message
        names the file and the problem.
    """
    text = str(spec)
    if not isinstance(spec, Path) and text in builtin_worlds():
        return load_world_json(builtin_path(text))
    path = Path(spec)
    if not path.exists():
        raise WorldError(f"world {text!r}: not a built-in world ({', '.join(builtin_worlds())}) and no such file")
    if path.suffix.lower() in (".yaml", ".yml"):
        return load_ros_map(path)
    return load_world_json(path)


def load_world_json(path: str | Path) -> World:
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except OSError as e:
        raise WorldError(f"{path}: cannot read: {e.strerror or e}") from e
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise WorldError(f"{path}: not valid JSON: {e}") from e
    return world_from_dict(data, source=str(path))


def world_from_dict(data: Any, *, source: str = "<memory>", raster: Raster | None = None) -> World:
    """Validate a world description (the JSON file format) and build the :class:`World`."""
    if not isinstance(data, dict):
        raise WorldError(f"{source}: a world must be a JSON object, got {type(data).__name__}")
    name = data.get("name", Path(source).stem)
    if not isinstance(name, str) or not name:
        raise WorldError(f"{source}: 'name' must be a non-empty string")
    raw_walls = data.get("walls")
    if not isinstance(raw_walls, list) or not raw_walls:
        raise WorldError(f"{source}: no walls: 'walls' must be a non-empty list of [x1, y1, x2, y2]")
    walls = np.empty((len(raw_walls), 4))
    for i, wall in enumerate(raw_walls):
        walls[i] = _numbers(wall, 4, f"walls[{i}]", source)
        if walls[i, 0] == walls[i, 2] and walls[i, 1] == walls[i, 3]:
            raise WorldError(f"{source}: walls[{i}] has zero length")
    walls.flags.writeable = False
    if "start" not in data:
        raise WorldError(f"{source}: missing 'start': [x, y, heading_rad]")
    sx, sy, sh = _numbers(data["start"], 3, "start", source)
    disturbances = []
    raw_dist = data.get("magnetic_disturbances", [])
    if not isinstance(raw_dist, list):
        raise WorldError(f"{source}: 'magnetic_disturbances' must be a list")
    for i, d in enumerate(raw_dist):
        where = f"magnetic_disturbances[{i}]"
        if not isinstance(d, dict):
            raise WorldError(f"{source}: {where} must be an object with x, y, radius, deviation_deg")
        vals = [_number(d.get(k), f"{where}.{k}", source) for k in ("x", "y", "radius", "deviation_deg")]
        if vals[2] <= 0:
            raise WorldError(f"{source}: {where}.radius must be positive, got {vals[2]}")
        disturbances.append(MagneticDisturbance(*vals))
    routes = {}
    raw_routes = data.get("routes", {})
    if not isinstance(raw_routes, dict):
        raise WorldError(f"{source}: 'routes' must be an object: name -> [[x, y], ...]")
    for rname, pts in raw_routes.items():
        if not isinstance(pts, list) or len(pts) < 2:
            raise WorldError(f"{source}: routes.{rname} must be a list of at least two [x, y] points")
        arr = np.array([_numbers(p, 2, f"routes.{rname}[{j}]", source) for j, p in enumerate(pts)])
        arr.flags.writeable = False
        routes[rname] = arr
    world = World(name=name, walls=walls, start=(sx, sy, sh), magnetic_disturbances=tuple(disturbances),
                  routes=routes, source=source, raster=raster)
    xmin, ymin, xmax, ymax = world.bounds
    if not (xmin <= sx <= xmax and ymin <= sy <= ymax):
        raise WorldError(f"{source}: start ({sx:g}, {sy:g}) lies outside the walls "
                         f"(x {xmin:g}..{xmax:g}, y {ymin:g}..{ymax:g})")
    dist = point_segment_distance(np.array([[sx, sy]]), walls)[0]
    nearest = int(np.argmin(dist))
    if dist[nearest] < ROBOT_RADIUS_M:
        raise WorldError(f"{source}: start ({sx:g}, {sy:g}) is inside a wall: {dist[nearest]:.3f} m from "
                         f"walls[{nearest}], the robot needs {ROBOT_RADIUS_M} m of clearance")
    if raster is not None and raster.occupied_at(np.array([[sx, sy]]))[0]:
        raise WorldError(f"{source}: start ({sx:g}, {sy:g}) is inside a wall: the cell is occupied")
    return world


def _number(value: Any, where: str, source: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise WorldError(f"{source}: {where} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise WorldError(f"{source}: {where} must be finite, got {value!r}")
    return float(value)


def _numbers(value: Any, n: int, where: str, source: str) -> list[float]:
    if not isinstance(value, list | tuple) or len(value) != n:
        raise WorldError(f"{source}: {where} must be a list of {n} numbers, got {value!r}")
    return [_number(v, f"{where}[{k}]", source) for k, v in enumerate(value)]


# -- ROS map_server ----------------------------------------------------------------------------------


def load_ros_map(yaml_path: str | Path) -> World:
    """A world from a ROS map_server pair: occupied cells become walls.

    Reads ``image``, ``resolution``, ``origin``, ``negate``, ``occupied_thresh``, ``mode`` as map_server
    does. Two optional keys of our own: ``start: [x, y, heading_rad]`` (else the free cell farthest
    from any occupied cell) and ``name``.
    """
    path = Path(yaml_path)
    try:
        meta = _parse_flat_yaml(path.read_text(encoding="utf-8"))
    except OSError as e:
        raise WorldError(f"{path}: cannot read: {e.strerror or e}") from e
    except ValueError as e:
        raise WorldError(f"{path}: {e}") from e
    src = str(path)
    image = meta.get("image")
    if not isinstance(image, str) or not image:
        raise WorldError(f"{src}: missing 'image' (the .pgm or .png file)")
    res = _number(meta.get("resolution"), "resolution", src)
    if res <= 0:
        raise WorldError(f"{src}: resolution must be positive, got {res}")
    origin = _numbers(meta.get("origin"), 3, "origin", src)
    negate = int(_number(meta.get("negate", 0), "negate", src))
    occ_th = _number(meta.get("occupied_thresh", 0.65), "occupied_thresh", src)
    mode = meta.get("mode", "trinary")
    img_path = (path.parent / image) if not Path(image).is_absolute() else Path(image)
    pixels = _read_image(img_path, src)
    if mode == "raw":
        occupied = (pixels <= 100) & (pixels > occ_th * 100)
    else:
        p = pixels / 255.0 if negate else (255.0 - pixels) / 255.0
        occupied = p > occ_th
    occupied = occupied[::-1, :]  # image row 0 is the top (largest y); ours is the bottom
    if not occupied.any():
        raise WorldError(f"{src}: no walls: {img_path.name} has no occupied cell")
    raster = Raster(occupied=occupied, resolution_m=res, origin_x_m=origin[0], origin_y_m=origin[1],
                    yaw_rad=origin[2])
    walls = raster_walls(occupied, res, origin[0], origin[1], origin[2])
    if "start" in meta:
        start = _numbers(meta["start"], 3, "start", src)
    else:
        start = _widest_free_cell(raster)
    data = {"name": meta.get("name", path.stem), "walls": walls.tolist(), "start": list(start)}
    return world_from_dict(data, source=src, raster=raster)


def _widest_free_cell(raster: Raster) -> list[float]:
    from scipy import ndimage

    occ = raster.occupied
    dist = ndimage.distance_transform_edt(np.pad(~occ, 1, constant_values=False))[1:-1, 1:-1]
    r, c = np.unravel_index(int(np.argmax(dist)), dist.shape)
    lx, ly = (c + 0.5) * raster.resolution_m, (r + 0.5) * raster.resolution_m
    cs, sn = math.cos(raster.yaw_rad), math.sin(raster.yaw_rad)
    return [raster.origin_x_m + cs * lx - sn * ly, raster.origin_y_m + sn * lx + cs * ly, 0.0]


def _read_image(path: Path, src: str) -> np.ndarray:
    try:
        from PIL import Image, UnidentifiedImageError
    except ImportError as e:  # Pillow comes with rerun-sdk
        raise WorldError(f"{src}: reading {path.name} needs Pillow") from e
    try:
        with Image.open(path) as img:
            return np.asarray(img.convert("L"), dtype=float)
    except FileNotFoundError as e:
        raise WorldError(f"{src}: map image {path} not found") from e
    except (UnidentifiedImageError, OSError) as e:
        raise WorldError(f"{src}: cannot read map image {path.name}: {e}") from e


def _parse_flat_yaml(text: str) -> dict[str, Any]:
    """The flat ``key: value`` YAML of map_server: numbers, strings and ``[a, b, c]`` lists."""
    out: dict[str, Any] = {}
    for n, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        key, sep, value = line.partition(":")
        if not sep or not key.strip():
            raise ValueError(f"line {n}: expected 'key: value', got {line!r}")
        value = value.strip()
        if value.startswith("["):
            if not value.endswith("]"):
                raise ValueError(f"line {n}: unterminated list {value!r}")
            out[key.strip()] = [_scalar(v.strip()) for v in value[1:-1].split(",") if v.strip()]
        else:
            out[key.strip()] = _scalar(value)
    return out


def _scalar(text: str) -> Any:
    if len(text) >= 2 and text[0] == text[-1] and text[0] in "'\"":
        return text[1:-1]
    for conv in (int, float):
        try:
            return conv(text)
        except ValueError:
            pass
    return text
