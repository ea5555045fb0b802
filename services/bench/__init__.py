"""``relaxmap bench NAME``: benchmarks that print tables with ratios against a reference run alongside."""

from __future__ import annotations

import argparse
import importlib

# name -> module; each module has ``add_arguments(parser)`` and ``main(args) -> int``, and keeps its
# heavy imports inside ``main`` so that ``relaxmap --help`` stays fast.
BENCHES: dict[str, tuple[str, str]] = {
    "map": ("services.bench.mapping", "latency from a link measurement to its map update, by map size"),
    "bus": ("services.bench.bus", "typed pub/sub and queries between two processes; msgspec vs json"),
    "places": ("services.bench.places", "recognition time per scan against the map size; exploration wall time"),
    "relax": ("services.bench.relax", "pose graphs vs GTSAM LM, compass sweeps, on-line cycle cost and memory"),
    "sim": ("services.bench.sim", "simulation steps/s, ray casts/s, real-time factor of sensor_sim + DR"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="bench", metavar="NAME", required=True)
    for name, (module, help_) in BENCHES.items():
        p = sub.add_parser(name, help=help_, description=help_)
        p.set_defaults(_bench_module=module)
        importlib.import_module(module).add_arguments(p)


def main(args: argparse.Namespace) -> int:
    return int(importlib.import_module(args._bench_module).main(args) or 0)
