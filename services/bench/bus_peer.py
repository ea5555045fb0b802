"""The far end of ``relaxmap bench bus``: records one-way latencies and answers queries, own process."""

from __future__ import annotations

import argparse
import sys
import threading
import time

import zenoh

from messages.types import CompassReading
from services.runtime import Node, QueryParams, service_main

TYPED_KEY = "relaxmap/bench/typed"
RAW_KEY = "relaxmap/bench/raw"
STATS_KEY = "relaxmap/bench/stats"
ECHO_KEY = "relaxmap/bench/echo"


def run(session: zenoh.Session, args: argparse.Namespace, stop: threading.Event) -> None:
    latencies: list[float] = []
    raw_count = [0]
    lock = threading.Lock()

    # Latency is taken where a service sees the message (the node's event loop, after decoding):
    # CLOCK_MONOTONIC is shared by all processes of the machine, and the sender puts its send time
    # in ``stamp``.
    def on_typed(msg: CompassReading) -> None:
        lat = time.monotonic() - msg.stamp
        with lock:
            latencies.append(lat)

    def on_raw(_sample: zenoh.Sample) -> None:
        with lock:
            raw_count[0] += 1

    with Node(session, "bench_peer", robot="bench") as node:
        node.subscribe(TYPED_KEY, CompassReading, on_typed)
        raw_sub = session.declare_subscriber(RAW_KEY, on_raw)

        def on_stats(_key: str, params: QueryParams) -> dict:
            with lock:
                out = {"typed": list(latencies), "raw": raw_count[0]}
                if params.str("reset", "0") == "1":
                    latencies.clear()
                    raw_count[0] = 0
            return out

        node.queryable(STATS_KEY, on_stats, params=("reset",))
        node.queryable(ECHO_KEY, lambda _k, p: {"n": p.int("n", 0)}, params=("n",))
        node.spin(stop)
        raw_sub.undeclare()


if __name__ == "__main__":
    sys.exit(service_main("bench_peer", run, description="far end of relaxmap bench bus"))
