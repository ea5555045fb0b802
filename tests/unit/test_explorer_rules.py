"""Explorer rules: prediction, confirmation, deletion, confidence, loop closing, completion."""

from __future__ import annotations

import math

import numpy as np
import pytest

from messages.types import Pose2
from services.explorer import (
    Explorer,
    ExplorerParams,
    LinkConfidenceEvent,
    LinkDeletedEvent,
    LinkInferredEvent,
    PlaceConfirmedEvent,
    PlaceDeletedEvent,
    PlaceFix,
    PlacePredictedEvent,
    clear_towards,
    confidence_after_failure,
    confidence_after_traversal,
)
from services.explorer.core import INFERRED, PREDICTED, TRAVERSED, Link, Place
from tests.unit._sonar_rooms import box, scan_at

OPEN_ROOM = box(-4, -4, 4, 4)
CORRIDOR = box(-4, -0.8, 4, 0.8)  # 1.6 m wide, along x


def _pose(x, y, h=0.0):
    return Pose2(x_m=x, y_m=y, heading_rad=h)


def _of(events, kind):
    return [e for e in events if isinstance(e, kind)]


def test_confidence_rules_eqs_17_18():
    c = 0.5
    c = confidence_after_traversal(c, 0.5)
    assert c == 0.75
    assert confidence_after_traversal(c, 0.5) == 0.875
    assert confidence_after_failure(0.75, 0.5) == 0.375
    assert confidence_after_failure(0.375, 0.5) == 0.1875  # below 0.2: the link goes


def test_first_step_confirms_place_zero_and_predicts_open_directions():
    ex = Explorer()
    out = ex.step(0.0, _pose(0.0, 0.0), scan_at(0.0, 0.0, 0.0, CORRIDOR)[0])
    assert out.events[0] == PlaceConfirmedEvent(0, 0.0, 0.0)
    predicted = _of(out.events, PlacePredictedEvent)
    # only east and west are open in a 1.6 m corridor
    assert sorted((round(e.x_m, 6), round(e.y_m, 6)) for e in predicted) == [(-1.0, 0.0), (1.0, 0.0)]
    assert all(e.parent_id == 0 for e in predicted)
    assert out.status.predicted == 2 and out.status.confirmed == 1 and not out.status.complete
    assert ex.leg is not None and ex.leg[0] == 0


def test_open_room_predicts_the_four_axes_and_diagonals_only_where_room_is_left():
    ex = Explorer()
    out = ex.step(0.0, _pose(0.0, 0.0), scan_at(0.0, 0.0, 0.0, OPEN_ROOM)[0])
    pts = {(round(e.x_m, 3), round(e.y_m, 3)) for e in _of(out.events, PlacePredictedEvent)}
    # a diagonal candidate is 0.765 m from its axis neighbours: within the 0.8 m separation
    assert pts == {(1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0)}
    walls = box(-4, -0.6, 4, 4)  # south closed at 0.6 m: the south diagonals have no axis neighbour
    ex = Explorer(ExplorerParams(open_half_width_m=0.2))
    out = ex.step(0.0, _pose(0.0, 0.0), scan_at(0.0, 0.0, 0.0, walls)[0])
    pts = {(round(e.x_m, 3), round(e.y_m, 3)) for e in _of(out.events, PlacePredictedEvent)}
    assert pts == {(1.0, 0.0), (0.0, 1.0), (-1.0, 0.0)}


def test_free_space_classifier_needs_seen_free_space():
    scan = scan_at(0.0, 0.0, 0.0, CORRIDOR)[0]
    assert clear_towards(0.0, scan, 0.0, 1.5, half_width_m=0.2, sample_step_m=0.1)
    assert not clear_towards(0.0, scan, math.pi / 2, 1.5, half_width_m=0.2, sample_step_m=0.1)
    assert clear_towards(0.0, scan, math.pi / 2, 0.3, half_width_m=0.2, sample_step_m=0.1)
    # heading does not matter: the scan is placed by the compass heading
    turned = scan_at(0.0, 0.0, 1.0, CORRIDOR)[0]
    assert clear_towards(1.0, turned, math.pi, 1.5, half_width_m=0.2, sample_step_m=0.1)
    assert not clear_towards(1.0, turned, -math.pi / 2, 1.5, half_width_m=0.2, sample_step_m=0.1)


