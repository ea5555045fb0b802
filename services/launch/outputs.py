"""The files a run leaves in its output directory, written from what the services answer."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
from PIL import Image

from messages.types import MapGraph, MapStats, OccupancyGrid
from services.common.files import atomic_write
from services.launch.evaluate import Similarity, ate_m, similarity_about

log = logging.getLogger(__name__)


def grid_image(grid: OccupancyGrid) -> np.ndarray:
    """The grid as a ROS map_server image: rows top (north) first; free white, occupied black, unknown grey."""
    cells = np.frombuffer(grid.cells, np.uint8).reshape(grid.height, grid.width)
    img = np.where(cells == 255, 205, 255 - np.round(cells.astype(float) * 2.55)).astype(np.uint8)
    return img[::-1]


def write_grid(grid: OccupancyGrid, png: Path, yaml: Path | None) -> None:
    """``png`` (8-bit grey) and, if named, its map_server ``yaml`` (origin = lower-left corner)."""
    img = grid_image(grid) if grid.width and grid.height else np.full((1, 1), 205, np.uint8)
    atomic_write(png, lambda f: Image.fromarray(img, mode="L").save(f, format="PNG"))
    if yaml is not None:
        text = (f"image: {png.name}\nresolution: {grid.resolution_m:g}\n"
                f"origin: [{grid.origin_x_m:.6f}, {grid.origin_y_m:.6f}, 0.0]\n"
                "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n")
        atomic_write(yaml, text.encode())


def summary(*, world: str, seed: int, graph: MapGraph, stats: MapStats, links_measured: int, links_lost: int,
            links_inferred: int, sim_time_s: float, wall_time_s: float, complete: bool,
            ate_relaxed_m: float, ate_dead_reckoning_m: float, restarts: dict[str, int], parts: int = 1,
            similarity: Similarity | None = None) -> dict:
    """summary.json's content (architecture.md), with loss made visible (``links_lost``) and the relaxed
    map's error split into its turn and scale about the first place and the rest (``similarity``)."""
    return {
        "world": world,
        "seed": seed,
        "places": len(graph.places),
        "links_traversed": len(graph.links),
        "links_inferred": links_inferred,
        "links_measured": links_measured,
        "links_lost": links_lost,
        "sim_time_s": round(sim_time_s, 3),
        "wall_time_s": round(wall_time_s, 3),
        "real_time_factor": round(sim_time_s / wall_time_s, 2) if wall_time_s > 0 else None,
        "exploration_complete": complete,
        "energy": graph.energy,
        "ate_relaxed_m": None if np.isnan(ate_relaxed_m) else round(ate_relaxed_m, 4),
        "ate_dead_reckoning_m": None if np.isnan(ate_dead_reckoning_m) else round(ate_dead_reckoning_m, 4),
        "map_scale": None if similarity is None else round(similarity.scale, 5),
        "map_turn_deg": None if similarity is None else round(math.degrees(similarity.turn_rad), 3),
        "ate_relaxed_similarity_m": None if similarity is None else round(similarity.residual_m, 4),
        "iterations": stats.iterations,
        "updates": stats.updates,
        "cycle_ms_mean": round(stats.cycle_ms_mean, 3),
        "cycle_ms_p99": round(stats.cycle_ms_p99, 3),
        "noise": {"s_dd": graph.noise.s_dd, "s_aa": graph.noise.s_aa, "s_da": graph.noise.s_da},
        "restarts": restarts,
        "parts": parts,
    }


def write_json(path: Path, obj: object) -> None:
    atomic_write(path, (json.dumps(obj, indent=2) + "\n").encode())


COMPASS_HEADING_INFORMATION = 1e6  # map.g2o: headings are known from the compass (all 0), held tight


def core_graph(graph: MapGraph):
    """The relaxer's array graph and coordinates rebuilt from a ``map/graph`` reply."""
    from services.relaxer.graph import MapGraph as Graph

    g = Graph()
    g.add_places([p.place_id for p in graph.places])
    for lk in graph.links:
        g.add_link(lk.from_id, lk.to_id, d_m=lk.d_m, theta_rad=lk.theta_rad, steps=lk.steps,
                   mean_step_m=lk.mean_step_m, variance_m2=lk.variance_m2)
    xy = np.array([(p.x_m, p.y_m) for p in graph.places], dtype=float).reshape(-1, 2)
    return g, xy


