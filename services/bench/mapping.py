"""``relaxmap bench map``: latency from a link measurement to the map update that includes it."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--places", type=int, nargs="+", default=[100, 1000],
                        help="map sizes at which the latency is measured")
    parser.add_argument("--measure", type=int, default=300,
                        help="places added (with their links) while measuring: 300 time over 400 links, so that "
                             "the p99 is not just the slowest one or two")
    parser.add_argument("--seed", type=int, default=0, help="seed of the generated office-like map")


def _events(office, first: int, last: int, stamp0: float):
    """Messages of places ``first..last-1`` in exploration order: each place, then its links to earlier ones."""
    import math

    from messages.types import LinkMeasured, PlaceConfirmed

    g = office.graph
    src, dst = g.src, g.dst
    by_place: dict[int, list[int]] = {}
    for s in range(g.n_links):
        by_place.setdefault(int(max(src[s], dst[s])), []).append(s)
    out = []
    for i in range(first, last):
        x, y = office.xy_dead_reckoning[i]
        out.append(PlaceConfirmed(stamp=stamp0 + i, seq=i, place_id=int(g.ids[i]), x_m=float(x), y_m=float(y)))
        for s in by_place.get(i, []):
            out.append(LinkMeasured(stamp=stamp0 + i, seq=s, from_id=int(g.ids[src[s]]), to_id=int(g.ids[dst[s]]),
                                    d_m=float(g.d_m[s]), theta_rad=float(math.remainder(g.theta_rad[s], 2 * math.pi)),
                                    steps=int(g.steps[s]), mean_step_m=float(g.mean_step_m[s])))
    return out


def main(args: argparse.Namespace) -> int:
    import os
    import subprocess
    import sys
    import tempfile
    import threading
    import time

    import numpy as np
    import zenoh

    from messages import topics
    from messages.codec import codec
    from messages.types import LinkMeasured, MapStats, MapUpdate, PlaceConfirmed
    from services.bench.table import print_table
    from services.relaxer.online import OnlineMap
    from services.relaxer.synthetic import office_map
    from services.runtime import AliveWatcher, loopback_config, query
    from services.runtime.procs import free_port, stop_group

    robot = "benchmap"
    rows = []
    for n in args.places:
        office = office_map(n + args.measure, rng=np.random.default_rng(args.seed))
        fill = _events(office, 0, n, 0.0)
        probe = _events(office, n, n + args.measure, 0.0)
        # reference: the same events through the relaxer's core in this process, no bus
        core = OnlineMap()
        for msg in fill:
            (core.on_place_confirmed if isinstance(msg, PlaceConfirmed) else core.on_link_measured)(msg)
        core_ms = []
        for msg in probe:
            t = time.perf_counter()
            (core.on_place_confirmed if isinstance(msg, PlaceConfirmed) else core.on_link_measured)(msg)
            if isinstance(msg, LinkMeasured):
                core_ms.append((time.perf_counter() - t) * 1e3)
        with tempfile.TemporaryDirectory() as tmp:
            endpoint = f"tcp/127.0.0.1:{free_port()}"
            session = zenoh.open(loopback_config(listen=[endpoint]))
            proc = subprocess.Popen([sys.executable, "-m", "services.relaxer", "--robot", robot, "--connect", endpoint,
                                     "--store", os.path.join(tmp, "map.sqlite")], start_new_session=True,
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            try:
                watcher = AliveWatcher(session, robot)
                if not watcher.wait_alive(["relaxer"], 60):
                    print("relaxer did not start", file=sys.stderr)
                    return 1
                watcher.close()
                versions: list[int] = []
                arrived = threading.Condition()
                dec = codec(MapUpdate)

                def on_update(sample: zenoh.Sample) -> None:
                    with arrived:
                        versions.append(dec.decode(sample.payload.to_bytes()).version)
                        arrived.notify_all()

                sub = session.declare_subscriber(topics.map_update(robot), on_update)
                pubs = {PlaceConfirmed: session.declare_publisher(topics.places_confirmed(robot)),
                        LinkMeasured: session.declare_publisher(topics.links_measured(robot))}
                while not all(p.matching_status for p in pubs.values()):
                    time.sleep(0.01)
                for msg in fill:
                    pubs[type(msg)].put(codec(type(msg)).encode(msg))
                filled_links = sum(isinstance(m, LinkMeasured) for m in fill)
                deadline = time.monotonic() + 600
                while (query(session, topics.map_stats(robot), type_=MapStats).links < filled_links
                       and time.monotonic() < deadline):
                    time.sleep(0.2)
                bus_ms = []
                for msg in probe:
                    with arrived:
                        before = len(versions)
                    t = time.perf_counter()
                    pubs[type(msg)].put(codec(type(msg)).encode(msg))
                    with arrived:
                        arrived.wait_for(lambda: len(versions) > before, timeout=10)
                    if isinstance(msg, LinkMeasured):
                        bus_ms.append((time.perf_counter() - t) * 1e3)
                stats = query(session, topics.map_stats(robot), type_=MapStats)
                sub.undeclare()
                for p in pubs.values():
                    p.undeclare()
            finally:
                stop_group(proc)
                session.close()
        b, c = np.array(bus_ms), np.array(core_ms)
        rows.append((stats.places, len(b), *np.percentile(b, [50, 90, 99]), float(b.max()),
                     *np.percentile(c, [50, 99]), float(np.median(b) / np.median(c)),
                     ", ".join(f"{k} {v}" for k, v in sorted(stats.methods.items()))))
    print_table("link measurement -> map update, relaxer as a process on loopback (ms; reference: the same "
                "events through the core in one process)",
                ["places", "links timed", "p50", "p90", "p99", "max", "core p50", "core p99", "bus/core p50",
                 "cycles by method"], rows)
    return 0
