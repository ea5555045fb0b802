"""The place recognizer core driven through a corridor: places, recognition, links and their fusion."""

from __future__ import annotations

import math

import numpy as np
import pytest

from messages.types import DeadReckonedPose, Pose2
from services.place_recognizer import NO_PLACE, LinkAccumulator, PlaceRecognizer, PlaceRecognizerParams
from tests.unit._sonar_rooms import box, scan_at

# a 8 m x 3 m hall cut by two partial walls, so that every metre looks a little different
WALLS = box(0, 0, 8, 3) + [(3, 0, 3, 1.0), (3, 2.0, 3, 3), (5.5, 0, 5.5, 2.2)]
STEP_M = 0.05  # odometry step length


class _Drive:
    """Perfect dead reckoning along a polyline, one sonar scan every 0.1 m, a second apart."""

    def __init__(self, rec: PlaceRecognizer):
        self.rec, self.steps, self.path, self.prev, self.stamp = rec, 0, 0.0, None, -1.0
        self.places: dict[int, tuple[float, float]] = {}
        self.links = []
        self.at: list[int] = []

    def dr(self, x, y, heading=0.0) -> DeadReckonedPose:
        self.stamp += 1.0
        if self.prev is not None:
            d = float(np.hypot(x - self.prev[0], y - self.prev[1]))
            self.path += d
            self.steps += int(round(d / STEP_M))
        self.prev = (x, y)
        pose = Pose2(x_m=x, y_m=y, heading_rad=heading)
        return DeadReckonedPose(stamp=self.stamp, seq=0, compass=pose, raw=pose, steps=self.steps, path_length_m=self.path)

    def visit(self, x, y, *, confirm_new: bool) -> None:
        dr = self.dr(x, y)
        out = self.rec.step(dr, scan_at(x, y, 0.0, WALLS)[0])
        self.links += out.links
        self.at.append(out.localization.place_id)
        if confirm_new and out.localization.place_id == NO_PLACE and all(
            np.hypot(x - px, y - py) > 0.95 for px, py in self.places.values()
        ):
            pid = len(self.places)
            self.places[pid] = (x, y)
            added = self.rec.add_place(pid, x, y, dr)
            self.links += added.links
            self.at.append(added.localization.place_id)


@pytest.fixture(scope="module")
def drive():
    d = _Drive(PlaceRecognizer())
    for k in range(51):  # east along the hall, places confirmed every metre
        d.visit(1.5 + 0.1 * k, 1.5, confirm_new=True)
    d.first_pass_links = list(d.links)
    d.first_pass_at = list(d.at)
    d.links.clear()
    d.at.clear()
    for k in range(1, 51):  # and back west: only recognition
        d.visit(6.5 - 0.1 * k, 1.5, confirm_new=False)
    return d


def test_places_are_confirmed_every_metre(drive):
    assert drive.places == {i: pytest.approx((1.5 + i, 1.5)) for i in range(6)}


def test_first_traversal_links_match_the_true_displacement(drive):
    links = drive.first_pass_links
    assert [(link.from_id, link.to_id) for link in links] == [(i, i + 1) for i in range(5)]
    for link in links:
        assert link.d_m == pytest.approx(1.0, abs=0.03)
        assert link.theta_rad == pytest.approx(0.0, abs=0.03)
        assert link.traversals == 1
        assert link.mean_step_m == pytest.approx(STEP_M)
        assert link.steps == round(link.d_m / STEP_M)  # the whole centre-to-centre distance in 5 cm steps


def test_known_places_are_recognised_on_the_way_back(drive):
    seen = [p for i, p in enumerate(drive.at) if p != NO_PLACE and (i == 0 or drive.at[i - 1] != p)]
    assert seen == [5, 4, 3, 2, 1, 0]


def test_later_traversals_are_fused(drive):
    back = drive.links
    assert sorted((link.from_id, link.to_id) for link in back) == [(i, i + 1) for i in range(5)]
    for link in back:
        assert link.traversals == 2
        assert link.d_m == pytest.approx(1.0, abs=0.05)
        assert link.theta_rad == pytest.approx(0.0, abs=0.05)
        assert link.steps == 10  # two traversals of T = 20 each: 1 / (1/20 + 1/20)
    assert drive.rec.link(3, 2) == drive.rec.link(2, 3)


