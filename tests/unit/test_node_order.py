"""The explorer's and the recognizer's shells wait for what a message names, not for its order.

zenoh keeps the order of one key's messages, not across keys: a scan can come after the odometry
step of its tick, a place event after the velocity command sent after it. The odometry step names
the latest scan of its tick or before (``sonar_seq``) and the command the latest place events
(``confirmed_seq``, ``deleted_seq``, ``links_deleted_seq``); these tests hand the shells their inputs
in the wrong order and check that the outcome is the one of the right order.
"""

from __future__ import annotations

import numpy as np
from msgspec.structs import replace as msgspec_replace

from messages.types import (DeadReckonedPose, LocalizationBelief, MapUpdate, NoiseParams, PlaceConfirmed,
                            PlacePosition, RecognizerProgress, VelocityCommand)
from services.dead_reckoning import core as dr_core
from services.explorer.node import ExplorerNodeParams, ExplorerShell
from services.place_recognizer.node import PlaceRecognizerNodeParams, RecognizerShell
from services.sensor_sim import core as sim_core
from sim.world import load_world


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def frames(n: int):
    """``n`` ticks of campus with a scan at every tick, and their dead-reckoned poses."""
    model = sim_core.SimModel(load_world("campus"), sim_core.SensorSimParams(sonar_every_m=0.0, sonar_period_s=0.1))
    rng = np.random.default_rng(0)
    state, frame = sim_core.start(model, rng)
    dr = dr_core.DrState()
    out = []
    for _ in range(n):
        dr, poses = dr_core.step(dr, frame.compass)
        if frame.odometry is not None:
            dr, more = dr_core.step(dr, frame.odometry)
            poses += more
        out.append((frame, poses[-1]))
        state, frame = sim_core.step(state, (0.3, 0.0), model, rng)
    return out


def test_odometry_names_the_scan_of_its_own_tick():
    fs = frames(4)
    for (before, _), (frame, _) in zip(fs, fs[1:]):
        assert frame.odometry.sonar_seq == frame.sonar.seq == before.sonar.seq + 1


def explorer(clock: Clock) -> tuple[ExplorerShell, list]:
    sent: list = []
    shell = ExplorerShell(ExplorerNodeParams(wait_localization=False, localization_timeout_s=2.0),
                          lambda name, msg: sent.append((name, msg)), clock=clock)
    return shell, sent


def commands(sent: list) -> list[VelocityCommand]:
    return [m for name, m in sent if name == "cmd_velocity"]


def test_explorer_waits_for_the_scan_an_odometry_step_names():
    clock = Clock()
    (f0, p0), (f1, p1), (f2, p2) = frames(3)
    shell, sent = explorer(clock)
    shell.on_dr_pose(p0)
    assert [c.tick for c in commands(sent)] == [0]
    shell.on_sonar(f0.sonar)
    # tick 1: the scan comes after the odometry step and the pose that name it
    shell.on_odometry(f1.odometry)
    shell.on_dr_pose(p1)
    clock.t += 1.0
    shell.check_timeout()
    assert [c.tick for c in commands(sent)] == [0], "tick 1 answered before the scan of tick 1 was heard"
    shell.on_sonar(f1.sonar)
    assert [c.tick for c in commands(sent)] == [0, 1]
    assert shell.counts["scans"] == 1  # tick 1 is answered with the scan of tick 0
    shell.on_sonar(f2.sonar)  # tick 2 in order
    shell.on_odometry(f2.odometry)
    shell.on_dr_pose(p2)
    assert [c.tick for c in commands(sent)] == [0, 1, 2]
    assert shell.counts["scans"] == 2 and shell.counts["late_scans"] == 0 and shell.counts["scan_timeouts"] == 0


