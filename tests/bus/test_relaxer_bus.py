"""The relaxer as a process on loopback: map updates, the query API, bad queries, and resume after SIGKILL."""

from __future__ import annotations

import math
import os
import signal
import time

import pytest

from messages import topics
from messages.codec import codec
from messages.types import (
    LinkMeasured,
    LocalizationBelief,
    MapGraph,
    MapStats,
    MapUpdate,
    OccupancyGrid,
    PathReply,
    PlaceConfirmed,
    PlaceReply,
    Pose2,
    ScanSet,
    SonarScan,
)
from services.runtime import AliveWatcher, QueryFailed, query
from tests.conftest import wait_until

ROBOT = "relaxtest"


class Bus:
    def __init__(self, session):
        self.session = session
        self.updates: list[MapUpdate] = []
        dec = codec(MapUpdate)
        self.sub = session.declare_subscriber(topics.map_update(ROBOT),
                                              lambda s: self.updates.append(dec.decode(s.payload.to_bytes())))
        self.places = session.declare_publisher(topics.places_confirmed(ROBOT))
        self.links = session.declare_publisher(topics.links_measured(ROBOT))

    def place(self, i, x, y):
        self.places.put(codec(PlaceConfirmed).encode(PlaceConfirmed(stamp=i, seq=i, place_id=i, x_m=x, y_m=y)))

    def link(self, a, b, dx, dy, seq=0):
        self.links.put(codec(LinkMeasured).encode(LinkMeasured(
            stamp=10.0 + seq, seq=seq, from_id=a, to_id=b, d_m=math.hypot(dx, dy), theta_rad=math.atan2(dy, dx),
            steps=10, mean_step_m=0.1)))

    def close(self):
        for e in (self.sub, self.places, self.links):
            e.undeclare()


def _start(processes, endpoint, store):
    return processes.python("services.relaxer", "--robot", ROBOT, "--connect", endpoint,
                            "--listen", "tcp/127.0.0.1:0", "--store", str(store))


@pytest.fixture
def relaxer(hub, processes, tmp_path):
    session, endpoint = hub
    watcher = AliveWatcher(session, ROBOT)
    proc = _start(processes, endpoint, tmp_path / "map.sqlite")
    assert watcher.wait_alive(["relaxer"], 20)
    bus = Bus(session)
    assert wait_until(lambda: bus.places.matching_status and bus.links.matching_status, 10)
    yield session, endpoint, proc, watcher, bus
    bus.close()
    watcher.close()


def _square(bus):
    for i, (x, y) in enumerate([(0, 0), (1.0, 0.05), (1.1, 1.05), (0.1, 1.15)]):
        bus.place(i, x, y)
    for k, (a, b, dx, dy) in enumerate([(0, 1, 1, 0), (1, 2, 0, 1), (2, 3, -1, 0), (3, 0, 0, -1)]):
        bus.link(a, b, dx, dy, seq=k)


