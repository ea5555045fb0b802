"""The ``relaxmap`` command line: one subcommand per module, imported only when it runs."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

# name -> (module, one-line help). Each module has ``add_arguments(parser)`` and ``main(args) -> int``,
# and keeps its heavy imports inside ``main`` so that ``relaxmap --help`` stays fast.
COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("services.launch.run_cli", "explore a world with every service and write the map"),
    "router": ("services.router_cli", "run a zenoh router that the services of other hosts connect to"),
    "certs": ("services.certs_cli", "write a CA and certificates for the TLS configurations"),
    "schema": ("services.schema_cli", "print the JSON Schema of every bus message"),
    "query": ("services.query_cli", "ask a running system (prints JSON)"),
    "bench": ("services.bench", "run the benchmarks (tables, never pass/fail)"),
    "relax": ("services.relaxer.cli", "optimise a stored map (g2o pose graph or compass map.json)"),
    "worlds": ("services.worlds_cli", "list the built-in worlds with their sizes"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="relaxmap",
        description="Fast, on-line learning of globally consistent robot maps.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-vv: debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (module, help_) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        p.set_defaults(_module=module)
        importlib.import_module(module).add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    level = logging.WARNING - 10 * args.verbose
    logging.basicConfig(level=max(level, logging.DEBUG), format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        return int(importlib.import_module(args._module).main(args) or 0)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