def test_explorer_stops_waiting_for_a_scan_lost_for_good():
    clock = Clock()
    (f0, p0), (f1, p1), (f2, p2), (f3, p3) = frames(4)
    shell, sent = explorer(clock)
    shell.on_dr_pose(p0)
    shell.on_odometry(f1.odometry)  # the scans of ticks 0 and 1 never come
    shell.on_dr_pose(p1)
    assert [c.tick for c in commands(sent)] == [0]
    clock.t += 2.5
    shell.check_timeout()
    assert [c.tick for c in commands(sent)] == [0, 1]
    assert shell.counts["scan_timeouts"] == 1 and shell.counts["scans"] == 0
    shell.on_sonar(f1.sonar)  # late after all: it serves tick 2; from here on in order, no wait
    shell.on_sonar(f2.sonar)
    shell.on_odometry(f2.odometry)
    shell.on_dr_pose(p2)
    assert [c.tick for c in commands(sent)] == [0, 1, 2]
    assert shell.counts["scan_timeouts"] == 1 and shell.counts["scans"] == 1


def test_explorer_command_names_the_place_events_before_it():
    clock = Clock()
    shell, sent = explorer(clock)
    ticks = frames(40)
    for frame, pose in ticks:
        if frame.odometry is not None:
            shell.on_odometry(frame.odometry)
        shell.on_dr_pose(pose)
        shell.on_sonar(frame.sonar)
    seen = {"places_confirmed": -1, "places_deleted": -1}
    checked = 0
    for name, msg in sent:
        if name in seen:
            seen[name] = msg.seq
        elif name == "cmd_velocity":
            assert (msg.confirmed_seq, msg.deleted_seq) == (seen["places_confirmed"], seen["places_deleted"])
            checked += seen["places_confirmed"] >= 0
    assert checked > 0, "no place was confirmed in 4 s of driving"


def recognizer(clock: Clock) -> tuple[RecognizerShell, list]:
    beliefs: list = []
    shell = RecognizerShell(PlaceRecognizerNodeParams(order_timeout_s=0.5), beliefs.append, lambda msg: None,
                            clock=clock)
    return shell, beliefs


def confirmation(pose: DeadReckonedPose, seq: int = 0) -> PlaceConfirmed:
    return PlaceConfirmed(stamp=pose.stamp, seq=seq, place_id=7, x_m=pose.compass.x_m, y_m=pose.compass.y_m)


def command(pose: DeadReckonedPose, tick: int, confirmed_seq: int) -> VelocityCommand:
    return VelocityCommand(stamp=pose.stamp, seq=tick, v_mps=0.3, omega_radps=0.0, tick=tick,
                           confirmed_seq=confirmed_seq)


def feed_tick(shell: RecognizerShell, frame, pose: DeadReckonedPose) -> None:
    if frame.odometry is not None:
        shell.on_odometry(frame.odometry)
    shell.on_dr_pose(pose)
    shell.on_sonar(frame.sonar)


def test_recognizer_applies_a_place_event_heard_after_the_command_before_the_next_scan():
    clock = Clock()
    (f0, p0), (f1, p1) = frames(2)
    shell, beliefs = recognizer(clock)
    feed_tick(shell, f0, p0)
    assert len(beliefs) == 1
    shell.on_command(command(p0, 0, confirmed_seq=0))  # the explorer confirmed place 7 at tick 0
    feed_tick(shell, f1, p1)
    clock.t += 0.1
    shell.drain()
    assert len(beliefs) == 1, "the scan of tick 1 was localised before the place event it comes after"
    shell.on_explorer_event(confirmation(p0))
    assert len(beliefs) == 2
    assert beliefs[-1].place_id == 7  # localised at the place confirmed before it
    assert shell.counts["late_events"] == 0 and shell.counts["order_timeouts"] == 0


def test_recognizer_applies_a_place_event_after_the_scan_its_odometry_step_names():
    clock = Clock()
    (f0, p0), (f1, p1), (f2, p2) = frames(3)
    shell, beliefs = recognizer(clock)
    feed_tick(shell, f0, p0)
    shell.on_command(command(p0, 0, confirmed_seq=-1))
    # tick 1: odometry and pose, the scan late; the explorer confirms a place at tick 1
    shell.on_odometry(f1.odometry)
    shell.on_dr_pose(p1)
    shell.on_command(command(p1, 1, confirmed_seq=0))
    shell.on_odometry(f2.odometry)
    shell.on_dr_pose(p2)
    shell.on_explorer_event(confirmation(p1))
    clock.t += 0.1
    shell.drain()
    assert shell.counts["places"] == 0, "the place of tick 1 was applied before the scan of tick 1"
    shell.on_sonar(f1.sonar)
    assert shell.counts["places"] == 1 and len(beliefs) == 2
    assert beliefs[-1].place_id != 7  # the scan of tick 1 was localised before place 7 existed
    shell.on_sonar(f2.sonar)
    assert len(beliefs) == 3 and beliefs[-1].place_id == 7
    assert shell.counts["late_events"] == 0 and shell.counts["order_timeouts"] == 0


