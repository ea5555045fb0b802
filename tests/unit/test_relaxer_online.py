"""The relaxer service's core: events in, updates and store transactions out, queries answered."""

from __future__ import annotations

import math

import numpy as np
import pytest

from messages.types import LinkMeasured, PlaceConfirmed
from services.relaxer.online import OnlineMap, UnknownPlace
from services.relaxer.store import MapStore, StoredScan


def _place(i: int, x: float, y: float) -> PlaceConfirmed:
    return PlaceConfirmed(stamp=float(i), seq=i, place_id=i, x_m=x, y_m=y)


def _link(a: int, b: int, dx: float, dy: float, traversals: int = 1, stamp: float = 10.0) -> LinkMeasured:
    return LinkMeasured(stamp=stamp, seq=0, from_id=a, to_id=b, d_m=math.hypot(dx, dy), theta_rad=math.atan2(dy, dx),
                        steps=10, mean_step_m=0.1, traversals=traversals)


def square(m: OnlineMap) -> None:
    """Four places on a 1 m square, dead reckoning drifted, the loop closed by the last link."""
    for i, (x, y) in enumerate([(0, 0), (1.0, 0.05), (1.1, 1.05), (0.1, 1.15)]):
        m.on_place_confirmed(_place(i, x, y))
    m.on_link_measured(_link(0, 1, 1, 0))
    m.on_link_measured(_link(1, 2, 0, 1))
    m.on_link_measured(_link(2, 3, -1, 0))
    m.on_link_measured(_link(3, 0, 0, -1))


def test_updates_count_up_and_relax_the_loop():
    m = OnlineMap()
    square(m)
    assert m.version == 8
    for _ in range(200):
        out = m.cycle(20.0)
    xy = m.coordinates()
    assert xy[0] == (0.0, 0.0)  # pinned
    for pid, want in {1: (1, 0), 2: (1, 1), 3: (0, 1)}.items():
        assert np.allclose(xy[pid], want, atol=1e-6)
    assert out.update.version == m.version and out.update.places == 4 and out.update.links == 4


def test_link_before_its_places_waits_for_them():
    m = OnlineMap()
    m.on_place_confirmed(_place(0, 0, 0))
    out = m.on_link_measured(_link(0, 1, 1, 0))
    assert out.update is None and m.links == {}
    out = m.on_place_confirmed(_place(1, 0.9, 0.0))
    assert (0, 1) in m.links and out.update.links == 1
    assert [lk for lk, _ in out.tx.links][0].to_id == 1


def test_later_traversal_replaces_the_measurement():
    m = OnlineMap()
    square(m)
    m.on_link_measured(_link(1, 0, -1.02, 0.0, traversals=2))
    assert len(m.links) == 4 and m.links[(0, 1)].traversals == 2 and m.links[(0, 1)].from_id == 1


def test_delete_place_and_link():
    m = OnlineMap()
    square(m)
    m.on_link_deleted(3, 0, 30.0)
    assert (0, 3) not in m.links
    out = m.on_place_deleted(2, 31.0)
    assert out.tx.deleted_places == [2]
    assert set(m.coordinates()) == {0, 1, 3}
    assert set(m.links) == {(0, 1)}
    m.on_place_deleted(9, 32.0)  # a place the map never held (a predicted one): its id is taken too
    assert m.graph().deleted == [2, 9]


def test_a_deletion_heard_again_does_not_remove_the_link_measured_after_it(tmp_path):
    """A link deleted at 30 s and measured again at 40 s stays when the deletion comes again (the
    subscriber's history after a restart), in memory and after a resume from the store."""
    store = MapStore(tmp_path / "m.sqlite")
    m = OnlineMap()
    for i, (x, y) in enumerate([(0, 0), (1.0, 0.05)]):
        store.commit(m.on_place_confirmed(_place(i, x, y)).tx)
    store.commit(m.on_link_measured(_link(0, 1, 1, 0, stamp=10.0)).tx)
    store.commit(m.on_link_deleted(0, 1, 30.0).tx)
    assert (0, 1) not in m.links
    store.commit(m.on_link_measured(_link(1, 0, -1, 0, traversals=2, stamp=40.0)).tx)
    assert m.on_link_deleted(0, 1, 30.0).update is None and (0, 1) in m.links
    store.close()
    again = OnlineMap(stored=MapStore(tmp_path / "m.sqlite").load())
    assert again.on_link_deleted(1, 0, 30.0).update is None and (0, 1) in again.links
    assert again.on_link_deleted(1, 0, 50.0).update is not None and (0, 1) not in again.links


