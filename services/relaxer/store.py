"""The relaxer's map on disk: SQLite (WAL), one transaction per map update, so a restart resumes it.

Standard-library sqlite3: durable against a killed process (WAL with ``synchronous=NORMAL`` loses no
committed transaction when the process dies; only a power cut may lose the last ones), readable by
any SQLite tool, and no server to run.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from messages.types import MapLink, NoiseParams

SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS places (
    id INTEGER PRIMARY KEY, x REAL NOT NULL, y REAL NOT NULL, x0 REAL NOT NULL, y0 REAL NOT NULL,
    stamp REAL NOT NULL);
CREATE TABLE IF NOT EXISTS links (
    a INTEGER NOT NULL, b INTEGER NOT NULL, d REAL NOT NULL, theta REAL NOT NULL, steps INTEGER NOT NULL,
    mean_step REAL NOT NULL, variance REAL, traversals INTEGER NOT NULL, stamp REAL NOT NULL,
    PRIMARY KEY (a, b)) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS scans (
    id INTEGER PRIMARY KEY, stamp REAL NOT NULL, place_id INTEGER NOT NULL, off_x REAL NOT NULL,
    off_y REAL NOT NULL, dr_x REAL NOT NULL, dr_y REAL NOT NULL, heading REAL NOT NULL,
    angles BLOB NOT NULL, ranges BLOB NOT NULL, beam_width REAL NOT NULL, max_range REAL NOT NULL);
CREATE TABLE IF NOT EXISTS received (topic TEXT PRIMARY KEY, seq INTEGER NOT NULL) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS deleted_places (id INTEGER PRIMARY KEY);
"""
SCHEMA_VERSION = 1


@dataclass
class StoredScan:
    """A sonar scan taken at a place: offset from the place centre, and the dead-reckoned pose."""

    stamp: float
    place_id: int
    off_x: float
    off_y: float
    dr_x: float
    dr_y: float
    heading: float
    angles: np.ndarray
    ranges: np.ndarray
    beam_width: float
    max_range: float


@dataclass
class StoredMap:
    """Everything the store holds, as loaded at start."""

    places: dict[int, tuple[float, float]]  # id -> relaxed (x, y)
    initial: dict[int, tuple[float, float]]  # id -> (x, y) as first confirmed (dead reckoning)
    links: list[MapLink]
    version: int = 0
    noise: NoiseParams | None = None
    received: dict[str, int] = field(default_factory=dict)  # topic -> last sequence number applied
    deleted: set[int] = field(default_factory=set)  # ids of places deleted for good
    link_stamps: dict[tuple[int, int], float] = field(default_factory=dict)  # (a, b) -> latest measurement


@dataclass
class Transaction:
    """The changes of one map update, written atomically by ``MapStore.commit``."""

    new_places: list[tuple[int, float, float, float]] = field(default_factory=list)  # id, x, y, stamp
    deleted_places: list[int] = field(default_factory=list)
    links: list[tuple[MapLink, float]] = field(default_factory=list)  # upserted, with stamp
    deleted_links: list[tuple[int, int]] = field(default_factory=list)
    moved: list[tuple[int, float, float]] = field(default_factory=list)  # id, new x, new y
    scans: list[StoredScan] = field(default_factory=list)
    received: dict[str, int] = field(default_factory=dict)
    version: int | None = None
    noise: NoiseParams | None = None

    def __bool__(self) -> bool:
        return bool(self.new_places or self.deleted_places or self.links or self.deleted_links or self.moved
                    or self.scans or self.received or self.version is not None)


class StoreError(RuntimeError):
    """The store file cannot be used (not a relaxmap map, or a newer schema)."""