def test_predicted_place_confirmed_when_reached_at_the_robot_position():
    ex = Explorer()
    ex.step(0.0, _pose(0.0, 0.0), scan_at(0.0, 0.0, 0.0, CORRIDOR)[0])
    target = ex.places[ex.leg[1]]
    x, y = target.x_m + 0.06, target.y_m - 0.05  # within the 0.1 m tolerance
    out = ex.step(5.0, _pose(x, y), scan_at(x, y, 0.0, CORRIDOR)[0])
    conf = _of(out.events, PlaceConfirmedEvent)
    assert conf == [PlaceConfirmedEvent(target.place_id, pytest.approx(x), pytest.approx(y))]
    assert LinkConfidenceEvent(0, target.place_id, 0.5) in out.events
    assert ex.links[tuple(sorted((0, target.place_id)))].kind == TRAVERSED
    # the next predicted place lies 1 m further along the corridor, not back near place 0
    new = _of(out.events, PlacePredictedEvent)
    assert [(round(e.x_m - x, 6), round(e.y_m - y, 6)) for e in new] == [(round(math.copysign(1.0, target.x_m), 6), 0.0)]


def test_predicted_place_deleted_when_the_leg_times_out():
    p = ExplorerParams(leg_timeout_base_s=10.0, leg_timeout_per_m_s=5.0)
    ex = Explorer(p)
    ex.step(0.0, _pose(0.0, 0.0), scan_at(0.0, 0.0, 0.0, CORRIDOR)[0])
    target = ex.leg[1]
    assert _of(ex.step(14.9, _pose(0.0, 0.0)).events, PlaceDeletedEvent) == []
    out = ex.step(15.1, _pose(0.0, 0.0))  # 10 s + 5 s/m * 1 m
    deleted = _of(out.events, PlaceDeletedEvent)
    assert [e.place_id for e in deleted] == [target] and "timeout" in deleted[0].reason
    assert target not in ex.places
    assert ex.leg is not None and ex.leg[1] != target  # on to the other predicted place


def test_predicted_place_deleted_when_blocked():
    p = ExplorerParams(blocked_timeout_s=2.0)
    ex = Explorer(p)
    walls = box(-4, -0.8, 0.25, 0.8)  # wall 0.25 m east of the robot
    scan = scan_at(0.0, 0.0, 0.0, walls)[0]
    ex.step(0.0, _pose(0.0, 0.0), scan)
    ex.leg, ex.target = (0, ex.places[1].place_id), 1
    ex.places[1].x_m, ex.places[1].y_m = 1.0, 0.0
    ex._start_leg((0, 1), 1, 0.0)
    out = ex.step(0.1, _pose(0.0, 0.0), scan)
    assert out.command.blocked and out.command.v_mps == 0.0
    ex.step(1.0, _pose(0.0, 0.0), scan)
    out = ex.step(2.2, _pose(0.0, 0.0), scan)
    assert [e.place_id for e in _of(out.events, PlaceDeletedEvent)] == [1]
    assert "blocked" in _of(out.events, PlaceDeletedEvent)[0].reason


def test_predicted_place_deleted_when_the_robot_comes_no_nearer():
    """Dithering in front of a door frame (neither blocked nor stalled for long): the leg fails once the
    robot has come no nearer its end by ``progress_m`` in ``progress_timeout_s``, long before its timeout."""
    ex = Explorer(ExplorerParams(progress_timeout_s=10.0, progress_m=0.1))
    ex.step(0.0, _pose(0.0, 0.0), scan_at(0.0, 0.0, 0.0, CORRIDOR)[0])
    target = ex.leg[1]
    sign = math.copysign(1.0, ex.places[target].x_m)
    t, events = 0.0, []
    while t < 9.9:  # 0.3 m nearer, then back and forth by 5 cm
        t = round(t + 0.1, 1)
        x = sign * (min(t, 3.0) * 0.1 + (0.05 if int(t * 10) % 2 else 0.0))
        events += ex.step(t, _pose(x, 0.0)).events
    assert _of(events, PlaceDeletedEvent) == []
    while not _of(events, PlaceDeletedEvent) and t < 20.0:
        t = round(t + 0.1, 1)
        x = sign * (0.3 + (0.05 if int(t * 10) % 2 else 0.0))
        events += ex.step(t, _pose(x, 0.0)).events
    deleted = _of(events, PlaceDeletedEvent)
    assert [e.place_id for e in deleted] == [target] and "no progress" in deleted[0].reason
    assert t <= 13.1  # 10 s after it last came 0.1 m nearer (by 3 s); the leg timeout is 40 s


