"""The files a run leaves in its output directory, written from what the services answer."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

from messages.types import MapGraph, MapStats, OccupancyGrid


def atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename: never a half-written file."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def grid_image(grid: OccupancyGrid) -> np.ndarray:
    """The grid as a ROS map_server image: rows top (north) first; free white, occupied black, unknown grey."""
    cells = np.frombuffer(grid.cells, np.uint8).reshape(grid.height, grid.width)
    img = np.where(cells == 255, 205, 255 - np.round(cells.astype(float) * 2.55)).astype(np.uint8)
    return img[::-1]


def write_grid(grid: OccupancyGrid, png: Path, yaml: Path | None) -> None:
    """``png`` (8-bit grey) and, if named, its map_server ``yaml`` (origin = lower-left corner)."""
    img = grid_image(grid) if grid.width and grid.height else np.full((1, 1), 205, np.uint8)
    fd, tmp = tempfile.mkstemp(dir=png.parent, prefix=f".{png.name}.", suffix=".png")
    os.close(fd)
    try:
        Image.fromarray(img, mode="L").save(tmp, format="PNG")
        os.replace(tmp, png)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    if yaml is not None:
        text = (f"image: {png.name}\nresolution: {grid.resolution_m:g}\n"
                f"origin: [{grid.origin_x_m:.6f}, {grid.origin_y_m:.6f}, 0.0]\n"
                "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n")
        atomic_write(yaml, text.encode())


def summary(*, world: str, seed: int, graph: MapGraph, stats: MapStats, links_measured: int,
            links_inferred: int, sim_time_s: float, wall_time_s: float, complete: bool,
            ate_relaxed_m: float, ate_dead_reckoning_m: float, restarts: dict[str, int]) -> dict:
    """summary.json's content (architecture.md), with loss made visible (``links_lost``)."""
    in_map = {(min(lk.from_id, lk.to_id), max(lk.from_id, lk.to_id)) for lk in graph.links}
    return {
        "world": world,
        "seed": seed,
        "places": len(graph.places),
        "links_traversed": len(graph.links),
        "links_inferred": links_inferred,
        "links_measured": links_measured,
        "links_lost": max(links_measured - len(in_map), 0),
        "sim_time_s": round(sim_time_s, 3),
        "wall_time_s": round(wall_time_s, 3),
        "real_time_factor": round(sim_time_s / wall_time_s, 2) if wall_time_s > 0 else None,
        "exploration_complete": complete,
        "energy": graph.energy,
        "ate_relaxed_m": None if np.isnan(ate_relaxed_m) else round(ate_relaxed_m, 4),
        "ate_dead_reckoning_m": None if np.isnan(ate_dead_reckoning_m) else round(ate_dead_reckoning_m, 4),
        "iterations": stats.iterations,
        "updates": stats.updates,
        "cycle_ms_mean": round(stats.cycle_ms_mean, 3),
        "cycle_ms_p99": round(stats.cycle_ms_p99, 3),
        "noise": {"s_dd": graph.noise.s_dd, "s_aa": graph.noise.s_aa, "s_da": graph.noise.s_da},
        "restarts": restarts,
    }


def write_json(path: Path, obj: object) -> None:
    atomic_write(path, (json.dumps(obj, indent=2) + "\n").encode())
