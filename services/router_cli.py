"""``relaxmap router``: a zenoh router that the services of other hosts reach (and that chains to others)."""

from __future__ import annotations

import argparse

DEFAULT_CONFIG = "router.json5"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="zenoh JSON5 configuration (default: deploy/router.json5; "
                                         "deploy/router-secure.json5 for TLS and access control)")
    parser.add_argument("--listen", action="append", metavar="ENDPOINT",
                        help="endpoint to listen on, e.g. tcp/10.0.0.1:7447 (repeatable; replaces the file's)")
    parser.add_argument("--connect", action="append", metavar="ENDPOINT",
                        help="another router to chain to, e.g. tcp/10.0.0.2:7447 (repeatable; replaces the file's)")
    parser.add_argument("--robot", default="robot0", help="robot whose services are reported as they come and go")


def main(args: argparse.Namespace) -> int:
    import sys

    import zenoh

    from services.runtime import AliveWatcher, deploy_file, load_config, shutdown_event

    path = args.config or deploy_file(DEFAULT_CONFIG)
    try:
        conf = load_config(path, mode="router", connect=args.connect, listen=args.listen)
    except ValueError as e:
        print(f"relaxmap router: {e}", file=sys.stderr)
        return 2
    stop = shutdown_event()
    robot = args.robot
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as e:
        print(f"relaxmap router: cannot start with {path}: {e}", file=sys.stderr)
        return 1
    with session:
        print(f"relaxmap router {session.zid()} up ({path}); Ctrl-C stops it", file=sys.stderr, flush=True)

        def on_change(name: str, up: bool) -> None:
            print(f"{robot}/{name} {'joined' if up else 'left'}", file=sys.stderr, flush=True)

        watcher = AliveWatcher(session, robot, on_change=on_change)
        try:
            while not stop.wait(0.5):
                pass
        finally:
            watcher.close()
    print("relaxmap router stopped", file=sys.stderr)
    return 0
