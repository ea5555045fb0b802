"""Faults in a full run: every service SIGKILLed once loses no link; garbage on every key changes no map."""

from __future__ import annotations

import json
import os
import random
import signal
import sqlite3
import subprocess
import sys
import threading
import time

import zenoh
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from messages import topics
from messages.codec import DecodeError, codec
from messages.types import Health, LinkDeleted, TruthPose
from services.launch.graph import load_graph
from services.place_recognizer.node import read_links_log
from services.relaxer.mapjson import read_map_json
from services.runtime import QueryFailed, deploy_file, loopback_config, query
from services.runtime.procs import free_port, stop_group
from tests.conftest import reproducible_graph

# Simulated seconds of the run (CI size); the seed picks the order and the moments of the kills.
FAULTS_SIM_S = float(os.environ.get("RELAXMAP_FAULTS_SIM_S", "600"))
FAULTS_SEED = int(os.environ.get("RELAXMAP_FAULTS_SEED", "0"))
ROBOT = topics.DEFAULT_ROBOT


class RunListener:
    """The latest simulated time heard on the truth topic, and the links the explorer deleted."""

    def __init__(self, session: zenoh.Session) -> None:
        self.sim_s = 0.0
        self._deleted: dict[frozenset[int], float] = {}  # link -> simulated time of its latest deletion
        self._lock = threading.Lock()
        dec, dec_deleted = codec(TruthPose), codec(LinkDeleted)

        def on_truth(sample: zenoh.Sample) -> None:
            try:
                stamp = dec.decode(sample.payload.to_bytes()).stamp
            except DecodeError:
                return
            with self._lock:
                self.sim_s = max(self.sim_s, stamp)

        def on_deleted(sample: zenoh.Sample) -> None:
            try:
                msg = dec_deleted.decode(sample.payload.to_bytes())
            except DecodeError:
                return
            with self._lock:
                pair = frozenset((msg.from_id, msg.to_id))
                self._deleted[pair] = max(self._deleted.get(pair, msg.stamp), msg.stamp)

        self._subs = [session.declare_subscriber(topics.truth_pose(ROBOT), on_truth),
                      session.declare_subscriber(topics.links_deleted(ROBOT), on_deleted)]

    def now(self) -> float:
        with self._lock:
            return self.sim_s

    def deleted_links(self) -> dict[frozenset[int], float]:
        with self._lock:
            return dict(self._deleted)

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()


def _pid(session: zenoh.Session, service: str) -> int | None:
    try:
        return query(session, topics.health(ROBOT, service), type_=Health, timeout_s=1).pid
    except QueryFailed:
        return None


def _kill_schedule(services: list[str], rng: random.Random) -> list[tuple[float, str]]:
    """Each service once, in a random order, at random simulated times in the first half of the run
    (a restart takes seconds of wall time, in which the simulation goes on)."""
    order = services[:]
    rng.shuffle(order)
    moments = sorted(rng.uniform(0.05, 0.5) * FAULTS_SIM_S for _ in order)
    return list(zip(moments, order, strict=True))


def _wait(cond, timeout_s: float, what: str, proc: subprocess.Popen) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if proc.poll() is not None:
            _, err = proc.communicate()
            raise AssertionError(f"the run ended while waiting for {what}: {err[-3000:]}")
        assert time.monotonic() < deadline, f"no {what} within {timeout_s:g} s"
        time.sleep(0.05)


