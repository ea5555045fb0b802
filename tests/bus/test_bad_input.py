"""Garbage on every key each service subscribes to, and random queries on every queryable: every service
stays alive, answers, and counts what it could not decode."""

from __future__ import annotations

import subprocess
import time

import msgspec
import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from messages import ALL_MESSAGES, ALL_REPLIES, topics
from messages.codec import codec
from messages.types import (
    CompassReading,
    DeadReckonedPose,
    ErrorReply,
    ExplorationStatus,
    Health,
    LinkConfidence,
    LinkDeleted,
    LinkInferred,
    LinkMeasured,
    LocalizationBelief,
    MapGraph,
    MapStats,
    MapUpdate,
    OccupancyGrid,
    OdometryStep,
    PathReply,
    PlaceConfirmed,
    PlaceDeleted,
    PlacePredicted,
    RecognizerProgress,
    ScanSet,
    SonarScan,
    TruthPose,
    VelocityCommand,
)
from services.launch.graph import load_graph
from services.runtime import AliveWatcher, deploy_file, query
from tests.conftest import wait_until
from tests.unit.test_messages import message_strategy

ROBOT = "garbage"
EXAMPLES = 40  # hypothesis examples per service (each one a message or a query)

# What each key of messages/topics.py carries (a reply type for the queryables). The test checks that
# this covers every key, so a new topic cannot be left out.
CARRIES = {
    "odometry": OdometryStep, "compass": CompassReading, "sonar": SonarScan, "truth_pose": TruthPose,
    "dr_pose": DeadReckonedPose, "localization": LocalizationBelief, "recognizer_progress": RecognizerProgress,
    "links_measured": LinkMeasured,
    "places_predicted": PlacePredicted, "places_confirmed": PlaceConfirmed, "places_deleted": PlaceDeleted,
    "links_inferred": LinkInferred, "links_confidence": LinkConfidence, "links_deleted": LinkDeleted,
    "cmd_velocity": VelocityCommand, "exploration_status": ExplorationStatus, "map_update": MapUpdate,
    "map_graph": MapGraph, "map_path": PathReply, "map_grid": OccupancyGrid, "map_stats": MapStats,
    "map_scans": ScanSet,
}
OVERSIZED = [
    b"\xff" * (1 << 20),  # a megabyte of bytes that are no msgpack
    b"\xdd\xff\xff\xff\xff",  # a msgpack array that claims 4 billion items and has none
    b"\xdf\xff\xff\xff\xff" + b"\xa1a\x01" * 1000,  # a map that claims 4 billion entries
    b"\xc6\x7f\xff\xff\xff",  # a bin of 2 GiB announced, none there
]


def _args(name: str, tmp) -> list[str]:
    """Each service's own arguments, as in deploy/graph.json, with its files in ``tmp``."""
    spec = {s.name: s for s in load_graph(deploy_file("graph.json")).services}[name]
    values = {"world": "orebro-office", "seed": "0", "out": str(tmp), "max_sim_time": "100000", "viewer": "",
              "recording": str(tmp / "recording.rrd"), "recording_id": "bad-input",
              **{f"resume_{s}": "" for s in ("sensor_sim", "dead_reckoning", "place_recognizer", "explorer")}}
    args = [a for a in (x.format(**values) for x in spec.args) if a]
    if name == "sensor_sim":  # alone on the bus: no service to wait for
        args = [a for i, a in enumerate(args) if a != "--wait-for" and (i == 0 or args[i - 1] != "--wait-for")]
    return [spec.module, *args]


def _subscribed(session: zenoh.Session, keys: dict[str, str]) -> dict[str, str]:
    """The keys of ``keys`` that a subscriber on the bus matches (the service is the only one there)."""
    pubs = {name: session.declare_publisher(key) for name, key in keys.items()}
    try:
        time.sleep(0.5)  # declarations propagate
        found: dict[str, str] = {}
        stable_since = time.monotonic()
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and time.monotonic() - stable_since < 1.0:
            now = {name: keys[name] for name, p in pubs.items() if p.matching_status.matching}
            if now != found:
                found, stable_since = now, time.monotonic()
            time.sleep(0.05)
        return found
    finally:
        for p in pubs.values():
            p.undeclare()


def _health(session: zenoh.Session, service: str) -> Health:
    return query(session, topics.health(ROBOT, service), type_=Health, timeout_s=5)


_scalars = (st.none() | st.booleans() | st.integers(min_value=-(2**63), max_value=2**64 - 1)
            | st.floats() | st.text(max_size=30) | st.binary(max_size=30))
_structures = st.recursive(_scalars, lambda inner: st.lists(inner, max_size=6)
                           | st.dictionaries(st.text(max_size=10) | st.integers(-(2**63), 2**63 - 1), inner,
                                                           max_size=6), max_leaves=25)