def test_recognizer_stops_waiting_for_a_place_event_lost_for_good():
    clock = Clock()
    (f0, p0), (f1, p1), (f2, p2) = frames(3)
    shell, beliefs = recognizer(clock)
    feed_tick(shell, f0, p0)
    shell.on_command(command(p0, 0, confirmed_seq=0))  # place event 0 never comes
    feed_tick(shell, f1, p1)
    assert len(beliefs) == 1
    clock.t += 0.6
    shell.drain()
    assert len(beliefs) == 2 and shell.counts["order_timeouts"] == 1
    shell.on_command(command(p1, 1, confirmed_seq=0))
    feed_tick(shell, f2, p2)  # no second wait for the same event
    assert len(beliefs) == 3 and shell.counts["order_timeouts"] == 1


def test_recognizer_relocalises_after_the_scan_of_the_tick_whose_command_asked_and_once_per_request():
    clock = Clock()
    (f0, p0), (f1, p1), (f2, p2), (f3, p3) = frames(4)
    shell, beliefs = recognizer(clock)
    feed_tick(shell, f0, p0)
    shell.on_command(command(p0, 0, confirmed_seq=-1))
    # the explorer answers tick 1 with a request before the recognizer has the scan of tick 1
    shell.on_command(VelocityCommand(stamp=p1.stamp, seq=1, v_mps=0.3, omega_radps=0.0, tick=1, relocalisations=1))
    feed_tick(shell, f1, p1)
    assert len(beliefs) == 2 and shell.counts["relocalisations"] == 0 == shell.core.relocalisations
    feed_tick(shell, f2, p2)
    assert len(beliefs) == 3 and shell.counts["relocalisations"] == 1 == shell.core.relocalisations
    assert shell.checkpoint().relocalisations == 1
    shell.on_command(VelocityCommand(stamp=p2.stamp, seq=2, v_mps=0.3, omega_radps=0.0, tick=2, relocalisations=1))
    feed_tick(shell, f3, p3)  # the same count again: nothing new
    assert len(beliefs) == 4 and shell.core.relocalisations == 1


def test_explorer_command_carries_its_count_of_relocalisation_requests():
    clock = Clock()
    shell, sent = explorer(clock)
    (f0, p0), (f1, p1) = frames(2)
    shell.on_dr_pose(p0)
    shell.core.relocalisations = 2  # as _failed leaves it after two held failures
    shell.on_odometry(f1.odometry)
    shell.on_sonar(f0.sonar)
    shell.on_sonar(f1.sonar)
    shell.on_dr_pose(p1)
    assert [c.relocalisations for c in commands(sent)] == [0, 2]


def map_update(seq: int, link_seq: int, confirmed_seq: int = -1, changed=()) -> MapUpdate:
    return MapUpdate(stamp=0.0, seq=seq, version=seq + 1, changed=list(changed), full=False, places=1, links=0,
                     energy=0.0, iterations=1, method="sweep", noise=NoiseParams(s_dd=1e-4, s_aa=1e-3, s_da=0.0),
                     link_seq=link_seq, confirmed_seq=confirmed_seq)


