"""Checkpoints survive a save cut short; event logs survive a line cut short."""

from __future__ import annotations

import numpy as np
import pytest

from messages.types import PlaceConfirmed, PlaceDeleted
from services.place_recognizer.core import PlaceSignature
from services.place_recognizer.histogram import Histograms
from services.runtime.checkpoint import Checkpoint, CheckpointError, EventLog


def _signature(k: float) -> PlaceSignature:
    return PlaceSignature(np.full((4, 3), k), Histograms(np.arange(6).reshape(3, 2) * k, np.zeros((3, 2))), (k, -k))


def _same(a: PlaceSignature, b: PlaceSignature) -> bool:
    return (np.array_equal(a.logodds, b.logodds) and np.array_equal(a.hist.x, b.hist.x)
            and np.array_equal(a.hist.y, b.hist.y) and tuple(a.anchor_dr_xy) == tuple(b.anchor_dr_xy))


def test_round_trip_with_arrays(tmp_path):
    ckpt = Checkpoint(tmp_path / "s", PlaceSignature)
    assert ckpt.load() is None
    ckpt.save(_signature(1.5))
    back = Checkpoint(tmp_path / "s", PlaceSignature).load()
    assert _same(back, _signature(1.5)) and back.logodds.dtype == np.float64 and back.logodds.shape == (4, 3)


def test_a_save_cut_short_leaves_the_previous_one(tmp_path):
    ckpt = Checkpoint(tmp_path / "s", PlaceSignature)
    for k in (1.0, 2.0, 3.0):
        ckpt.save(_signature(k))
    newest = tmp_path / "s.1"  # saves 1, 2, 3 went to s.1, s.0, s.1
    data = newest.read_bytes()
    newest.write_bytes(data[: len(data) // 2])  # the process died in the middle of the write
    again = Checkpoint(tmp_path / "s", PlaceSignature)
    assert _same(again.load(), _signature(2.0))
    again.save(_signature(4.0))  # overwrites the torn file, not the whole one
    assert _same(Checkpoint(tmp_path / "s", PlaceSignature).load(), _signature(4.0))


def test_unreadable_checkpoints_are_an_error(tmp_path):
    (tmp_path / "s.0").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="neither holds a whole checkpoint"):
        Checkpoint(tmp_path / "s", PlaceSignature).load()
    Checkpoint(tmp_path / "t", PlaceConfirmed).save(PlaceConfirmed(stamp=0, seq=0, place_id=1, x_m=0, y_m=0))
    with pytest.raises(CheckpointError, match="not a PlaceSignature"):
        Checkpoint(tmp_path / "t", PlaceSignature).load()


def test_remove_deletes_both_files(tmp_path):
    ckpt = Checkpoint(tmp_path / "s", PlaceSignature)
    ckpt.save(_signature(1.0))
    ckpt.save(_signature(2.0))
    ckpt.remove()
    assert not list(tmp_path.iterdir())


def test_event_log_keeps_whole_lines_in_order(tmp_path):
    log = EventLog(tmp_path / "events", PlaceConfirmed | PlaceDeleted)
    assert log.read() == []
    events = [PlaceConfirmed(stamp=1, seq=0, place_id=0, x_m=0, y_m=0),
              PlaceDeleted(stamp=2, seq=0, place_id=0, reason="unreachable"),
              PlaceConfirmed(stamp=3, seq=1, place_id=1, x_m=1, y_m=0)]
    log.append(events[:2])
    log.append(events[2:])
    with open(tmp_path / "events", "ab") as f:
        f.write(b'{"type":"PlaceConfirmed","stamp":4,')  # the process died in the middle of a line
    assert log.read() == events
