"""The built-in worlds drawn as free-space rectangles; ``python -m sim.worldgen`` rewrites sim/worlds/*.json."""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sim.world import raster_walls

RES_M = 0.25  # raster cell: every rectangle corner is a multiple of this

Rect = tuple[float, float, float, float]  # x0, y0, x1, y1 (metres)


@dataclass(frozen=True)
class Plan:
    """A floor plan: everything is solid except ``free`` rectangles, then ``solid`` ones are put back."""

    name: str
    width_m: float
    height_m: float
    free: list[Rect]
    solid: list[Rect]
    start: list[float]  # x_m, y_m, heading_rad
    disturbances: list[tuple[float, float, float, float]]  # x, y, radius, deviation_deg
    routes: dict[str, list[list[float]]] = field(default_factory=dict)


def plan_walls(plan: Plan) -> np.ndarray:
    """The outline of the plan's free space as wall segments (the raster's outer border dropped)."""
    cols, rows = round(plan.width_m / RES_M), round(plan.height_m / RES_M)
    occ = np.ones((rows, cols), dtype=bool)

    def cells(r: Rect) -> tuple[slice, slice]:
        x0, y0, x1, y1 = r
        return slice(round(y0 / RES_M), round(y1 / RES_M)), slice(round(x0 / RES_M), round(x1 / RES_M))

    for r in plan.free:
        occ[cells(r)] = False
    for r in plan.solid:
        occ[cells(r)] = True
    walls = raster_walls(occ, RES_M)
    w, h = plan.width_m, plan.height_m
    on_border = (((walls[:, 0] == 0) & (walls[:, 2] == 0)) | ((walls[:, 0] == w) & (walls[:, 2] == w))
                 | ((walls[:, 1] == 0) & (walls[:, 3] == 0)) | ((walls[:, 1] == h) & (walls[:, 3] == h)))
    return walls[~on_border]


def plan_json(plan: Plan) -> str:
    """The world file of a plan: one wall per line."""
    walls = [[round(float(v), 3) for v in wall] for wall in plan_walls(plan)]
    dist = [{"x": x, "y": y, "radius": r, "deviation_deg": d} for x, y, r, d in plan.disturbances]

    def block(items: list[str]) -> str:
        return ",\n".join(f"    {i}" for i in items)

    routes = [f"{json.dumps(k)}: {json.dumps(v)}" for k, v in plan.routes.items()]
    return (f'{{\n  "name": {json.dumps(plan.name)},\n  "walls": [\n{block([json.dumps(w) for w in walls])}\n  ],\n'
            f'  "start": {json.dumps(plan.start)},\n'
            f'  "magnetic_disturbances": [\n{block([json.dumps(d) for d in dist])}\n  ],\n'
            f'  "routes": {{\n{block(routes)}\n  }}\n}}\n')


# -- orebro-office: about 46 x 12 m, rooms off a corridor and an open lab (the paper's Figure 11) --------
OREBRO = Plan(
    name="orebro-office", width_m=46.0, height_m=12.0,
    free=[
        (0.25, 5.0, 32.25, 7.0),  # the corridor, 2 m wide
        # rooms south of the corridor
        (0.25, 0.25, 6.0, 4.75), (6.25, 0.25, 12.0, 4.75), (12.25, 0.25, 18.0, 4.75),
        (18.25, 0.25, 24.0, 4.75), (24.25, 0.25, 32.0, 4.75),
        # rooms north of the corridor
        (0.25, 7.25, 7.0, 11.75), (7.25, 7.25, 13.0, 11.75), (13.25, 7.25, 20.0, 11.75),
        (20.25, 7.25, 26.0, 11.75), (26.25, 7.25, 32.0, 11.75),
        # 1.25 m doors through the corridor walls
        (2.0, 4.75, 3.25, 5.0), (8.5, 4.75, 9.75, 5.0), (13.0, 4.75, 14.25, 5.0), (16.25, 4.75, 17.5, 5.0),
        (20.5, 4.75, 21.75, 5.0), (27.0, 4.75, 28.25, 5.0), (30.0, 4.75, 31.25, 5.0),
        (3.0, 7.0, 4.25, 7.25), (9.0, 7.0, 10.25, 7.25), (17.5, 7.0, 18.75, 7.25), (22.0, 7.0, 23.25, 7.25),
        (28.5, 7.0, 29.75, 7.25),
        # doors between neighbouring rooms (loops through two rooms)
        (13.0, 9.0, 13.25, 10.25), (24.0, 1.5, 24.25, 2.75),
        # the open lab at the east end, reached from the end of the corridor
        (32.25, 0.25, 45.75, 11.75),
    ],
    solid=[
        (32.0, 0.25, 32.25, 4.25), (32.0, 8.0, 32.25, 11.75),  # walls beside the lab entrance
        (36.5, 4.5, 41.5, 7.5),  # the lab's central bench island
        (44.0, 0.25, 45.75, 1.5), (33.0, 10.25, 35.5, 11.75),  # cupboards
        (0.25, 0.25, 1.5, 1.25), (10.5, 10.5, 12.5, 11.75), (19.0, 2.0, 20.5, 3.5), (29.0, 9.5, 31.0, 10.5),
    ],
    start=[2.0, 6.0, 0.0],
    disturbances=[(11.0, 6.0, 2.0, 12.0), (38.0, 2.0, 3.0, -18.0), (25.0, 9.5, 2.5, 8.0)],
    routes={
        "lab-loop": [[2.0, 6.0], [34.25, 6.0], [34.25, 2.5], [43.0, 2.5], [43.0, 9.0], [34.25, 9.0],
                     [34.25, 6.0]],
        "rooms-loop": [[9.625, 6.0], [9.625, 9.625], [18.125, 9.625], [18.125, 6.0]],
    },
)