def write_map_files(graph: MapGraph, map_json: Path, map_g2o: Path) -> None:
    """``map.json`` (compass mode, architecture.md) and ``map.g2o`` (the same map as a pose graph).

    In ``map.g2o`` every place is a pose with heading 0 and every link an edge whose translation is
    the measured displacement ``D_ji`` and whose information is ``C_ji^-1`` (Eq. 5), with a tight
    heading information (the compass fixes all headings).
    """
    from services.relaxer.compass import CompassNoise, link_information
    from services.relaxer.g2o import write_g2o
    from services.relaxer.mapjson import write_map_json
    from services.relaxer.pose import PoseGraph

    g, xy = core_graph(graph)
    noise = CompassNoise(s_dd_m2=graph.noise.s_dd, s_aa_rad2=graph.noise.s_aa, s_da_m_rad=graph.noise.s_da)
    write_map_json(map_json, g, xy, noise, graph.pinned)
    w = link_information(g, noise)
    info = np.zeros((g.n_links, 3, 3))
    info[:, 0, 0], info[:, 0, 1], info[:, 1, 1] = w[:, 0], w[:, 1], w[:, 2]
    info[:, 1, 0] = w[:, 1]
    info[:, 2, 2] = COMPASS_HEADING_INFORMATION
    z = np.column_stack([g.disp, np.zeros(g.n_links)]) if g.n_links else np.zeros((0, 3))
    pg = PoseGraph(ids=g.ids.copy(), i=g.src.copy(), j=g.dst.copy(), z=z, info=info)
    write_g2o(map_g2o, pg, np.column_stack([xy, np.zeros(len(xy))]))


def write_outputs(session, robot: str, out: Path, monitor, *, world: str, seed: int, wall_time_s: float,
                  restarts: dict[str, int], parts: int = 1, grid_resolution_m: float = 0.15) -> dict:
    """Ask the relaxer for the final map and write every output file of the run; returns the summary."""
    from messages import topics
    from services.runtime import query

    graph = query(session, topics.map_graph(robot), type_=MapGraph, timeout_s=30)
    stats = query(session, topics.map_stats(robot), type_=MapStats, timeout_s=30)
    if graph.places:
        write_map_files(graph, out / "map.json", out / "map.g2o")
    else:  # a map file without a place is not a map: no reader of map.json or g2o takes one
        log.warning("no place was confirmed: map.json and map.g2o are not written")
    for frame, png, yaml in (("relaxed", "grid.png", "grid.yaml"), ("dead_reckoning", "grid_dead_reckoning.png", None)):
        grid = query(session, topics.map_grid(robot), {"resolution": grid_resolution_m, "frame": frame},
                     type_=OccupancyGrid, timeout_s=120)
        write_grid(grid, out / png, out / yaml if yaml else None)
    relaxed = {p.place_id: (p.x_m, p.y_m) for p in graph.places}
    truth = monitor.place_truth()
    first = min(relaxed) if relaxed else -1
    in_map = {(min(lk.from_id, lk.to_id), max(lk.from_id, lk.to_id)) for lk in graph.links}
    lost = monitor.links_lost(in_map)
    result = summary(world=world, seed=seed, graph=graph, stats=stats, links_measured=len(monitor.measured),
                     links_lost=len(lost), links_inferred=len(monitor.inferred), sim_time_s=monitor.sim_time_s,
                     wall_time_s=wall_time_s, complete=bool(monitor.progress()["complete"]),
                     ate_relaxed_m=ate_m(relaxed, truth, first),
                     ate_dead_reckoning_m=ate_m(monitor.place_dead_reckoning(), truth, first), restarts=restarts,
                     parts=parts, similarity=similarity_about(relaxed, truth, first))
    if lost:
        result["links_lost_pairs"] = sorted(lost)
    write_json(out / "truth.json", {"places": [{"id": i, "x": x, "y": y} for i, (x, y) in sorted(truth.items())],
                                    "note": "true position of each place (the robot's when it was confirmed)"})
    write_json(out / "summary.json", result)
    return result