class MapStore:
    """A map in one SQLite file."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        try:
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.executescript(SCHEMA)
            row = self._db.execute("SELECT value FROM meta WHERE key='schema'").fetchone()
        except sqlite3.DatabaseError as e:
            self._db.close()
            raise StoreError(f"{self.path}: not a relaxmap map store ({e})") from e
        if row is None:
            self._db.execute("INSERT INTO meta VALUES ('schema', ?)", (SCHEMA_VERSION,))
        elif int(row[0]) > SCHEMA_VERSION:
            self._db.close()
            raise StoreError(f"{self.path}: schema {row[0]} is newer than this relaxmap's ({SCHEMA_VERSION})")

    def load(self) -> StoredMap:
        db = self._db
        places, initial = {}, {}
        for pid, x, y, x0, y0 in db.execute("SELECT id, x, y, x0, y0 FROM places"):
            places[pid] = (x, y)
            initial[pid] = (x0, y0)
        links, link_stamps = [], {}
        for a, b, d, t, s, m, v, n, stamp in db.execute(
                "SELECT a, b, d, theta, steps, mean_step, variance, traversals, stamp FROM links ORDER BY stamp"):
            links.append(MapLink(from_id=a, to_id=b, d_m=d, theta_rad=t, steps=s, mean_step_m=m, variance_m2=v,
                                 traversals=n))
            link_stamps[(min(a, b), max(a, b))] = stamp
        meta = dict(db.execute("SELECT key, value FROM meta"))
        noise = None
        if "s_dd" in meta:
            noise = NoiseParams(s_dd=meta["s_dd"], s_aa=meta["s_aa"], s_da=meta["s_da"])
        received = dict(db.execute("SELECT topic, seq FROM received"))
        deleted = {r[0] for r in db.execute("SELECT id FROM deleted_places")}
        return StoredMap(places=places, initial=initial, links=links, version=int(meta.get("version", 0)),
                         noise=noise, received=received, deleted=deleted, link_stamps=link_stamps)

    def commit(self, tx: Transaction) -> None:
        """Write one update in one transaction: all of it or, if the process dies, none of it."""
        if not tx:
            return
        db = self._db
        db.execute("BEGIN")
        try:
            db.executemany("INSERT OR REPLACE INTO places VALUES (?, ?, ?, ?, ?, ?)",
                           ((i, x, y, x, y, s) for i, x, y, s in tx.new_places))
            db.executemany("UPDATE places SET x=?, y=? WHERE id=?", ((x, y, i) for i, x, y in tx.moved))
            db.executemany("INSERT OR REPLACE INTO links VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                           ((lk.from_id, lk.to_id, lk.d_m, lk.theta_rad, lk.steps, lk.mean_step_m,
                             lk.variance_m2, lk.traversals, stamp) for lk, stamp in tx.links))
            db.executemany("DELETE FROM links WHERE a=? AND b=?", tx.deleted_links)
            db.executemany("DELETE FROM links WHERE a=? OR b=?", ((i, i) for i in tx.deleted_places))
            db.executemany("DELETE FROM places WHERE id=?", ((i,) for i in tx.deleted_places))
            db.executemany("INSERT OR IGNORE INTO deleted_places VALUES (?)", ((i,) for i in tx.deleted_places))
            db.executemany("INSERT INTO scans (stamp, place_id, off_x, off_y, dr_x, dr_y, heading, angles, ranges,"
                           " beam_width, max_range) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                           ((s.stamp, s.place_id, s.off_x, s.off_y, s.dr_x, s.dr_y, s.heading,
                             np.asarray(s.angles, "<f8").tobytes(), np.asarray(s.ranges, "<f8").tobytes(),
                             s.beam_width, s.max_range) for s in tx.scans))
            db.executemany("INSERT OR REPLACE INTO received VALUES (?, ?)", tx.received.items())
            meta: list[tuple[str, float]] = []
            if tx.version is not None:
                meta.append(("version", tx.version))
            if tx.noise is not None:
                meta += [("s_dd", tx.noise.s_dd), ("s_aa", tx.noise.s_aa), ("s_da", tx.noise.s_da)]
            db.executemany("INSERT OR REPLACE INTO meta VALUES (?, ?)", meta)
            db.execute("COMMIT")
        except BaseException:
            db.execute("ROLLBACK")
            raise

    def scans(self, place_ids: Iterable[int] | None = None) -> list[StoredScan]:
        """Stored scans (of the given places only, if named), oldest first."""
        rows = self._db.execute("SELECT stamp, place_id, off_x, off_y, dr_x, dr_y, heading, angles, ranges,"
                                " beam_width, max_range FROM scans ORDER BY id")
        wanted = None if place_ids is None else set(place_ids)
        out = []
        for r in rows:
            if wanted is not None and r[1] not in wanted:
                continue
            out.append(StoredScan(*r[:7], np.frombuffer(r[7], "<f8"), np.frombuffer(r[8], "<f8"), r[9], r[10]))
        return out

    def count(self, table: str) -> int:
        if table not in ("places", "links", "scans"):
            raise ValueError(f"no table {table!r}")
        return self._db.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0]  # noqa: S608 (checked name)

    def close(self) -> None:
        self._db.close()


def links_by_key(links: Sequence[MapLink]) -> dict[tuple[int, int], MapLink]:
    """Links keyed by their unordered place pair (the map holds one link per pair)."""
    return {(min(lk.from_id, lk.to_id), max(lk.from_id, lk.to_id)): lk for lk in links}
