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
    parser.add_argument("--max-sim-time", type=float, default=3600.0, metavar="S",
                        help="stop after this many simulated seconds if exploration has not ended")
    parser.add_argument("--graph", help="process graph file (default: deploy/graph.json)")
    parser.add_argument("--port", type=int, default=7447,
                        help="loopback port of the run's hub (0: any free port)")
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