def test_every_service_killed_once_loses_no_link(tmp_path):
    services = load_graph(deploy_file("graph.json")).names()
    schedule = _kill_schedule(services, random.Random(FAULTS_SEED))
    port = free_port()
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", "--port", str(port), "--headless",
                             "--world", "orebro-office", "--seed", str(FAULTS_SEED), "--out", str(out),
                             "--max-sim-time", f"{FAULTS_SIM_S:g}"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    session = zenoh.open(loopback_config(connect=[f"tcp/127.0.0.1:{port}"]))
    heard = RunListener(session)
    killed: list[tuple[str, int, float]] = []
    try:
        for at_s, name in schedule:
            _wait(lambda: heard.now() >= at_s, 120, f"simulated time {at_s:.0f} s", proc)
            _wait(lambda: _pid(session, name) is not None, 30, f"health of {name}", proc)
            pid = _pid(session, name)
            assert pid is not None
            os.kill(pid, signal.SIGKILL)
            killed.append((name, pid, heard.now()))
            # the next kill only once this service is back (another pid answers its health)
            _wait(lambda: (p := _pid(session, name)) is not None and p != pid, 60, f"{name} back after SIGKILL",
                  proc)
        _, err = proc.communicate(timeout=300)
        deleted_links = heard.deleted_links()
    finally:
        heard.close()
        session.close()
        stop_group(proc)
    print("\nkilled (service, pid, simulated s):", [(n, p, round(t, 1)) for n, p, t in killed])
    assert proc.returncode == 0, err[-3000:]
    for name, _, _ in killed:
        assert f"{name} ended (killed by SIGKILL)" in err, name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["restarts"] == {name: 1 for name in services}, summary["restarts"]
    assert summary["links_lost"] == 0, summary.get("links_lost_pairs")
    assert summary["sim_time_s"] >= FAULTS_SIM_S - 1

    # the recognizer's own record of what it measured, against the final map
    recorded = read_links_log(out / "links_measured.jsonl")
    assert recorded, "the recognizer recorded no link"
    m = read_map_json(out / "map.json")
    ids = m.graph.ids.tolist()
    in_map = {}
    for a, b, d, steps in zip(m.graph.src.tolist(), m.graph.dst.tolist(), m.graph.d_m.tolist(),
                              m.graph.steps.tolist(), strict=True):
        in_map[frozenset((ids[a], ids[b]))] = (d, steps)
    with sqlite3.connect(f"file:{out / 'map.sqlite'}?mode=ro", uri=True) as db:
        deleted = {r[0] for r in db.execute("SELECT id FROM deleted_places")}
    missing, differ, of_deleted = [], [], 0
    for lk in recorded:
        pair = frozenset((lk.from_id, lk.to_id))
        if lk.from_id in deleted or lk.to_id in deleted or deleted_links.get(pair, -1.0) >= lk.stamp:
            of_deleted += 1  # the explorer deleted it (after this measurement) or a place of it: dropped on purpose
            continue
        if pair not in in_map:
            missing.append(sorted(pair))
        elif abs(in_map[pair][0] - lk.d_m) > 1e-9 or in_map[pair][1] != lk.steps:
            differ.append((sorted(pair), in_map[pair], (lk.d_m, lk.steps)))
    print(f"links recorded {len(recorded)}, in the map {len(in_map)}, deleted (or of deleted places) {of_deleted}; "
          f"summary: {summary['places']} places, {summary['links_measured']} links measured")
    assert not missing, f"links measured but not in the map: {missing}"
    assert not differ, f"the map holds another measurement than the latest recorded: {differ}"
    for log in (out / "logs").iterdir():
        assert "Traceback" not in log.read_text(), log.read_text()[-2000:]



GARBAGE_SIM_S = float(os.environ.get("RELAXMAP_GARBAGE_SIM_S", "300"))


def _run(out, graph, port: int | None = None, *, seed: int = 3) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "services.cli", "run", "--port", str(port or free_port()),
                             "--headless", "--graph", str(graph), "--world", "orebro-office", "--seed", str(seed),
                             "--out", str(out), "--max-sim-time", f"{GARBAGE_SIM_S:g}"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)


def _finish(proc: subprocess.Popen) -> None:
    try:
        _, err = proc.communicate(timeout=600)
    finally:
        stop_group(proc)
    assert proc.returncode == 0, err[-3000:]