def _chain_explorer(params=None) -> Explorer:
    """Confirmed places 0-1-2 on a line 1 m apart, traversed links, robot at 2; nothing predicted."""
    ex = Explorer(params)
    ex.step(0.0, _pose(2.0, 0.0), scan_at(2.0, 0.0, 0.0, OPEN_ROOM)[0])  # confirms 0 and predicts
    for pid in [k for k, q in ex.places.items() if not q.confirmed]:
        ex._delete_place(pid, "test setup")
    ex.places = {0: Place(0, 0.0, 0.0, True, -1), 1: Place(1, 1.0, 0.0, True, 0), 2: Place(2, 2.0, 0.0, True, 1)}
    ex.links = {(0, 1): Link(0, 1, TRAVERSED, 0.5), (1, 2): Link(1, 2, TRAVERSED, 0.5)}
    ex._next_id = 3
    ex.current = ex.last_place = 2
    ex.leg = None
    ex.complete = False
    return ex


def test_exploration_complete_without_predicted_places():
    ex = _chain_explorer()
    out = ex.step(1.0, _pose(2.0, 0.0))
    assert out.status.complete and out.status.predicted == 0 and out.status.target_id == -1
    assert out.command.v_mps == 0.0 and out.command.omega_radps == 0.0


def test_traversal_raises_and_failure_lowers_confidence_then_deletes_link_and_unreachable_places():
    ex = _chain_explorer(ExplorerParams(leg_timeout_base_s=10.0, leg_timeout_per_m_s=0.0))
    ex.places[3] = Place(3, -1.0, 0.0, False, 0)
    ex.links[(0, 3)] = Link(0, 3, PREDICTED, 0.5)
    # predicted 4 beyond place 2, dearer to reach than 3 (path length over confidence 10 against 6)
    ex.places[4] = Place(4, 3.0, 0.0, False, 2)
    ex.links[(2, 4)] = Link(2, 4, PREDICTED, 0.1)
    ex._next_id = 5
    ex.step(0.0, _pose(2.0, 0.0))
    assert ex.leg == (2, 1) and ex.target == 3
    # the recognizer reports place 1: the leg succeeded, Eq. 17
    out = ex.step(1.0, _pose(1.05, 0.0), fix=PlaceFix(1, 0.05, 0.0, 1.0))
    assert LinkConfidenceEvent(2, 1, 0.75) in out.events
    assert ex.leg == (1, 0)
    # the robot never gets to place 0: timeout, Eq. 18 (0.5 -> 0.25), then again (0.25 -> 0.125)
    out = ex.step(11.5, _pose(1.05, 0.0))
    assert LinkConfidenceEvent(1, 0, 0.25) in out.events
    assert ex.leg == (1, 0)
    out = ex.step(22.0, _pose(1.05, 0.0))
    assert LinkConfidenceEvent(1, 0, 0.125) in out.events
    deleted_links = _of(out.events, LinkDeletedEvent)
    assert [(e.from_id, e.to_id) for e in deleted_links] == [(1, 0)]
    # 0 and the predicted 3 hang off the deleted link: no path reaches them; 4 is still in reach
    assert sorted(e.place_id for e in _of(out.events, PlaceDeletedEvent)) == [0, 3]
    assert set(ex.places) == {1, 2, 4}
    # the deletion was due on a leg from the robot's place: the recognizer is asked to relocalise
    assert not out.status.complete and ex.target == 4 and ex.relocalisations == 1


def _on_the_leg_towards_the_only_predicted_place(params: ExplorerParams) -> Explorer:
    """The chain 0-1-2 with place 3 predicted beyond 0 and nothing else: the robot, at place 1, on the leg 1 -> 0."""
    ex = _chain_explorer(params)
    ex.places[3] = Place(3, -1.0, 0.0, False, 0)
    ex.links[(0, 3)] = Link(0, 3, PREDICTED, 0.5)
    ex.step(0.0, _pose(2.0, 0.0))
    ex.step(1.0, _pose(1.05, 0.0), fix=PlaceFix(1, 0.05, 0.0, 1.0))
    return ex