def test_updates_and_queries(relaxer):
    session, _, proc, _, bus = relaxer
    _square(bus)
    assert wait_until(lambda: bus.updates and bus.updates[-1].links == 4, 10)
    # one update per event that changed the map (a link that arrives before its places waits for them)
    versions = [u.version for u in bus.updates]
    assert versions == list(range(1, len(versions) + 1)) and 4 <= len(versions) <= 8
    # each update names the latest link and place confirmation taken in (what followers wait for)
    named = [(u.link_seq, u.confirmed_seq) for u in bus.updates]
    assert named == sorted(named) and named[-1] == (3, 3) and named[0][1] >= 0
    g = query(session, topics.map_graph(ROBOT), type_=MapGraph)
    assert {p.place_id for p in g.places} == {0, 1, 2, 3} and len(g.links) == 4
    assert g.version in (versions[-1], versions[-1] + 1)  # asked for whole, a map short of its minimum settles
    g_json = query(session, topics.map_graph(ROBOT), fmt="json")
    assert len(g_json["places"]) == 4
    assert query(session, topics.map_place(ROBOT, 2), type_=PlaceReply).place.place_id == 2
    path = query(session, topics.map_path(ROBOT), "from=0&to=2", type_=PathReply)
    assert path.places[0] == 0 and path.places[-1] == 2 and path.length_m == pytest.approx(2.0)
    grid = query(session, topics.map_grid(ROBOT), "resolution=0.5", type_=OccupancyGrid)
    assert grid.resolution_m == 0.5
    assert query(session, topics.map_scans(ROBOT), "place=1&max_offset=0.5", type_=ScanSet).scans == []
    st = query(session, topics.map_stats(ROBOT), type_=MapStats)
    assert st.places == 4 and st.links == 4 and st.updates == g.version
    bad = [
        (topics.map_place(ROBOT, 99), "", "no place 99"),
        (topics.map_place(ROBOT, "abc"), "", "place id must be an integer"),
        (topics.map_path(ROBOT), "from=0", "missing parameter 'to'"),
        (topics.map_path(ROBOT), "from=0&to=x", "parameter 'to' must be an integer"),
        (topics.map_path(ROBOT), "from=0&to=42", "no place 42"),
        (topics.map_grid(ROBOT), "resolution=-1", "must be at least"),
        (topics.map_grid(ROBOT), "resolution=nan", "must be finite"),
        (topics.map_grid(ROBOT), "frame=sideways", "must be one of"),
        (topics.map_graph(ROBOT), "x=" + "y" * 5000, "unknown parameter"),
        (topics.map_scans(ROBOT), "place=99", "no place 99"),
        (topics.map_scans(ROBOT), "latest=-1", "must be at least 0"),
        (topics.map_scans(ROBOT), "max_offset=far", "must be a number"),
    ]
    for key, params, expected in bad:
        with pytest.raises(QueryFailed, match=expected):
            query(session, key, params)
    assert proc.poll() is None
    assert query(session, topics.map_stats(ROBOT), type_=MapStats).places == 4


def test_the_whole_map_asked_for_is_at_its_minimum(relaxer):
    """A chain confirmed far from where its links put it: one sweep per event leaves it short of the
    minimum, and the relaxer waits for a pause before it solves it exactly; asked for the whole map
    (map/graph) before that, it solves it first, so a map written at the end of a run is the minimum
    of its links whatever the timing (for a tree: every link met)."""
    session, _, proc, _, bus = relaxer
    for i in range(8):
        bus.place(i, 1.3 * i, 0.4 * i)  # dead reckoning 30% long and drifting
    for i in range(7):
        bus.link(i, i + 1, 1.0, 0.0, seq=i)
    assert wait_until(lambda: query(session, topics.map_stats(ROBOT), type_=MapStats).links == 7, 10)
    # the update with the seventh link may still be on its way to this session (a loaded machine)
    assert wait_until(lambda: bool(bus.updates) and bus.updates[-1].links == 7, 10)
    swept = {p.place_id: (p.x_m, p.y_m) for u in list(bus.updates) for p in u.changed}  # as last published
    g = query(session, topics.map_graph(ROBOT), type_=MapGraph)
    xy = {p.place_id: (p.x_m, p.y_m) for p in g.places}
    assert max(abs(x - i) for i, (x, _) in swept.items()) > 0.05  # the last sweep left it short
    for i in range(8):
        assert xy[i] == pytest.approx((float(i), 0.0), abs=1e-6)
    assert wait_until(lambda: bus.updates[-1].version == g.version, 5)  # the solve was published
    assert proc.poll() is None


