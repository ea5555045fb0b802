"""Multi-hypothesis belief over places: motion prior from dead reckoning, match likelihood, offset filter."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np


@dataclass(frozen=True)
class Belief:
    """Probability of each known place and of "none of them", with the robot's offset per place.

    Attributes
    ----------
    ids : numpy.ndarray
        Place ids, shape ``(P,)``.
    centres : numpy.ndarray
        Place centres, shape ``(P, 2)``, metres.
    probs : numpy.ndarray
        Probability that the robot is at each place, shape ``(P,)``.
    offsets : numpy.ndarray
        Filtered offset of the robot from each centre (robot minus centre), ``(P, 2)``, metres.
    offset_vars : numpy.ndarray
        Variance of each offset per axis, ``(P, 2)``, m^2.
    none_prob : float
        Probability that the robot is at no known place (between places, or at a new one).
    none_xy : numpy.ndarray
        Expected robot position under the "none" hypothesis, ``(2,)``: its most probable component's.
    none_var_m2 : float
        Its variance per axis.
    none_parts : numpy.ndarray
        "None" as a mixture: each component's share of ``none_prob``, position and variance per axis,
        ``(K, 4)`` (columns share, x, y, variance); empty for the one component given by ``none_xy``
        and ``none_var_m2``.
    """

    ids: np.ndarray
    centres: np.ndarray
    probs: np.ndarray
    offsets: np.ndarray
    offset_vars: np.ndarray
    none_prob: float
    none_xy: np.ndarray
    none_var_m2: float
    none_parts: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))

    def none_mixture(self) -> np.ndarray:
        """The "none" components, ``(K, 4)``: share of ``none_prob``, x, y, variance per axis."""
        if self.none_parts.shape[0]:
            return self.none_parts
        return np.array([[1.0, self.none_xy[0], self.none_xy[1], self.none_var_m2]])

    @classmethod
    def empty(cls, xy: tuple[float, float] = (0.0, 0.0)) -> Belief:
        """No place known: the robot is certainly at "none", at ``xy``."""
        return cls(ids=np.zeros(0, dtype=int), centres=np.zeros((0, 2)), probs=np.zeros(0),
                   offsets=np.zeros((0, 2)), offset_vars=np.zeros((0, 2)), none_prob=1.0,
                   none_xy=np.asarray(xy, dtype=float), none_var_m2=0.0)

    def index(self, place_id: int) -> int:
        """Row of ``place_id``; ``KeyError`` when unknown."""
        hits = np.flatnonzero(self.ids == place_id)
        if hits.size == 0:
            raise KeyError(place_id)
        return int(hits[0])


def _logsumexp(a: np.ndarray, axis: int) -> np.ndarray:
    m = np.max(a, axis=axis, keepdims=True)
    return (m + np.log(np.exp(a - m).sum(axis=axis, keepdims=True))).squeeze(axis)


def predict(belief: Belief, displacement_xy: np.ndarray, *, transition_std_m: float,
            transition_var_per_m_m2: float, place_radius_m: float, uniform_transition: float,
            unknown_offset_var_m2: float, relocalise_std_m: float = math.inf,
            min_source_probability: float = 1e-12, none_components: int = 1, none_gate_sd: float = 3.0) -> Belief:
    """Move the belief by a dead-reckoned displacement (the prior of the next observation).

    Notes
    -----
    Every hypothesis ``h`` (each place, and "none") is a source with an expected robot position
    ``u_h`` (place centre plus offset, or the "none" position) moved by the displacement ``D``:
    ``u_h + D``, with variance ``v_h + q |D|`` per axis (``q = transition_var_per_m_m2``). Its mass
    goes to place ``j`` in proportion to ``exp(-|u_h + D - c_j|^2 / (2 s_h^2))``, with
    ``s_h^2 = v_h + q |D| + transition_std_m^2``, and to "none" in proportion to
    ``exp(-R^2 / (2 s_h^2))`` (``R = place_radius_m``): "none" acts as a virtual place at distance
    ``R``, so the mass leaves a place when the robot moves beyond its radius. A fraction
    ``uniform_transition`` of all mass is spread over the places and "none" (relocalisation after a
    long loop, when dead reckoning and the map disagree by more than the kernel allows): "none" and
    each place ``j`` in proportion to ``g_j = exp(-|c_j - m|^2 / (2 s_r^2))``, ``m`` the expected
    robot position of the moved belief and ``s_r = relocalise_std_m`` (``g = 1`` for "none"; an
    infinite ``s_r`` spreads it evenly). Dead reckoning with a compass errs by a metre or two around a
    loop, not by ten: a look-alike place across the building gets no mass to jump to. That part
    carries no position, so it arrives at the centre with ``unknown_offset_var_m2``.
    The offsets of each target (and the "none" position) are the moment-matched mixture of what
    arrives (mean and variance per axis). Only hypotheses at least ``min_source_probability``
    probable are moved as sources (the others' mass is dropped before normalising): most places of a
    large map hold next to nothing, and moving every one to every other costs ``O(P^2)``.
    "None" is a mixture of up to ``none_components`` Gaussians (:func:`_reduce`), so that the mass a
    look-alike neighbour hands to it does not move the robot's own.
    """
    d = np.asarray(displacement_xy, dtype=float)
    dist = float(np.hypot(*d))
    P = belief.ids.size
    parts = belief.none_mixture()
    ps_all = np.concatenate([belief.probs, belief.none_prob * parts[:, 0]])
    src = np.flatnonzero(ps_all >= min_source_probability)  # sources: rows of places, then "none"'s parts
    ps = ps_all[src]
    pos = np.vstack([belief.centres + belief.offsets + d, parts[:, 1:3] + d])[src]  # (S, 2)
    src_var = np.vstack([belief.offset_vars, np.repeat(parts[:, 3:4], 2, axis=1)])[src]
    src_var = src_var + transition_var_per_m_m2 * dist
    kvar = src_var.mean(axis=1) + transition_std_m**2  # (S,)
    diff = pos[:, None, :] - belief.centres[None, :, :]  # (S, P, 2): offset from each target centre
    log_k = np.concatenate(
        [-(diff**2).sum(axis=-1) / (2.0 * kvar[:, None]), (-(place_radius_m**2) / (2.0 * kvar))[:, None]],
        axis=1,
    )  # (S, P + 1): last column is "none"
    trans = np.exp(log_k - _logsumexp(log_k, axis=1)[:, None])
    informed = (1.0 - uniform_transition) * ps[:, None] * trans  # (S, P + 1)
    g = np.ones(P + 1)
    if math.isfinite(relocalise_std_m) and P:
        expected = (ps[:, None] * pos).sum(axis=0) / max(ps.sum(), 1e-300)
        g[:P] = np.exp(-((belief.centres - expected) ** 2).sum(axis=1) / (2.0 * relocalise_std_m**2))
    uniform = uniform_transition * ps_all.sum() * g / g.sum()  # (P + 1,)
    prior = informed.sum(axis=0) + uniform  # (P + 1,)

    w = informed[:, :P]  # (S, P)
    tot = prior[:P, None]
    some = tot > 0.0  # a place no mass reaches (far from every hypothesis) keeps an unknown offset
    mean = np.divide(np.einsum("sp,spk->pk", w, diff), tot, out=np.zeros((P, 2)), where=some)
    second = np.divide(np.einsum("sp,spk->pk", w, src_var[:, None, :] + diff**2)
                       + uniform[:P, None] * unknown_offset_var_m2, tot,
                       out=np.full((P, 2), unknown_offset_var_m2), where=some)
    var = np.maximum(second - mean**2, 0.0)

    wn = informed[:, P]
    if wn.sum() > 0.0:
        new_parts = _reduce(wn, pos, src_var, none_components, none_gate_sd)
    else:
        new_parts = parts + np.array([0.0, d[0], d[1], transition_var_per_m_m2 * dist])
    total = prior.sum()
    return replace(belief, probs=prior[:P] / total, offsets=mean, offset_vars=var,
                   none_prob=float(prior[P] / total), none_xy=new_parts[0, 1:3].copy(),
                   none_var_m2=float(new_parts[0, 3]), none_parts=new_parts if none_components > 1 else np.zeros((0, 4)))


def _reduce(w: np.ndarray, xy: np.ndarray, var: np.ndarray, k: int, gate_sd: float) -> np.ndarray:
    """Gaussians (weights ``w``, positions ``xy``, variances ``var`` per axis, ``(S, 2)``) merged to at most ``k``.

    Greedy, most weight first: a component takes every remaining Gaussian within ``gate_sd`` standard
    deviations (both variances) of its seed; once ``k`` are seeded, what is left joins the nearest.
    Each component is the moment-matched mixture of its members. Rows: share of the total weight, x,
    y, variance per axis (most weight first). With ``k = 1`` it is the moment match of them all.
    """
    total = w.sum()
    group = np.full(w.size, -1)
    if k <= 1:
        group[:] = 0  # every source, the ones without weight too: the sums are the plain moment match's
        count = 1
    else:
        order = np.argsort(-w, kind="stable")
        order = order[w[order] > 0.0]
        seeds: list[int] = []
        for i in order:
            if group[i] >= 0:
                continue
            if len(seeds) == k:
                break
            seeds.append(int(i))
            left = order[group[order] < 0]
            near = ((xy[left] - xy[i]) ** 2).sum(axis=1) <= gate_sd**2 * (var[left] + var[i]).mean(axis=1)
            group[left[near]] = len(seeds) - 1
        rest = order[group[order] < 0]
        if rest.size:
            group[rest] = np.argmin(((xy[rest][:, None, :] - xy[seeds][None]) ** 2).sum(axis=-1), axis=1)
        count = len(seeds)
    out = np.zeros((count, 4))
    for c in range(count):
        m = group == c
        wc = w[m]
        mu = (wc[:, None] * xy[m]).sum(axis=0) / wc.sum()
        second = (wc[:, None] * (var[m] + (xy[m] - mu) ** 2)).sum(axis=0) / wc.sum()
        out[c] = (wc.sum() / total, mu[0], mu[1], float(second.mean()))
    return out[np.argsort(-out[:, 0], kind="stable")]


def spread(belief: Belief, fraction: float, *, std_m: float, unknown_offset_var_m2: float) -> Belief:
    """Move ``fraction`` of the mass to the places near the robot and to "none" (a relocalisation).

    Notes
    -----
    As the relocalisation part of :func:`predict`, at once: "none" and each place ``j`` receive in
    proportion to ``g_j = exp(-|c_j - m|^2 / (2 std_m^2))`` (``g = 1`` for "none"), ``m`` the robot's
    expected position; the mass arrives without a position, at the centre with
    ``unknown_offset_var_m2``, and each place's offset is the moment-matched mixture of what it kept
    and what arrived.
    """
    n = belief.ids.size
    if n == 0 or fraction <= 0.0:
        return belief
    keep = 1.0 - fraction
    pos = belief.centres + belief.offsets
    total = belief.probs.sum() + belief.none_prob
    expected = (belief.probs @ pos + belief.none_prob * belief.none_xy) / max(total, 1e-300)
    g = np.append(np.exp(-((belief.centres - expected) ** 2).sum(axis=1) / (2.0 * std_m**2)), 1.0)
    arriving = fraction * total * g / g.sum()
    kept = keep * belief.probs
    probs = kept + arriving[:n]
    some = probs[:, None] > 0.0
    mean = np.divide(kept[:, None] * belief.offsets, probs[:, None], out=np.zeros((n, 2)), where=some)
    second = np.divide(kept[:, None] * (belief.offset_vars + belief.offsets**2)
                       + arriving[:n, None] * unknown_offset_var_m2, probs[:, None],
                       out=np.full((n, 2), unknown_offset_var_m2), where=some)
    return replace(belief, probs=probs, offsets=mean, offset_vars=np.maximum(second - mean**2, 0.0),
                   none_prob=float(keep * belief.none_prob + arriving[n]))


def correct(belief: Belief, scores: np.ndarray, observed_offsets: np.ndarray,
            observed_vars: np.ndarray, *, match_sharpness: float, new_place_match: float) -> Belief:
    """Bayes update with the match scores, and the offset filter (Eqs. 22-23).

    Parameters
    ----------
    scores : numpy.ndarray
        Match score of each place in ``[0, 1]``, ``(P,)``; NaN where a place has no signature.
    observed_offsets, observed_vars : numpy.ndarray
        ``r*`` and ``sigma*^2`` per place and axis, ``(P, 2)`` (from the best shift, Eqs. 20-21).
    match_sharpness, new_place_match : float
        ``beta`` and the virtual score ``M_new`` of the "none" hypothesis.

    Notes
    -----
    Likelihood ``exp(beta (M_j - 1))`` for place ``j`` and ``exp(beta (M_new - 1))`` for "none"; a
    place without a signature gets the "none" likelihood (no evidence either way). Offsets, per
    axis, with ``r'`` and ``s'^2`` from :func:`predict`:

        r = r' + s'^2 / (s'^2 + s*^2) (r* - r')        (Eq. 22)
        1 / s^2 = 1 / s'^2 + 1 / s*^2                   (Eq. 23)
    """
    scores = np.asarray(scores, dtype=float)
    has = ~np.isnan(scores)
    log_lik = np.where(has, match_sharpness * (np.nan_to_num(scores) - 1.0),
                       match_sharpness * (new_place_match - 1.0))
    log_post = np.append(np.log(np.maximum(belief.probs, 1e-300)) + log_lik,
                         np.log(max(belief.none_prob, 1e-300)) + match_sharpness * (new_place_match - 1.0))
    post = np.exp(log_post - _logsumexp(log_post, axis=0))

    v_prior = belief.offset_vars
    den = v_prior + observed_vars
    gain = np.divide(v_prior, den, out=np.zeros_like(v_prior), where=den > 0)
    gain = np.where(has[:, None], gain, 0.0)
    offsets = belief.offsets + gain * (np.nan_to_num(observed_offsets) - belief.offsets)
    var = np.where(has[:, None], (1.0 - gain) * v_prior, v_prior)  # equals Eq. 23
    return replace(belief, probs=post[:-1], none_prob=float(post[-1]), offsets=offsets, offset_vars=var)


def add_place(belief: Belief, place_id: int, centre_xy: tuple[float, float], *, probability: float) -> Belief:
    """Append a place the robot is at now (offset zero, exactly known) with ``probability``."""
    keep = 1.0 - probability
    return replace(
        belief,
        ids=np.append(belief.ids, place_id),
        centres=np.vstack([belief.centres, np.asarray(centre_xy, dtype=float)[None]]),
        probs=np.append(belief.probs * keep, probability),
        offsets=np.vstack([belief.offsets, np.zeros((1, 2))]),
        offset_vars=np.vstack([belief.offset_vars, np.zeros((1, 2))]),
        none_prob=belief.none_prob * keep,
    )


def remove_place(belief: Belief, place_id: int) -> Belief:
    """Drop a place and renormalise (its mass goes to every other hypothesis in proportion)."""
    keep = belief.ids != place_id
    probs = belief.probs[keep]
    total = probs.sum() + belief.none_prob
    if total <= 0.0:
        probs, none_prob = probs, 1.0
    else:
        probs, none_prob = probs / total, belief.none_prob / total
    return replace(belief, ids=belief.ids[keep], centres=belief.centres[keep], probs=probs,
                   offsets=belief.offsets[keep], offset_vars=belief.offset_vars[keep], none_prob=none_prob)


def move_places(belief: Belief, centres: dict[int, tuple[float, float]]) -> Belief:
    """New centre coordinates (e.g. after relaxation); offsets are relative and stay."""
    new = belief.centres.copy()
    for row, pid in enumerate(belief.ids):
        if int(pid) in centres:
            new[row] = centres[int(pid)]
    return replace(belief, centres=new)