def test_a_link_that_would_cut_the_robot_off_from_every_predicted_place_is_held_and_asks_to_relocalise():
    """The same failing leg 1 -> 0 with nothing predicted beyond place 2: deleting the link would leave
    no predicted place within reach and end the exploration (a lost robot's legs fail like that). It is
    kept through max_held_failures failures below confidence_min, each a relocalisation request."""
    params = ExplorerParams(leg_timeout_base_s=10.0, leg_timeout_per_m_s=0.0, max_held_failures=3)
    ex = _on_the_leg_towards_the_only_predicted_place(params)
    assert ex.leg == (1, 0)
    t, confidences, requests = 1.0, [], []
    for _ in range(4):  # 0.25, then below 0.2: held three times
        t += 10.5
        out = ex.step(t, _pose(1.05, 0.0))
        confidences += [e.confidence for e in _of(out.events, LinkConfidenceEvent)]
        requests.append(ex.relocalisations)
        assert not _of(out.events, LinkDeletedEvent) and not out.status.complete and ex.leg == (1, 0)
    assert confidences == [0.25, 0.125, 0.0625, 0.03125] and requests == [0, 1, 2, 3]
    # the snapshot keeps the count of held failures and of requests
    clone = Explorer(params)
    clone.restore_snapshot(ex.snapshot())
    assert clone._held == {(0, 1): 3} and clone.relocalisations == 3
    # a fourth failure below the threshold: Eq. 18 after all, and the prune ends the exploration
    out = ex.step(t + 10.5, _pose(1.05, 0.0))
    assert [(e.from_id, e.to_id) for e in _of(out.events, LinkDeletedEvent)] == [(1, 0)]
    assert sorted(e.place_id for e in _of(out.events, PlaceDeletedEvent)) == [0, 3]
    assert ex.relocalisations == 4 and ex._held == {} and out.status.complete


def test_a_held_link_travelled_after_all_starts_its_count_afresh():
    params = ExplorerParams(leg_timeout_base_s=10.0, leg_timeout_per_m_s=0.0, max_held_failures=3)
    ex = _on_the_leg_towards_the_only_predicted_place(params)
    ex.step(11.5, _pose(1.05, 0.0))
    ex.step(22.0, _pose(1.05, 0.0))
    assert ex._held == {(0, 1): 1} and ex.relocalisations == 1
    out = ex.step(23.0, _pose(0.05, 0.0), fix=PlaceFix(0, 0.05, 0.0, 23.0))  # relocalised: there after all
    assert LinkConfidenceEvent(1, 0, 0.5625) in out.events and ex._held == {} and ex.leg == (0, 3)


def test_the_last_link_of_the_robots_place_is_kept_however_often_its_legs_fail():
    """A robot stuck at place 2, whose one link fails again and again: without the link no path would
    reach the rest of the map, and every predicted place would be pruned as out of reach."""
    ex = _chain_explorer(ExplorerParams(leg_timeout_base_s=10.0, leg_timeout_per_m_s=0.0))
    ex.places[3] = Place(3, -1.0, 0.0, False, 0)
    ex.links[(0, 3)] = Link(0, 3, PREDICTED, 0.5)
    ex.step(0.0, _pose(2.0, 0.0))
    assert ex.leg == (2, 1)
    confidences = []
    for k in range(1, 5):  # the robot never leaves place 2
        out = ex.step(10.5 * k, _pose(2.0, 0.0))
        confidences += [e.confidence for e in _of(out.events, LinkConfidenceEvent)]
        assert not _of(out.events, LinkDeletedEvent) and not _of(out.events, PlaceDeletedEvent)
    assert confidences == [0.25, 0.125, 0.0625, 0.03125]  # Eq. 18, below confidence_min from the second
    assert ex.relocalisations == 3  # each failure below it asks the recognizer to relocalise
    assert set(ex.places) == {0, 1, 2, 3} and not out.status.complete
    assert ex.leg == (2, 1)  # and it tries again
    # once it gets there, the link is traversed (Eq. 17) and the exploration goes on beyond
    out = ex.step(43.0, _pose(1.05, 0.0), fix=PlaceFix(1, 0.05, 0.0, 1.0))
    assert LinkConfidenceEvent(2, 1, 0.515625) in out.events and ex.leg == (1, 0)


