"""A service's state on disk, so that a restarted process goes on where the killed one stopped."""

from __future__ import annotations

import logging
import os
import struct
import zlib
from pathlib import Path
from typing import Any, Generic, TypeVar

import msgspec
import numpy as np

T = TypeVar("T")
log = logging.getLogger(__name__)


class CheckpointError(RuntimeError):
    """A checkpoint file exists but cannot be read as the service's state; the message says which."""


# both hooks handle every type a checkpoint holds; any other is a TypeError (msgspec passes it on from
# encode, and turns it into a ValidationError, a DecodeError, from decode)
def _enc_hook(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        a = np.ascontiguousarray(obj)
        return (a.dtype.str, list(a.shape), a.tobytes())
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot checkpoint {type(obj).__name__}")


def _dec_hook(type_: type, obj: Any) -> Any:
    if type_ is np.ndarray and isinstance(obj, (list, tuple)) and len(obj) == 3:
        dtype, shape, data = obj
        return np.frombuffer(data, dtype=np.dtype(dtype)).reshape(shape).copy()
    raise TypeError(f"cannot restore {type_!r} from {type(obj).__name__}")


class Checkpoint(Generic[T]):
    """A value of type ``T`` (msgspec Structs and dataclasses, numpy arrays inside) kept in two files.

    ``save`` overwrites the older of ``<path>.0`` and ``<path>.1`` with a header (a sequence number,
    the length and a CRC-32 of the payload) and the msgpack payload; ``load`` takes the newer one whose
    CRC holds. A process killed in the middle of a save leaves the other file whole, so a restart
    finds the previous state or the new one, never half of one. There is no fsync and no rename (a
    rename over a file costs a flush on ext4): the files survive the death of the process, since the
    kernel still writes them, but not a power cut. That is what a supervisor's restart needs, at a
    cost small enough to save on every tick.
    """

    _HEADER = struct.Struct("<8sQII")  # magic, sequence number, payload length, CRC-32 of the payload
    _MAGIC = b"relaxckp"

    def __init__(self, path: str | os.PathLike, type_: type[T]) -> None:
        self.path = Path(path)
        self.type = type_
        self._files = (self.path.with_name(self.path.name + ".0"), self.path.with_name(self.path.name + ".1"))
        self._fds: list[int | None] = [None, None]
        self._encoder = msgspec.msgpack.Encoder(enc_hook=_enc_hook)
        self._decoder = msgspec.msgpack.Decoder(type_, dec_hook=_dec_hook)
        self._seq: int | None = None  # sequence number of the newest whole save
        self.saves = 0

    def _read(self, file: Path) -> tuple[int, bytes] | None:
        """(sequence number, payload) of one file, None when it is missing, short or torn."""
        try:
            data = file.read_bytes()
        except FileNotFoundError:
            return None
        except OSError as e:
            raise CheckpointError(f"{file}: {e.strerror}") from e
        h = self._HEADER
        if len(data) < h.size:
            return None
        magic, seq, length, crc = h.unpack_from(data)
        payload = data[h.size:h.size + length]
        if magic != self._MAGIC or len(payload) != length or zlib.crc32(payload) != crc:
            return None
        return seq, payload

    def load(self) -> T | None:
        """The state saved last, or ``None`` when nothing was saved yet.

        Raises
        ------
        CheckpointError
            The files exist but neither holds a whole save, or the newest is not a ``T``.
        """
        found = [r for f in self._files if (r := self._read(f)) is not None]
        if not found:
            if any(f.exists() for f in self._files):
                raise CheckpointError(f"{self.path}.0 and .1: neither holds a whole checkpoint")
            self._seq = 0
            return None
        seq, payload = max(found)
        self._seq = seq
        try:
            return self._decoder.decode(payload)
        except (msgspec.DecodeError, ValueError, TypeError) as e:
            raise CheckpointError(f"{self.path}: not a {getattr(self.type, '__name__', self.type)} "
                                  f"checkpoint ({e})") from e

    def save(self, value: T) -> None:
        """Replace the saved state with ``value`` (the older of the two files is overwritten)."""
        if self._seq is None:
            found = [r[0] for f in self._files if (r := self._read(f)) is not None]
            self._seq = max(found, default=0)
        seq = self._seq + 1
        slot = seq % 2
        fd = self._fds[slot]
        if fd is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = self._fds[slot] = os.open(self._files[slot], os.O_WRONLY | os.O_CREAT, 0o644)
        payload = self._encoder.encode(value)
        os.pwrite(fd, self._HEADER.pack(self._MAGIC, seq, len(payload), zlib.crc32(payload)) + payload, 0)
        self._seq = seq
        self.saves += 1

    def remove(self) -> None:
        """Delete both files (a state that no longer exists)."""
        self.close()
        for f in self._files:
            f.unlink(missing_ok=True)

    def close(self) -> None:
        for i, fd in enumerate(self._fds):
            if fd is not None:
                os.close(fd)
                self._fds[i] = None


class EventLog(Generic[T]):
    """Messages appended one JSON line each, read back in order: what a service published (or is about
    to), so that a restarted process can publish again what its killed predecessor may not have sent.

    One ``write`` per append: a killed process leaves whole lines (a line cut short is skipped on reading).
    """

    def __init__(self, path: str | os.PathLike, type_: Any) -> None:
        self.path = Path(path)
        self._encoder = msgspec.json.Encoder()
        self._decoder = msgspec.json.Decoder(type_)

    def append(self, messages: list) -> None:
        if messages:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.path, "ab") as f:
                f.write(b"".join(self._encoder.encode(m) + b"\n" for m in messages))

    def read(self) -> list:
        """Every whole message logged, oldest first."""
        try:
            lines = self.path.read_bytes().splitlines()
        except FileNotFoundError:
            return []
        out = []
        for line in lines:
            try:
                out.append(self._decoder.decode(line))
            except msgspec.DecodeError:
                log.warning("%s: skipping a line that is not a logged message: %r", self.path, line[:80])
        return out
