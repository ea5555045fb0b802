"""The relaxer's SQLite store: round trip, atomic transactions, and survival of SIGKILL."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import time

import numpy as np
import pytest

from messages.types import MapLink, NoiseParams
from services.relaxer.store import MapStore, StoredScan, StoreError, Transaction


def _link(a: int, b: int, d: float = 1.0) -> MapLink:
    return MapLink(from_id=a, to_id=b, d_m=d, theta_rad=0.5, steps=10, mean_step_m=0.1, variance_m2=None)


def test_round_trip(tmp_path):
    store = MapStore(tmp_path / "map.sqlite")
    tx = Transaction(new_places=[(0, 0.0, 0.0, 0.0), (1, 1.0, 0.1, 1.0), (2, 2.0, 0.0, 2.0)],
                     links=[(_link(0, 1), 1.0), (_link(1, 2, 1.1), 2.0)], version=3,
                     noise=NoiseParams(s_dd=1e-4, s_aa=2e-3, s_da=0.0), received={"links": 7})
    tx.scans.append(StoredScan(2.0, 1, 0.1, -0.1, 1.0, 0.1, 0.3, np.arange(16.0), np.full(16, 2.5), 0.4, 6.5))
    store.commit(tx)
    store.commit(Transaction(moved=[(1, 1.05, 0.0)], deleted_links=[(1, 2)], version=4))
    store.close()
    m = MapStore(tmp_path / "map.sqlite").load()
    assert m.places == {0: (0.0, 0.0), 1: (1.05, 0.0), 2: (2.0, 0.0)}
    assert m.initial[1] == (1.0, 0.1)
    assert m.links == [_link(0, 1)]
    assert m.version == 4 and m.noise == NoiseParams(s_dd=1e-4, s_aa=2e-3, s_da=0.0)
    assert m.received == {"links": 7}
    scans = MapStore(tmp_path / "map.sqlite").scans([1])
    assert len(scans) == 1 and np.array_equal(scans[0].angles, np.arange(16.0))


def test_deleting_a_place_deletes_its_links(tmp_path):
    store = MapStore(tmp_path / "m.sqlite")
    store.commit(Transaction(new_places=[(i, float(i), 0.0, 0.0) for i in range(3)],
                             links=[(_link(0, 1), 0.0), (_link(1, 2), 0.0)]))
    store.commit(Transaction(deleted_places=[1]))
    m = store.load()
    assert set(m.places) == {0, 2} and m.links == []


def test_failed_transaction_leaves_nothing(tmp_path):
    store = MapStore(tmp_path / "m.sqlite")
    store.commit(Transaction(new_places=[(0, 0.0, 0.0, 0.0)], version=1))
    bad = Transaction(new_places=[(1, 1.0, 0.0, 0.0)], links=[(_link(0, 1), 0.0)], version=2)
    bad.scans.append(StoredScan(0.0, 1, 0, 0, 0, 0, 0, np.zeros(2), np.zeros(2), 0.4, None))  # NOT NULL
    with pytest.raises(sqlite3.IntegrityError):
        store.commit(bad)
    m = store.load()
    assert set(m.places) == {0} and m.links == [] and m.version == 1


def test_not_a_store(tmp_path):
    junk = tmp_path / "junk.sqlite"
    junk.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(StoreError, match="not a relaxmap map store"):
        MapStore(junk)


WRITER = """
import sys, time
from messages.types import MapLink
from services.relaxer.store import MapStore, Transaction
store = MapStore(sys.argv[1])
i = 0
while True:
    link = MapLink(from_id=i, to_id=i + 1, d_m=1.0, theta_rad=0.0, steps=10, mean_step_m=0.1)
    store.commit(Transaction(new_places=[(i + 1, float(i + 1), 0.0, 0.0)], links=[(link, 0.0)], version=i + 1))
    if i == 0:
        print("writing", flush=True)
    i += 1
"""


def test_survives_sigkill_mid_write(tmp_path):
    path = tmp_path / "m.sqlite"
    MapStore(path).commit(Transaction(new_places=[(0, 0.0, 0.0, 0.0)], version=0))
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(path)], stdout=subprocess.PIPE,
                            start_new_session=True)
    try:
        assert proc.stdout.readline() == b"writing\n"
        time.sleep(0.5)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.stdout.close()
    m = MapStore(path).load()
    assert m.version > 10
    # every committed version has exactly its places and links: nothing half-written
    assert set(m.places) == set(range(m.version + 1))
    assert len(m.links) == m.version
