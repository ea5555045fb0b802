"""Shared fixtures: free loopback ports, a hub zenoh session, and processes cleaned up by pid."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.runtime.procs import free_port  # noqa: F401 (tests import it from here)

REPO = Path(__file__).resolve().parents[1]
DATASETS = Path(os.environ.get("RELAXMAP_DATASETS", REPO.parent / "shared" / "datasets"))


@pytest.fixture
def hub() -> Iterator[tuple[object, str]]:
    """A zenoh peer listening on a fresh loopback port: (session, endpoint for others to connect to)."""
    import zenoh

    from services.runtime import loopback_config

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = zenoh.open(loopback_config(listen=[endpoint]))
    try:
        yield session, endpoint
    finally:
        session.close()


class Processes:
    """Starts processes in their own process group and kills every one of them by pid at the end."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen] = []

    def start(self, args: list[str], **kwargs) -> subprocess.Popen:
        kwargs.setdefault("stdout", subprocess.PIPE)
        kwargs.setdefault("stderr", subprocess.STDOUT)
        kwargs.setdefault("cwd", REPO)
        proc = subprocess.Popen(args, start_new_session=True, **kwargs)
        self.procs.append(proc)
        return proc

    def python(self, module: str, *args: str, **kwargs) -> subprocess.Popen:
        return self.start([sys.executable, "-m", module, *args], **kwargs)

    def stop(self, proc: subprocess.Popen, sig: int = signal.SIGTERM, timeout_s: float = 10.0) -> int:
        if proc.poll() is None:
            os.killpg(proc.pid, sig)
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        return proc.returncode

    def cleanup(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                try:
                    os.killpg(proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                proc.wait()
            for stream in (proc.stdout, proc.stderr):
                if stream is not None:
                    stream.close()


@pytest.fixture
def processes() -> Iterator[Processes]:
    procs = Processes()
    try:
        yield procs
    finally:
        procs.cleanup()


# A lockstep run's wall-time limits, raised so that no input of a loaded machine misses its turn; the
# explorer and the recognizer keep their own place centres (relaxed coordinates arrive when the relaxer
# is done, not at a tick).
PATIENT = {"explorer": ["--no-follow-map", "--localization-timeout-s", "30"],
           "place_recognizer": ["--no-follow-map", "--order-timeout-s", "30"],
           "sensor_sim": ["--lockstep-timeout-s", "30"]}


def reproducible_graph(tmp_path: Path) -> Path:
    """deploy/graph.json with the PATIENT arguments, written to ``tmp_path``: two lockstep runs of a
    seed make the same map (docs/runtime.md)."""
    graph = json.loads((REPO / "deploy" / "graph.json").read_text())
    for s in graph["services"]:
        s["args"].extend(PATIENT.get(s["name"], []))
    path = tmp_path / "graph.json"
    path.write_text(json.dumps(graph))
    return path


def wait_until(predicate, timeout_s: float, period_s: float = 0.02) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(period_s)
    return predicate()


class Collector:
    """Collects the decoded messages of one key (from zenoh's threads)."""

    def __init__(self, session, key, type_):
        from messages.codec import codec

        self.msgs = []
        self._lock = threading.Lock()
        dec = codec(type_)

        def on_sample(sample):
            msg = dec.decode(sample.payload.to_bytes())
            with self._lock:
                self.msgs.append(msg)

        self._sub = session.declare_subscriber(key, on_sample)

    def snapshot(self):
        with self._lock:
            return list(self.msgs)

    def close(self):
        self._sub.undeclare()