def test_after_a_failed_leg_the_robot_goes_back_to_the_legs_start_first():
    """Wedged 0.7 m beside place 2 (a side passage), heading straight for place 1 makes no progress: the
    next leg takes the robot back to place 2's centre before it heads for place 1 again."""
    ex = _chain_explorer(ExplorerParams(leg_timeout_base_s=100.0, leg_timeout_per_m_s=0.0))
    ex.places[3] = Place(3, -1.0, 0.0, False, 0)
    ex.links[(0, 3)] = Link(0, 3, PREDICTED, 0.5)
    ex.step(0.0, _pose(2.0, 0.0))
    ex.step(0.1, _pose(2.0, 0.7, -math.pi / 2))  # dead reckoning: the robot is 0.7 m beside place 2
    assert ex.leg == (2, 1)
    out = ex.step(10.5, _pose(2.0, 0.7, -math.pi / 2))
    assert LinkConfidenceEvent(2, 1, 0.25) in out.events and ex.leg == (2, 1)
    # facing south, place 2 straight ahead: forward without turning (place 1 would be 55 degrees right)
    assert out.command.v_mps > 0.0 and abs(out.command.omega_radps) < 1e-6
    out = ex.step(20.0, _pose(2.0, 0.45, -math.pi / 2))  # progress towards place 2: no failure
    assert not _of(out.events, LinkConfidenceEvent) and ex._via == 2
    out = ex.step(21.0, _pose(2.0, 0.15, -math.pi / 2))  # back within 0.2 m: on to place 1
    assert ex._via == -1 and ex.leg == (2, 1) and out.command.omega_radps < 0.0


def test_a_predicted_place_whose_legs_keep_ending_elsewhere_is_deleted():
    """Places 1 and 2 near-duplicates (the recognizer flips between them): every leg 2 -> 3 towards the
    predicted 3 ends at place 1, and the robot went back and forth for ever."""
    ex = _chain_explorer()
    ex.places[1] = Place(1, 1.7, 0.0, True, 0)  # 0.3 m from place 2
    ex.places[3] = Place(3, 3.0, 0.0, False, 2)
    ex.links[(2, 3)] = Link(2, 3, PREDICTED, 0.5)
    t = 0.0
    ex.step(t, _pose(2.0, 0.0))
    for n in range(1, 4):
        assert ex.leg == (2, 3)
        t += 1.0
        out = ex.step(t, _pose(2.1, 0.0), fix=PlaceFix(1, 0.4, 0.0, t))  # recognised at 1 on the way
        deleted = _of(out.events, PlaceDeletedEvent)
        if n < 3:
            assert ex._interrupted == {3: n} and not deleted and ex.leg == (1, 2)
            t += 1.0
            ex.step(t, _pose(2.0, 0.0), fix=PlaceFix(2, 0.0, 0.0, t))  # back at 2: towards 3 again
    assert [e.place_id for e in deleted] == [3] and "3 legs" in deleted[0].reason
    assert out.status.complete and ex._interrupted == {}


def test_arriving_at_another_place_is_a_failed_traversal():
    ex = _chain_explorer()
    ex.places[3] = Place(3, 3.0, 1.0, True, 2)
    ex.links[(2, 3)] = Link(2, 3, TRAVERSED, 0.5)
    ex.places[4] = Place(4, -1.0, 0.0, False, 0)
    ex.links[(0, 4)] = Link(0, 4, PREDICTED, 0.5)
    ex.step(0.0, _pose(2.0, 0.0))
    assert ex.leg == (2, 1)
    out = ex.step(1.0, _pose(3.0, 1.0), fix=PlaceFix(3, 0.0, 0.0, 1.0))  # ended up at 3 instead
    assert LinkConfidenceEvent(2, 1, 0.25) in out.events  # Eq. 18 on the planned link
    assert LinkConfidenceEvent(2, 3, 0.75) in out.events  # Eq. 17 on the one travelled
    assert ex.last_place == 3