def test_place_signature_is_stored_on_confirmation(drive):
    sig = drive.rec.signature(0)
    n = sig.x.shape[1]
    assert sig.x.shape == (3, n) and sig.y.shape == (3, n)
    assert (sig.x.sum(axis=0) == n).all()  # every column counts all its cells
    assert sig.x[0].sum() > 0 and sig.x[1].sum() > 0  # walls and free space seen


def test_link_accumulator_weights_by_inverse_steps():
    acc = LinkAccumulator.first(4, 9, np.array([0.0, 2.0]), steps=40, mean_step_m=0.05)
    # a reverse traversal: negated, weight 1/10 against 1/40
    assert acc.add(9, 4, np.array([0.0, -1.5]), steps=10, mean_step_m=0.15, gate_m=1.0)
    e = acc.estimate()
    # D = (2.0/40 + 1.5/10) / (1/40 + 1/10) = 0.2 / 0.125 = 1.6; T = 1 / 0.125 = 8
    assert (e.from_id, e.to_id, e.traversals, e.steps) == (4, 9, 2, 8)
    assert e.d_m == pytest.approx(1.6)
    assert e.theta_rad == pytest.approx(np.pi / 2)
    assert e.mean_step_m == pytest.approx((0.05 / 40 + 0.15 / 10) / 0.125)
    # further than the gate from the fused 1.6 m: rejected, nothing changes
    assert not acc.add(4, 9, np.array([0.0, 3.0]), steps=10, mean_step_m=0.1, gate_m=1.0)
    assert acc.estimate() == e


def test_remove_place_forgets_it():
    d = _Drive(PlaceRecognizer(PlaceRecognizerParams()))
    for k in range(21):
        d.visit(1.5 + 0.1 * k, 1.5, confirm_new=True)
    assert set(d.places) == {0, 1, 2}
    assert d.rec.link(0, 1) is not None
    d.rec.remove_place(1)
    assert d.rec.link(0, 1) is None and d.rec.link(1, 2) is None
    assert 1 not in d.rec.belief.ids.tolist()
    assert d.rec.belief.probs.sum() + d.rec.belief.none_prob == pytest.approx(1.0)


def test_move_places_keeps_offsets():
    d = _Drive(PlaceRecognizer())
    for k in range(4):
        d.visit(1.5 + 0.1 * k, 1.5, confirm_new=True)
    before = d.rec.localization()
    d.rec.move_places({0: (10.0, -3.0)})
    after = d.rec.localization()
    assert after.place_id == before.place_id == 0
    assert (after.offset_x_m, after.offset_y_m) == (before.offset_x_m, before.offset_y_m)
    np.testing.assert_allclose(d.rec.belief.centres[0], [10.0, -3.0])


def test_a_traversal_that_contradicts_the_map_is_not_a_link():
    """Place 1 is confirmed where the map (explorer) says, 1.2 m off the robot's dead-reckoned
    position: the traversal 0 -> 1 disagrees with the centres by more than ``link_map_gate_m``."""
    for map_x, expect_link in ((2.6, True), (3.7, False)):
        rec = PlaceRecognizer(PlaceRecognizerParams(link_map_gate_m=0.75))
        d = _Drive(rec)
        dr = d.dr(1.5, 1.5)
        rec.step(dr, scan_at(1.5, 1.5, 0.0, WALLS)[0])
        rec.add_place(0, 1.5, 1.5, dr)
        for k in range(1, 11):
            dr = d.dr(1.5 + 0.1 * k, 1.5)
            rec.step(dr, scan_at(1.5 + 0.1 * k, 1.5, 0.0, WALLS)[0])
        out = rec.add_place(1, map_x, 1.5, dr)
        assert bool(out.links) is expect_link
        assert (rec.link(0, 1) is not None) is expect_link
        assert rec.rejected_traversals == (0 if expect_link else 1)


