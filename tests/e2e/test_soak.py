"""Soak: a ``relaxmap run`` on the campus world with every service's memory sampled over the run."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import psutil
import pytest
import zenoh

from messages import topics
from messages.types import Health
from services.launch.graph import load_graph
from services.runtime import QueryFailed, deploy_file, loopback_config, query
from services.runtime.procs import free_port, stop_group

# Simulated seconds of the soak: CI runs this small size; RELAXMAP_SOAK_SIM_S=3600 soaks for an hour
# of simulated time.
SOAK_SIM_S = float(os.environ.get("RELAXMAP_SOAK_SIM_S", "300"))
SERVICES = load_graph(deploy_file("graph.json")).names()  # the services `relaxmap run` starts
SAMPLE_PERIOD_S = 0.2
HEALTH_EVERY = 10  # samples between two health queries (the largest event queue of each service)
# Bounded memory: after the first third of the run (imports, first allocations, the allocator's
# arenas), the largest resident size of the last third exceeds that of the middle third by at most
# this fraction plus this many bytes. A leak per message (the sensor streams run at 10 frames per
# simulated second) grows without bound and fails it; the map itself grows with the places, which the
# absolute allowance covers at this size.
GROWTH_FRACTION = 0.25
GROWTH_BYTES = 16 * 2**20


def _healths(session: zenoh.Session) -> dict[str, Health]:
    healths = {}
    for name in SERVICES:
        try:
            healths[name] = query(session, topics.health(topics.DEFAULT_ROBOT, name), type_=Health, timeout_s=2)
        except QueryFailed:
            pass
    return healths


def _rss(pid: int) -> int | None:
    try:
        return psutil.Process(pid).memory_info().rss
    except psutil.Error:
        return None


@pytest.mark.slow
@pytest.mark.timeout(max(600.0, SOAK_SIM_S / 4))  # campus runs at 10-20x real time on 2 cores
def test_memory_stays_bounded_on_campus(tmp_path):
    port = free_port()
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", "--port", str(port), "--headless",
                             "--world", "campus", "--seed", "0", "--out", str(out),
                             "--max-sim-time", f"{SOAK_SIM_S:g}"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    samples: dict[str, list[int]] = {name: [] for name in SERVICES}
    session = zenoh.open(loopback_config(connect=[f"tcp/127.0.0.1:{port}"]))
    try:
        deadline = time.monotonic() + 120
        pids: dict[str, int] = {}
        while len(pids) < len(SERVICES) and time.monotonic() < deadline and proc.poll() is None:
            pids = {name: h.pid for name, h in _healths(session).items()}
            time.sleep(0.2)
        assert len(pids) == len(SERVICES), f"health answered by {sorted(pids)} only"
        queued = dict.fromkeys(SERVICES, 0)  # the most messages a service had received and not handled yet
        rounds = 0
        while proc.poll() is None:
            for name, pid in pids.items():
                rss = _rss(pid)
                if rss is not None:
                    samples[name].append(rss)
            rounds += 1
            if rounds % HEALTH_EVERY == 0:
                for name, h in _healths(session).items():
                    queued[name] = max(queued[name], int(h.detail.get("queued", 0)))
            time.sleep(SAMPLE_PERIOD_S)
        _, err = proc.communicate(timeout=60)
    finally:
        session.close()
        stop_group(proc)
    assert proc.returncode == 0, err[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["sim_time_s"] >= SOAK_SIM_S - 1 and all(n == 0 for n in summary["restarts"].values())
    mib = 2**20
    print(f"\nRSS over a {SOAK_SIM_S:g} s campus run ({summary['wall_time_s']:.0f} s wall), MiB:")
    print(f"{'service':18} {'samples':>7} {'first':>7} {'max 1/3':>7} {'max 2/3':>7} {'max 3/3':>7} {'queued':>7}")
    too_big = {}
    for name, rss in samples.items():
        n = len(rss)
        assert n >= 9, f"{name}: {n} memory samples only"
        thirds = [max(rss[i * n // 3:(i + 1) * n // 3]) for i in range(3)]
        print(f"{name:18} {n:7d} {rss[0] / mib:7.1f} " + " ".join(f"{t / mib:7.1f}" for t in thirds)
              + f" {queued[name]:7d}")
        if thirds[2] > thirds[1] * (1 + GROWTH_FRACTION) + GROWTH_BYTES:
            too_big[name] = [round(t / mib, 1) for t in thirds]
    assert not too_big, f"resident memory still growing (MiB per third): {too_big}"
