"""The sensor_sim step and the dead_reckoning filter as pure cores, together and apart."""

from __future__ import annotations

import math

import numpy as np
import pytest

from messages.codec import codec
from messages.types import CompassReading, OdometryStep
from services.dead_reckoning import core as dr
from services.sensor_sim import core as ss
from sim.geometry import wrap_angle
from sim.route import RouteDriver, RouteParams, RouteState, drive
from sim.world import load_world

MANCHESTER = load_world("manchester-corridors")


def _run(world, seed, ticks, params=ss.SensorSimParams(), route="outer-loop"):
    model = ss.SimModel(world, params)
    rng = np.random.default_rng(seed)
    state, frame = ss.start(model, rng)
    frames = [frame]
    driver = RouteDriver(world.routes[route])
    for _ in range(ticks):
        state, frame = ss.step(state, driver.command(state.pose), model, rng)
        frames.append(frame)
    return state, frames


# -- sensor_sim core -----------------------------------------------------------------------------------


def test_frames_ticks_and_seqs():
    state, frames = _run(MANCHESTER, 1, 200)
    assert frames[0].odometry is None and frames[0].sonar is not None and frames[0].sonar.seq == 0
    for k, f in enumerate(frames):
        assert f.tick == k and f.truth.seq == k and f.compass.seq == k
        assert f.truth.stamp == f.compass.stamp == pytest.approx(0.1 * k)
        if k:
            assert f.odometry.seq == k - 1 and f.odometry.stamp == f.truth.stamp and f.odometry.dt_s == 0.1
    scans = [f.sonar for f in frames if f.sonar is not None]
    assert [s.seq for s in scans] == list(range(len(scans)))
    assert len(scans[0].ranges_m) == 16 and scans[0].max_range_m == 6.5
    travelled = sum(abs(f.odometry.distance_m) for f in frames[1:])
    assert len(scans) - 1 == pytest.approx(travelled / 0.5, abs=1.5)  # one scan every 0.5 m
    assert state.collisions == 0 and state.tick == 200
    for f in frames[:20]:  # every message encodes as it is (plain floats, no numpy scalars)
        for msg in (f.truth, f.compass, f.odometry, f.sonar):
            if msg is not None:
                assert codec(type(msg)).decode(codec(type(msg)).encode(msg)) == msg


def test_sonar_at_a_set_rate():
    params = ss.SensorSimParams(sonar_every_m=0.0, sonar_period_s=1.0)
    _, frames = _run(MANCHESTER, 1, 100, params)
    assert [f.tick for f in frames if f.sonar is not None] == list(range(0, 101, 10))


def test_same_seed_same_frames_other_seed_differs():
    _, a = _run(MANCHESTER, 7, 150)
    _, b = _run(MANCHESTER, 7, 150)
    _, c = _run(MANCHESTER, 8, 150)
    assert a == b
    assert [f.compass for f in a] != [f.compass for f in c]
    assert [f.odometry for f in a[1:]] != [f.odometry for f in c[1:]]


# -- dead_reckoning core ----------------------------------------------------------------------------------


def _odo(k, d, r=0.0):
    return OdometryStep(stamp=0.1 * (k + 1), seq=k, distance_m=d, rotation_rad=r, dt_s=0.1)


def _cmp(k, h):
    return CompassReading(stamp=0.1 * k, seq=k, heading_rad=h)


def _feed(state, msgs):
    out = []
    for m in msgs:
        state, poses = dr.step(state, m)
        out += poses
    return state, out


def test_dr_integrates_compass_and_raw_side_by_side():
    # heading north by the compass, the wheels believe they turn 0.01 rad per step
    msgs = [_cmp(0, math.pi / 2)]
    for k in range(10):
        msgs += [_cmp(k + 1, math.pi / 2), _odo(k, 0.1, 0.01)]
    state, out = _feed(dr.DrState(), msgs)
    assert out[0].steps == 0 and out[0].compass.heading_rad == pytest.approx(math.pi / 2)
    last = out[-1]
    assert last.steps == 10 and last.path_length_m == pytest.approx(1.0) and last.gaps == 0
    assert (last.compass.x_m, last.compass.y_m) == pytest.approx((0.0, 1.0), abs=1e-12)
    assert last.raw.heading_rad == pytest.approx(math.pi / 2 + 0.1)
    assert last.raw.x_m < -0.04  # the raw pose curved left
    assert [p.seq for p in out] == list(range(len(out)))
    assert state.steps == 10


