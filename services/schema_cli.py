"""``relaxmap schema``: the JSON Schema of every bus message, for clients in other languages."""

from __future__ import annotations

import argparse
import sys

import msgspec

from messages import ALL_MESSAGES, ALL_REPLIES


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--indent", type=int, default=2, help="indentation of the printed JSON")


def schema() -> dict:
    """One JSON Schema document whose ``$defs`` hold every message type and every query reply."""
    _, components = msgspec.json.schema_components((*ALL_MESSAGES, *ALL_REPLIES))
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "relaxmap bus messages",
        "description": "msgpack on the bus, JSON from the query API. New fields only with defaults.",
        "$defs": components,
    }


def main(args: argparse.Namespace) -> int:
    sys.stdout.write(msgspec.json.format(msgspec.json.encode(schema()), indent=args.indent).decode())
    sys.stdout.write("\n")
    return 0
