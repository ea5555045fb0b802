"""A small service used by the bus tests: echoes compass readings and adds numbers on request."""

from __future__ import annotations

import argparse
import sys
import threading

import zenoh

from messages.types import CompassReading
from services.runtime import Node, QueryParams, service_main


def in_key(robot: str) -> str:
    return f"relaxmap/{robot}/test/in"


def out_key(robot: str) -> str:
    return f"relaxmap/{robot}/test/out"


def sum_key(robot: str) -> str:
    return f"relaxmap/{robot}/test/sum"


def run(session: zenoh.Session, args: argparse.Namespace, stop: threading.Event) -> None:
    with Node(session, "echo", robot=args.robot) as node:
        out = node.publisher(out_key(args.robot), CompassReading)
        seq = iter(range(1 << 62))

        def on_in(msg: CompassReading) -> None:
            out.put(CompassReading(stamp=msg.stamp, seq=next(seq), heading_rad=msg.heading_rad))

        def on_sum(_key: str, params: QueryParams) -> dict:
            a = params.float("a")
            b = params.float("b", 0.0)
            return {"sum": a + b}

        node.subscribe(in_key(args.robot), CompassReading, on_in)
        node.queryable(sum_key(args.robot), on_sum, params=("a", "b"))
        print("echo ready", flush=True)
        node.spin(stop)


if __name__ == "__main__":
    sys.exit(service_main("echo", run, description="echo node for the bus tests"))