def test_a_place_confirmed_between_scans_dates_its_zero_offset_at_the_confirmation():
    """The explorer confirms places at any dead-reckoned pose, not only where a scan was taken: the
    offsets that follow count the travel from the confirmation, and the links measure the true spacing."""
    d = _Drive(PlaceRecognizer())
    offsets = []
    for k in range(26):  # east along the hall, a scan every 0.2 m, a place 0.15 m after every fifth scan
        x = 1.5 + 0.2 * k
        d.visit(x, 1.5, confirm_new=False)
        if k % 5 == 0:
            pid = len(d.places)
            d.places[pid] = (x + 0.15, 1.5)
            d.links += d.rec.add_place(pid, x + 0.15, 1.5, d.dr(x + 0.15, 1.5)).links
        elif k % 5 == 1:
            loc = d.rec.localization()
            offsets.append((loc.place_id, loc.offset_x_m))
    assert [pid for pid, _ in offsets] == list(range(5))
    assert [off for _, off in offsets] == pytest.approx([0.05] * 5, abs=0.04)  # not the 0.2 m since the scan
    assert [(lk.from_id, lk.to_id) for lk in d.links] == [(i, i + 1) for i in range(5)]
    assert [lk.d_m for lk in d.links] == pytest.approx([1.0] * 5, abs=0.03)


def test_a_restored_recognizer_continues_the_map(drive):
    """Part two of a run: places, fused links and signatures restored from what the relaxer keeps
    (centres, link measurements, scans placed at their offsets); the way back is recognised as in
    one unbroken run, and the later traversals are fused into the restored links."""
    from services.place_recognizer.grid import PlacedScan

    rec = PlaceRecognizer()
    scans = {}
    for pid, (px, py) in drive.places.items():  # the scans taken within 0.4 m of each centre
        scans[pid] = [PlacedScan.from_message(scan_at(px + dx, py, 0.0, WALLS)[0],
                                              Pose2(x_m=dx, y_m=0.0, heading_rad=0.0))
                      for dx in np.arange(-0.4, 0.41, 0.1)]
    rec.restore(drive.places, drive.first_pass_links, scans, at_place=5, offset_xy=(0.0, 0.0), dr_xy=(6.5, 1.5))
    assert rec.link(0, 1) == drive.first_pass_links[0]
    assert rec.localization().hypotheses[0] == (5, pytest.approx(0.95))
    again = _Drive(rec)
    again.places = dict(drive.places)
    again.prev, again.steps, again.path = (6.5, 1.5), 1000, 50.0
    for k in range(1, 51):
        again.visit(6.5 - 0.1 * k, 1.5, confirm_new=False)
    seen = [p for i, p in enumerate(again.at) if p != NO_PLACE and (i == 0 or again.at[i - 1] != p)]
    assert seen == [5, 4, 3, 2, 1, 0]
    assert sorted((link.from_id, link.to_id) for link in again.links) == [(i, i + 1) for i in range(5)]
    assert all(link.traversals == 2 and link.steps == 10 for link in again.links)
    with pytest.raises(ValueError, match="without places"):
        rec.restore(drive.places, [], {}, at_place=0, offset_xy=(0.0, 0.0), dr_xy=(0.0, 0.0))


def test_a_recognition_far_from_where_dead_reckoning_puts_the_robot_is_a_jump():
    """Place 0 is confirmed; dead reckoning then says the robot drove 10 m east while the scans come
    back to place 0 (a look-alike, as far as the recognizer can tell). With relocalisation mass to
    spare the belief takes place 0; the arrival gate keeps the robot between places instead."""
    for gate_m, expect_at_0 in ((math.inf, True), (2.5, False)):
        rec = PlaceRecognizer(PlaceRecognizerParams(relocalise_std_m=math.inf, uniform_transition=0.05,
                                                    arrival_gate_m=gate_m))
        d = _Drive(rec)
        dr = d.dr(1.5, 1.5)
        rec.step(dr, scan_at(1.5, 1.5, 0.0, WALLS)[0])
        rec.add_place(0, 1.5, 1.5, dr)
        for k in range(1, 51):  # the true path goes 5 m east, dead reckoning says 10 m
            rec.step(d.dr(1.5 + 0.2 * k, 1.5), scan_at(1.5 + 0.1 * k, 1.5, 0.0, WALLS)[0])
        at = []
        for k in range(1, 11):  # back at place 0 for real, dead reckoning 11.5 m east
            out = rec.step(d.dr(10.6 + 0.01 * k, 1.5), scan_at(1.5, 1.5, 0.0, WALLS)[0])
            at.append(out.localization.place_id)
        assert (0 in at) is expect_at_0, at
        assert int(np.argmax(rec.belief.probs)) == 0  # the belief itself does go there
        assert (rec.rejected_arrivals > 0) is not expect_at_0