def test_a_continued_run_goes_on_from_the_saved_pose_and_tick():
    """Split one drive in two: the second part starts at the first's last tick, true pose and
    dead-reckoned state, and carries on from there (stamps, seqs, poses, step record)."""
    model = ss.SimModel(MANCHESTER)
    driver = RouteDriver(MANCHESTER.routes["outer-loop"])
    rng = np.random.default_rng(3)
    state, frame = ss.start(model, rng)
    filt, _ = dr.step(dr.DrState(), frame.compass)
    for _ in range(150):
        state, frame = ss.step(state, driver.command(state.pose), model, rng)
        filt, _ = dr.step(filt, frame.compass)
        filt, poses = dr.step(filt, frame.odometry)
    last = poses[-1]
    # the second part
    rng2 = np.random.default_rng((3, state.tick))
    state2, frame2 = ss.start(model, rng2, pose=state.pose, tick=state.tick)
    assert frame2.tick == 150 and frame2.truth.stamp == pytest.approx(15.0) and frame2.compass.seq == 150
    assert (frame2.truth.pose.x_m, frame2.truth.pose.y_m) == (state.pose[0], state.pose[1])
    assert frame2.odometry is None and frame2.sonar is not None
    raw = (last.raw.x_m, last.raw.y_m, last.raw.heading_rad)
    filt2 = dr.continued_state((last.compass.x_m, last.compass.y_m), raw, steps=last.steps,
                               path_length_m=last.path_length_m)
    filt2, first = dr.step(filt2, frame2.compass)
    assert (first[0].compass.x_m, first[0].compass.y_m) == (last.compass.x_m, last.compass.y_m)
    assert first[0].steps == 150 and first[0].path_length_m == last.path_length_m
    filt2, again = dr.step(filt2, frame2.compass)  # the start frame repeats until the first command
    assert again[0].steps == 150
    for _ in range(50):
        state2, frame2 = ss.step(state2, driver.command(state2.pose), model, rng2)
        filt2, _ = dr.step(filt2, frame2.compass)
        filt2, poses2 = dr.step(filt2, frame2.odometry)
    assert state2.tick == 200 and poses2[-1].stamp == pytest.approx(20.0) and poses2[-1].steps == 200
    drift = math.hypot(poses2[-1].compass.x_m - state2.pose[0], poses2[-1].compass.y_m - state2.pose[1])
    before = math.hypot(last.compass.x_m - state.pose[0], last.compass.y_m - state.pose[1])
    assert drift < before + 0.5  # dead reckoning went on from its own frame, not from the origin
    moved = math.hypot(state2.pose[0] - state.pose[0], state2.pose[1] - state.pose[1])
    assert moved > 0.5 and poses2[-1].path_length_m > last.path_length_m + 0.5


def test_dr_uses_the_mean_heading_of_a_step():
    state, out = _feed(dr.DrState(), [_cmp(0, 0.0), _cmp(1, math.pi / 2), _odo(0, 1.0, math.pi / 2)])
    assert (out[-1].compass.x_m, out[-1].compass.y_m) == pytest.approx((math.sqrt(0.5), math.sqrt(0.5)))


def test_dr_odometry_before_its_compass_reading_waits():
    state, out = _feed(dr.DrState(), [_cmp(0, 0.0), _odo(0, 0.5)])
    assert len(out) == 1 and len(state.pending) == 1
    state, out = _feed(state, [_cmp(1, 0.0)])
    assert len(out) == 1 and out[0].compass.x_m == pytest.approx(0.5) and not state.pending


