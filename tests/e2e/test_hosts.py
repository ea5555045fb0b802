"""`relaxmap run` across hosts: network namespaces joined by veth pairs, zenoh routers between them.

Three namespaces stand for three machines: the relaxer's host, the router's host, and the robot's
host (every other service, behind a second router chained to the first). The map written on the
robot's host equals the map of a single-host run with the same seed.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import REPO, reproducible_graph

SEED = 1  # a minute of it makes 17 places; seed 3 spends its first minute on the doors by its start
MAX_SIM_TIME_S = 60
# a launcher gives its services 10 s to stop before it kills them, then exits: wait longer than that
LAUNCHER_STOP_S = 30.0
PORT = 7447
XY_TOLERANCE_M = 0.05  # the relaxer takes events from different topics in arrival order: sweeps differ a little


def _ip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30)


class Hosts:
    """Network namespaces (by name unique to this test process) and the veth pairs between them."""

    def __init__(self) -> None:
        tag = f"rmh{os.getpid()}"
        self.names = {role: f"{tag}{role}" for role in ("router", "relaxer", "robot")}
        self.created: list[str] = []

    def setup(self) -> None:
        for ns in self.names.values():
            done = _ip("netns", "add", ns)
            if done.returncode != 0:
                if not self.created and ("Operation not permitted" in done.stderr or "Permission denied" in done.stderr):
                    pytest.skip(f"this machine forbids network namespaces: {done.stderr.strip()}")
                raise RuntimeError(f"ip netns add {ns}: {done.stderr.strip()}")
            self.created.append(ns)
            self._check("-n", ns, "link", "set", "lo", "up")
        # router <-> relaxer on 10.77.1.0/24, router <-> robot on 10.77.2.0/24
        r = self.names["router"]
        for i, role in ((1, "relaxer"), (2, "robot")):
            near, far = f"rm{os.getpid() % 100000}{role[1]}0", f"rm{os.getpid() % 100000}{role[1]}1"
            self._check("link", "add", near, "netns", r, "type", "veth", "peer", "name", far, "netns", self.names[role])
            self._check("-n", r, "addr", "add", f"10.77.{i}.1/24", "dev", near)
            self._check("-n", self.names[role], "addr", "add", f"10.77.{i}.2/24", "dev", far)
            self._check("-n", r, "link", "set", near, "up")
            self._check("-n", self.names[role], "link", "set", far, "up")

    def _check(self, *args: str) -> None:
        done = _ip(*args)
        if done.returncode != 0:
            raise RuntimeError(f"ip {' '.join(args)}: {done.stderr.strip()}")

    def run_in(self, role: str, *args: str) -> list[str]:
        return ["ip", "netns", "exec", self.names[role], sys.executable, "-m", "services.cli", *args]

    def teardown(self) -> None:
        for ns in self.created:
            _ip("netns", "del", ns)  # its veth ends go with it


@pytest.fixture
def hosts(processes):
    if shutil.which("ip") is None:
        pytest.skip("no `ip` command (iproute2) to make network namespaces")
    h = Hosts()
    try:
        h.setup()
        yield h
    finally:
        processes.cleanup()  # every process in the namespaces, by pid, before the namespaces go
        h.teardown()


def _wait_for_line(path: Path, text: str, proc: subprocess.Popen, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if text in path.read_text():
            return
        if proc.poll() is not None:
            break
        time.sleep(0.1)
    raise AssertionError(f"no {text!r} from {proc.args}: {path.read_text()[-2000:]}")


def _map(out: Path) -> tuple[dict[int, tuple[float, float]], set[tuple[int, int]]]:
    m = json.loads((out / "map.json").read_text())
    return ({p["id"]: (p["x"], p["y"]) for p in m["places"]},
            {(min(lk["from"], lk["to"]), max(lk["from"], lk["to"])) for lk in m["links"]})


def _counters(out: Path) -> list[str]:
    """The closing lines of the services that order their inputs (timeouts there break determinism)."""
    return [line.split(" INFO ", 1)[-1] for log in sorted((out / "logs").glob("*.log"))
            for line in log.read_text().splitlines() if "timeouts" in line]


def test_relaxer_on_another_host_makes_the_same_map(hosts, processes, tmp_path):
    graph = reproducible_graph(tmp_path)
    common = ["--seed", str(SEED), "--graph", str(graph), "--headless"]

    def single_host(out: Path) -> Path:
        """The reference: one host, loopback."""
        done = subprocess.run([sys.executable, "-m", "services.cli", "run", "--port", "0", "--out", str(out),
                               "--max-sim-time", str(MAX_SIM_TIME_S), *common], capture_output=True, text=True,
                              timeout=300, cwd=REPO, start_new_session=True)
        assert done.returncode == 0, done.stderr[-3000:]
        return out

    single = single_host(tmp_path / "single")

    logs = tmp_path / "logs"
    logs.mkdir()

    def start(role: str, name: str, *args: str) -> tuple[subprocess.Popen, Path]:
        log = logs / f"{name}.log"
        with log.open("wb") as f:
            return processes.start(hosts.run_in(role, *args), stdout=f, stderr=subprocess.STDOUT), log

    # the router's host, reached from both sides; the robot's host has its own router chained to it
    router, router_log = start("router", "router", "router", "--listen", f"tcp/10.77.1.1:{PORT}",
                               "--listen", f"tcp/10.77.2.1:{PORT}")
    _wait_for_line(router_log, "up (", router, 30)
    edge, edge_log = start("robot", "edge-router", "router", "--listen", f"tcp/127.0.0.1:{PORT}",
                           "--connect", f"tcp/10.77.2.1:{PORT}")
    _wait_for_line(edge_log, "up (", edge, 30)
    relaxer_out, robot_out = tmp_path / "relaxer-host", tmp_path / "robot-host"
    relaxer, relaxer_log = start("relaxer", "relaxer-host", "run", "--only", "relaxer", "--connect",
                                 f"tcp/10.77.1.1:{PORT}", "--out", str(relaxer_out), *common)
    robot, robot_log = start("robot", "robot-host", "run", "--skip", "relaxer", "--connect", f"tcp/127.0.0.1:{PORT}",
                             "--out", str(robot_out), "--max-sim-time", str(MAX_SIM_TIME_S),
                             "--start-timeout-s", "120", *common)
    assert robot.wait(300) == 0, robot_log.read_text()[-3000:]
    assert processes.stop(relaxer, timeout_s=LAUNCHER_STOP_S) == 0, relaxer_log.read_text()[-3000:]
    assert "serving relaxer on tcp/10.77.1.1" in relaxer_log.read_text()
    for proc in (edge, router):
        assert processes.stop(proc, timeout_s=LAUNCHER_STOP_S) == 0
    # every service came through the routers: the relaxer ran (and stored the map) on its own host only
    assert (relaxer_out / "map.sqlite").is_file() and not (robot_out / "map.sqlite").exists()
    assert sorted(p.name for p in (robot_out / "logs").iterdir()) == [
        "dead_reckoning.log", "explorer.log", "place_recognizer.log", "recorder.log", "sensor_sim.log"]
    assert "robot0/relaxer joined" in router_log.read_text()
    summary = json.loads((robot_out / "summary.json").read_text())
    assert summary["sim_time_s"] >= MAX_SIM_TIME_S - 1 and summary["links_lost"] == 0, summary

    places, links = _map(robot_out)
    ref_places, ref_links = _map(single)
    assert len(ref_places) >= 10
    why = f"single host: {_counters(single)}\nseveral hosts: {_counters(robot_out)}"
    assert set(places) == set(ref_places), why
    assert links == ref_links, why
    worst = max(max(abs(places[i][0] - ref_places[i][0]), abs(places[i][1] - ref_places[i][1])) for i in places)
    assert worst <= XY_TOLERANCE_M, f"places differ by up to {worst:.3f} m"


@pytest.fixture
def secure_hosts(tmp_path, processes):
    """`relaxmap certs`, then a router with deploy/router-secure.json5 on loopback, each host in its own
    folder holding its secrets/. Yields (folder of each identity's host, endpoint)."""
    from services.runtime.certs import write_certs

    folders = write_certs(tmp_path / "ca", ["relaxer", "robot"])
    homes = {}
    for name, folder in folders.items():
        homes[name] = tmp_path / f"{name}-host"
        shutil.copytree(folder, homes[name] / "secrets")
    from tests.conftest import free_port

    endpoint = f"tls/127.0.0.1:{free_port()}"
    log = tmp_path / "router.log"
    with log.open("wb") as f:
        router = processes.start([sys.executable, "-m", "services.cli", "router", "--config",
                                  str(REPO / "deploy" / "router-secure.json5"), "--listen", endpoint],
                                 cwd=homes["router"], stdout=f, stderr=subprocess.STDOUT)
    _wait_for_line(log, "up (", router, 30)
    yield homes, endpoint
    assert processes.stop(router, timeout_s=LAUNCHER_STOP_S) == 0


def _secure_run(processes, home: Path, endpoint: str, out: str, *args: str) -> tuple[subprocess.Popen, Path]:
    log = home / f"{out}.log"
    with log.open("wb") as f:
        proc = processes.start([sys.executable, "-m", "services.cli", "run", "--config",
                                str(REPO / "deploy" / "client-secure.json5"), "--connect", endpoint,
                                "--out", out, "--seed", str(SEED), "--headless", *args],
                               cwd=home, stdout=f, stderr=subprocess.STDOUT)
    return proc, log


def test_tls_and_access_control_let_the_whole_run_through(secure_hosts, processes):
    """Every key the services use passes deploy/router-secure.json5 when the relaxer shows its certificate."""
    homes, endpoint = secure_hosts
    relaxer, relaxer_log = _secure_run(processes, homes["relaxer"], endpoint, "relaxer-out", "--only", "relaxer")
    robot, robot_log = _secure_run(processes, homes["robot"], endpoint, "out", "--skip", "relaxer", "--max-sim-time", "30",
                                   "--start-timeout-s", "120")
    assert robot.wait(300) == 0, robot_log.read_text()[-3000:]
    assert processes.stop(relaxer, timeout_s=LAUNCHER_STOP_S) == 0, relaxer_log.read_text()[-3000:]
    summary = json.loads((homes["robot"] / "out" / "summary.json").read_text())
    assert summary["places"] >= 5 and summary["links_lost"] == 0, summary
    assert (homes["robot"] / "out" / "grid.png").is_file()


def test_a_relaxer_without_the_relaxer_certificate_is_not_heard(secure_hosts, processes):
    """The relaxer started with the robot's certificate: alive, but its map never reaches the run."""
    homes, endpoint = secure_hosts
    relaxer, relaxer_log = _secure_run(processes, homes["robot"], endpoint, "relaxer-out", "--only", "relaxer")
    robot, robot_log = _secure_run(processes, homes["robot"], endpoint, "out", "--skip", "relaxer", "--max-sim-time", "10",
                                   "--start-timeout-s", "120", "--settle-timeout-s", "3")
    assert robot.wait(300) == 1, robot_log.read_text()[-3000:]
    assert processes.stop(relaxer, timeout_s=LAUNCHER_STOP_S) == 0, relaxer_log.read_text()[-3000:]
    text = robot_log.read_text()
    assert "all 6 services alive" in text and "the relaxer does not answer relaxmap/robot0/map/stats" in text, \
        text[-3000:]