def _payload(key_type: type) -> st.SearchStrategy[bytes]:
    """Bytes that do not decode as ``key_type``: random bytes, random msgpack, or another message."""
    others = [t for t in ALL_MESSAGES + ALL_REPLIES if t is not key_type]
    another = st.sampled_from(others).flatmap(lambda t: message_strategy(t).map(codec(t).encode))
    return st.one_of(st.binary(max_size=3000), _structures.map(msgspec.msgpack.encode), another)


_param_text = st.text(alphabet=st.characters(blacklist_categories=("Cs",)), max_size=40)
_place_ids = st.text(alphabet="0123456789-+.eEx_", min_size=1, max_size=30)
_params = st.dictionaries(_param_text, _param_text | st.integers().map(str) | st.just("x" * 20_000), max_size=4)


def test_every_topic_has_a_type():
    assert set(CARRIES) == set(topics.all_topics(ROBOT))


@pytest.mark.parametrize("service", load_graph(deploy_file("graph.json")).names())
def test_garbage_is_counted_and_the_service_goes_on(service, hub, processes, tmp_path):
    session, endpoint = hub
    watcher = AliveWatcher(session, ROBOT)
    module, *args = _args(service, tmp_path)
    log_path = tmp_path / f"{service}.log"  # a file, not a pipe: every bad message is logged, nobody reads
    with open(log_path, "wb") as log_file:
        proc = processes.python(module, *args, "--robot", ROBOT, "--connect", endpoint, "--listen",
                                "tcp/127.0.0.1:0", stdout=log_file, stderr=subprocess.STDOUT)
    try:
        assert watcher.wait_alive([service], 60), f"{service} not alive"
        keys = topics.all_topics(ROBOT)
        subscribed = _subscribed(session, keys)
        assert subscribed, f"{service} subscribes to none of {sorted(keys)}"
        print(f"\n{service} subscribes to {sorted(subscribed)}")
        declared = {s.name: s for s in load_graph(deploy_file("graph.json")).services}[service].inputs
        assert set(subscribed) <= set(declared), f"deploy/graph.json does not declare {set(subscribed) - set(declared)}"
        # block, not drop, under congestion: every message sent must reach the service
        pubs = {name: session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
                for name, key in subscribed.items()}
        time.sleep(0.3)
        before = _health(session, service)
        sent = {"n": 0}

        # the oversized ones on every key, once
        for pub in pubs.values():
            for data in OVERSIZED:
                pub.put(data)
                sent["n"] += 1

        @settings(max_examples=EXAMPLES, deadline=None, database=None,
                  suppress_health_check=list(HealthCheck))
        @given(data=st.data())
        def garbage(data):
            name = data.draw(st.sampled_from(sorted(pubs)))
            pubs[name].put(data.draw(_payload(CARRIES[name])))
            sent["n"] += 1

        garbage()
        expected = before.decode_errors + sent["n"]
        assert wait_until(lambda: _health(session, service).decode_errors >= expected, 30), (
            f"{service} counted {_health(session, service).decode_errors - before.decode_errors} "
            f"decode errors of {sent['n']} undecodable messages")
        after = _health(session, service)
        assert after.decode_errors == expected, "a message that cannot decode was taken as one"
        assert after.messages_in == before.messages_in, "garbage reached a callback"
        assert after.detail.get("handler_errors", 0) == 0
        for pub in pubs.values():
            pub.undeclare()

        # random and oversized parameters on every key (the service's queryables among them)
        query_keys = [*keys.values(), topics.map_place(ROBOT, 0), topics.health(ROBOT, service)]

        @settings(max_examples=EXAMPLES, deadline=None, database=None,
                  suppress_health_check=list(HealthCheck))
        @given(key=st.sampled_from(query_keys) | _place_ids.map(lambda t: topics.map_place(ROBOT, t)),
               params=_params)
        def bad_query(key, params):
            text = ";".join(f"{k}={v}" for k, v in params.items())
            try:
                replies = list(session.get(zenoh.Selector(key, text), timeout=10))
            except (zenoh.ZError, ValueError):  # a selector zenoh itself refuses never leaves this session
                return
            for reply in replies:
                if reply.err is not None:
                    raw = reply.err.payload.to_bytes()
                    try:
                        err = msgspec.json.decode(raw, type=ErrorReply)
                    except msgspec.DecodeError:
                        raise AssertionError(f"{key}?{text[:100]}: error reply {raw[:200]!r}") from None
                    assert err.error and not err.error.startswith("internal error"), err

        bad_query()
        assert proc.poll() is None, f"{service} died"
        assert service in watcher.alive, f"{service} lost its liveliness token"
        health = _health(session, service)  # a good query is still answered
        assert health.pid == proc.pid and health.decode_errors == expected
    finally:
        watcher.close()
        processes.stop(proc)
    log = log_path.read_text(errors="replace")
    assert "Traceback" not in log, log[-3000:]
    assert "undecodable message" in log  # and logged