def test_relocalising_lifts_the_gate_anchored_at_a_wrong_place_and_measures_no_link_from_it():
    """Places 0 and 1 a metre apart; the robot goes back to place 0 while dead reckoning says it drove
    8 m east of place 1. The belief takes place 0, the arrival gate (anchored at place 1) refuses it
    scan after scan. Asked to relocalise, the recognizer puts the robot at place 0 without measuring
    the link 1 -> 0 from that departure (the map gate, which would, is off here); from place 0 the
    gate and the links are back: the next traversal 0 -> 1 is measured and fused."""

    def run(relocalise: bool):
        rec = PlaceRecognizer(PlaceRecognizerParams(relocalise_std_m=math.inf, uniform_transition=0.05,
                                                    arrival_gate_m=2.5, link_map_gate_m=math.inf))
        d = _Drive(rec)
        dr = d.dr(1.5, 1.5)
        rec.step(dr, scan_at(1.5, 1.5, 0.0, WALLS)[0])
        rec.add_place(0, 1.5, 1.5, dr)
        links = []
        for k in range(1, 11):
            links += rec.step(d.dr(1.5 + 0.1 * k, 1.5), scan_at(1.5 + 0.1 * k, 1.5, 0.0, WALLS)[0]).links
        links += rec.add_place(1, 2.5, 1.5, d.dr(2.5, 1.5)).links
        for k in range(1, 41):  # truly back west to place 0; dead reckoning: 8 m further east
            x = max(2.5 - 0.1 * k, 1.5)
            links += rec.step(d.dr(2.5 + 0.2 * k, 1.5), scan_at(x, 1.5, 0.0, WALLS)[0]).links
        for k in range(1, 6):
            links += rec.step(d.dr(10.5 + 0.01 * k, 1.5), scan_at(1.5, 1.5, 0.0, WALLS)[0]).links
        rejected = rec.rejected_arrivals
        assert rejected > 0 and rec.current == NO_PLACE and int(np.argmax(rec.belief.probs)) == 0
        if relocalise:
            rec.relocalise()
        at = []
        for k in range(1, 16):  # at place 0
            out = rec.step(d.dr(10.6 + 0.01 * k, 1.5), scan_at(1.5, 1.5, 0.0, WALLS)[0])
            links += out.links
            at.append(out.localization.place_id)
        for k in range(1, 21):  # on to place 1, dead reckoning right
            out = rec.step(d.dr(10.75 + 0.1 * min(k, 10), 1.5), scan_at(1.5 + 0.1 * min(k, 10), 1.5, 0.0, WALLS)[0])
            links += out.links
            at.append(out.localization.place_id)
        return rec, rejected, at, [(lk.from_id, lk.to_id, lk.traversals) for lk in links]

    rec, rejected, at, links = run(relocalise=False)
    assert set(at) == {NO_PLACE} and rec.rejected_arrivals > rejected and links == [(0, 1, 1)]
    rec, rejected, at, links = run(relocalise=True)
    assert rec.relocalisations == 1 and rec.rejected_arrivals == rejected
    assert at[:15] == [0] * 15 and at[-5:] == [1] * 5
    assert links == [(0, 1, 1), (0, 1, 2)]  # nothing from place 1 to 0; the second traversal fused


