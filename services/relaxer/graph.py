"""Growable compass-mode map graph: places with dense indices, links in doubling numpy arrays."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

__all__ = ["GraphError", "MapGraph", "colour_places", "link_geometry"]


class GraphError(ValueError):
    """A place or link that cannot be added to, or found in, a map graph."""


def link_geometry(d_m: np.ndarray, theta_rad: np.ndarray, steps: np.ndarray, mean_step_m: np.ndarray,
                  variance_m2: np.ndarray) -> tuple[np.ndarray, ...]:
    """Fixed per-link quantities from which every noise-dependent array is a linear combination.

    Parameters
    ----------
    d_m, theta_rad, steps, mean_step_m, variance_m2 : ndarray, shape (K,)
        Link measurements; ``variance_m2`` is NaN for links with the three-parameter noise model.

    Returns
    -------
    disp : ndarray, shape (K, 2)
        Measured displacement ``D_ji = d (cos theta, sin theta)`` from the link's first place to its second.
    u_scaled, v_scaled : ndarray, shape (K, 2)
        ``u / sqrt(T)`` and ``u_perp / (sqrt(T) delta_bar)`` (zero for circular-noise links).
    inv_var : ndarray, shape (K,)
        ``1 / v`` for circular-noise links, zero otherwise.
    basis : ndarray, shape (K, 3, 4)
        The link information ``W = C^-1`` stored as ``(W_xx, W_xy, W_yy)`` is ``basis @ coef`` with
        ``coef = (a, b, c, 1)`` from :func:`services.relaxer.compass.information_coefficients`.

    Notes
    -----
    Eq. 5 gives ``C_local = T [[S_dd, delta S_da], [delta S_da, delta^2 S_aa]]`` in the frame
    ``(u, u_perp)`` of travel. Its inverse is
    ``a u u^T / T + b (u u_perp^T + u_perp u^T) / (T delta) + c u_perp u_perp^T / (T delta^2)`` with
    ``(a, b, c) = (S_aa, -S_da, S_dd) / (S_dd S_aa - S_da^2)``: linear in three global numbers, so
    re-estimating the noise (Eqs. 12-14) never needs per-link inversions. Appendix A links add
    ``I / v`` instead.
    """
    c, s = np.cos(theta_rad), np.sin(theta_rad)
    disp = np.stack([d_m * c, d_m * s], axis=1)
    circular = np.isfinite(variance_m2)
    sq = np.sqrt(np.where(circular, 1.0, steps))
    scale_u = np.where(circular, 0.0, 1.0 / sq)
    scale_v = np.where(circular, 0.0, 1.0 / (sq * np.where(circular, 1.0, mean_step_m)))
    u = np.stack([c, s], axis=1) * scale_u[:, None]
    v = np.stack([-s, c], axis=1) * scale_v[:, None]
    inv_var = np.where(circular, 1.0 / np.where(circular, variance_m2, 1.0), 0.0)
    basis = np.empty((len(d_m), 3, 4))
    basis[:, 0, 0] = u[:, 0] * u[:, 0]
    basis[:, 1, 0] = u[:, 0] * u[:, 1]
    basis[:, 2, 0] = u[:, 1] * u[:, 1]
    basis[:, 0, 1] = 2.0 * u[:, 0] * v[:, 0]
    basis[:, 1, 1] = u[:, 0] * v[:, 1] + u[:, 1] * v[:, 0]
    basis[:, 2, 1] = 2.0 * u[:, 1] * v[:, 1]
    basis[:, 0, 2] = v[:, 0] * v[:, 0]
    basis[:, 1, 2] = v[:, 0] * v[:, 1]
    basis[:, 2, 2] = v[:, 1] * v[:, 1]
    basis[:, 0, 3] = inv_var
    basis[:, 1, 3] = 0.0
    basis[:, 2, 3] = inv_var
    return disp, u, v, inv_var, basis


def colour_places(n: int, src: np.ndarray, dst: np.ndarray, active: np.ndarray) -> np.ndarray:
    """Colour the ``active`` places so that no link joins two places of one colour (-1: not coloured).

    Vectorised Jones-Plassmann: in each round, the uncoloured places whose (hashed) priority beats
    every uncoloured neighbour take the smallest colour no coloured neighbour has. This gives at most
    ``max degree + 1`` colours in a few rounds for the bounded-degree graphs of maps.
    """
    src, dst = np.asarray(src, dtype=np.int64), np.asarray(dst, dtype=np.int64)
    colour = np.full(n, -1, dtype=np.int64)
    active = np.asarray(active, dtype=bool)
    if n == 0 or not active.any():
        return colour
    deg = np.bincount(src, minlength=n) + np.bincount(dst, minlength=n)
    if deg.max() >= 63:  # colours must fit in one 64-bit mask: colour greedily instead
        nbrs: list[list[int]] = [[] for _ in range(n)]
        for a, b in zip(src.tolist(), dst.tolist()):
            nbrs[a].append(b)
            nbrs[b].append(a)
        for i in np.flatnonzero(active).tolist():
            used = {int(colour[j]) for j in nbrs[i]}
            c = 0
            while c in used:
                c += 1
            colour[i] = c
        return colour
    i = np.arange(n, dtype=np.uint64)
    prio = (i * np.uint64(2654435761) + np.uint64(12345)) % np.uint64(4294967291)
    one = np.uint64(1)
    while True:
        unc = active & (colour < 0)
        if not unc.any():
            return colour
        both = unc[src] & unc[dst]
        a, b = src[both], dst[both]
        lose = np.zeros(n, dtype=bool)
        lose[np.where(prio[a] < prio[b], a, b)] = True
        win = unc & ~lose
        used = np.zeros(n, dtype=np.uint64)
        for x, y in ((src, dst), (dst, src)):
            sel = win[x] & (colour[y] >= 0)
            np.bitwise_or.at(used, x[sel], np.left_shift(one, colour[y[sel]].astype(np.uint64)))
        uw = used[win]
        low = ~uw & (uw + one)
        colour[win] = np.round(np.log2(low.astype(np.float64))).astype(np.int64)


def _grown(arr: np.ndarray, need: int) -> np.ndarray:
    if need <= arr.shape[0]:
        return arr
    cap = max(need, 2 * arr.shape[0], 16)
    out = np.empty((cap, *arr.shape[1:]), dtype=arr.dtype)
    out[: arr.shape[0]] = arr
    return out


class MapGraph:
    """Places and physically traversed links of a compass-mode map, growing and shrinking on-line.

    Places have caller-chosen integer ids and dense indices ``0..n_places-1``; links are stored once
    per unordered pair of places in preallocated arrays that double in size when full. Removal moves
    the last place (or link) into the freed slot, so every operation is O(1) amortised (removing a
    place also removes its links). Coordinates are not stored here: they are the solver's state.

    Examples
    --------
    >>> g = MapGraph()
    >>> g.add_place(10), g.add_place(11)
    (0, 1)
    >>> g.add_link(10, 11, d_m=1.0, theta_rad=0.0, steps=10, mean_step_m=0.1)
    0
    >>> g.n_places, g.n_links
    (2, 1)
    """

    _LINK_FLOAT = ("_d", "_theta", "_steps", "_mean_step", "_variance", "_inv_var")

    def __init__(self, capacity: int = 16) -> None:
        cap = max(int(capacity), 1)
        self._n = 0
        self._k = 0
        self._ids = np.empty(cap, dtype=np.int64)
        self._index: dict[int, int] = {}
        self._adj: list[dict[int, None]] = []  # per place: its link slots (ordered set)
        self._src = np.empty(cap, dtype=np.int64)
        self._dst = np.empty(cap, dtype=np.int64)
        self._d = np.empty(cap)
        self._theta = np.empty(cap)
        self._steps = np.empty(cap)
        self._mean_step = np.empty(cap)
        self._variance = np.empty(cap)  # NaN: three-parameter noise model (Eq. 5)
        self._disp = np.empty((cap, 2))
        self._u = np.empty((cap, 2))
        self._v = np.empty((cap, 2))
        self._inv_var = np.empty(cap)
        self._basis = np.empty((cap, 3, 4))
        self._link_slot: dict[tuple[int, int], int] = {}  # (smaller id, larger id) -> slot
        self.version = 0  # incremented by every structural change

    # ----------------------------------------------------------------------------------- places
    @property
    def n_places(self) -> int:
        return self._n

    @property
    def n_links(self) -> int:
        return self._k

    @property
    def ids(self) -> np.ndarray:
        """Place ids by dense index (a read-only view)."""
        v = self._ids[: self._n]
        v.flags.writeable = False
        return v

    def index_of(self, place_id: int) -> int:
        try:
            return self._index[int(place_id)]
        except KeyError:
            raise GraphError(f"no place with id {place_id}") from None

    def has_place(self, place_id: int) -> bool:
        return int(place_id) in self._index

    def degree(self, index: int) -> int:
        return len(self._adj[index])

    def link_slots_of(self, index: int) -> list[int]:
        """Slots of the links at the place with dense ``index``."""
        return list(self._adj[index])

    def add_place(self, place_id: int) -> int:
        """Add a place; return its dense index."""
        pid = int(place_id)
        if pid in self._index:
            raise GraphError(f"duplicate place id {pid}")
        i = self._n
        self._ids = _grown(self._ids, i + 1)
        self._ids[i] = pid
        self._index[pid] = i
        self._adj.append({})
        self._n = i + 1
        self.version += 1
        return i

    def add_places(self, place_ids: Iterable[int]) -> np.ndarray:
        """Add many places; return their dense indices."""
        ids = np.asarray(list(place_ids) if not isinstance(place_ids, np.ndarray) else place_ids, dtype=np.int64)
        start = self._n
        new = {int(p): start + j for j, p in enumerate(ids.tolist())}
        if len(new) != len(ids):
            seen: set[int] = set()
            dup = next(p for p in ids.tolist() if p in seen or seen.add(p))
            raise GraphError(f"duplicate place id {dup}")
        clash = new.keys() & self._index.keys()
        if clash:
            raise GraphError(f"duplicate place id {min(clash)}")
        self._ids = _grown(self._ids, start + len(ids))
        self._ids[start: start + len(ids)] = ids
        self._index.update(new)
        self._adj.extend({} for _ in range(len(ids)))
        self._n = start + len(ids)
        self.version += 1
        return np.arange(start, self._n)

    def remove_place(self, place_id: int) -> tuple[int, int, list[tuple[int, int]]]:
        """Remove a place and its links.

        Returns
        -------
        index : int
            The dense index the place had.
        moved_from : int
            The former index of the place now at ``index`` (``index`` itself if it was the last).
        link_moves : list of (slot, moved_from)
            The link removals done, in order, as returned by :meth:`remove_link_slot`.
        """
        i = self.index_of(place_id)
        link_moves = []
        while self._adj[i]:
            link_moves.append(self.remove_link_slot(next(iter(self._adj[i]))))
        last = self._n - 1
        if i != last:
            moved_id = int(self._ids[last])
            self._ids[i] = moved_id
            self._index[moved_id] = i
            self._adj[i] = self._adj[last]
            for s in self._adj[i]:
                if self._src[s] == last:
                    self._src[s] = i
                if self._dst[s] == last:
                    self._dst[s] = i
        self._adj.pop()
        del self._index[int(place_id)]
        self._n = last
        self.version += 1
        return i, last, link_moves

    # ------------------------------------------------------------------------------------ links
    def link_slot(self, a_id: int, b_id: int) -> int:
        key = (min(int(a_id), int(b_id)), max(int(a_id), int(b_id)))
        try:
            return self._link_slot[key]
        except KeyError:
            raise GraphError(f"no link between places {a_id} and {b_id}") from None

    def has_link(self, a_id: int, b_id: int) -> bool:
        return (min(int(a_id), int(b_id)), max(int(a_id), int(b_id))) in self._link_slot

    def add_link(self, from_id: int, to_id: int, *, d_m: float, theta_rad: float, steps: int = 1,
                 mean_step_m: float = 1.0, variance_m2: float | None = None) -> int:
        """Add the traversed link ``from -> to``; return its slot.

        ``d_m`` and ``theta_rad`` measure the displacement of ``to`` from ``from`` (distance and compass
        angle), ``steps`` is ``T_ji`` and ``mean_step_m`` is ``delta_bar_ji`` (Eq. 5). ``variance_m2``
        selects the circular-noise model of Appendix A for this link.
        """
        return int(self.add_links([from_id], [to_id], d_m=[d_m], theta_rad=[theta_rad], steps=[steps],
                                  mean_step_m=[mean_step_m],
                                  variance_m2=[np.nan if variance_m2 is None else variance_m2])[0])

    def add_links(self, from_ids: Iterable[int], to_ids: Iterable[int], *, d_m, theta_rad, steps,
                  mean_step_m, variance_m2) -> np.ndarray:
        """Add many links at once (vectorised); see :meth:`add_link`. Returns their slots."""
        fr = [int(x) for x in from_ids]
        to = [int(x) for x in to_ids]
        m = len(fr)
        arrs = [np.asarray(x, dtype=float).reshape(-1) for x in (d_m, theta_rad, steps, mean_step_m, variance_m2)]
        if len(to) != m or any(len(a) != m for a in arrs):
            raise GraphError("link arrays differ in length")
        d, th, st, ms, var = arrs
        src = np.empty(m, dtype=np.int64)
        dst = np.empty(m, dtype=np.int64)
        keys = []
        seen = set(self._link_slot)
        for j, (a, b) in enumerate(zip(fr, to)):
            if a == b:
                raise GraphError(f"link from place {a} to itself")
            if a not in self._index:
                raise GraphError(f"link {a} -> {b}: no place with id {a}")
            if b not in self._index:
                raise GraphError(f"link {a} -> {b}: no place with id {b}")
            key = (min(a, b), max(a, b))
            if key in seen:
                raise GraphError(f"duplicate link between places {a} and {b}")
            seen.add(key)
            keys.append(key)
            src[j] = self._index[a]
            dst[j] = self._index[b]
        circular = np.isfinite(var)
        bad = ~np.isfinite(d) | (d < 0) | ~np.isfinite(th)
        bad |= circular & ~(var > 0)
        bad |= ~circular & (~(st >= 1) | ~(ms > 0) | ~np.isfinite(st) | ~np.isfinite(ms) | np.isinf(var))
        if bad.any():
            j = int(np.flatnonzero(bad)[0])
            raise GraphError(f"link {fr[j]} -> {to[j]}: need finite d >= 0 and theta, and either variance > 0 "
                             f"or steps >= 1 and mean_step > 0 (got d={d[j]}, theta={th[j]}, steps={st[j]}, "
                             f"mean_step={ms[j]}, variance={var[j]})")
        k0 = self._k
        need = k0 + m
        for name in ("_src", "_dst", "_disp", "_u", "_v", "_basis", *self._LINK_FLOAT):
            setattr(self, name, _grown(getattr(self, name), need))
        sl = slice(k0, need)
        self._src[sl], self._dst[sl] = src, dst
        self._d[sl], self._theta[sl], self._steps[sl], self._mean_step[sl], self._variance[sl] = d, th, st, ms, var
        disp, u, v, inv_var, basis = link_geometry(d, th, st, ms, var)
        self._disp[sl], self._u[sl], self._v[sl], self._inv_var[sl], self._basis[sl] = disp, u, v, inv_var, basis
        for j, key in enumerate(keys):
            s = k0 + j
            self._link_slot[key] = s
            self._adj[src[j]][s] = None
            self._adj[dst[j]][s] = None
        self._k = need
        self.version += 1
        return np.arange(k0, need)

    def remove_link(self, a_id: int, b_id: int) -> tuple[int, int]:
        """Remove the link between two places; see :meth:`remove_link_slot`."""
        return self.remove_link_slot(self.link_slot(a_id, b_id))

    def remove_link_slot(self, slot: int) -> tuple[int, int]:
        """Remove the link in ``slot``; the last link moves into it.

        Returns
        -------
        (slot, moved_from) : tuple of int
            ``moved_from`` is the former slot of the link now in ``slot`` (``slot`` if it was the last).
        """
        s = int(slot)
        if not 0 <= s < self._k:
            raise GraphError(f"no link in slot {s}")
        a, b = int(self._src[s]), int(self._dst[s])
        del self._adj[a][s]
        del self._adj[b][s]
        ia, ib = int(self._ids[a]), int(self._ids[b])
        del self._link_slot[(min(ia, ib), max(ia, ib))]
        last = self._k - 1
        if s != last:
            la, lb = int(self._src[last]), int(self._dst[last])
            for name in ("_src", "_dst", "_disp", "_u", "_v", "_basis", *self._LINK_FLOAT):
                arr = getattr(self, name)
                arr[s] = arr[last]
            del self._adj[la][last]
            del self._adj[lb][last]
            self._adj[la][s] = None
            self._adj[lb][s] = None
            ja, jb = int(self._ids[la]), int(self._ids[lb])
            self._link_slot[(min(ja, jb), max(ja, jb))] = s
        self._k = last
        self.version += 1
        return s, last

    # ------------------------------------------------------------------------ array views (K,...)
    def _view(self, name: str) -> np.ndarray:
        arr = getattr(self, name)[: self._k]
        arr.flags.writeable = False
        return arr

    @property
    def src(self) -> np.ndarray:
        """Dense index of each link's first place (the ``j`` of ``D_ji``)."""
        return self._view("_src")

    @property
    def dst(self) -> np.ndarray:
        """Dense index of each link's second place (the ``i`` of ``D_ji``)."""
        return self._view("_dst")

    @property
    def d_m(self) -> np.ndarray:
        return self._view("_d")

    @property
    def theta_rad(self) -> np.ndarray:
        return self._view("_theta")

    @property
    def steps(self) -> np.ndarray:
        return self._view("_steps")

    @property
    def mean_step_m(self) -> np.ndarray:
        return self._view("_mean_step")

    @property
    def variance_m2(self) -> np.ndarray:
        """Per-link circular variance (Appendix A); NaN for the three-parameter model."""
        return self._view("_variance")

    @property
    def disp(self) -> np.ndarray:
        """``D_ji``, shape (K, 2)."""
        return self._view("_disp")

    @property
    def u_scaled(self) -> np.ndarray:
        return self._view("_u")

    @property
    def v_scaled(self) -> np.ndarray:
        return self._view("_v")

    @property
    def inv_var(self) -> np.ndarray:
        return self._view("_inv_var")

    @property
    def basis(self) -> np.ndarray:
        return self._view("_basis")

    @property
    def circular(self) -> np.ndarray:
        """True for links with the circular-noise model of Appendix A."""
        return np.isfinite(self._variance[: self._k])

    def components(self) -> tuple[int, np.ndarray]:
        """Connected components: ``(count, label per place)``."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        n = self._n
        adj = coo_matrix((np.ones(self._k), (self._src[: self._k], self._dst[: self._k])), shape=(n, n))
        count, labels = connected_components(adj, directed=False)
        return int(count), labels

    def copy(self) -> MapGraph:
        g = MapGraph.__new__(MapGraph)
        for key, val in self.__dict__.items():
            if isinstance(val, np.ndarray):
                setattr(g, key, val.copy())
            elif key == "_adj":
                g._adj = [dict(a) for a in val]
            elif isinstance(val, dict):
                setattr(g, key, dict(val))
            else:
                setattr(g, key, val)
        return g

    def nbytes(self) -> int:
        """Bytes held by the numpy arrays (capacity included)."""
        return sum(v.nbytes for v in self.__dict__.values() if isinstance(v, np.ndarray))