def test_dr_counts_gaps_duplicates_and_reordering():
    msgs = [_cmp(0, 0.0), _cmp(0, 0.0), _cmp(0, 0.0)]  # tick 0 repeated while the run starts
    msgs += [_cmp(1, 0.0), _odo(0, 0.1)]
    msgs += [_odo(1, 0.1)]  # its compass reading (seq 2) is lost...
    msgs += [_cmp(3, 0.0), _odo(2, 0.1)]  # ...which the next reading shows
    msgs += [_cmp(4, 0.0), _cmp(5, 0.0), _odo(4, 0.1)]  # odometry seq 3 goes missing
    state, out = _feed(dr.DrState(), msgs)
    assert [p.steps for p in out[:3]] == [0, 0, 0]  # the start phase repeats the initial pose
    assert state.compass.duplicates == 2 and state.compass.gaps == 1
    assert state.odometry.gaps == 1 and out[-1].gaps == 2 and out[-1].steps == 4
    assert out[-1].compass.x_m == pytest.approx(0.4)
    state, out = _feed(state, [_odo(3, 0.1)])  # the missing step arrives late
    assert state.odometry.reordered == 1 and state.odometry.gaps == 0
    assert out[-1].steps == 5 and out[-1].compass.x_m == pytest.approx(0.5) and out[-1].gaps == 1
    state, out = _feed(state, [_odo(3, 0.1)])  # and once more: a duplicate, ignored
    assert out == [] and state.odometry.duplicates == 1


def test_dr_odometry_before_the_first_compass_reading_is_dropped():
    state, out = _feed(dr.DrState(), [_odo(4, 0.1), _odo(5, 0.1), _cmp(6, 1.0), _odo(6, 0.1), _cmp(7, 1.0)])
    assert state.dropped == 2 and out[-1].steps == 1
    assert out[-1].compass.x_m == pytest.approx(0.1 * math.cos(1.0))


def test_dr_rejects_other_messages():
    with pytest.raises(TypeError):
        dr.step(dr.DrState(), "not a message")


def test_track_sequence_numbers():
    s = dr.StreamSeq()
    verdicts = []
    for seq in (5, 6, 9, 7, 7, 10, 3):
        s, v = dr.track(s, seq, 16)
        verdicts.append(v)
    assert verdicts == [dr.NEW, dr.NEW, dr.NEW, dr.LATE, dr.DUPLICATE, dr.NEW, dr.DUPLICATE]
    assert s.gaps == 1 and s.reordered == 1 and s.duplicates == 2 and s.missing == {8}


# -- the route driver ---------------------------------------------------------------------------------------


def test_route_driver_turns_then_drives_and_finishes():
    pts = np.array([[1.0, 0.0], [1.0, 1.0]])
    state, (v, w) = drive(RouteState(), (0.0, 0.0, math.pi), pts, loop=False)
    assert v == 0.0 and abs(w) == RouteParams().max_turn_radps  # facing away: turn in place first
    state, (v, w) = drive(RouteState(), (0.0, 0.0, 0.0), pts, loop=False)
    assert v == pytest.approx(0.5) and w == 0.0
    state, _ = drive(state, (1.0, 0.05, math.pi / 2), pts, loop=False)
    assert state.index == 1
    state, cmd = drive(state, (1.0, 0.95, math.pi / 2), pts, loop=False)
    assert state.done and cmd == (0.0, 0.0)


def test_every_builtin_route_is_driven_without_collision():
    for name in ("orebro-office", "manchester-corridors", "campus"):
        world = load_world(name)
        model = ss.SimModel(world)
        for rname, pts in world.routes.items():
            rng = np.random.default_rng(0)
            state, _ = ss.start(model, rng)
            state = ss.SimState(tick=0, pose=(pts[0][0], pts[0][1], 0.0), travel_since_scan_m=0.0,
                                 time_since_scan_s=0.0, scans=1, collisions=0, path_length_m=0.0)
            driver = RouteDriver(pts, loop=True)
            while driver.state.laps < 1 and state.tick < 20000:
                state, _ = ss.step(state, driver.command(state.pose), model, rng)
            assert driver.state.laps == 1, (name, rname)
            assert state.collisions == 0, (name, rname)