def test_a_deletion_keeps_a_waiting_measurement_taken_after_it():
    m = OnlineMap()
    m.on_place_confirmed(_place(0, 0, 0))
    m.on_link_measured(_link(0, 1, 1, 0, stamp=40.0))  # place 1 is on its way
    m.on_link_deleted(0, 1, 30.0)
    m.on_place_confirmed(_place(1, 0.9, 0.0))
    assert (0, 1) in m.links


def test_queries():
    m = OnlineMap()
    square(m)
    g = m.graph()
    assert len(g.places) == 4 and len(g.links) == 4 and g.pinned == 0
    assert m.place(2).place.place_id == 2 and len(m.place(2).links) == 2
    with pytest.raises(UnknownPlace):
        m.place(99)
    p = m.path(0, 2)
    assert p.places in ([0, 1, 2], [0, 3, 2]) and p.length_m == pytest.approx(2.0)
    m.on_place_confirmed(_place(7, 5, 5))
    assert m.path(0, 7) is None
    st = m.stats()
    assert st.places == 5 and st.links == 4 and st.updates == m.updates


def test_grid_places_scans_at_relaxed_coordinates():
    m = OnlineMap()
    square(m)
    angles = np.deg2rad(np.arange(16) * 22.5)
    ranges = np.full(16, 6.5)
    ranges[4] = 1.0  # a wall 1 m north of place 2
    m.add_scan(StoredScan(0.0, 2, 0.0, 0.0, 50.0, 50.0, 0.0, angles, ranges, np.deg2rad(25), 6.5))
    relaxed = m.grid(0.15, "relaxed")
    dr = m.grid(0.15, "dead_reckoning")
    x2, y2 = m.coordinates()[2]
    for grid, (x, y) in ((relaxed, (x2, y2 + 1.0)), (dr, (50.0, 51.0))):
        cells = np.frombuffer(grid.cells, np.uint8).reshape(grid.height, grid.width)
        col = int((x - grid.origin_x_m) / grid.resolution_m)
        row = int((y - grid.origin_y_m) / grid.resolution_m)
        assert cells[row, col] > 60
    with pytest.raises(ValueError, match="cells"):
        m.grid(0.001, "relaxed", max_cells=1000)


def test_scan_set_filters_by_place_offset_and_recency():
    m = OnlineMap()
    square(m)
    angles, ranges = np.zeros(4), np.full(4, 2.0)
    for k, (pid, off) in enumerate([(0, 0.1), (1, 0.2), (1, 1.2), (2, 0.3), (1, 0.4)]):
        m.add_scan(StoredScan(float(k), pid, off, 0.0, 10.0 + k, 0.0, 0.5, angles, ranges, 0.4, 6.5))
    every = m.scan_set()
    assert [s.stamp for s in every.scans] == [0.0, 1.0, 2.0, 3.0, 4.0] and every.version == m.version
    assert every.scans[2].place_id == 1 and every.scans[2].offset_x_m == 1.2 and every.scans[2].dr_x_m == 12.0
    assert every.scans[2].ranges_m == [2.0] * 4 and every.scans[2].heading_rad == 0.5
    assert [s.stamp for s in m.scan_set(place_id=1).scans] == [1.0, 2.0, 4.0]
    assert [s.stamp for s in m.scan_set(place_id=1, max_offset_m=0.5).scans] == [1.0, 4.0]
    assert [s.stamp for s in m.scan_set(max_offset_m=0.25).scans] == [0.0, 1.0]
    assert [s.stamp for s in m.scan_set(latest=2).scans] == [3.0, 4.0]
    assert m.scan_set(latest=0).scans == []
    with pytest.raises(UnknownPlace, match="no place 42"):
        m.scan_set(place_id=42)


