"""``python -m services.relaxer``: the relaxer service.

Flags: the bus flags (``--config --mode --connect --listen --robot``), ``--store PATH`` (the SQLite map;
an existing one is resumed), ``--seed S``, ``--duration-s S`` (stop after S wall seconds; 0 runs until
a signal).
"""

from __future__ import annotations

import argparse
import sys
import threading

import zenoh

from services.relaxer.node import RelaxerParams, run
from services.runtime import service_main


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--store", default=RelaxerParams().store_path, help="SQLite file of the map")
    parser.add_argument("--seed", type=int, default=0, help="seed of the noise estimator's random draws")
    parser.add_argument("--duration-s", type=float, default=0.0, help="stop after this many seconds (0: never)")


def _run(session: zenoh.Session, args: argparse.Namespace, stop: threading.Event) -> None:
    if args.duration_s > 0:
        timer = threading.Timer(args.duration_s, stop.set)
        timer.daemon = True
        timer.start()
    run(session, RelaxerParams(store_path=args.store, seed=args.seed), robot=args.robot, stop=stop)


if __name__ == "__main__":
    sys.exit(service_main("relaxer", _run, description="the map relaxer service", add_arguments=add_arguments))
