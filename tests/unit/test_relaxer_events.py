"""The relaxer applies the explorer's map events of one step together, whatever order they come in."""

from __future__ import annotations

import math

from messages.types import LinkDeleted, LinkMeasured, PlaceConfirmed, PlaceDeleted, VelocityCommand
from services.relaxer.node import ExplorerEvents
from services.relaxer.online import OnlineMap


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def place(seq: int, pid: int, x: float, y: float, stamp: float = 1.0) -> PlaceConfirmed:
    return PlaceConfirmed(stamp=stamp, seq=seq, place_id=pid, x_m=x, y_m=y)


def link(seq: int, a: int, b: int, dx: float, dy: float) -> LinkMeasured:
    return LinkMeasured(stamp=1.0, seq=seq, from_id=a, to_id=b, d_m=math.hypot(dx, dy), theta_rad=math.atan2(dy, dx),
                        steps=10, mean_step_m=0.1)


def command(tick: int, confirmed: int = -1, deleted: int = -1, links_deleted: int = -1) -> VelocityCommand:
    return VelocityCommand(stamp=tick * 0.1, seq=tick, v_mps=0.0, omega_radps=0.0, tick=tick, confirmed_seq=confirmed,
                           deleted_seq=deleted, links_deleted_seq=links_deleted)


def test_before_any_command_each_event_is_applied_as_it_comes():
    ev = ExplorerEvents(0.5, Clock())
    ev.add(place(0, 0, 0.0, 0.0))
    assert ev.ready() == [[place(0, 0, 0.0, 0.0)]]
    assert ev.applied == [0, -1, -1] and ev.ready() == []


def test_the_events_a_command_names_are_applied_together_once_all_are_heard():
    clock = Clock()
    ev = ExplorerEvents(0.5, clock)
    ev.command(command(0))
    deletion = PlaceDeleted(stamp=1.0, seq=0, place_id=3, reason="duplicate")
    ev.add(place(4, 9, 1.0, 0.0))  # heard before the command that names it, the deletion after it
    assert ev.ready() == []
    ev.command(command(1, confirmed=4, deleted=0))
    clock.t += 0.1
    assert ev.ready() == [], "applied before the place deletion the command names was heard"
    ev.add(deletion)
    assert ev.ready() == [[place(4, 9, 1.0, 0.0), deletion]]
    assert ev.applied == [4, 0, -1] and ev.timeouts == 0


def test_events_are_not_held_for_ever():
    clock = Clock()
    ev = ExplorerEvents(0.5, clock)
    ev.command(command(0))
    ev.command(command(1, confirmed=0, links_deleted=2))  # link deletion 2 never comes
    ev.add(place(0, 0, 0.0, 0.0))
    assert ev.ready() == []
    clock.t += 0.6
    assert ev.ready() == [[place(0, 0, 0.0, 0.0)]] and ev.timeouts == 1
    ev.add(place(1, 1, 1.0, 0.0))  # named by no command
    clock.t += 0.6
    assert ev.ready() == [[place(1, 1, 1.0, 0.0)]] and ev.timeouts == 2 and ev.applied == [1, -1, 2]


def test_an_event_heard_again_is_applied_at_once():
    clock = Clock()
    ev = ExplorerEvents(0.5, clock)
    ev.command(command(1, confirmed=0))
    ev.add(place(0, 0, 0.0, 0.0))
    assert ev.ready() == [[place(0, 0, 0.0, 0.0)]]
    ev.add(place(0, 0, 0.0, 0.0))  # history, after a restart of the explorer
    assert ev.ready() == [[place(0, 0, 0.0, 0.0)]]


def test_a_step_of_events_gives_one_update_and_the_same_map_in_any_order():
    def build(order: list) -> OnlineMap:
        m = OnlineMap()
        m.on_place_confirmed(place(0, 0, 0.0, 0.0))
        m.on_place_confirmed(place(1, 1, 1.1, 0.0))
        m.on_link_measured(link(0, 0, 1, 1.0, 0.0))
        m.on_link_measured(link(1, 2, 1, 1.0, 0.0))  # waits for place 2
        version = m.version
        out = m.on_explorer_events(order, 2.0)
        assert m.version == version + 1 and out.update is not None
        return m

    events = [place(2, 2, 0.05, 0.1, stamp=2.0), place(3, 3, 2.0, 0.0, stamp=2.0),
              LinkDeleted(stamp=2.0, seq=0, from_id=0, to_id=1, reason="blocked")]
    a, b = build(events), build(events[::-1])
    assert a.coordinates() == b.coordinates()
    assert set(a.links) == set(b.links) == {(1, 2)}


def test_a_step_whose_events_change_nothing_still_gives_an_update():
    """The recognizer and the explorer wait for the update that names the events applied."""
    m = OnlineMap()
    m.on_place_confirmed(place(0, 0, 0.0, 0.0))
    unknown = LinkDeleted(stamp=2.0, seq=0, from_id=0, to_id=5, reason="inferred, never measured")
    version = m.version
    out = m.on_explorer_events([unknown], 2.0)
    assert out.update is not None and out.update.changed == [] and out.update.iterations == 0
    assert m.version == version + 1 and m.coordinates() == {0: (0.0, 0.0)}
    assert m.on_link_deleted(0, 5, 2.0).update is None  # one event on its own: no update for nothing