def drive_to_a_second_place(clock: Clock, *, map_heard: bool):
    """Place 7 confirmed at tick 0, place 8 at tick 40 (1.2 m on): the recognizer measures the link 7 -> 8
    when it applies the second confirmation, after the scan of tick 40 and before that of tick 41."""
    fs = frames(42)
    beliefs: list = []
    links: list = []
    shell = RecognizerShell(PlaceRecognizerNodeParams(order_timeout_s=0.5), beliefs.append, links.append, clock=clock)
    if map_heard:  # the relaxer's update for the first place
        shell.on_map_update(map_update(0, link_seq=-1, confirmed_seq=0))
    (f0, p0) = fs[0]
    feed_tick(shell, f0, p0)
    shell.on_command(command(p0, 0, confirmed_seq=0))
    shell.on_explorer_event(confirmation(p0))
    for j in range(1, 41):
        f, p = fs[j]
        feed_tick(shell, f, p)
        shell.on_command(command(p, j, confirmed_seq=1 if j == 40 else 0))
    p40 = fs[40][1]
    shell.on_explorer_event(PlaceConfirmed(stamp=p40.stamp, seq=1, place_id=8, x_m=p40.compass.x_m,
                                           y_m=p40.compass.y_m))
    feed_tick(shell, *fs[41])
    if map_heard:
        assert not links, "place 8 applied before the relaxer had it"
        shell.on_map_update(map_update(1, link_seq=-1, confirmed_seq=1))  # the relaxer's update for place 8
    return shell, beliefs, links


def test_recognizer_waits_for_the_map_update_that_holds_its_link():
    clock = Clock()
    shell, beliefs, links = drive_to_a_second_place(clock, map_heard=True)
    assert [(lk.from_id, lk.to_id, lk.seq) for lk in links] == [(7, 8, 0)]
    assert len(beliefs) == 41, "the scan of tick 41 was localised before the map update of the link before it"
    shell.on_map_update(map_update(2, link_seq=-1, confirmed_seq=1))  # an update that does not hold it yet
    assert len(beliefs) == 41
    shell.on_map_update(map_update(3, link_seq=0, confirmed_seq=1,
                                   changed=[PlacePosition(place_id=8, x_m=5.0, y_m=5.0)]))
    assert len(beliefs) == 42 and beliefs[-1].link_seq == 0
    assert shell.core.belief.centres[shell.core.belief.index(8)].tolist() == [5.0, 5.0]
    assert shell.counts["map_timeouts"] == 0 == shell.counts["order_timeouts"]


def test_recognizer_goes_on_without_a_map_update_that_does_not_come():
    clock = Clock()
    shell, beliefs, links = drive_to_a_second_place(clock, map_heard=True)
    assert len(links) == 1 and len(beliefs) == 41
    clock.t += 0.6
    shell.drain()
    assert len(beliefs) == 42 and shell.counts["map_timeouts"] == 1 and shell.counts["order_timeouts"] == 0


def test_recognizer_without_a_relaxer_does_not_wait_for_map_updates():
    clock = Clock()
    shell, beliefs, links = drive_to_a_second_place(clock, map_heard=False)
    assert len(links) == 1 and len(beliefs) == 42 and shell.counts["map_timeouts"] == 0


def belief_of(pose: DeadReckonedPose, seq: int, link_seq: int) -> LocalizationBelief:
    return LocalizationBelief(stamp=pose.stamp, seq=seq, place_id=-1, probability=0.0, offset_x_m=0.0,
                              offset_y_m=0.0, offset_var_m2=1.0, link_seq=link_seq)


def map_following_explorer(clock: Clock, first) -> tuple[ExplorerShell, list]:
    """An explorer that has heard a relaxer, past tick 0 with its scan and localization."""
    (f0, p0), link_seq = first
    sent: list = []
    shell = ExplorerShell(ExplorerNodeParams(localization_timeout_s=2.0, map_timeout_s=0.5),
                          lambda name, msg: sent.append((name, msg)), clock=clock)
    shell.on_map_update(map_update(0, link_seq=-1))
    shell.on_dr_pose(p0)
    shell.on_sonar(f0.sonar)
    shell.on_localization(belief_of(p0, 0, link_seq=link_seq))
    return shell, sent