# -- manchester-corridors: about 34 x 33 m of corridor loops (the paper's Figure 4) ----------------------
MANCHESTER = Plan(
    name="manchester-corridors", width_m=34.0, height_m=33.0,
    free=[
        (0.25, 0.25, 2.25, 32.75), (31.75, 0.25, 33.75, 32.75),  # west and east corridors
        (0.25, 0.25, 33.75, 2.25), (0.25, 30.75, 33.75, 32.75),  # south and north corridors
        (0.25, 15.5, 33.75, 17.5),  # the middle cross corridor
        (16.0, 0.25, 18.0, 17.5),  # the middle north-south corridor
        (4.0, 4.0, 14.0, 13.5), (8.0, 2.25, 9.25, 4.0),  # lower left: a room off the south corridor
        (20.0, 5.0, 29.5, 12.0), (18.0, 8.0, 20.0, 9.25), (29.5, 6.0, 31.75, 7.25),  # lower right: a short cut
        (3.0, 18.5, 9.0, 23.0), (5.0, 17.5, 6.25, 18.5),  # two offices off the cross corridor
        (10.0, 18.5, 15.0, 23.0), (12.0, 17.5, 13.25, 18.5),
        (20.0, 21.0, 30.0, 29.0), (24.0, 17.5, 25.5, 21.0), (22.0, 29.0, 23.5, 30.75),  # a hall: cross to north
    ],
    solid=[(24.0, 24.0, 26.0, 26.0), (6.0, 7.0, 7.0, 8.0), (11.0, 10.0, 12.0, 11.0)],  # pillars
    start=[8.0, 1.25, 0.0],
    disturbances=[(10.0, 1.25, 2.5, 12.0), (32.75, 20.0, 3.0, -15.0), (17.0, 16.5, 2.0, 10.0),
                  (25.0, 31.75, 3.0, -8.0), (1.25, 26.0, 2.0, 6.0)],
    routes={
        "outer-loop": [[8.0, 1.25], [32.75, 1.25], [32.75, 31.75], [1.25, 31.75], [1.25, 1.25]],
        "figure-eight": [[8.0, 1.25], [17.0, 1.25], [17.0, 16.5], [32.75, 16.5], [32.75, 31.75],
                         [1.25, 31.75], [1.25, 16.5], [17.0, 16.5], [17.0, 1.25]],
    },
)

# -- campus: 110 x 64 m, 3 m corridors around six blocks with halls and courtyards, for scale ------------
_XS = (0.25, 36.25, 72.25, 106.75)  # west edges of the north-south corridors
_YS = (0.25, 30.5, 60.75)  # south edges of the east-west corridors
CAMPUS = Plan(
    name="campus", width_m=110.0, height_m=64.0,
    free=[(x, 0.25, x + 3.0, 63.75) for x in _XS] + [(0.25, y, 109.75, y + 3.0) for y in _YS] + [
        (8.0, 8.0, 28.0, 24.0), (15.0, 3.25, 16.5, 8.0), (28.0, 14.0, 36.25, 15.5),  # hall, two doors
        (42.0, 6.0, 66.0, 26.0), (50.0, 3.25, 51.5, 6.0), (66.0, 18.0, 72.25, 19.5),  # courtyard
        (80.0, 8.0, 100.0, 26.0), (88.0, 26.0, 89.5, 30.5),  # hall
        (6.0, 38.0, 30.0, 56.0), (3.25, 46.0, 6.0, 47.5), (20.0, 56.0, 21.5, 60.75),  # courtyard
        (44.0, 38.0, 64.0, 54.0), (52.0, 33.5, 53.5, 38.0),  # hall
        (78.0, 36.0, 102.0, 56.0), (75.25, 44.0, 78.0, 45.5), (102.0, 40.0, 106.75, 41.5),  # courtyard
    ],
    solid=[(14.0, 14.0, 16.0, 16.0), (20.0, 14.0, 22.0, 16.0), (52.0, 14.0, 56.0, 18.0),
           (86.0, 14.0, 94.0, 20.0), (16.0, 45.0, 20.0, 49.0), (88.0, 44.0, 92.0, 48.0),
           (52.0, 44.0, 56.0, 46.0)],
    start=[10.0, 1.75, 0.0],
    disturbances=[(20.0, 1.75, 4.0, 10.0), (108.25, 30.0, 5.0, -14.0), (37.75, 45.0, 4.0, 9.0),
                  (73.75, 15.0, 3.0, -6.0), (60.0, 62.25, 5.0, 12.0), (1.75, 50.0, 4.0, -10.0)],
    routes={
        "perimeter": [[10.0, 1.75], [108.25, 1.75], [108.25, 62.25], [1.75, 62.25], [1.75, 1.75]],
        "west-loops": [[10.0, 1.75], [37.75, 1.75], [37.75, 32.0], [73.75, 32.0], [73.75, 62.25],
                       [1.75, 62.25], [1.75, 1.75]],
    },
)

PLANS = (OREBRO, MANCHESTER, CAMPUS)


def main(argv: list[str] | None = None) -> int:
    out_dir = Path(argv[0]) if argv else Path(__file__).with_name("worlds")
    out_dir.mkdir(parents=True, exist_ok=True)
    for plan in PLANS:
        (out_dir / f"{plan.name}.json").write_text(plan_json(plan), encoding="utf-8")
        print(f"{out_dir / plan.name}.json: {len(plan_walls(plan))} walls")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
