"""World loading: the built-in worlds, ROS map_server pairs, malformed files; ground-truth queries."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from sim.geometry import ray_cast
from sim.world import (
    ROBOT_RADIUS_M,
    WorldError,
    builtin_worlds,
    load_world,
    raster_walls,
    world_from_dict,
)

SIZES = {"orebro-office": (46.0, 12.0), "manchester-corridors": (34.0, 33.0)}


def test_builtin_worlds_are_listed():
    assert set(builtin_worlds()) >= {"orebro-office", "manchester-corridors", "campus"}


@pytest.mark.parametrize("name", builtin_worlds())
def test_every_builtin_world_loads(name):
    w = load_world(name)
    assert w.name == name
    assert w.walls.ndim == 2 and w.walls.shape[1] == 4 and w.walls.shape[0] >= 20
    width, height = w.size_m
    if name in SIZES:
        assert width == pytest.approx(SIZES[name][0], abs=1.0)
        assert height == pytest.approx(SIZES[name][1], abs=1.0)
    if name == "campus":
        assert width >= 100 and height >= 60
    assert w.clearance(*w.start[:2]) >= ROBOT_RADIUS_M
    assert w.magnetic_disturbances, "every built-in world has magnetic disturbances"
    # every route is drivable: each leg (and the closing leg) is free for the robot's disc
    assert w.routes
    for rname, pts in w.routes.items():
        legs = list(zip(pts, np.roll(pts, -1, axis=0), strict=True))
        for a, b in legs:
            assert w.segment_free(a[0], a[1], b[0], b[1]), f"{name} route {rname}: leg {a} -> {b} blocked"
    # the free space reachable from the start is most of the floor and never touches a wall
    grid = w.truth_grid(0.25)
    assert grid.reachable.sum() * 0.0625 > 0.2 * width * height
    assert not (grid.reachable & grid.occupied).any()


def test_corridors_are_wide_enough_for_the_robot():
    # along every route the robot keeps its radius + 0.2 m from every wall (doors are 1.25 m), and
    # across the middle of every leg longer than 4 m (a corridor) there are at least 1.5 m
    for name in builtin_worlds():
        w = load_world(name)
        for rname, pts in w.routes.items():
            for a, b in zip(pts, np.roll(pts, -1, axis=0), strict=True):
                length = math.hypot(*(b - a))
                for t in np.linspace(0, 1, int(length / 0.25) + 1):
                    p = a + t * (b - a)
                    assert w.clearance(*p) >= ROBOT_RADIUS_M + 0.2, (name, rname, p)
                if length > 4.0:
                    across = math.atan2(*(b - a)[::-1]) + math.pi / 2
                    ranges, _, _ = ray_cast((a + b) / 2, np.array([across, across + math.pi]), w.walls, 50.0)
                    assert ranges.sum() >= 1.5, (name, rname, a, b, ranges)


def test_ray_cast_in_a_builtin_world():
    w = load_world("manchester-corridors")
    # on the south corridor's centre line (corridor from y 0.25 to 2.25): 1 m to either wall
    ranges, _, _ = ray_cast(np.array([8.0, 1.25]), np.radians([90.0, -90.0]), w.walls, 6.5)
    assert ranges == pytest.approx([1.0, 1.0])


def test_ground_truth_queries():
    w = load_world("manchester-corridors")
    assert w.segment_free(3.0, 1.25, 7.0, 1.25)
    assert not w.segment_free(3.0, 1.25, 3.0, 5.0)  # into the wall of the lower-left block
    assert not w.segment_free(3.0, 1.25, 3.0, 1.25 + 0.8)  # the disc would touch the wall at 2.25
    occ = w.occupied(np.array([[8.0, 1.25], [8.0, 2.25], [8.0, 2.3], [-1.0, 1.0], [5.0, 3.0]]))
    assert list(occ) == [False, True, True, True, False]


def test_raster_walls_merge_edges():
    one = raster_walls(np.array([[True]]), 1.0)
    assert one.shape == (4, 4)
    block = raster_walls(np.array([[True, True, True]]), 0.5, origin_x_m=10.0, origin_y_m=-1.0)
    assert block.shape == (4, 4)  # three cells, one rectangle: collinear edges merged
    xs, ys = block[:, [0, 2]], block[:, [1, 3]]
    assert xs.min() == 10.0 and xs.max() == 11.5 and ys.min() == -1.0 and ys.max() == -0.5
    ring = np.ones((3, 3), dtype=bool)
    ring[1, 1] = False
    assert raster_walls(ring, 1.0).shape == (8, 4)  # outer square and inner square


# -- ROS map_server pairs --------------------------------------------------------------------------------


def _room_image(rows=40, cols=60):
    """A 0.1 m map: a 6 x 4 m room whose walls are one cell thick, a pillar inside; unknown corner."""
    img = np.full((rows, cols), 254, dtype=np.uint8)  # free
    img[0, :] = img[-1, :] = img[:, 0] = img[:, -1] = 0  # occupied border
    img[18:22, 40:44] = 0  # a pillar
    img[1:4, 1:4] = 205  # unknown
    return img


def _write_pgm(path, img):
    h, w = img.shape
    path.write_bytes(f"P5\n{w} {h}\n255\n".encode() + img.tobytes())


def test_ros_map_pair_pgm(tmp_path):
    _write_pgm(tmp_path / "room.pgm", _room_image())
    (tmp_path / "room.yaml").write_text(
        "image: room.pgm\nresolution: 0.1  # m per cell\norigin: [-1.0, 2.0, 0.0]\nnegate: 0\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.196\n")
    w = load_world(tmp_path / "room.yaml")
    assert w.name == "room"
    assert w.size_m == pytest.approx((6.0, 4.0))
    assert w.bounds[:2] == pytest.approx((-1.0, 2.0))
    # the start was chosen in free space with clearance
    assert w.clearance(*w.start[:2]) >= ROBOT_RADIUS_M
    assert not w.occupied(np.array([w.start[:2]]))[0]
    # image row 0 is the top: the pillar (rows 18..21, cols 40..43) spans y 2 + (40 - 22) * 0.1 = 3.8 .. 4.2
    assert w.occupied(np.array([[-1.0 + 4.2, 4.0]]))[0]
    assert not w.occupied(np.array([[-1.0 + 2.0, 4.0]]))[0]
    # from (0, 4): east, the pillar face at x = -1 + 4.0 = 3.0; west, the inside of the border at -0.9
    ranges, _, _ = ray_cast(np.array([0.0, 4.0]), np.array([0.0, math.pi]), w.walls, 6.5)
    assert ranges == pytest.approx([3.0, 0.9])


def test_ros_map_pair_png_with_start_and_negate(tmp_path):
    from PIL import Image

    Image.fromarray(255 - _room_image()).save(tmp_path / "neg.png")
    (tmp_path / "neg.yaml").write_text(
        "image: neg.png\nresolution: 0.1\norigin: [0.0, 0.0, 0.0]\nnegate: 1\nstart: [1.0, 1.0, 0.5]\nname: lab\n")
    w = load_world(str(tmp_path / "neg.yaml"))
    assert w.name == "lab" and w.start == (1.0, 1.0, 0.5)
    assert w.size_m == pytest.approx((6.0, 4.0))


# -- malformed worlds --------------------------------------------------------------------------------------

GOOD = {"name": "box", "walls": [[0, 0, 4, 0], [4, 0, 4, 4], [4, 4, 0, 4], [0, 4, 0, 0]], "start": [2, 2, 0]}


def _write(tmp_path, data, name="w.json"):
    p = tmp_path / name
    p.write_text(json.dumps(data) if not isinstance(data, str) else data)
    return p


def test_good_minimal_world(tmp_path):
    w = load_world(_write(tmp_path, GOOD))
    assert w.name == "box" and w.walls.shape == (4, 4) and not w.walls.flags.writeable


@pytest.mark.parametrize("patch, message", [
    ({"walls": []}, "no walls"),
    ({"walls": None}, "no walls"),
    ({"start": [0.1, 2.0, 0.0]}, "is inside a wall"),
    ({"start": [2.0, 3.9, 0.0]}, "is inside a wall"),
    ({"start": [9.0, 2.0, 0.0]}, "outside the walls"),
    ({"walls": [[0, 0, 4, "x"]]}, "walls[0][3] must be a number, got 'x'"),
    ({"walls": [[0, 0, 4]]}, "walls[0] must be a list of 4 numbers"),
    ({"walls": [[0, 0, 4, 0], [1, 1, 1, 1]]}, "walls[1] has zero length"),
    ({"start": [2, "two", 0]}, "start[1] must be a number"),
    ({"start": [2, 2, True]}, "start[2] must be a number, got True"),
    ({"start": None}, "start must be a list of 3 numbers"),
    ({"magnetic_disturbances": [{"x": 1, "y": 1, "radius": "big", "deviation_deg": 5}]},
     "magnetic_disturbances[0].radius must be a number"),
    ({"magnetic_disturbances": [{"x": 1, "y": 1, "radius": -1, "deviation_deg": 5}]}, "radius must be positive"),
    ({"routes": {"r": [[1, 1]]}}, "routes.r must be a list of at least two"),
])
def test_malformed_worlds_name_the_file_and_problem(tmp_path, patch, message):
    path = _write(tmp_path, {**GOOD, **patch})
    with pytest.raises(WorldError) as err:
        load_world(path)
    assert str(path) in str(err.value)
    assert message in str(err.value)


def test_missing_start_and_bad_json(tmp_path):
    data = dict(GOOD)
    del data["start"]
    with pytest.raises(WorldError, match="missing 'start'"):
        load_world(_write(tmp_path, data))
    with pytest.raises(WorldError, match="not valid JSON"):
        load_world(_write(tmp_path, "{walls: ", "bad.json"))
    with pytest.raises(WorldError, match="must be a JSON object"):
        load_world(_write(tmp_path, [1, 2], "list.json"))
    with pytest.raises(WorldError, match="not a built-in world"):
        load_world("no-such-world")
    with pytest.raises(WorldError, match="must be finite"):
        world_from_dict({**GOOD, "start": [2, float("nan"), 0]})


def test_malformed_ros_maps(tmp_path):
    _write_pgm(tmp_path / "room.pgm", _room_image())
    empty = np.full((10, 10), 254, dtype=np.uint8)
    _write_pgm(tmp_path / "empty.pgm", empty)
    cases = {
        "noimage.yaml": ("resolution: 0.1\norigin: [0, 0, 0]\n", "missing 'image'"),
        "gone.yaml": ("image: gone.pgm\nresolution: 0.1\norigin: [0, 0, 0]\n", "not found"),
        "empty.yaml": ("image: empty.pgm\nresolution: 0.1\norigin: [0, 0, 0]\n", "no walls"),
        "res.yaml": ("image: room.pgm\nresolution: fine\norigin: [0, 0, 0]\n", "resolution must be a number"),
        "origin.yaml": ("image: room.pgm\nresolution: 0.1\norigin: [0, 0]\n", "origin must be a list of 3"),
        "start.yaml": ("image: room.pgm\nresolution: 0.1\norigin: [0, 0, 0]\nstart: [4.15, 1.95, 0]\n",
                       "is inside a wall"),
        "syntax.yaml": ("image room.pgm\n", "expected 'key: value'"),
    }
    for name, (text, message) in cases.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(WorldError) as err:
            load_world(tmp_path / name)
        assert str(tmp_path / name) in str(err.value), name
        assert message in str(err.value), (name, str(err.value))
    (tmp_path / "junk.pgm").write_bytes(b"not an image")
    (tmp_path / "junk.yaml").write_text("image: junk.pgm\nresolution: 0.1\norigin: [0, 0, 0]\n")
    with pytest.raises(WorldError, match="cannot read map image junk.pgm"):
        load_world(tmp_path / "junk.yaml")


def test_builtin_world_files_match_their_plans():
    from sim.world import builtin_path
    from sim.worldgen import PLANS, plan_json

    for plan in PLANS:
        assert builtin_path(plan.name).read_text(encoding="utf-8") == plan_json(plan), (
            f"{plan.name}.json is stale: run python -m sim.worldgen")
