"""The process side of a service: flags, logging, signals, a session, then the node's ``run``."""

from __future__ import annotations

import argparse
import logging
import math
import os
import signal
import sys
import threading
from collections.abc import Callable

import zenoh

from services.runtime.config import add_bus_arguments, config_from_args

log = logging.getLogger("relaxmap.runtime")


def shutdown_event() -> threading.Event:
    """An event set by SIGINT or SIGTERM, so that ``run`` loops end and sessions close cleanly."""
    stop = threading.Event()

    def handler(signum: int, _frame: object) -> None:
        log.info("signal %s: stopping", signal.Signals(signum).name)
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop


# Set by a launcher to its own pid: the service stops when that process is gone, even if it was
# SIGKILLed and could not stop its children itself.
PARENT_PID_ENV = "RELAXMAP_PARENT_PID"
PARENT_POLL_S = 0.5


def stop_with_parent(stop: threading.Event, *, poll_s: float = PARENT_POLL_S) -> threading.Thread | None:
    """Set ``stop`` once the launcher named in ``RELAXMAP_PARENT_PID`` has ended (the service is then
    adopted by another process, so its parent pid changes). A polling thread rather than Linux's
    PR_SET_PDEATHSIG, which fires when the forking thread ends, not the process, and is Linux-only."""
    value = os.environ.get(PARENT_PID_ENV)
    if not value:
        return None
    try:
        parent = int(value)
    except ValueError:
        log.warning("%s=%r is not a pid: not watching the launcher", PARENT_PID_ENV, value)
        return None

    def watch() -> None:
        while not stop.is_set():
            if os.getppid() != parent:
                log.warning("launcher (pid %d) is gone: stopping", parent)
                stop.set()
                return
            stop.wait(poll_s)

    thread = threading.Thread(target=watch, name="parent-watch", daemon=True)
    thread.start()
    return thread


def setup_logging(verbose: int = 0) -> None:
    level = logging.INFO if verbose == 0 else logging.DEBUG
    logging.basicConfig(level=level, stream=sys.stderr,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")


def service_main(
    name: str,
    run: Callable[[zenoh.Session, argparse.Namespace, threading.Event], None],
    *,
    description: str,
    add_arguments: Callable[[argparse.ArgumentParser], None] | None = None,
    argv: list[str] | None = None,
) -> int:
    """Parse the shared and the service's flags, open a session and call ``run(session, args, stop)``.

    Returns the process exit code: 0 after a clean stop, 2 for a bad configuration.
    """
    parser = argparse.ArgumentParser(prog=f"python -m services.{name}", description=description)
    add_bus_arguments(parser)
    parser.add_argument("-v", "--verbose", action="count", default=0)
    if add_arguments is not None:
        add_arguments(parser)
    args = parser.parse_args(argv)
    setup_logging(args.verbose)
    stop = shutdown_event()
    stop_with_parent(stop)
    try:
        conf = config_from_args(args)
    except ValueError as e:
        print(f"{name}: {e}", file=sys.stderr)
        return 2
    with zenoh.open(conf) as session:
        log.info("%s up (zid %s)", name, session.zid())
        run(session, args, stop)
    log.info("%s stopped", name)
    return 0


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    value = _finite(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text!r}")
    return value


def nonnegative_float(text: str) -> float:
    """argparse type: a finite number >= 0."""
    value = _finite(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text!r}")
    return value


def finite_float(text: str) -> float:
    """argparse type: a finite number."""
    return _finite(text)


def nonnegative_int(text: str) -> int:
    """argparse type: an integer >= 0."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {text!r}")
    return value


def _finite(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be finite, got {text!r}")
    return value
