"""The runtime over real zenoh sessions: a service process and the test process on loopback."""

from __future__ import annotations

import json
import os
import signal
import time

import msgspec
import pytest
import zenoh

from messages.codec import codec
from messages.types import CompassReading, Health
from services.runtime import AliveWatcher, QueryFailed, query
from tests.bus.echo_node import in_key, out_key, sum_key
from tests.conftest import wait_until

ROBOT = "bustest"


@pytest.fixture
def echo(hub, processes):
    """The echo service as its own process, alive on the bus."""
    session, endpoint = hub
    watcher = AliveWatcher(session, ROBOT)
    proc = processes.python("tests.bus.echo_node", "--robot", ROBOT, "--connect", endpoint,
                            "--listen", "tcp/127.0.0.1:0")
    try:
        assert watcher.wait_alive(["echo"], timeout_s=15), "echo service never became alive"
        yield session, proc, watcher
    finally:
        watcher.close()


def _health(session) -> Health:
    return query(session, f"relaxmap/{ROBOT}/health/echo", type_=Health)


def test_typed_pub_sub_between_processes(echo):
    session, proc, _ = echo
    got: list[CompassReading] = []
    dec = codec(CompassReading)
    sub = session.declare_subscriber(out_key(ROBOT), lambda s: got.append(dec.decode(s.payload.to_bytes())))
    pub = session.declare_publisher(in_key(ROBOT))
    # The echo node's subscriber must be known to us before publishing (zenoh does no history here).
    assert wait_until(lambda: pub.matching_status, 10)
    n = 200
    for i in range(n):
        pub.put(codec(CompassReading).encode(CompassReading(stamp=i * 0.1, seq=i, heading_rad=i / n)))
    assert wait_until(lambda: len(got) >= n, 10), f"only {len(got)} of {n} echoes"
    assert [m.heading_rad for m in got] == [i / n for i in range(n)]
    assert [m.seq for m in got] == list(range(n))
    h = _health(session)
    assert h.messages_in == n and h.messages_out == n and h.decode_errors == 0
    assert h.pid == proc.pid
    sub.undeclare()
    pub.undeclare()


def test_query_good_and_bad_parameters(echo):
    session, proc, _ = echo
    assert query(session, sum_key(ROBOT), "a=1.5&b=2") == {"sum": 3.5}
    assert query(session, sum_key(ROBOT), {"a": 4}, fmt="json") == {"sum": 4.0}
    bad = {
        "a=abc": "parameter 'a' must be a number, got 'abc'",
        "b=1": "missing parameter 'a'",
        "a=1&zzz=2": "unknown parameter 'zzz'",
        "a=inf": "parameter 'a' must be finite",
        "a=" + "9" * 1000: "characters long",
        "a=1&format=xml": "parameter 'format' must be one of msgpack, json",
    }
    for params, expected in bad.items():
        with pytest.raises(QueryFailed) as err:
            query(session, sum_key(ROBOT), params)
        assert expected in str(err.value), (params, str(err.value))
    assert proc.poll() is None
    assert query(session, sum_key(ROBOT), "a=2&b=-1") == {"sum": 1.0}
    assert _health(session).query_errors == len(bad)


def test_garbage_does_not_stop_the_subscriber(echo):
    session, proc, _ = echo
    rng = __import__("random").Random(7)
    got = []
    sub = session.declare_subscriber(out_key(ROBOT), lambda s: got.append(s))
    pub = session.declare_publisher(in_key(ROBOT))
    assert wait_until(lambda: pub.matching_status, 10)
    garbage = [bytes(rng.randrange(256) for _ in range(rng.randrange(1, 64))) for _ in range(50)]
    # wrong-type but valid msgpack as well: a map with the wrong tag, a list, a bare integer
    garbage += [msgspec.msgpack.encode({"type": "Nope", "stamp": 1}), msgspec.msgpack.encode([1, 2]),
                msgspec.msgpack.encode(5)]
    for g in garbage:
        pub.put(g)
    assert wait_until(lambda: _health(session).decode_errors == len(garbage), 10), _health(session)
    pub.put(codec(CompassReading).encode(CompassReading(stamp=0.0, seq=0, heading_rad=0.25)))
    assert wait_until(lambda: len(got) == 1, 10)
    assert proc.poll() is None
    sub.undeclare()
    pub.undeclare()


