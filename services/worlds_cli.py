"""``relaxmap worlds``: the built-in worlds with their sizes (and any world file given, checked)."""

from __future__ import annotations

import argparse
import json
import sys


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("files", nargs="*", metavar="FILE",
                        help="world files (JSON or ROS map .yaml) to check and list as well")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")


def main(args: argparse.Namespace) -> int:
    from sim.world import WorldError, builtin_worlds, load_world

    rows = []
    status = 0
    for spec in [*builtin_worlds(), *args.files]:
        try:
            w = load_world(spec)
        except WorldError as e:
            print(f"relaxmap worlds: {e}", file=sys.stderr)
            status = 1
            continue
        width, height = w.size_m
        rows.append({"name": w.name, "width_m": round(width, 2), "height_m": round(height, 2),
                     "walls": int(w.walls.shape[0]), "magnetic_disturbances": len(w.magnetic_disturbances),
                     "routes": sorted(w.routes), "start": [round(v, 3) for v in w.start],
                     "source": spec if spec in builtin_worlds() else w.source})
    if args.json:
        print(json.dumps(rows, indent=2))
        return status
    header = ("name", "size (m)", "walls", "disturbances", "routes", "source")
    lines = [(r["name"], f"{r['width_m']:g} x {r['height_m']:g}", str(r["walls"]), str(r["magnetic_disturbances"]),
              ", ".join(r["routes"]) or "-", "built-in" if r["source"] == r["name"] else r["source"])
             for r in rows]
    widths = [max(len(h), *(len(line[i]) for line in lines)) if lines else len(h) for i, h in enumerate(header)]
    for line in (header, *lines):
        print("  ".join(cell.ljust(widths[i]) for i, cell in enumerate(line)).rstrip())
    return status