def test_a_place_on_the_way_continues_the_leg_only_along_a_link():
    """Recognised at place 1 on the way from 0 to 2: the leg goes on as 1 -> 2 over their link; without
    that link the leg ends there, a failed traversal of 0 -> 2 (a leg 1 -> 2 with no link under it could
    fail for ever without changing the map)."""
    for linked in (True, False):
        ex = _chain_explorer()
        ex.places[3] = Place(3, 3.0, 0.0, False, 2)
        ex.links[(2, 3)] = Link(2, 3, PREDICTED, 0.5)
        ex.links[(0, 2)] = Link(0, 2, INFERRED, 0.5)
        del ex.links[(0, 1)]
        if not linked:
            del ex.links[(1, 2)]
            ex.links[(0, 1)] = Link(0, 1, TRAVERSED, 0.5)
        ex.current = ex.last_place = 0
        ex.step(0.0, _pose(0.0, 0.0))
        assert ex.leg == (0, 2)
        out = ex.step(3.0, _pose(1.0, 0.0), fix=PlaceFix(1, 0.0, 0.0, 3.0))
        if linked:
            assert ex.leg == (1, 2) and LinkConfidenceEvent(0, 2, 0.25) not in out.events
        else:
            assert LinkConfidenceEvent(0, 2, 0.25) in out.events and ex.leg != (1, 2)
        assert ex.last_place == 1


def test_loop_closing_goes_directly_when_the_traversed_path_is_long():
    # a U of traversed places 0-1-2-3-4; the predicted place 5 at (0, 1) closes it next to 0
    ex = Explorer()
    ex.step(0.0, _pose(1.0, 1.0), scan_at(1.0, 1.0, 0.0, OPEN_ROOM)[0])
    ex.places = {0: Place(0, 0.0, 0.0, True, -1), 1: Place(1, 1.0, 0.0, True, 0), 2: Place(2, 2.0, 0.0, True, 1),
                 3: Place(3, 2.0, 1.0, True, 2), 4: Place(4, 1.0, 1.0, True, 3), 5: Place(5, 0.0, 1.0, False, 4)}
    ex.links = {(0, 1): Link(0, 1, TRAVERSED, 0.5), (1, 2): Link(1, 2, TRAVERSED, 0.5),
                (2, 3): Link(2, 3, TRAVERSED, 0.5), (3, 4): Link(3, 4, TRAVERSED, 0.5),
                (4, 5): Link(4, 5, PREDICTED, 0.5)}
    ex._next_id, ex.current, ex.last_place, ex.leg, ex.loop_queue = 6, 4, 4, None, []
    ex.step(1.0, _pose(1.0, 1.0), scan_at(1.0, 1.0, 0.0, OPEN_ROOM)[0])
    assert ex.leg == (4, 5)
    out = ex.step(5.0, _pose(0.0, 1.0), scan_at(0.0, 1.0, 0.0, OPEN_ROOM)[0])
    assert PlaceConfirmedEvent(5, 0.0, 1.0) in out.events
    inferred = {(e.from_id, e.to_id): e.d_m for e in _of(out.events, LinkInferredEvent)}
    # within 2 m of 5: 0 (1 m, traversed path 5-4-3-2-1-0 = 5 m) and 1 (1.41 m, path 4 m); 3 is 2 m away
    assert inferred == {(5, 0): pytest.approx(1.0), (5, 1): pytest.approx(math.sqrt(2))}
    assert ex.loop_queue[1:] == [(5, 1)]
    assert ex.leg == (5, 0)  # straight to 0, before exploring further
    assert ex.links[(0, 5)].kind == INFERRED
    # arriving at 0 makes the link traversed and takes the next loop-closing link
    out = ex.step(10.0, _pose(0.0, 0.02), fix=PlaceFix(0, 0.0, 0.02, 10.0))
    assert LinkConfidenceEvent(5, 0, 0.75) in out.events
    assert ex.links[(0, 5)].kind == TRAVERSED
    assert ex.leg == (0, 5) and ex.loop_queue == [(5, 1)]


def test_no_loop_closing_when_the_traversed_path_is_short():
    ex = Explorer()
    ex.step(0.0, _pose(1.0, 1.0), scan_at(1.0, 1.0, 0.0, OPEN_ROOM)[0])
    ex.places = {0: Place(0, 0.0, 0.0, True, -1), 1: Place(1, 1.0, 0.0, True, 0), 2: Place(2, 1.0, 1.0, False, 1)}
    ex.links = {(0, 1): Link(0, 1, TRAVERSED, 0.5), (1, 2): Link(1, 2, PREDICTED, 0.5)}
    ex._next_id, ex.current, ex.last_place, ex.leg, ex.loop_queue = 3, 1, 1, None, []
    ex.step(1.0, _pose(1.0, 0.0), scan_at(1.0, 0.0, 0.0, OPEN_ROOM)[0])
    out = ex.step(5.0, _pose(1.0, 1.0), scan_at(1.0, 1.0, 0.0, OPEN_ROOM)[0])
    assert [(e.from_id, e.to_id) for e in _of(out.events, LinkInferredEvent)] == [(2, 0)]
    assert ex.loop_queue == []  # 2-1-0 is 2 m of traversed path


