"""place_recognizer and explorer as processes with sensor_sim and dead_reckoning, in lockstep on loopback."""

from __future__ import annotations

import os

import pytest

from messages import topics
from messages.types import ExplorationStatus, Health, LinkMeasured, LocalizationBelief, PlaceConfirmed, VelocityCommand
from services.launch.inprocess import InProcessParams, InProcessRun
from services.runtime import AliveWatcher, query
from services.sensor_sim.core import SensorSimParams
from sim.world import load_world
from tests.conftest import Collector, wait_until

WORLD = "orebro-office"
SIM_S = 40.0  # simulated seconds of the run: the first places along the corridor
SONAR = ["--sonar-every-m", "0.2", "--sonar-period-s", "1.0"]  # as the in-process loop's default



def _start(processes, endpoint, robot, seed, watcher):
    """The mapping services first; the simulator once they serve (as ``relaxmap run`` starts them)."""
    common = ["--robot", robot, "--connect", endpoint, "--listen", "tcp/127.0.0.1:0"]
    limit = ["--duration-s", "120"]
    processes.python("services.dead_reckoning", *common, *limit)
    processes.python("services.place_recognizer", *common, *limit, "--no-follow-map")
    processes.python("services.explorer", *common, *limit, "--no-follow-map", "--localization-timeout-s", "10")
    assert watcher.wait_alive(["dead_reckoning", "place_recognizer", "explorer"], 30), watcher.alive
    processes.python("services.sensor_sim", *common, *limit, "--world", WORLD, "--seed", str(seed), "--lockstep",
                     "--lockstep-timeout-s", "30", "--max-sim-time", str(SIM_S), *SONAR)


def _health(session, robot, service) -> Health:
    return query(session, topics.health(robot, service), type_=Health)


@pytest.fixture(scope="module")
def inprocess():
    """The same run without the bus (no relaxation fed back, as the processes run without a relaxer)."""
    params = InProcessParams(seed=5, max_sim_time_s=SIM_S, stop_when_complete=False, relax=False,
                             sim=SensorSimParams(sonar_every_m=0.2, sonar_period_s=1.0))
    run = InProcessRun(load_world(WORLD), params)
    return run.run()


def test_localization_places_links_and_health_over_the_bus(hub, processes, inprocess):
    session, endpoint = hub
    robot = f"busplaces{os.getpid()}"
    watcher = AliveWatcher(session, robot)
    beliefs = Collector(session, topics.localization(robot), LocalizationBelief)
    confirmed = Collector(session, topics.places_confirmed(robot), PlaceConfirmed)
    links = Collector(session, topics.links_measured(robot), LinkMeasured)
    status = Collector(session, topics.exploration_status(robot), ExplorationStatus)
    cmds = Collector(session, topics.cmd_velocity(robot), VelocityCommand)
    last_tick = round(SIM_S / 0.1)
    try:
        _start(processes, endpoint, robot, 5, watcher)
        assert watcher.wait_alive(["sensor_sim"], 30), watcher.alive
        assert wait_until(lambda: any(c.tick >= last_tick - 1 for c in cmds.snapshot()), 90), (
            f"{len(cmds.snapshot())} commands; last {cmds.snapshot()[-1:]}")
        # health is refreshed every few tens of milliseconds
        assert wait_until(lambda: _health(session, robot, "explorer").detail["ticks"] >= last_tick - 1, 10)
        h_rec = _health(session, robot, "place_recognizer")
        h_exp = _health(session, robot, "explorer")
    finally:
        for r in (beliefs, confirmed, links, status, cmds):
            r.close()
        watcher.close()

    got_beliefs = beliefs.snapshot()
    got_places = confirmed.snapshot()
    got_links = links.snapshot()
    assert len(got_places) >= 5, got_places
    assert any(b.place_id >= 0 for b in got_beliefs)
    assert len(got_links) >= 4 and all(lk.d_m > 0.5 for lk in got_links)
    assert status.snapshot() and status.snapshot()[-1].confirmed >= 5
    # every tick answered once, in order (tick 0 may be answered again while the simulator starts)
    ticks = [c.tick for c in cmds.snapshot()]
    assert sorted(set(ticks)) == list(range(0, max(ticks) + 1))
    assert ticks == sorted(ticks)
    # health: the counters of both services
    assert h_rec.service == "place_recognizer" and h_rec.detail["scans"] >= 20
    assert h_rec.detail["places"] >= 5 and h_rec.detail["links"] >= 4
    assert h_exp.service == "explorer" and h_exp.detail["ticks"] >= last_tick - 1
    assert h_exp.detail["localization_timeouts"] == 0
    # lockstep is reproducible: the processes make the very places and links of the in-process loop,
    # whenever zenoh delivered every input in its session's order (both services count the exceptions,
    # which can happen while the peers' direct links are still being set up)
    in_order = (h_exp.detail["late_scans"] == 0 and h_rec.detail["late_events"] == 0
                and h_rec.detail["order_timeouts"] == 0)
    if not in_order:
        return
    want = [(p.place_id, round(p.map_xy[0], 9), round(p.map_xy[1], 9)) for p in inprocess.places.values()]
    have = [(p.place_id, round(p.x_m, 9), round(p.y_m, 9)) for p in got_places]
    assert have == want[: len(have)] and len(have) >= len(want) - 1, ({k: h_exp.detail[k] for k in ("scans", "fixes", "late_scans", "localization_timeouts")}, {k: h_rec.detail[k] for k in ("scans", "late_events", "repeated_scans", "unpaired_scans")})
    assert [(lk.from_id, lk.to_id, round(lk.d_m, 9)) for lk in got_links] == [
        (lk.from_id, lk.to_id, round(lk.d_m, 9)) for lk in inprocess.links][: len(got_links)]