def test_a_spread_belief_keeps_its_mass_and_favours_the_places_near_the_robot():
    from services.place_recognizer import belief as bf

    b = bf.Belief(ids=np.array([0, 1, 2]), centres=np.array([[0.0, 0.0], [1.0, 0.0], [5.0, 0.0]]),
                  probs=np.array([0.9, 0.05, 0.0]), offsets=np.array([[0.2, 0.0], [0.0, 0.0], [0.0, 0.0]]),
                  offset_vars=np.full((3, 2), 0.01), none_prob=0.05, none_xy=np.array([0.5, 0.0]), none_var_m2=0.1)
    s = bf.spread(b, 0.5, std_m=2.0, unknown_offset_var_m2=0.25)
    assert s.probs.sum() + s.none_prob == pytest.approx(1.0)
    assert s.probs[0] > s.probs[1] > s.probs[2] > 0.0  # the robot is expected about 0.2 m from place 0
    m = 0.9 * 0.2 + 0.05 * 1.0 + 0.05 * 0.5  # the expected position along x: places and "none"
    g = np.append(np.exp(-(np.array([0.0, 1.0, 5.0]) - m) ** 2 / (2 * 2.0**2)), 1.0)
    assert s.probs[2] == pytest.approx(0.5 * g[2] / g.sum(), rel=1e-6)
    # place 0's offset: the kept half at 0.2 m, the arriving mass at the centre, mixed by their weights
    kept, arriving = 0.45, 0.5 * g[0] / g.sum()
    assert s.offsets[0, 0] == pytest.approx(kept * 0.2 / (kept + arriving))
    assert s.offset_vars[2, 0] == pytest.approx(0.25) and bf.spread(b, 0.0, std_m=2.0, unknown_offset_var_m2=0.25) is b


def test_the_first_new_place_after_a_restore_is_linked_from_the_place_the_robot_was_saved_at(drive):
    """A continued run joins the saved map: the robot was saved 0.45 m past place 5, on its way out, and
    drives on east without being at place 5 again; the place confirmed next is linked from place 5,
    with the saved offset carried on by dead reckoning."""
    from services.place_recognizer.grid import PlacedScan

    rec = PlaceRecognizer()
    scans = {pid: [PlacedScan.from_message(scan_at(px + dx, py, 0.0, WALLS)[0], Pose2(x_m=dx, y_m=0.0, heading_rad=0.0))
                   for dx in np.arange(-0.4, 0.41, 0.1)] for pid, (px, py) in drive.places.items()}
    x5, y5 = drive.places[5]
    rec.restore(drive.places, drive.first_pass_links, scans, at_place=5, offset_xy=(0.45, 0.0), dr_xy=(30.0, 4.0))
    d = _Drive(rec)
    d.prev, d.steps, d.path = (30.0, 4.0), 500, 25.0  # dead reckoning's own frame, far from the map's
    at = []
    for k in range(1, 6):  # on east, 0.5 m more
        out = rec.step(d.dr(30.0 + 0.1 * k, 4.0), scan_at(x5 + 0.45 + 0.1 * k, y5, 0.0, WALLS)[0])
        at.append(out.localization.place_id)
        assert not out.links
    assert 5 not in at
    out = rec.add_place(6, x5 + 0.95, y5, d.dr(30.5, 4.0))
    assert [(lk.from_id, lk.to_id) for lk in out.links] == [(5, 6)]
    assert out.links[0].d_m == pytest.approx(0.95, abs=0.02) and out.links[0].theta_rad == pytest.approx(0.0, abs=0.02)


