"""``relaxmap query KEY [k=v ...]``: ask a running system and print the reply as JSON."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from services.runtime import add_bus_arguments

    parser.add_argument("key", help="key expression, e.g. map/stats or relaxmap/robot0/map/stats "
                                    "(a key not starting with relaxmap/ is taken below relaxmap/<robot>/)")
    parser.add_argument("params", nargs="*", metavar="k=v", help="query parameters")
    parser.add_argument("--timeout-s", type=float, default=5.0, help="how long to wait for a reply")
    add_bus_arguments(parser)


def main(args: argparse.Namespace) -> int:
    import sys

    import msgspec
    import zenoh

    from messages import topics
    from services.runtime import QueryFailed, config_from_args, query

    for p in args.params:
        if "=" not in p:
            print(f"relaxmap query: parameter {p!r} is not of the form k=v", file=sys.stderr)
            return 2
    key = args.key if args.key.startswith(topics.ROOT + "/") else f"{topics.ROOT}/{args.robot}/{args.key}"
    try:
        conf = config_from_args(args)
    except ValueError as e:
        print(f"relaxmap query: {e}", file=sys.stderr)
        return 2
    with zenoh.open(conf) as session:
        try:
            reply = query(session, key, ";".join(args.params), fmt="json", timeout_s=args.timeout_s)
        except QueryFailed as e:
            print(f"relaxmap query: {e}", file=sys.stderr)
            return 1
    sys.stdout.write(msgspec.json.format(msgspec.json.encode(reply), indent=2).decode() + "\n")
    return 0
