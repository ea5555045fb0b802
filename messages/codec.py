"""One msgpack and one JSON encoder/decoder per message type, built once and reused."""

from __future__ import annotations

import functools
from typing import Generic, TypeVar

import msgspec

T = TypeVar("T")


class Codec(Generic[T]):
    """Encode and decode one type, msgpack for the bus and JSON for the query API."""

    def __init__(self, type_: type[T]) -> None:
        self.type = type_
        self._mp_dec = msgspec.msgpack.Decoder(type_)
        self._js_dec = msgspec.json.Decoder(type_)

    def encode(self, msg: T) -> bytes:
        return _MP_ENC.encode(msg)

    def decode(self, data: bytes | bytearray | memoryview) -> T:
        """Decode msgpack bytes; raises ``msgspec.DecodeError`` (or ValidationError) on bad input."""
        return self._mp_dec.decode(data)

    def encode_json(self, msg: T) -> bytes:
        return _JS_ENC.encode(msg)

    def decode_json(self, data: bytes | str) -> T:
        return self._js_dec.decode(data)


# Encoders carry no type: one of each serves every type.
_MP_ENC = msgspec.msgpack.Encoder()
_JS_ENC = msgspec.json.Encoder()


@functools.cache
def codec(type_: type[T]) -> Codec[T]:
    """The shared codec of ``type_``."""
    return Codec(type_)


def encode(msg: object, fmt: str = "msgpack") -> bytes:
    """Encode any msgspec-serialisable value as ``msgpack`` or ``json``."""
    if fmt == "msgpack":
        return _MP_ENC.encode(msg)
    if fmt == "json":
        return _JS_ENC.encode(msg)
    raise ValueError(f"unknown format {fmt!r}: expected 'msgpack' or 'json'")


# msgspec.ValidationError (wrong types) is a subclass of DecodeError (bad bytes).
DecodeError = msgspec.DecodeError