def test_explorer_waits_for_the_recognizer_and_the_map_update_of_the_links_it_names():
    clock = Clock()
    (f0, p0), (f1, p1), (f2, p2) = frames(3)
    shell, sent = map_following_explorer(clock, ((f0, p0), -1))
    shell.on_sonar(f1.sonar)
    shell.on_odometry(f1.odometry)
    shell.on_dr_pose(p1)
    assert [c.tick for c in commands(sent)] == [0], "tick 1 answered before the recognizer's work of tick 1"
    shell.on_localization(belief_of(p1, 1, link_seq=3))  # the recognizer published links 0-3 by then
    shell.on_progress(RecognizerProgress(stamp=p1.stamp, seq=0, tick=1, link_seq=3))
    assert [c.tick for c in commands(sent)] == [0], "tick 1 answered before the map held link 3"
    shell.on_map_update(map_update(1, link_seq=3))
    assert [c.tick for c in commands(sent)] == [0, 1] and shell.counts["map_timeouts"] == 0
    confirmed = [m.seq for name, m in sent if name == "places_confirmed"]
    assert confirmed == [0]  # the first place, at tick 1: the recognizer applies it at tick 2
    shell.on_sonar(f2.sonar)
    shell.on_odometry(f2.odometry)
    shell.on_dr_pose(p2)
    assert [c.tick for c in commands(sent)] == [0, 1], "tick 2 answered before the recognizer's work of tick 2"
    shell.on_progress(RecognizerProgress(stamp=p2.stamp, seq=1, tick=2, link_seq=3))
    assert [c.tick for c in commands(sent)] == [0, 1], "tick 2 answered before the map held the place it confirmed"
    shell.on_map_update(map_update(2, link_seq=3, confirmed_seq=0))
    assert [c.tick for c in commands(sent)] == [0, 1, 2] and shell.counts["map_timeouts"] == 0


def test_explorer_answers_a_tick_without_a_scan_or_a_place_event_before_it_at_once():
    clock = Clock()
    fs = frames(3)
    sent: list = []
    shell = ExplorerShell(ExplorerNodeParams(localization_timeout_s=2.0, map_timeout_s=0.5),
                          lambda name, msg: sent.append((name, msg)), clock=clock)
    shell.on_map_update(map_update(0, link_seq=-1, confirmed_seq=0))
    shell.on_dr_pose(fs[0][1])  # confirms place 0
    shell.on_progress(RecognizerProgress(stamp=0.1, seq=0, tick=1, link_seq=-1))
    for j in (1, 2):
        f, p = fs[j]
        shell.on_odometry(msgspec_replace(f.odometry, sonar_seq=-1))  # no scan at these ticks
        shell.on_dr_pose(p)
    assert [c.tick for c in commands(sent)] == [0, 1, 2] and shell.counts["map_timeouts"] == 0


def test_explorer_answers_without_a_map_update_that_does_not_come():
    clock = Clock()
    (f0, p0), (f1, p1) = frames(2)
    shell, sent = map_following_explorer(clock, ((f0, p0), 0))
    shell.on_sonar(f1.sonar)
    shell.on_odometry(f1.odometry)
    shell.on_dr_pose(p1)
    assert [c.tick for c in commands(sent)] == [0]
    clock.t += 0.6
    shell.check_timeout()
    assert [c.tick for c in commands(sent)] == [0, 1] and shell.counts["map_timeouts"] == 1


def test_recognizer_says_when_the_work_of_a_tick_is_done():
    clock = Clock()
    (f0, p0), (f1, p1), (f2, p2) = frames(3)
    progress: list = []
    beliefs: list = []
    shell = RecognizerShell(PlaceRecognizerNodeParams(order_timeout_s=0.5), beliefs.append, lambda msg: None,
                            clock=clock, publish_progress=progress.append)
    feed_tick(shell, f0, p0)
    assert [p.tick for p in progress] == [0]  # after the scan of tick 0
    shell.on_command(command(p0, 0, confirmed_seq=0))
    shell.on_explorer_event(confirmation(p0))
    # tick 1 has no scan: the work of tick 1 is the place event of tick 0
    shell.on_odometry(msgspec_replace(f1.odometry, sonar_seq=f0.sonar.seq))
    shell.on_dr_pose(p1)
    assert shell.counts["places"] == 1 and [p.tick for p in progress] == [0, 1]
    shell.on_command(command(p1, 1, confirmed_seq=0))
    feed_tick(shell, f2, p2)
    assert [p.tick for p in progress] == [0, 1, 2] and len(beliefs) == 2
    assert shell.counts["order_timeouts"] == 0