def test_bad_match_parameters_are_refused():
    with pytest.raises(ValueError, match="match_axes"):
        PlaceRecognizerParams(match_axes="max")
    with pytest.raises(ValueError, match="match_weights"):
        PlaceRecognizerParams(match_weights=(0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="match_offset_max_sd_m"):
        PlaceRecognizerParams(match_offset_max_sd_m=0.0)
    assert PlaceRecognizerParams(match_axes="mean", match_weights=(1.0, 1.0, 1.0)).match_axes == "mean"


def test_equal_scores_keep_the_predicted_offset():
    """Along a stretch that looks the same the match is flat: of equal best scores within the window the
    shift nearest the predicted offset wins (the smallest shift would pull the offset to the centre)."""
    from services.place_recognizer import belief as _belief
    from services.place_recognizer.histogram import AxisMatch

    rec = PlaceRecognizer(PlaceRecognizerParams())
    cell = rec.params.cell_m
    rec.belief = _belief.Belief(
        ids=np.array([7, 8]), centres=np.zeros((2, 2)), probs=np.array([0.5, 0.5]),
        offsets=np.array([[3.2 * cell, -2.0 * cell], [-0.4 * cell, 0.0]]),
        offset_vars=np.full((2, 2), (2.0 * cell) ** 2), none_prob=0.0, none_xy=np.zeros(2), none_var_m2=0.0)
    shifts = np.arange(-10, 11)
    flat = np.full((2, shifts.size), 0.8)
    flat[1, shifts == 4] = 0.9  # place 8: one clearly better shift inside its window wins
    m = AxisMatch(scores=flat, best_shift=np.zeros(2, dtype=int), best_score=flat.max(axis=1),
                  mean_score=flat.mean(axis=1))
    best_shift, best_score = rec._plausible_best(m, [0, 1], 0, 10)
    assert best_shift.tolist() == [3, 4] and best_score.tolist() == [0.8, 0.9]
    best_shift, _ = rec._plausible_best(AxisMatch(scores=np.full((2, shifts.size), 0.8), best_shift=np.zeros(2, dtype=int),
                                                  best_score=np.full(2, 0.8), mean_score=np.full(2, 0.8)), [0, 1], 1, 10)
    assert best_shift.tolist() == [-2, 0]


def _confirm_and_drive_east(rec: PlaceRecognizer) -> _Drive:
    """Place 0 confirmed at (1.5, 1.5), then 5 m east, a scan every 0.2 m."""
    d = _Drive(rec)
    dr = d.dr(1.5, 1.5)
    rec.step(dr, scan_at(1.5, 1.5, 0.0, WALLS)[0])
    rec.add_place(0, 1.5, 1.5, dr)
    for k in range(1, 26):
        rec.step(d.dr(1.5 + 0.2 * k, 1.5), scan_at(1.5 + 0.2 * k, 1.5, 0.0, WALLS)[0])
    return d


def _scans_until_taken(weight: float, motion: str) -> int:
    """Place 0 is confirmed at (1.5, 1.5); dead reckoning then drives 5 m east, and the scans come
    back from place 0 while it says the robot ``motion``: "drives" on east (0.2 m a scan, as the
    simulator's distance trigger has them), stands "still", is "turning" on the spot or "rocking" 0.3 m
    back and forth. Returns the scans until the belief holds place 0 above 0.5 (100 if never).
    "None" is one Gaussian here and a match as sharp as one observation alone (``none_components`` 1,
    ``match_sharpness`` 25): with three tracks the robot's own, dead reckoning driving on east, keeps
    it from place 0 for good (400 scans and more), so that only a robot not moving on is taken back,
    and what is measured here is how much its scans weigh."""
    rec = PlaceRecognizer(PlaceRecognizerParams(relocalise_std_m=math.inf, uniform_transition=1e-3,
                                                arrival_gate_m=math.inf, repeat_scan_weight=weight,
                                                none_components=1, match_sharpness=25.0))
    d = _confirm_and_drive_east(rec)
    for n in range(1, 101):
        x = {"drives": 6.5 + 0.2 * n, "rocking": 6.5 + 0.3 * (n % 2)}.get(motion, 6.5)
        heading = 0.7 * n if motion == "turning" else 0.0
        rec.step(d.dr(x, 1.5, heading), scan_at(1.5, 1.5, heading, WALLS)[0])
        if rec.belief.ids.size and rec.belief.probs[rec.belief.index(0)] > 0.5:
            return n
    return 100


def test_a_robot_that_does_not_move_on_weighs_its_repeated_scans_less():
    """The same echoes seen again from the same spot are not new evidence: a look-alike 5 m away
    takes the belief of a robot standing still, turning on the spot or rocking back and forth after
    several times as many scans as of a moving one."""
    # a moving robot's scans count in full, whatever the weight
    assert _scans_until_taken(0.2, "drives") == _scans_until_taken(1.0, "drives") < 100
    for motion in ("still", "turning", "rocking"):
        tempered, untempered = _scans_until_taken(0.2, motion), _scans_until_taken(1.0, motion)
        assert tempered > 2 * untempered, (motion, tempered, untempered)


def test_a_restored_recognizer_goes_on_identically(tmp_path):
    """A snapshot taken while the robot stands still, restored into a new recognizer: the scans that
    follow weigh the same (the scans counted in full are part of the state), and so does the belief."""
    from services.place_recognizer.core import RecognizerState
    from services.runtime.checkpoint import Checkpoint

    params = PlaceRecognizerParams(relocalise_std_m=math.inf, uniform_transition=1e-3, arrival_gate_m=math.inf)
    a = PlaceRecognizer(params)
    d = _confirm_and_drive_east(a)
    saved = Checkpoint(tmp_path / "recognizer", RecognizerState)
    saved.save(a.snapshot())
    state = saved.load()
    b = PlaceRecognizer(params)
    b.restore_snapshot(state, a.signatures())
    for _ in range(6):  # standing still, place 0's echoes coming back
        dr = d.dr(6.5, 1.5)
        out_a, out_b = a.step(dr, scan_at(1.5, 1.5, 0.0, WALLS)[0]), b.step(dr, scan_at(1.5, 1.5, 0.0, WALLS)[0])
        assert out_a.localization == out_b.localization
        np.testing.assert_array_equal(a.belief.probs, b.belief.probs)


@pytest.mark.parametrize("enabled", [True, False])
def test_the_motion_through_a_disturbance_is_turned_into_the_maps_frame(enabled):
    """The map's links are corrected for the compass's deviation and the dead reckoning is not: the
    belief moves by the dead-reckoned displacement turned by the deviation where the robot is."""
    from services.place_recognizer.deviation import DeviationParams

    rec = PlaceRecognizer(PlaceRecognizerParams(deviation=DeviationParams(enabled=enabled)))
    d = _Drive(rec)
    dr = d.dr(1.5, 1.5)
    rec.step(dr, scan_at(1.5, 1.5, 0.0, WALLS)[0])
    rec.add_place(0, 1.5, 1.5, dr)
    rec.deviations.estimate[0] = math.radians(10.0)  # the compass reads 10 degrees more at place 0
    row = rec.belief.index(0)
    before = rec.belief.offsets[row].copy()
    rec._move_belief_to((2.0, 1.5))  # 0.5 m east by the compass
    moved = rec.belief.offsets[rec.belief.index(0)] - before
    turn = math.radians(-10.0) if enabled else 0.0
    np.testing.assert_allclose(moved, [0.5 * math.cos(turn), 0.5 * math.sin(turn)], atol=1e-3)  # 0.087 m apart


def _offset_errors_back_along_a_plain_corridor(max_sd_m: float) -> np.ndarray:
    """A plain corridor 20 m x 2 m: places every metre driving east (perfect dead reckoning, a scan
    every 0.2 m), then back west from 18 m to 9 m. Returns the filtered offset's error along the
    corridor at every scan localised at a place on the way back."""
    walls = box(0, 0, 20, 2.0)
    d = _Drive(PlaceRecognizer(PlaceRecognizerParams(match_offset_max_sd_m=max_sd_m)))
    places: dict[int, float] = {}
    for k in range(81):
        x = 2.0 + 0.2 * k
        dr = d.dr(x, 1.0)
        out = d.rec.step(dr, scan_at(x, 1.0, 0.0, walls)[0])
        if out.localization.place_id == NO_PLACE and all(abs(x - px) > 0.95 for px in places.values()):
            places[len(places)] = x
            d.rec.add_place(len(places) - 1, x, 1.0, dr)
    errors = []
    for k in range(1, 46):
        x = 18.0 - 0.2 * k
        loc = d.rec.step(d.dr(x, 1.0), scan_at(x, 1.0, 0.0, walls)[0]).localization
        if loc.place_id != NO_PLACE:
            errors.append(loc.offset_x_m - (x - places[loc.place_id]))
    return np.array(errors)


def test_a_flat_match_leaves_the_offset_as_dead_reckoning_predicts_it():
    """Along a plain corridor the match has nothing to lock onto: its best shift is where its scans'
    coverage lines up with the signature's, and each observation pulls the offset that way. Matches
    less certain than ``match_offset_max_sd_m`` leave the offset to dead reckoning (exact here)."""
    pulled = _offset_errors_back_along_a_plain_corridor(math.inf)
    kept = _offset_errors_back_along_a_plain_corridor(0.4)
    assert len(pulled) > 30 and len(kept) > 30  # localised at a place on most scans either way
    assert np.abs(kept).max() < 0.02
    assert np.abs(pulled).max() > 0.05