def test_no_inferred_link_through_a_wall():
    walls = OPEN_ROOM + [(-1.0, 0.5, 1.0, 0.5)]  # wall between y=0 and y=1 west of x=1
    ex = Explorer()
    ex.step(0.0, _pose(1.5, 1.0), scan_at(1.5, 1.0, 0.0, walls)[0])
    ex.places = {0: Place(0, 0.0, 0.0, True, -1), 1: Place(1, 1.5, 0.0, True, 0), 2: Place(2, 1.5, 1.0, True, 1),
                 3: Place(3, 0.5, 1.0, False, 2)}
    ex.links = {(0, 1): Link(0, 1, TRAVERSED, 0.5), (1, 2): Link(1, 2, TRAVERSED, 0.5),
                (2, 3): Link(2, 3, PREDICTED, 0.5)}
    ex._next_id, ex.current, ex.last_place, ex.leg, ex.loop_queue = 4, 2, 2, None, []
    ex.step(1.0, _pose(1.5, 1.0), scan_at(1.5, 1.0, 0.0, walls)[0])
    out = ex.step(5.0, _pose(0.5, 1.0), scan_at(0.5, 1.0, 0.0, walls)[0])
    assert PlaceConfirmedEvent(3, 0.5, 1.0) in out.events
    inferred = [(e.from_id, e.to_id) for e in _of(out.events, LinkInferredEvent)]
    assert (3, 0) not in inferred  # 0 is 1.1 m away, behind the wall


def test_restore_continues_places_links_and_predicts_afresh():
    """A continued run: confirmed places and traversed links come back, places are predicted anew
    around them from their scans, ids go on above every id used, the robot plans from its place."""
    places = {0: (-3.0, 0.0), 1: (-2.0, 0.0), 2: (-1.0, 0.0), 5: (0.0, 0.0)}
    scans = {pid: (0.0, scan_at(x, y, 0.0, CORRIDOR)[0]) for pid, (x, y) in places.items()}
    ex = Explorer()
    events = ex.restore(places, [(0, 1, 1), (1, 2, 2), (2, 5, 1)], scans, at_place=5, robot_xy=(0.1, 0.0),
                        pose=_pose(7.0, 3.0), scan=scans[5][1], next_place_id=9)
    predicted = _of(events, PlacePredictedEvent)
    # only east of the last place is open and free of places (the west end is a wall)
    assert [(e.place_id, round(e.x_m, 6), round(e.y_m, 6), e.parent_id) for e in predicted] == [(9, 1.0, 0.0, 5)]
    assert all(ex.places[i].confirmed for i in places)
    assert ex.links[(1, 2)] == Link(1, 2, TRAVERSED, confidence_after_traversal(0.5, 0.5))
    assert ex.links[(0, 1)].kind == TRAVERSED and ex.links[(0, 1)].confidence == 0.5
    # the next step plans from place 5 towards the new prediction; dead reckoning moves the robot on
    out = ex.step(100.0, _pose(7.2, 3.0))
    assert ex.robot_xy == pytest.approx((0.3, 0.0))
    assert ex.leg == (5, 9) and out.status.predicted == 1 and out.status.confirmed == 4
    assert not _of(out.events, PlaceDeletedEvent)  # nothing of the saved map is pruned
    with pytest.raises(ValueError, match="without places"):
        ex.restore(places, [], {}, at_place=5, robot_xy=(0, 0), pose=_pose(0, 0))
    with pytest.raises(ValueError, match="not among"):
        Explorer().restore(places, [], {}, at_place=7, robot_xy=(0, 0), pose=_pose(0, 0))


def test_restore_takes_ids_above_the_saved_places():
    ex = Explorer()
    events = ex.restore({3: (0.0, 0.0), 12: (1.0, 0.0)}, [(3, 12, 1)], {3: (0.0, scan_at(0, 0, 0, OPEN_ROOM)[0])},
                        at_place=3, robot_xy=(0.0, 0.0), pose=_pose(0, 0), next_place_id=4)
    assert min(e.place_id for e in _of(events, PlacePredictedEvent)) == 13
