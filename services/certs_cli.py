"""``relaxmap certs``: a CA and one certificate per identity (router, relaxer, ...) for the TLS configs."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("names", nargs="+", metavar="NAME",
                        help="identities to certify (the common names the router's access control sees), "
                             "e.g. relaxer robot; a `router` certificate is always written")
    parser.add_argument("--out", default="secrets", help="folder of the CA and of one sub-folder per identity")
    parser.add_argument("--router-host", action="append", default=[], metavar="HOST",
                        help="address or DNS name clients use to reach a router (repeatable; "
                             "127.0.0.1 and localhost are always named)")
    parser.add_argument("--days", type=int, default=365, help="validity of the certificates")


def main(args: argparse.Namespace) -> int:
    import sys

    from services.runtime.certs import write_certs

    try:
        folders = write_certs(args.out, list(dict.fromkeys(args.names)), router_hosts=args.router_host,
                              days=args.days)
    except (ValueError, OSError) as e:
        print(f"relaxmap certs: {e}", file=sys.stderr)
        return 2
    for name, folder in folders.items():
        print(f"{name}: {folder}/ (copy it as secrets/ to the host that runs as {name})")
    return 0