def test_killed_service_leaves_liveliness_within_2s(echo, processes):
    session, proc, watcher = echo
    t0 = time.monotonic()
    os.killpg(proc.pid, signal.SIGKILL)
    assert watcher.wait_gone("echo", timeout_s=2.0), "still alive 2 s after SIGKILL"
    assert time.monotonic() - t0 < 2.0
    proc.wait(5)


def test_sigterm_stops_cleanly(echo, processes):
    session, proc, watcher = echo
    assert processes.stop(proc, signal.SIGTERM) == 0
    assert watcher.wait_gone("echo", timeout_s=2.0)


def test_bad_config_file_is_a_clear_error(processes, tmp_path):
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: 'peer', listen: ")
    proc = processes.python("tests.bus.echo_node", "--config", str(bad))
    out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 2
    assert str(bad) in out.decode()
    missing = processes.python("tests.bus.echo_node", "--config", str(tmp_path / "nope.json5"))
    out, _ = missing.communicate(timeout=30)
    assert missing.returncode == 2 and "no such file" in out.decode()


def test_zenoh_session_from_default_config_is_loopback_only():
    from services.runtime import load_config

    conf = load_config()
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert all("127.0.0.1" in e for e in json.loads(conf.get_json("listen/endpoints")))
    assert all("127.0.0.1" in e for e in json.loads(conf.get_json("connect/endpoints")))
    assert isinstance(conf, zenoh.Config)


def test_query_command_prints_json_and_reports_errors(echo, hub):
    import subprocess
    import sys

    _, endpoint = hub
    base = [sys.executable, "-m", "services.cli", "query", "--robot", ROBOT, "--connect", endpoint,
            "--listen", "tcp/127.0.0.1:0"]
    ok = subprocess.run([*base, "test/sum", "a=2", "b=0.5"], capture_output=True, text=True, timeout=60)
    assert ok.returncode == 0, ok.stderr
    assert json.loads(ok.stdout) == {"sum": 2.5}
    bad = subprocess.run([*base, "test/sum", "a=x"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 1 and "parameter 'a' must be a number" in bad.stderr
    malformed = subprocess.run([*base, "test/sum", "a"], capture_output=True, text=True, timeout=60)
    assert malformed.returncode == 2 and "not of the form k=v" in malformed.stderr


def test_history_reaches_a_subscriber_that_starts_late(hub):
    """A publisher with history: a subscriber declared later (or restarted) still gets every message."""
    from services.runtime import Node, loopback_config

    session, endpoint = hub
    key = f"relaxmap/{ROBOT}/test/history"
    with Node(session, "pub", robot=ROBOT) as pub_node:
        pub = pub_node.publisher(key, CompassReading, history=1000)
        for i in range(20):
            pub.put(CompassReading(stamp=float(i), seq=i, heading_rad=0.0))
        live: list[int] = []
        for attempt in range(2):  # a first subscriber, then a "restarted" one
            late = zenoh.open(loopback_config(connect=[endpoint]))
            try:
                with Node(late, "sub", robot=ROBOT) as sub_node:
                    got: list[int] = []
                    sub_node.subscribe(key, CompassReading, lambda m: got.append(m.seq), history=True)
                    want = [*range(20), *live]
                    assert wait_until(lambda: sub_node.spin_once(0.05) and len(got) >= len(want), 10), got
                    live.append(100 + attempt)
                    pub.put(CompassReading(stamp=99.0, seq=live[-1], heading_rad=0.0))
                    assert wait_until(lambda: sub_node.spin_once(0.05) and live[-1] in got, 10), got
                    assert got == [*want, live[-1]]
            finally:
                late.close()
