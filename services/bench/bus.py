"""``relaxmap bench bus``: typed pub/sub and queries between two processes, msgspec against json."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--messages", type=int, default=20000, help="messages per throughput run")
    parser.add_argument("--queries", type=int, default=1000, help="queries for the round-trip figures")
    parser.add_argument("--rate-hz", type=float, default=1000.0, help="send rate of the latency run")


def main(args: argparse.Namespace) -> int:
    import json
    import subprocess
    import sys
    import time

    import numpy as np
    import zenoh

    from messages.codec import codec
    from messages.types import CompassReading, Pose2, SonarScan, DeadReckonedPose
    from services.bench import bus_peer
    from services.bench.table import print_table, time_call
    from services.runtime import AliveWatcher, Node, loopback_config, query
    from services.runtime.procs import free_port, stop_group

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = zenoh.open(loopback_config(listen=[endpoint]))
    peer = subprocess.Popen([sys.executable, "-m", "services.bench.bus_peer", "--robot", "bench",
                             "--connect", endpoint], start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    rows = []
    try:
        watcher = AliveWatcher(session, "bench")
        if not watcher.wait_alive(["bench_peer"], 30):
            print("bench peer did not start", file=sys.stderr)
            return 1
        enc = codec(CompassReading)
        node = Node(session, "bench", robot="bench")
        typed = node.publisher(bus_peer.TYPED_KEY, CompassReading)
        raw = session.declare_publisher(bus_peer.RAW_KEY)
        while not (typed.matching_status and raw.matching_status):
            time.sleep(0.01)

        def stats(reset: bool = True) -> dict:
            return query(session, bus_peer.STATS_KEY, {"reset": int(reset)}, timeout_s=30)

        def drain(kind: str, n: int) -> float:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                st = stats(reset=False)
                got = len(st["typed"]) if kind == "typed" else st["raw"]
                if got >= n:
                    return time.monotonic()
                time.sleep(0.005)
            return float("nan")

        # 1. throughput: as fast as the sender can put, until the receiver has them all
        n = args.messages
        stats()
        payload = enc.encode(CompassReading(stamp=0.0, seq=0, heading_rad=0.1))
        t0 = time.monotonic()
        for _ in range(n):
            raw.put(payload)
        raw_rate = n / (drain("raw", n) - t0)
        stats()
        t0 = time.monotonic()
        for i in range(n):
            typed.put(CompassReading(stamp=time.monotonic(), seq=i, heading_rad=0.1))
        typed_rate = n / (drain("typed", n) - t0)
        stats()
        # 2. latency at a steady rate (one-way, CLOCK_MONOTONIC shared by both processes)
        m = max(100, min(n, int(args.rate_hz * 5)))
        period = 1.0 / args.rate_hz
        next_t = time.monotonic()
        for i in range(m):
            time.sleep(max(0.0, next_t - time.monotonic()))
            typed.put(CompassReading(stamp=time.monotonic(), seq=i, heading_rad=0.1))
            next_t += period
        drain("typed", m)
        lat = np.array(stats()["typed"]) * 1e6
        # 3. query round trip
        rtts = []
        for i in range(args.queries):
            t = time.perf_counter()
            query(session, bus_peer.ECHO_KEY, {"n": i})
            rtts.append(time.perf_counter() - t)
        rtt = np.array(rtts) * 1e6
        rows.append(("raw bytes put -> subscriber (reference)", f"{raw_rate:,.0f}", "-", "-", "-", 1.0))
        rows.append(("typed pub/sub (TypedPublisher -> Node.subscribe)", f"{typed_rate:,.0f}", *np.percentile(lat, [50, 90, 99]),
                     typed_rate / raw_rate))
        rows.append(("query round trip (Node queryable)", f"{1e6 / rtt.mean():,.0f}",
                     *np.percentile(rtt, [50, 90, 99]), float("nan")))
        watcher.close()
        node.close()
        raw.undeclare()
    finally:
        stop_group(peer)
        session.close()
    print_table(f"bus: two processes on loopback ({n} messages, latency at {args.rate_hz:g} Hz)",
                ["what", "messages/s", "p50 us", "p90 us", "p99 us", "ratio to raw"], rows)

    # 4. codec: msgspec against the standard json module, on a sonar scan and a pose
    scan = SonarScan(stamp=1.0, seq=1, angles_rad=[i * 0.3927 for i in range(16)],
                     ranges_m=[1.0 + i * 0.1 for i in range(16)], beam_width_rad=0.436,
                     min_range_m=0.15, max_range_m=6.5)
    p = Pose2(x_m=1.0, y_m=2.0, heading_rad=0.3)
    pose = DeadReckonedPose(stamp=1.0, seq=1, compass=p, raw=p, steps=10, path_length_m=1.0)
    crow = []
    import msgspec

    for msg in (scan, pose):
        c = codec(type(msg))
        as_dict = msgspec.to_builtins(msg)
        mp = c.encode(msg)
        js = json.dumps(as_dict)
        t_enc = time_call(lambda: c.encode(msg))
        t_dec = time_call(lambda: c.decode(mp))
        t_jenc = time_call(lambda: json.dumps(msgspec.to_builtins(msg)))
        t_jdec = time_call(lambda: type(msg)(**{k: v for k, v in json.loads(js).items() if k != "type"}))
        crow.append((type(msg).__name__, len(mp), len(js), t_enc * 1e6, t_jenc * 1e6, t_jenc / t_enc,
                     t_dec * 1e6, t_jdec * 1e6, t_jdec / t_dec))
    print_table("codec: msgspec msgpack against stdlib json (typed objects both ways)",
                ["message", "msgpack B", "json B", "encode us", "json encode us", "ratio",
                 "decode us", "json decode us", "ratio"], crow)
    return 0
