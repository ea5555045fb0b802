"""Starts the services of a process graph as processes, restarts them by policy, stops them by pid."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from services.launch.graph import ProcessGraph, ServiceSpec, expand_args
from services.runtime.service import PARENT_PID_ENV

log = logging.getLogger("relaxmap.launch")


@dataclass
class Supervised:
    """One service's process and its restart bookkeeping."""

    spec: ServiceSpec
    args: list[str]
    proc: subprocess.Popen | None = None
    restarts: int = 0
    restart_at: float | None = None  # monotonic time of a pending restart
    exits: list[int] = field(default_factory=list)  # exit codes seen (negative: killed by signal)
    log_file: IO[bytes] | None = None
    halted: bool = False  # stopped on purpose before the others (never restarted)


class Supervisor:
    """Runs every service of ``graph`` as ``python -m <module>`` in its own process group.

    ``poll()`` must be called regularly: it notices exits and applies each service's restart policy
    (back-off doubling from ``backoff_s`` up to ``backoff_max_s``, at most ``max_restarts``). When a
    required service dies past its policy, ``failure`` says which and why.
    """

    def __init__(self, graph: ProcessGraph, *, common_args: list[str], values: dict[str, str],
                 log_dir: Path, on_event: Callable[[str], None] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.graph = graph
        self.log_dir = log_dir
        self.failure: str | None = None
        self.stopping = False
        self._on_event = on_event or (lambda msg: log.info("%s", msg))
        self._clock = clock
        self.services = {s.name: Supervised(s, [*common_args, *expand_args(s, values)]) for s in graph.services}

    def _spawn(self, sv: Supervised) -> None:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        if sv.log_file is None:
            sv.log_file = open(self.log_dir / f"{sv.spec.name}.log", "ab")  # noqa: SIM115 (kept open)
        cmd = [sys.executable, "-m", sv.spec.module, *sv.args]
        sv.log_file.write(f"\n=== start: {' '.join(cmd)}\n".encode())
        sv.log_file.flush()
        env = {**os.environ, PARENT_PID_ENV: str(os.getpid())}
        sv.proc = subprocess.Popen(cmd, stdout=sv.log_file, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                   start_new_session=True, env=env)
        sv.restart_at = None

    def start(self) -> None:
        for sv in self.services.values():
            self._spawn(sv)

    def pids(self) -> dict[str, int]:
        return {name: sv.proc.pid for name, sv in self.services.items() if sv.proc and sv.proc.poll() is None}

    def poll(self) -> None:
        """Notice exits, schedule and carry out restarts."""
        now = self._clock()
        for name, sv in self.services.items():
            if sv.halted:
                continue
            if sv.proc is None:
                if sv.restart_at is not None and now >= sv.restart_at and not self.stopping:
                    sv.restarts += 1
                    self._on_event(f"restarting {name} (restart {sv.restarts} of {sv.spec.restart.max_restarts})")
                    self._spawn(sv)
                continue
            code = sv.proc.poll()
            if code is None or self.stopping:
                continue
            sv.exits.append(code)
            sv.proc = None
            how = f"killed by {signal.Signals(-code).name}" if code < 0 else f"exit code {code}"
            pol = sv.spec.restart
            wants = pol.policy == "always" or (pol.policy == "on-failure" and code != 0)
            if wants and sv.restarts < pol.max_restarts:
                delay = min(pol.backoff_s * (2 ** sv.restarts), pol.backoff_max_s)
                sv.restart_at = now + delay
                self._on_event(f"{name} ended ({how}); restart in {delay:.1f} s")
            elif code != 0 and sv.spec.required:
                self.failure = (f"{name} ended ({how}) and was not restarted "
                                f"({sv.restarts} of {pol.max_restarts} restarts used, policy {pol.policy}); "
                                f"see {self.log_dir / (name + '.log')}")
                self._on_event(self.failure)
            else:
                self._on_event(f"{name} ended ({how})")

    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        """Send ``sig`` to a service's process group (fault injection, tests)."""
        sv = self.services[name]
        if sv.proc is not None and sv.proc.poll() is None:
            os.killpg(sv.proc.pid, sig)

    def halt(self, name: str, *, timeout_s: float = 10.0) -> int | None:
        """Stop one service now (SIGTERM, SIGKILL if it lingers) and never restart it; its exit code
        (None if it was not running)."""
        sv = self.services[name]
        sv.halted = True
        sv.restart_at = None
        if sv.proc is None:
            return None
        if sv.proc.poll() is None:
            _signal_group(sv.proc, signal.SIGTERM)
            try:
                sv.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self._on_event(f"{name} did not stop within {timeout_s:g} s: SIGKILL")
                _signal_group(sv.proc, signal.SIGKILL)
        code = sv.proc.wait()
        sv.exits.append(code)
        sv.proc = None
        return code

    def stop(self, *, order: list[str] | None = None, timeout_s: float = 10.0) -> dict[str, int]:
        """SIGTERM every service (in ``order``, default the graph's reverse), SIGKILL the ones that linger.

        Returns the exit code of each service that was running.
        """
        self.stopping = True
        names = order or list(reversed(self.graph.names()))
        codes: dict[str, int] = {}
        for name in names:
            sv = self.services[name]
            if sv.proc is not None and sv.proc.poll() is None:
                _signal_group(sv.proc, signal.SIGTERM)
        deadline = self._clock() + timeout_s
        for name in names:
            sv = self.services[name]
            if sv.proc is None:
                continue
            try:
                codes[name] = sv.proc.wait(max(0.0, deadline - self._clock()))
            except subprocess.TimeoutExpired:
                self._on_event(f"{name} did not stop within {timeout_s:g} s: SIGKILL")
                _signal_group(sv.proc, signal.SIGKILL)
                codes[name] = sv.proc.wait()
        for sv in self.services.values():
            if sv.log_file is not None:
                sv.log_file.close()
                sv.log_file = None
        return codes


def _signal_group(proc: subprocess.Popen, sig: int) -> None:
    """Send ``sig`` to the process group of ``proc`` (a group that is already gone is no error)."""
    try:
        os.killpg(proc.pid, sig)
    except ProcessLookupError:
        pass