# -- the long loop: compass dead reckoning against raw odometry (Figure 6) -------------------------------


def _long_loop(laps, seed=1):
    """Drive the outer loop of manchester-corridors; errors of both DR poses against the truth.

    Rows: distance travelled, |compass DR heading error|, compass DR position error, |raw heading
    error| (unwrapped: it keeps growing past 180 deg), raw position error.
    """
    model = ss.SimModel(MANCHESTER)
    rng = np.random.default_rng(seed)
    state, frame = ss.start(model, rng)
    filt, _ = dr.step(dr.DrState(), frame.compass)
    driver = RouteDriver(MANCHESTER.routes["outer-loop"])
    x0, y0, _ = MANCHESTER.start
    rows = []
    raw_turned = true_turned = 0.0
    while driver.state.laps < laps:
        before = state.pose[2]
        state, frame = ss.step(state, driver.command(state.pose), model, rng)
        filt, _ = dr.step(filt, frame.compass)
        filt, poses = dr.step(filt, frame.odometry)
        p = poses[-1]
        tx, ty, th = state.pose
        raw_turned += frame.odometry.rotation_rad
        true_turned += wrap_angle(th - before)
        rows.append((state.path_length_m,
                     abs(wrap_angle(p.compass.heading_rad - th)),
                     math.hypot(p.compass.x_m + x0 - tx, p.compass.y_m + y0 - ty),
                     abs(raw_turned - true_turned),
                     math.hypot(p.raw.x_m + x0 - tx, p.raw.y_m + y0 - ty)))
    return np.array(rows)


def _loop_report(r):
    n = len(r)
    out = {}
    for q in (0.25, 0.5, 0.75, 1.0):
        i = int(q * n) - 1
        out[q] = dict(dist_m=r[i, 0], compass_heading_max_deg=math.degrees(r[: i + 1, 1].max()),
                      compass_pos_m=r[i, 2], raw_heading_deg=math.degrees(r[i, 3]), raw_pos_m=r[i, 4])
    return out


def test_long_loop_compass_heading_bounded_raw_grows():
    r = _long_loop(laps=2)
    rep = _loop_report(r)
    for q, v in rep.items():
        print(f"{q:4.2f}: {v}")
    total = rep[1.0]["dist_m"]
    assert total > 230  # two laps of about 120 m
    # compass heading error: bounded by noise plus the largest disturbance (15 deg), never growing
    first, second = r[: len(r) // 2, 1], r[len(r) // 2:, 1]
    assert math.degrees(first.max()) < 25 and math.degrees(second.max()) < 25
    assert math.degrees(np.sqrt(np.mean(r[:, 1] ** 2))) < 6
    # raw heading error grows with the distance: about 1 deg per metre of drift
    assert rep[0.5]["raw_heading_deg"] > 60
    assert rep[1.0]["raw_heading_deg"] > 1.6 * rep[0.5]["raw_heading_deg"]
    # compass position error grows about linearly with distance (a few percent), not faster
    assert rep[1.0]["compass_pos_m"] < 0.03 * total
    assert rep[1.0]["compass_pos_m"] < 3.0 * max(rep[0.5]["compass_pos_m"], 0.5)
    assert max(r[:, 2] / np.maximum(r[:, 0], 10.0)) < 0.06
    # and raw odometry ends far worse
    assert r[:, 4].max() > 5 * r[:, 2].max()


@pytest.mark.slow
def test_long_loop_many_laps_and_seeds():
    for seed in (2, 3, 4):
        r = _long_loop(laps=5, seed=seed)
        total = r[-1, 0]
        assert math.degrees(r[:, 1].max()) < 25
        assert r[-1, 2] < 0.03 * total
        assert math.degrees(r[-1, 3]) > 300