def test_resume_after_sigkill(relaxer, processes, tmp_path):
    session, endpoint, proc, watcher, bus = relaxer
    _square(bus)
    assert wait_until(lambda: bus.updates and bus.updates[-1].links == 4, 10)
    before = query(session, topics.map_graph(ROBOT), type_=MapGraph)
    os.killpg(proc.pid, signal.SIGKILL)
    assert watcher.wait_gone("relaxer", 5)
    _start(processes, endpoint, tmp_path / "map.sqlite")
    assert watcher.wait_alive(["relaxer"], 20)
    after = query(session, topics.map_graph(ROBOT), type_=MapGraph)
    assert after.version == before.version
    # stored coordinates are written when a place moves more than 1e-6 m
    was = {p.place_id: (p.x_m, p.y_m) for p in before.places}
    now = {p.place_id: (p.x_m, p.y_m) for p in after.places}
    assert set(now) == set(was)
    assert all(math.dist(now[k], was[k]) < 1e-5 for k in now)
    assert sorted((lk.from_id, lk.to_id) for lk in after.links) == sorted((lk.from_id, lk.to_id) for lk in before.links)
    # mapping goes on from where it was
    assert wait_until(lambda: bus.places.matching_status, 10)
    bus.place(4, 2.0, 0.0)
    bus.link(1, 4, 1.0, 0.0, seq=9)
    assert wait_until(lambda: query(session, topics.map_stats(ROBOT), type_=MapStats).links == 5, 10)
    final = query(session, topics.map_graph(ROBOT), type_=MapGraph)
    assert final.version > before.version and len(final.places) == 5


def test_a_scan_is_kept_with_the_belief_of_its_stamp(relaxer):
    """A sonar scan is stored with the place, offset and dead-reckoned pose of the recognizer's belief
    of the same stamp, whichever of the two arrives first; a belief of another stamp is not used."""
    session, _, proc, _, bus = relaxer
    _square(bus)
    assert wait_until(lambda: bus.updates and bus.updates[-1].links == 4, 10)
    sonar = session.declare_publisher(topics.sonar(ROBOT))
    belief = session.declare_publisher(topics.localization(ROBOT))
    assert wait_until(lambda: sonar.matching_status and belief.matching_status, 10)

    def scan(stamp):
        sonar.put(codec(SonarScan).encode(SonarScan(
            stamp=stamp, seq=round(stamp), angles_rad=[0.0, math.pi], ranges_m=[1.0, 2.0], beam_width_rad=0.4,
            min_range_m=0.1, max_range_m=6.5)))

    def fix(stamp, place, off, pose):
        belief.put(codec(LocalizationBelief).encode(LocalizationBelief(
            stamp=stamp, seq=round(stamp), place_id=place, probability=0.9, offset_x_m=off[0], offset_y_m=off[1],
            offset_var_m2=0.01, pose=Pose2(x_m=pose[0], y_m=pose[1], heading_rad=pose[2]))))

    scan(20.0)
    time.sleep(0.3)  # so that it is handled first
    fix(19.0, 2, (0.4, 0.4), (9.0, 9.0, 0.0))  # the previous scan's belief: never paired with this one
    fix(20.0, 1, (0.1, -0.2), (1.1, -0.15, 0.5))  # after its scan
    fix(21.0, 2, (-0.05, 0.03), (1.05, 1.08, 1.5))  # before its scan
    time.sleep(0.3)
    scan(21.0)
    assert wait_until(lambda: len(query(session, topics.map_scans(ROBOT), type_=ScanSet).scans) == 2, 10)
    got = query(session, topics.map_scans(ROBOT), type_=ScanSet).scans
    assert [(s.stamp, s.place_id) for s in got] == [(20.0, 1), (21.0, 2)]
    assert (got[0].offset_x_m, got[0].offset_y_m, got[0].dr_x_m, got[0].dr_y_m, got[0].heading_rad) == \
        pytest.approx((0.1, -0.2, 1.1, -0.15, 0.5))
    assert (got[1].offset_x_m, got[1].offset_y_m, got[1].dr_x_m, got[1].dr_y_m) == pytest.approx((-0.05, 0.03, 1.05, 1.08))
    assert got[1].ranges_m == [1.0, 2.0]
    sonar.undeclare()
    belief.undeclare()