def test_resume_from_store(tmp_path):
    store = MapStore(tmp_path / "m.sqlite")
    m = OnlineMap()
    for msg in [_place(0, 0, 0), _place(1, 1.0, 0.1), _link(0, 1, 1, 0)]:
        out = m.on_place_confirmed(msg) if isinstance(msg, PlaceConfirmed) else m.on_link_measured(msg)
        store.commit(out.tx)
    store.close()
    again = OnlineMap(stored=MapStore(tmp_path / "m.sqlite").load())
    assert again.version == m.version
    a, b = again.coordinates(), m.coordinates()
    assert set(a) == set(b) and all(np.allclose(a[k], b[k], atol=1e-12) for k in a)
    assert again.links == m.links


def test_replays_and_any_order_leave_the_same_map():
    m = OnlineMap()
    square(m)
    version = m.version
    square(m)  # the whole history again: nothing changes
    assert m.version == version
    m.on_link_measured(_link(0, 1, 1.01, 0.0, traversals=3))
    m.on_link_measured(_link(0, 1, 1.0, 0.0, traversals=1))  # an older measurement comes late
    assert m.links[(0, 1)].traversals == 3
    m.on_place_deleted(3, 40.0)
    m.on_place_confirmed(_place(3, 0.1, 1.15))  # a replayed confirmation of a deleted place
    m.on_link_measured(_link(2, 3, -1, 0))
    assert 3 not in m.coordinates() and (2, 3) not in m.links
    m.on_place_deleted(9, 41.0)  # deleted before it was ever confirmed (topics are not ordered)
    m.on_place_confirmed(_place(9, 3.0, 3.0))
    assert 9 not in m.coordinates()


def test_anchor_finds_the_nearest_place_by_its_first_position():
    m = OnlineMap()
    square(m)
    assert m.anchor(1.05, 0.0) == (1, pytest.approx(0.05), pytest.approx(-0.05))
    assert m.anchor(10.0, 10.0) is None
    m.on_place_deleted(1, 50.0)
    assert m.anchor(1.05, 0.0)[0] != 1


@pytest.mark.parametrize("bad", [
    {"d_m": float("nan")}, {"d_m": -1.0}, {"theta_rad": float("inf")}, {"steps": 0}, {"mean_step_m": 0.0},
    {"variance_m2": -0.1}, {"variance_m2": float("nan")},
])
def test_impossible_measurements_are_refused_and_change_nothing(bad):
    import msgspec

    m = OnlineMap()
    square(m)
    before, version = m.coordinates(), m.version
    msg = msgspec.structs.replace(_link(0, 2, 1.0, 1.0), **bad)
    with pytest.raises(ValueError):
        m.on_link_measured(msg)
    with pytest.raises(ValueError):
        m.on_place_confirmed(msgspec.structs.replace(_place(9, 1.0, 1.0), x_m=float("nan")))
    assert m.coordinates() == before and m.version == version and (0, 2) not in m.links


def test_settle_brings_a_map_left_by_single_sweeps_to_its_minimum():
    """A chain whose places were confirmed far from where its links put them: one sweep per event
    leaves it short of the minimum; settle solves it exactly (for a tree: every link met), once."""
    m = OnlineMap()
    for i in range(8):
        m.on_place_confirmed(_place(i, 1.3 * i, 0.4 * i))  # dead reckoning 30% long and drifting
    for i in range(7):
        m.on_link_measured(_link(i, i + 1, 1.0, 0.0))
    before = m.coordinates()
    assert max(abs(before[i][0] - i) for i in range(8)) > 0.05  # not there yet
    v = m.version
    out = m.settle()
    assert out is not None and out.update is not None and m.version == v + 1
    xy = m.coordinates()
    for i in range(8):
        assert xy[i] == pytest.approx((float(i), 0.0), abs=1e-9)
    assert m.settle() is None  # at rest: nothing more to do
    m.on_link_measured(_link(0, 7, 7.0, 0.0))  # a loop closed (solved at once): still at rest
    assert m.settle() is None