def _map(path):
    m = read_map_json(path)
    ids = m.graph.ids.tolist()
    links = sorted((ids[a], ids[b], d, th, st_) for a, b, d, th, st_ in zip(
        m.graph.src.tolist(), m.graph.dst.tolist(), m.graph.d_m.tolist(), m.graph.theta_rad.tolist(),
        m.graph.steps.tolist(), strict=True))
    return ids, m.xy, links


def _garbage_pool(per_key: int = 20) -> dict[str, list[bytes]]:
    """Undecodable payloads for every key of messages/topics.py, drawn by hypothesis (the strategies of
    the bus test): random bytes, random msgpack, messages of other types."""
    from tests.bus.test_bad_input import CARRIES, _payload

    pool: dict[str, list[bytes]] = {name: [] for name in topics.all_topics(ROBOT)}

    @settings(max_examples=per_key * len(pool), phases=[Phase.generate], deadline=None, database=None,
              suppress_health_check=list(HealthCheck))
    @given(data=st.data())
    def draw(data):
        name = data.draw(st.sampled_from(sorted(pool)))
        pool[name].append(data.draw(_payload(CARRIES[name])))

    draw()
    return pool


def _same_map(a, b) -> bool:
    (ids_a, xy_a, links_a), (ids_b, xy_b, links_b) = _map(a), _map(b)
    return ids_a == ids_b and links_a == links_b and bool(abs(xy_a - xy_b).max() < 1e-9)


def _dirty_run(out, graph, pool) -> int:
    """A run with every key of messages/topics.py flooded with garbage, round after round; returns how
    many messages were sent."""
    port = free_port()
    proc = _run(out, graph, port)
    session = zenoh.open(loopback_config(connect=[f"tcp/127.0.0.1:{port}"]))
    pubs = {name: session.declare_publisher(key) for name, key in topics.all_topics(ROBOT).items()}
    sent = 0
    try:
        _wait(lambda: _pid(session, "sensor_sim") is not None, 60, "the run's start", proc)
        while proc.poll() is None:
            for name in sorted(pubs):
                pubs[name].put(pool[name][sent % len(pool[name])] if pool[name] else b"\xc1")
                sent += 1
            time.sleep(0.02)
    finally:
        for p in pubs.values():
            p.undeclare()
        session.close()
    _finish(proc)
    return sent


def test_garbage_on_every_key_leaves_the_map_as_a_clean_run_makes_it(tmp_path):
    """Garbage on every key during a whole run: every service logs it, nothing is lost, and the map
    is the clean run's.

    Both runs are lockstep with waits no input outlasts (tests.conftest.PATIENT): each service waits
    for the inputs its messages name (docs/runtime.md), so two runs of a seed make the same map."""
    pool = _garbage_pool()
    graph = reproducible_graph(tmp_path)
    _finish(_run(tmp_path / "clean", graph))
    dirty = tmp_path / "dirty"
    sent = _dirty_run(dirty, graph, pool)
    print(f"\n{sent} undecodable messages sent on {len(pool)} keys")
    for log in (dirty / "logs").iterdir():
        text = log.read_text()
        assert "Traceback" not in text, text[-2000:]
        assert "undecodable message" in text, f"{log.name}: no bad message noticed"
    summary = json.loads((dirty / "summary.json").read_text())
    assert summary["links_lost"] == 0 and summary["sim_time_s"] >= GARBAGE_SIM_S - 1, summary
    recorded = {frozenset((lk.from_id, lk.to_id)) for lk in read_links_log(dirty / "links_measured.jsonl")}
    m = read_map_json(dirty / "map.json")
    ids = m.graph.ids.tolist()
    assert recorded == {frozenset((ids[a], ids[b])) for a, b in zip(m.graph.src.tolist(), m.graph.dst.tolist())}
    assert _same_map(tmp_path / "clean" / "map.json", dirty / "map.json"), "the run with garbage made another map"
