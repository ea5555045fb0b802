"""``relaxmap run``: start every service of the process graph, watch the run, write its outputs."""

from __future__ import annotations

import argparse

DEFAULT_GRAPH = "graph.json"
DEFAULT_WORLD = "orebro-office"
DEFAULT_OUT = "relaxmap-out"
START_TIMEOUT_S = 60.0
RESUME_START_TIMEOUT_S = 600.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--world", default=None,
                        help=f"built-in world name or a world file (default {DEFAULT_WORLD}; "
                             "with --resume: the saved run's)")
    parser.add_argument("--seed", type=int, default=None,
                        help="seed of every random generator of the run (default 0; with --resume: the saved run's)")
    parser.add_argument("--out", default=None, help=f"output directory (default {DEFAULT_OUT})")
    parser.add_argument("--resume", metavar="DIR", default=None,
                        help="continue the run saved in DIR (its map, robot, world and seed); outputs go to DIR")
    parser.add_argument("--viewer", action="store_true", help="spawn the Rerun viewer as well")
    parser.add_argument("--headless", action="store_true", help="no progress bar (log lines instead)")
    parser.add_argument("--max-sim-time", type=float, default=10800.0, metavar="S",
                        help="stop after this many simulated seconds if exploration has not ended")
    parser.add_argument("--graph", help="process graph file (default: deploy/graph.json)")
    parser.add_argument("--port", type=int, default=7447,
                        help="loopback port of the run's hub (0: any free port); not used with --connect/--config")
    parser.add_argument("--settle-timeout-s", type=float, default=30.0,
                        help="at the end, how long to wait for the relaxer to take in the last places and links")
    hosts = parser.add_argument_group("several hosts (see README: Several hosts)")
    hosts.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                       help="reach the other hosts through this router, e.g. tcp/10.0.0.1:7447 (repeatable): "
                            "no loopback hub, every service connects there")
    hosts.add_argument("--config", help="zenoh JSON5 configuration of the launcher and of every service it starts "
                                        "(default with --connect: deploy/client.json5; "
                                        "deploy/client-secure.json5 for TLS)")
    part = hosts.add_mutually_exclusive_group()
    part.add_argument("--only", action="append", default=[], metavar="SERVICE",
                      help="start only this service of the graph (repeatable) and serve it until Ctrl-C; "
                           "the host that runs the rest watches the run and writes the outputs")
    part.add_argument("--skip", action="append", default=[], metavar="SERVICE",
                      help="start every service but this one (repeatable): it runs on another host "
                           "(`--only`), and the run waits for it to be alive there")
    parser.add_argument("--start-timeout-s", type=float, default=None,
                        help=f"how long the services may take to come alive (default {START_TIMEOUT_S:g} s; "
                             f"{RESUME_START_TIMEOUT_S:g} s with --resume, as the relaxer first re-integrates "
                             "every stored scan)")


def main(args: argparse.Namespace) -> int:
    from services.launch.runner import RunError, run

    try:
        return run(args)
    except RunError as e:
        import sys

        print(f"relaxmap run: {e}", file=sys.stderr)
        return 1
