"""The relaxer service's core: the on-line map that places and links flow into (pure, no bus).

Events (a place confirmed, a link measured, a place or link deleted) change the map; after each, one
relaxation cycle runs (the paper's on-line mode, with the engine's automatic strategy for large
loops) and the cycle's outcome is returned as a map update plus the store transaction that makes it
durable. Queries (graph, place, path, grid, stats) are answered from the same state.

Every event may come more than once (the bus replays its history to a relaxer that starts late or
restarts) and in any order across topics. So: a place already known is not added again; a deleted
place stays deleted (its id is kept); a link measurement replaces the pair's only when it fuses at
least as many traversals and differs; a link whose places are not known yet waits for them.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import msgspec
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from messages.types import (
    LinkDeleted,
    LinkMeasured,
    MapGraph,
    MapLink,
    MapPlace,
    MapStats,
    MapUpdate,
    NoiseParams,
    OccupancyGrid,
    PathReply,
    PlaceConfirmed,
    PlaceDeleted,
    PlacePosition,
    PlaceReply,
    PlaceScan,
    ScanSet,
)
from services.common.occupancy import GlobalGrid, SonarConeParams, compose
from services.relaxer.compass import CompassNoise, CompassParams, CompassRelaxer, estimate_noise_reml
from services.relaxer.graph import MapGraph as Graph
from services.relaxer.store import StoredMap, StoredScan, Transaction


class OnlineParams(msgspec.Struct, frozen=True, kw_only=True):
    """Parameters of the on-line map."""

    initial_noise: NoiseParams = NoiseParams(s_dd=1e-4, s_aa=1e-3, s_da=0.0)  # Figure 3 step 1
    # how the noise parameters are re-estimated: "reml" (restricted maximum likelihood after each loop
    # closure, held in between), "paper" (Eqs. 12-14 after every sweep, as Figure 3), "fixed"
    noise_estimation: str = "reml"
    reml_min_loops: int = 20  # REML needs this many independent loops (links - places + parts): with
    # fewer, its three parameters rest on a handful of residuals and can sink to a floor (a map bent by
    # metres with every link right)
    reml_loop_growth: float = 1.25  # ... and re-runs when the loops grew by this factor since the last
    reml_max_rounds: int = 30  # EM rounds per re-estimation (warm-started from the current noise)
    reml_samples: int = 16  # posterior samples of the EM's E-step
    changed_threshold_m: float = 1e-6  # a place whose coordinates move less is not in an update
    settled_step_m: float = 1e-6  # a sweep that moves no place further leaves the map settled (see settle)
    grid_resolution_m: float = 0.15  # default cell size of the global grid (Section 4.3)
    anchor_radius_m: float = 1.5  # a scan taken this close to a place's first position is kept with it
    relax: CompassParams = CompassParams()  # the relaxation engine's parameters (estimate_noise is set
    # from noise_estimation)
    cone: SonarConeParams = SonarConeParams()  # inverse sonar model of the global grid


class UnknownPlace(KeyError):
    """A query named a place the map does not hold."""


def _noise_msg(n: CompassNoise) -> NoiseParams:
    return NoiseParams(s_dd=n.s_dd_m2, s_aa=n.s_aa_rad2, s_da=n.s_da_m_rad)


def _noise_core(n: NoiseParams) -> CompassNoise:
    return CompassNoise(s_dd_m2=n.s_dd, s_aa_rad2=n.s_aa, s_da_m_rad=n.s_da)


def _pair(a: int, b: int) -> tuple[int, int]:
    return (a, b) if a <= b else (b, a)


_EVENT_ORDER = {PlaceConfirmed: 0, PlaceDeleted: 1, LinkDeleted: 2}  # within one step of the explorer


def _same(link: MapLink, msg: LinkMeasured) -> bool:
    """The held link is exactly this measurement (in either direction)."""
    fwd = (link.from_id, link.to_id) == (msg.from_id, msg.to_id)
    theta = msg.theta_rad if fwd else math.remainder(msg.theta_rad + math.pi, 2 * math.pi)
    return (link.traversals == msg.traversals and link.steps == msg.steps and link.d_m == msg.d_m
            and abs(math.remainder(link.theta_rad - theta, 2 * math.pi)) < 1e-12
            and link.mean_step_m == msg.mean_step_m and link.variance_m2 == msg.variance_m2)


@dataclass
class CycleOutcome:
    """What one event did: the update to publish (None if nothing changed) and what to store."""

    update: MapUpdate | None
    tx: Transaction


class OnlineMap:
    """The relaxer's map: places, traversed links, relaxed coordinates, scans for the grid."""

    def __init__(self, params: OnlineParams = OnlineParams(), stored: StoredMap | None = None, *,
                 rng: np.random.Generator | None = None) -> None:
        if params.noise_estimation not in ("reml", "paper", "fixed"):
            raise ValueError(f"noise_estimation {params.noise_estimation!r}: expected reml, paper or fixed")
        self.params = params
        self.rng = rng if rng is not None else np.random.default_rng(0)  # REML's posterior samples
        self.noise_estimates = 0
        self._loops_at_estimate = 0  # loops in the map at the last noise re-estimation
        self.version = 0
        self.seq = 0
        self.links: dict[tuple[int, int], MapLink] = {}
        self.link_stamps: dict[tuple[int, int], float] = {}  # simulated time of each link's latest measurement
        self._pending: dict[tuple[int, int], LinkMeasured] = {}  # links whose places are not known yet
        self.deleted: set[int] = set()  # places deleted for good: a replayed confirmation stays ignored
        self.initial: dict[int, tuple[float, float]] = {}  # place -> position when confirmed (dead reckoning)
        self.scans: list[StoredScan] = []
        # the grids at the default resolution, kept up to date scan by scan: one per place in
        # place-centred coordinates (shifted to the relaxed coordinates when asked) and one in the
        # dead-reckoning frame; other resolutions are built from the scans when asked
        self._place_grids: dict[int, GlobalGrid] = {}
        self._dr_grid = GlobalGrid(params.grid_resolution_m, params.cone)
        self.updates = 0
        self.iterations = 0
        self.methods: dict[str, int] = {}
        self.cycle_ms: deque[float] = deque(maxlen=10_000)  # the latest cycles' durations, for stats
        self.energy = 0.0
        self._settled = True  # the last cycle left the map at its minimum (an exact solve, or a still sweep)
        self._last_stamp = 0.0
        graph = Graph()
        xy = np.zeros((0, 2))
        noise = _noise_core(params.initial_noise)
        if stored is not None:
            ids = sorted(stored.places)
            graph.add_places(ids)
            xy = np.array([stored.places[i] for i in ids], dtype=float).reshape(-1, 2)
            for lk in stored.links:
                graph.add_link(lk.from_id, lk.to_id, d_m=lk.d_m, theta_rad=lk.theta_rad, steps=lk.steps,
                               mean_step_m=lk.mean_step_m, variance_m2=lk.variance_m2)
                self.links[_pair(lk.from_id, lk.to_id)] = lk
            self.link_stamps = dict(stored.link_stamps)
            self.version = stored.version
            self.deleted = set(stored.deleted)
            self.initial = dict(stored.initial)
            if stored.noise is not None:
                noise = _noise_core(stored.noise)
        relax = msgspec.structs.replace(params.relax, estimate_noise=params.noise_estimation == "paper")
        self.relaxer = CompassRelaxer(graph, xy, noise=noise, params=relax)
        if graph.n_places:
            self.energy = self.relaxer.energy()

    # -- events -----------------------------------------------------------------------------------
    @staticmethod
    def check_place(msg: PlaceConfirmed) -> None:
        """``ValueError`` for a confirmation no map can hold (coordinates that are not finite)."""
        if not (math.isfinite(msg.x_m) and math.isfinite(msg.y_m)):
            raise ValueError(f"place {msg.place_id} at ({msg.x_m}, {msg.y_m})")

    def on_place_confirmed(self, msg: PlaceConfirmed) -> CycleOutcome:
        """A confirmed place; ``ValueError`` (nothing changed) for coordinates that are not finite."""
        self.check_place(msg)
        return self.on_explorer_events([msg], msg.stamp, always=False)

    def on_explorer_events(self, events: list[PlaceConfirmed | PlaceDeleted | LinkDeleted], stamp: float, *,
                           always: bool = True) -> CycleOutcome:
        """The explorer's map events of one step (places confirmed, places and links deleted), applied
        together in a fixed order (confirmations, place deletions, link deletions, each in seq order)
        and relaxed by one cycle: the map after them does not depend on the order they came in. A step
        whose events change nothing (a link the map never held deleted) still gives an update, without a
        cycle, which tells the services waiting for it that the events are in (unless not ``always``)."""
        tx = Transaction()
        changed = False
        for ev in sorted(events, key=lambda e: (_EVENT_ORDER[type(e)], e.seq)):
            if isinstance(ev, PlaceConfirmed):
                changed |= self._confirm(ev, tx)
            elif isinstance(ev, PlaceDeleted):
                changed |= self._delete_place(ev.place_id, tx)
            else:
                changed |= self._delete_link(ev.from_id, ev.to_id, ev.stamp, tx)
        if changed:
            return self._cycle(stamp, tx)
        if always and events:
            self.version += 1
            tx.version = self.version
            return CycleOutcome(self._update(stamp, [], False, 0, "none"), tx)
        return CycleOutcome(None, tx)

    def _confirm(self, msg: PlaceConfirmed, tx: Transaction) -> bool:
        if self.relaxer.graph.has_place(msg.place_id) or msg.place_id in self.deleted:
            return False
        self.relaxer.add_place(msg.place_id, (msg.x_m, msg.y_m))
        self.initial[msg.place_id] = (msg.x_m, msg.y_m)
        tx.new_places.append((msg.place_id, msg.x_m, msg.y_m, msg.stamp))
        for key in [k for k in self._pending if msg.place_id in k]:
            lk = self._pending[key]
            if self.relaxer.graph.has_place(lk.from_id) and self.relaxer.graph.has_place(lk.to_id):
                del self._pending[key]
                self._put_link(lk, tx)
        return True

    def on_link_measured(self, msg: LinkMeasured) -> CycleOutcome:
        """A measured link; ``ValueError`` (nothing changed) for a measurement no map can hold."""
        tx = Transaction()
        g = self.relaxer.graph
        if msg.from_id == msg.to_id:
            raise ValueError(f"link from place {msg.from_id} to itself")
        if not (math.isfinite(msg.d_m) and msg.d_m >= 0 and math.isfinite(msg.theta_rad) and msg.steps >= 1
                and math.isfinite(msg.mean_step_m) and msg.mean_step_m > 0
                and (msg.variance_m2 is None or (math.isfinite(msg.variance_m2) and msg.variance_m2 > 0))):
            raise ValueError(f"link {msg.from_id}->{msg.to_id}: d {msg.d_m}, theta {msg.theta_rad}, steps {msg.steps}, "
                             f"mean step {msg.mean_step_m}, variance {msg.variance_m2} are not a measurement")
        key = _pair(msg.from_id, msg.to_id)
        if msg.from_id in self.deleted or msg.to_id in self.deleted:
            return CycleOutcome(None, tx)
        if not (g.has_place(msg.from_id) and g.has_place(msg.to_id)):
            old = self._pending.get(key)
            if old is None or msg.traversals >= old.traversals:
                self._pending[key] = msg  # its places are on their way
            return CycleOutcome(None, tx)
        old_link = self.links.get(key)
        if old_link is not None and (msg.traversals < old_link.traversals or _same(old_link, msg)):
            return CycleOutcome(None, tx)  # an older measurement, or a replay of the one held
        # a new link between two places that already have links closes a loop (or joins two parts):
        # the residual it leaves is spread by an exact solve rather than by many sweeps (Section 7)
        closes = old_link is None and g.degree(g.index_of(msg.from_id)) > 0 and g.degree(g.index_of(msg.to_id)) > 0
        self._put_link(msg, tx)
        return self._cycle(msg.stamp, tx, exact=closes)

    def _put_link(self, msg: LinkMeasured, tx: Transaction) -> None:
        key = _pair(msg.from_id, msg.to_id)
        if key in self.links:  # a later traversal, fused by the recognizer: the new measurement replaces it
            self.relaxer.remove_link(msg.from_id, msg.to_id)
        self.relaxer.add_link(msg.from_id, msg.to_id, d_m=msg.d_m, theta_rad=msg.theta_rad, steps=msg.steps,
                              mean_step_m=msg.mean_step_m, variance_m2=msg.variance_m2)
        link = MapLink(from_id=msg.from_id, to_id=msg.to_id, d_m=msg.d_m, theta_rad=msg.theta_rad,
                       steps=msg.steps, mean_step_m=msg.mean_step_m, variance_m2=msg.variance_m2,
                       traversals=msg.traversals)
        self.links[key] = link
        self.link_stamps[key] = msg.stamp
        tx.links.append((link, msg.stamp))

    def on_place_deleted(self, place_id: int, stamp: float) -> CycleOutcome:
        return self.on_explorer_events([PlaceDeleted(stamp=stamp, seq=0, place_id=place_id, reason="")], stamp,
                                       always=False)

    def on_link_deleted(self, a: int, b: int, stamp: float) -> CycleOutcome:
        return self.on_explorer_events([LinkDeleted(stamp=stamp, seq=0, from_id=a, to_id=b, reason="")], stamp,
                                       always=False)

    def _delete_place(self, place_id: int, tx: Transaction) -> bool:
        if not self.relaxer.graph.has_place(place_id):
            if place_id not in self.deleted:
                self.deleted.add(place_id)
                tx.deleted_places.append(place_id)
                self._pending = {k: v for k, v in self._pending.items() if place_id not in k}
            return False
        self.relaxer.remove_place(place_id)
        self.initial.pop(place_id, None)
        for key in [k for k in self.links if place_id in k]:
            del self.links[key]
            self.link_stamps.pop(key, None)
        self._pending = {k: v for k, v in self._pending.items() if place_id not in k}
        tx.deleted_places.append(place_id)
        self.deleted.add(place_id)
        return True

    def _delete_link(self, a: int, b: int, stamp: float, tx: Transaction) -> bool:
        key = _pair(a, b)
        pending = self._pending.get(key)
        if pending is not None and pending.stamp <= stamp:
            del self._pending[key]
        if key not in self.links:
            return False
        if stamp < self.link_stamps.get(key, -math.inf):
            return False  # a deletion heard again (history) after the link was measured anew
        lk = self.links.pop(key)
        self.link_stamps.pop(key, None)
        self.relaxer.remove_link(a, b)
        tx.deleted_links.append((lk.from_id, lk.to_id))
        return True

    def anchor(self, x_m: float, y_m: float) -> tuple[int, float, float] | None:
        """The place a scan taken at dead-reckoned ``(x_m, y_m)`` belongs to, with the offset from it.

        The place whose first (dead-reckoned) position is nearest, within ``anchor_radius_m``: dead
        reckoning is good locally, so the offset holds even when the whole frame has drifted. Used
        when the recognizer is not sure where the robot is.
        """
        if not self.initial:
            return None
        ids = np.fromiter(self.initial, dtype=np.int64, count=len(self.initial))
        xy = np.array(list(self.initial.values()))
        d2 = (xy[:, 0] - x_m) ** 2 + (xy[:, 1] - y_m) ** 2
        k = int(np.argmin(d2))
        if d2[k] > self.params.anchor_radius_m**2:
            return None
        return int(ids[k]), float(x_m - xy[k, 0]), float(y_m - xy[k, 1])

    def add_scan(self, scan: StoredScan) -> Transaction:
        """Keep a scan for the grids; the transaction that stores it."""
        self._integrate(scan)
        return Transaction(scans=[scan])

    def load_scans(self, scans: list[StoredScan]) -> None:
        """Scans from the store (at a restart)."""
        for scan in scans:
            self._integrate(scan)

    def _integrate(self, s: StoredScan) -> None:
        self.scans.append(s)
        kw = {"beam_width_rad": s.beam_width, "max_range_m": s.max_range}
        place = self._place_grids.get(s.place_id)
        if place is None:
            place = self._place_grids[s.place_id] = GlobalGrid(self.params.grid_resolution_m, self.params.cone)
        place.integrate(s.off_x, s.off_y, s.heading, s.angles, s.ranges, **kw)
        self._dr_grid.integrate(s.dr_x, s.dr_y, s.heading, s.angles, s.ranges, **kw)

    def cycle(self, stamp: float, tx: Transaction | None = None) -> CycleOutcome:
        """One relaxation cycle (also run after every event); its update and what to store."""
        return self._cycle(stamp, tx if tx is not None else Transaction())

    def _cycle(self, stamp: float, tx: Transaction, *, exact: bool = False) -> CycleOutcome:
        r = self.relaxer
        g = r.graph
        if g.n_places == 0:
            self.energy = 0.0
            self.version += 1
            tx.version = self.version
            return CycleOutcome(self._update(stamp, [], True, 0, "none"), tx)
        before = r.xy
        if exact:
            self._solve(r)
        report = r.cycle()
        after = r.xy
        n_before = len(before)
        moved = np.zeros(len(after), dtype=bool)
        moved[:n_before] = np.max(np.abs(after[:n_before] - before), axis=1) > self.params.changed_threshold_m
        moved[n_before:] = True
        ids = g.ids
        changed = [PlacePosition(place_id=int(ids[i]), x_m=float(after[i, 0]), y_m=float(after[i, 1]))
                   for i in np.flatnonzero(moved)]
        tx.moved.extend((p.place_id, p.x_m, p.y_m) for p in changed)
        method = "exact" if report.exact or exact else "sweep"
        self.methods[method] = self.methods.get(method, 0) + 1
        self.updates += 1
        self.iterations += 1
        self.energy = report.energy
        self._settled = bool(exact or report.exact or report.step_m <= self.params.settled_step_m)
        self._last_stamp = stamp
        self.version += 1
        tx.version = self.version
        tx.noise = _noise_msg(report.noise)
        return CycleOutcome(self._update(stamp, changed, bool(moved.all()), 1, method), tx)

    def settle(self) -> CycleOutcome | None:
        """When events have stopped coming: solve the map exactly if the last cycle's single sweep left
        it short of its minimum (None when it is there already).

        On-line, one sweep per event spreads a change over the following events (Figure 3); the last
        events of a run, or of a pause, have none after them. Settling makes the map at rest the
        minimum of its links, whatever order and timing they came in.
        """
        if self._settled or self.relaxer.graph.n_places == 0:
            return None
        return self._cycle(self._last_stamp, Transaction(), exact=True)

    def _solve(self, r: CompassRelaxer) -> None:
        """The exact minimum; with REML, the noise re-estimated first (when there are loops enough)."""
        g = r.graph
        loops = g.n_links - g.n_places + r.n_parts()
        p = self.params
        if (p.noise_estimation == "reml" and loops >= p.reml_min_loops
                and loops >= p.reml_loop_growth * self._loops_at_estimate):
            noise, xy, _ = estimate_noise_reml(g, r.xy, noise=r.noise, rng=self.rng, pinned=r.pinned_index,
                                               samples=self.params.reml_samples,
                                               max_rounds=self.params.reml_max_rounds, params=r.params)
            r.set_noise(noise)
            r.set_xy(xy)
            self.noise_estimates += 1
            self._loops_at_estimate = loops
        else:
            r.solve_exact()

    def _update(self, stamp: float, changed: list[PlacePosition], full: bool, iterations: int,
                method: str) -> MapUpdate:
        msg = MapUpdate(stamp=stamp, seq=self.seq, version=self.version, changed=changed, full=full,
                        places=self.relaxer.graph.n_places, links=len(self.links), energy=self.energy,
                        iterations=iterations, method=method, noise=_noise_msg(self.relaxer.noise))
        self.seq += 1
        return msg

    # -- queries ----------------------------------------------------------------------------------
    def coordinates(self) -> dict[int, tuple[float, float]]:
        xy = self.relaxer.xy
        return {int(pid): (float(xy[i, 0]), float(xy[i, 1])) for i, pid in enumerate(self.relaxer.graph.ids)}

    def graph(self) -> MapGraph:
        pinned = self.relaxer.graph.ids[self.relaxer.pinned_index] if self.relaxer.graph.n_places else -1
        return MapGraph(version=self.version,
                        places=[MapPlace(place_id=i, x_m=x, y_m=y) for i, (x, y) in self.coordinates().items()],
                        links=list(self.links.values()), energy=self.energy,
                        noise=_noise_msg(self.relaxer.noise), pinned=int(pinned), deleted=sorted(self.deleted))

    def place(self, place_id: int) -> PlaceReply:
        g = self.relaxer.graph
        if not g.has_place(place_id):
            raise UnknownPlace(f"no place {place_id} in the map ({g.n_places} places)")
        x, y = self.relaxer.position(place_id)
        links = [lk for key, lk in self.links.items() if place_id in key]
        return PlaceReply(place=MapPlace(place_id=place_id, x_m=float(x), y_m=float(y)), links=links)

    def path(self, from_id: int, to_id: int) -> PathReply | None:
        """Shortest path over traversed links (weights: measured distances); None if unconnected."""
        g = self.relaxer.graph
        for pid in (from_id, to_id):
            if not g.has_place(pid):
                raise UnknownPlace(f"no place {pid} in the map ({g.n_places} places)")
        ids = g.ids
        index = {int(pid): i for i, pid in enumerate(ids)}
        n = len(ids)
        if self.links:
            rows = np.array([index[a] for a, _ in self.links])
            cols = np.array([index[b] for _, b in self.links])
            w = np.array([max(lk.d_m, 1e-9) for lk in self.links.values()])
            adj = sp.coo_matrix((w, (rows, cols)), shape=(n, n)).tocsr()
        else:
            adj = sp.csr_matrix((n, n))
        dist, pred = dijkstra(adj, directed=False, indices=index[from_id], return_predecessors=True)
        t = index[to_id]
        if not np.isfinite(dist[t]):
            return None
        path = [t]
        while path[-1] != index[from_id]:
            path.append(int(pred[path[-1]]))
        return PathReply(from_id=from_id, to_id=to_id, places=[int(ids[i]) for i in reversed(path)],
                         length_m=float(dist[t]))

    def grid(self, resolution_m: float, frame: str = "relaxed", *, max_cells: int = 4_000_000) -> OccupancyGrid:
        """The global occupancy grid (Section 4.3, Figures 13-14) from the stored scans.

        ``frame="relaxed"`` places each scan at its place's relaxed coordinates plus the robot's
        offset from the place centre; ``frame="dead_reckoning"`` at the compass dead-reckoning pose.

        Raises
        ------
        ValueError
            When the grid would have more than ``max_cells`` cells at this resolution.
        """
        coords = self.coordinates()
        default = resolution_m == self.params.grid_resolution_m
        if default and frame == "relaxed":
            grid = compose([(g, *coords[pid]) for pid, g in self._place_grids.items() if pid in coords],
                           resolution_m)
        elif default:
            grid = self._dr_grid
        else:
            grid = self._build_grid(resolution_m, frame, coords, max_cells)
        if grid.logodds.size > max_cells:
            raise ValueError(f"a grid at {resolution_m:g} m would have {grid.logodds.size} cells "
                             f"(at most {max_cells}); ask a coarser resolution")
        cells = grid.occupancy_percent()
        return OccupancyGrid(resolution_m=resolution_m, origin_x_m=float(grid.origin[0]),
                             origin_y_m=float(grid.origin[1]), width=int(cells.shape[1] if cells.size else 0),
                             height=int(cells.shape[0] if cells.size else 0), cells=cells.tobytes(),
                             version=self.version)

    def _build_grid(self, resolution_m: float, frame: str, coords: dict[int, tuple[float, float]],
                    max_cells: int) -> GlobalGrid:
        """A grid at another resolution, from every scan (checked for size before it is built)."""
        placed = []
        for s in self.scans:
            if frame == "relaxed":
                if s.place_id not in coords:
                    continue
                px, py = coords[s.place_id]
                placed.append((px + s.off_x, py + s.off_y, s))
            else:
                placed.append((s.dr_x, s.dr_y, s))
        if placed:
            xy = np.array([(x, y) for x, y, _ in placed])
            reach = 2 * max(s.max_range for s in self.scans)
            cells = np.prod((np.ptp(xy, axis=0) + reach) / resolution_m + 1)
            if cells > max_cells:
                raise ValueError(f"a grid at {resolution_m:g} m would have {cells:.3g} cells "
                                 f"(at most {max_cells}); ask a coarser resolution")
        grid = GlobalGrid(resolution_m, self.params.cone)
        for x, y, s in placed:
            grid.integrate(x, y, s.heading, s.angles, s.ranges, beam_width_rad=s.beam_width, max_range_m=s.max_range)
        return grid

    def scan_set(self, *, place_id: int | None = None, max_offset_m: float | None = None,
                 latest: int | None = None) -> ScanSet:
        """The stored scans, oldest first: of one place only, only those taken within ``max_offset_m``
        of their place's centre, only the ``latest`` few of those (each filter when given).

        Raises
        ------
        UnknownPlace
            When ``place_id`` is given and the map does not hold it.
        """
        if place_id is not None and not self.relaxer.graph.has_place(place_id):
            raise UnknownPlace(f"no place {place_id} in the map ({self.relaxer.graph.n_places} places)")
        kept = [s for s in self.scans
                if (place_id is None or s.place_id == place_id)
                and (max_offset_m is None or math.hypot(s.off_x, s.off_y) <= max_offset_m)]
        if latest is not None:
            kept = kept[len(kept) - latest:] if latest > 0 else []
        return ScanSet(version=self.version, scans=[
            PlaceScan(stamp=s.stamp, place_id=s.place_id, offset_x_m=s.off_x, offset_y_m=s.off_y, dr_x_m=s.dr_x,
                      dr_y_m=s.dr_y, heading_rad=s.heading, angles_rad=np.asarray(s.angles, float).tolist(),
                      ranges_m=np.asarray(s.ranges, float).tolist(), beam_width_rad=s.beam_width,
                      max_range_m=s.max_range) for s in kept])

    def stats(self) -> MapStats:
        ms = np.array(self.cycle_ms) if self.cycle_ms else np.zeros(1)
        return MapStats(version=self.version, places=self.relaxer.graph.n_places, links=len(self.links),
                        energy=self.energy, updates=self.updates, iterations=self.iterations,
                        cycle_ms_mean=float(ms.mean()), cycle_ms_p99=float(np.percentile(ms, 99)),
                        methods=dict(self.methods), noise=_noise_msg(self.relaxer.noise))
