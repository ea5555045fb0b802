"""The recorder as its own process: scripted messages in, a valid Rerun file out, read back."""

from __future__ import annotations

import math
import random
import shutil
import signal
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import rerun as rr

from messages import topics
from messages.codec import codec
from messages.types import (
    DeadReckonedPose,
    ExplorationStatus,
    Health,
    Hypothesis,
    LinkInferred,
    LinkMeasured,
    LocalizationBelief,
    MapUpdate,
    NoiseParams,
    OccupancyGrid,
    PlaceConfirmed,
    PlacePosition,
    PlacePredicted,
    Pose2,
    SonarScan,
    TruthPose,
)
from services.runtime import AliveWatcher, query
from tests.conftest import wait_until

ROBOT = "rectest"
RERUN = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun") or "rerun"
NOISE = NoiseParams(s_dd=0.01, s_aa=0.001, s_da=0.0)
GRID = OccupancyGrid(resolution_m=0.5, origin_x_m=-1.0, origin_y_m=-2.0, width=4, height=3,
                     cells=bytes([0, 0, 100, 255] * 3), version=1)
# Record every message: no rate limits on simulated time, a grid on every map version.
FAST = ["--param", "live_period_s=0", "--param", "trail_period_s=0", "--param", "trail_spacing_m=0.01",
        "--param", "grid_every_versions=1", "--param", "map_period_s=0"]


def start_recorder(processes, hub, out: Path, *extra: str):
    session, endpoint = hub
    watcher = AliveWatcher(session, ROBOT)
    proc = processes.python("services.recorder", "--robot", ROBOT, "--connect", endpoint,
                            "--listen", "tcp/127.0.0.1:0", "--out", str(out), *FAST, *extra)
    try:
        assert watcher.wait_alive(["recorder"], timeout_s=20), _output(proc)
    finally:
        watcher.close()
    return proc


def _output(proc: subprocess.Popen) -> str:
    if proc.poll() is None:
        return "recorder still running"
    return proc.stdout.read().decode(errors="replace") if proc.stdout else ""


def health(session) -> Health:
    return query(session, topics.health(ROBOT, "recorder"), type_=Health)


class Script:
    """Publishers on the recorder's topics, declared once, each waiting for the recorder to match."""

    def __init__(self, session) -> None:
        self.session = session
        self.pubs = {}
        self.sent = 0

    def put(self, key: str, msg) -> None:
        pub = self.pubs.get(key)
        if pub is None:
            pub = self.pubs[key] = self.session.declare_publisher(key)
            assert wait_until(lambda: pub.matching_status, 10), f"nobody subscribes {key}"
        pub.put(codec(type(msg)).encode(msg))
        self.sent += 1

    def sync(self) -> None:
        """Wait until the recorder has taken in everything sent so far.

        zenoh hands each subscriber's samples over in its own thread: order holds per key, not across
        keys, so a script whose steps depend on each other waits between them.
        """
        assert wait_until(lambda: health(self.session).detail["handled"] == self.sent, 10), health(self.session)

    def raw(self, key: str, data: bytes) -> None:
        self.pubs[key].put(data)

    def close(self) -> None:
        for pub in self.pubs.values():
            pub.undeclare()


def verify(path: Path) -> subprocess.CompletedProcess:
    return subprocess.run([RERUN, "rrd", "verify", str(path)], capture_output=True, text=True, timeout=60)


def read_recording(path: Path) -> dict[str, list[tuple[float | None, dict]]]:
    """Entity path -> rows ``(sim_time seconds or None for static, {component: value})`` in time order."""
    rows: dict[str, list[tuple[float | None, dict]]] = defaultdict(list)
    for chunk in rr.chunk.RrdReader(path).store().stream().to_chunks():
        batch = chunk.to_record_batch()
        names = [n for n in batch.schema.names if n not in ("rerun.controls.RowId", "log_time", "sim_time",
                                                             "map_version")]
        times = (batch.column("sim_time").cast("int64").to_pylist() if "sim_time" in batch.schema.names
                 else [None] * batch.num_rows)
        columns = {n: batch.column(n).to_pylist() for n in names}
        for i, t in enumerate(times):
            values = {n: columns[n][i] for n in names if columns[n][i] is not None}
            rows[chunk.entity_path].append((None if t is None else t * 1e-9, values))
    for entity_rows in rows.values():
        entity_rows.sort(key=lambda r: -1.0 if r[0] is None else r[0])
    return rows


def last(rows, entity: str, component: str):
    """The latest logged value of ``component`` at ``entity``."""
    values = [v[component] for _, v in rows[f"/{entity}"] if component in v]
    assert values, f"nothing logged for /{entity} {component}"
    return values[-1]


def test_records_the_map_and_closes_the_file_on_sigterm(hub, processes, tmp_path):
    session, _ = hub
    grid_queries = []

    def on_grid(q) -> None:
        grid_queries.append(str(q.parameters))
        q.reply(q.key_expr, codec(OccupancyGrid).encode(GRID))

    grid_server = session.declare_queryable(topics.map_grid(ROBOT), on_grid)
    proc = start_recorder(processes, hub, tmp_path)
    s = Script(session)
    try:
        for i in range(5):  # the robot drives along +x, the raw odometry drifts to +y
            t = 0.1 * i
            s.put(topics.truth_pose(ROBOT), TruthPose(stamp=t, seq=i,
                                                      pose=Pose2(x_m=0.5 * i, y_m=0.0, heading_rad=0.0)))
            s.put(topics.dr_pose(ROBOT), DeadReckonedPose(
                stamp=t + 0.01, seq=i, compass=Pose2(x_m=0.5 * i, y_m=0.01 * i, heading_rad=0.0),
                raw=Pose2(x_m=0.5 * i, y_m=0.1 * i, heading_rad=0.1 * i), steps=10 * i, path_length_m=0.5 * i))
        s.put(topics.places_confirmed(ROBOT), PlaceConfirmed(stamp=0.5, seq=0, place_id=0, x_m=0.0, y_m=0.0))
        s.put(topics.places_confirmed(ROBOT), PlaceConfirmed(stamp=0.6, seq=1, place_id=1, x_m=2.0, y_m=0.0))
        s.sync()  # the places before what refers to them
        s.put(topics.places_predicted(ROBOT), PlacePredicted(stamp=0.7, seq=0, place_id=2, x_m=2.0, y_m=2.0,
                                                             parent_id=1))
        s.put(topics.links_measured(ROBOT), LinkMeasured(stamp=0.8, seq=0, from_id=0, to_id=1, d_m=2.0,
                                                         theta_rad=0.0, steps=20, mean_step_m=0.1))
        s.put(topics.links_inferred(ROBOT), LinkInferred(stamp=0.9, seq=0, from_id=1, to_id=2, d_m=2.0))
        s.put(topics.sonar(ROBOT), SonarScan(stamp=0.95, seq=0, angles_rad=[0.0, math.pi / 2], ranges_m=[1.0, 5.0],
                                             beam_width_rad=0.4, min_range_m=0.1, max_range_m=5.0))
        s.put(topics.localization(ROBOT), LocalizationBelief(
            stamp=0.97, seq=0, place_id=1, probability=0.9, offset_x_m=0.1, offset_y_m=0.0, offset_var_m2=0.01,
            hypotheses=[Hypothesis(place_id=1, probability=0.9), Hypothesis(place_id=0, probability=0.1)]))
        for version, (energy, iterations, x1) in enumerate([(3.5, 7, 2.1), (1.25, 4, 2.2)], start=1):
            s.sync()
            s.put(topics.map_update(ROBOT), MapUpdate(
                stamp=float(version), seq=version - 1, version=version,
                changed=[PlacePosition(place_id=0, x_m=0.0, y_m=0.0), PlacePosition(place_id=1, x_m=x1, y_m=0.1)],
                full=True, places=2, links=1, energy=energy, iterations=iterations, method="sweep", noise=NOISE))
        s.put(topics.exploration_status(ROBOT), ExplorationStatus(stamp=2.5, seq=0, complete=True, confirmed=2,
                                                                  predicted=1, target_id=-1))
        s.sync()
        assert wait_until(lambda: health(session).detail.get("grids_logged", 0) >= 2, 10), health(session)

        # garbage on a subscribed key: counted, not fatal
        rng = random.Random(3)
        for _ in range(20):
            s.raw(topics.map_update(ROBOT), bytes(rng.randrange(256) for _ in range(rng.randrange(1, 40))))
        assert wait_until(lambda: health(session).decode_errors == 20, 10), health(session)
        h = health(session)
        assert proc.poll() is None and h.detail["handler_errors"] == 0 and h.detail["grid_failures"] == 0
        assert h.detail["places"] == 2 and h.detail["predicted"] == 1 and h.detail["map_version"] == 2
    finally:
        s.close()
        grid_server.undeclare()

    assert processes.stop(proc, signal.SIGTERM) == 0, _output(proc)
    rrd = tmp_path / "recording.rrd"
    result = verify(rrd)
    assert result.returncode == 0, result.stdout + result.stderr
    assert grid_queries, "the grid was never asked for"

    rows = read_recording(rrd)
    # places with ids, at their relaxed coordinates; the predicted one moved with its parent
    np.testing.assert_allclose(last(rows, "map/places/confirmed", "Points2D:positions"), [[0, 0], [2.2, 0.1]],
                               atol=1e-6)
    assert last(rows, "map/places/confirmed", "Points2D:labels") == ["0", "1"]
    np.testing.assert_allclose(last(rows, "map/places/predicted", "Points2D:positions"), [[2.2, 2.1]], atol=1e-6)
    assert last(rows, "map/places/predicted", "Points2D:labels") == ["2"]
    # the places as first confirmed, before any map update
    first = [v for t, v in rows["/map/places/confirmed"] if t is not None and t < 1.0]
    np.testing.assert_allclose(first[-1]["Points2D:positions"], [[0, 0], [2.0, 0.0]], atol=1e-6)
    # traversed and inferred links apart, drawn differently
    np.testing.assert_allclose(last(rows, "map/links/traversed", "LineStrips2D:strips"), [[[0, 0], [2.2, 0.1]]],
                               atol=1e-6)
    np.testing.assert_allclose(last(rows, "map/links/inferred", "LineStrips2D:strips"),
                               [[[2.2, 0.1], [2.2, 2.1]]], atol=1e-6)
    assert (last(rows, "map/links/traversed", "LineStrips2D:colors")
            != last(rows, "map/links/inferred", "LineStrips2D:colors"))
    assert (last(rows, "map/links/traversed", "LineStrips2D:radii")
            != last(rows, "map/links/inferred", "LineStrips2D:radii"))
    # the three poses with their trails
    np.testing.assert_allclose(last(rows, "map/robot/truth/pose", "Arrows2D:origins"), [[2.0, 0.0]], atol=1e-6)
    np.testing.assert_allclose(last(rows, "map/robot/compass/pose", "Arrows2D:origins"), [[2.0, 0.04]], atol=1e-6)
    np.testing.assert_allclose(last(rows, "map/robot/raw/pose", "Arrows2D:origins"), [[2.0, 0.4]], atol=1e-6)
    np.testing.assert_allclose(last(rows, "map/robot/raw/trail", "LineStrips2D:strips"),
                               [[[0.5 * i, 0.1 * i] for i in range(5)]], atol=1e-6)
    # sonar rays from the true pose: forward 1 m (echo), left 5 m (none)
    np.testing.assert_allclose(last(rows, "map/sonar/rays", "LineStrips2D:strips"),
                               [[[2.0, 0.0], [3.0, 0.0]], [[2.0, 0.0], [2.0, 5.0]]], atol=1e-6)
    np.testing.assert_allclose(last(rows, "map/sonar/echoes", "Points2D:positions"), [[3.0, 0.0]], atol=1e-6)
    # the belief at place 1 (as confirmed then) plus the offset
    np.testing.assert_allclose(last(rows, "map/belief/estimate", "Ellipses2D:centers"), [[2.1, 0.0]], atol=1e-6)
    # energy and iterations as time series on simulated time
    energy = [(t, v["Scalars:scalars"]) for t, v in rows["/plots/energy"] if "Scalars:scalars" in v]
    assert energy == [(1.0, [3.5]), (2.0, [1.25])]
    iterations = [(t, v["Scalars:scalars"]) for t, v in rows["/plots/iterations"] if "Scalars:scalars" in v]
    assert iterations == [(1.0, [7.0]), (2.0, [4.0])]
    # the occupancy grid image placed in world coordinates
    assert last(rows, "map/grid", "Transform3D:translation") == [pytest.approx([-1.0, -2.0, 0.0])]
    assert last(rows, "map/grid", "Transform3D:scale") == [pytest.approx([0.5, 0.5, 1.0])]
    assert last(rows, "map/grid", "Image:buffer") == [[255, 255, 0, 128] * GRID.height]  # free, occupied, unknown
    # the y-up flip of the map and the events
    assert last(rows, "map", "Transform3D:scale") == [pytest.approx([1.0, -1.0, 1.0])]
    texts = [v["TextLog:text"] for _, v in rows["/events"] if "TextLog:text" in v]
    assert any("place 1 confirmed" in t[0] for t in texts) and any("exploration complete" in t[0] for t in texts)
    # a default blueprint travels with the recording
    assert rr.chunk.RrdReader(rrd).blueprints()


def test_map_changes_between_updates_are_logged_once_per_period(hub, processes, tmp_path):
    """With ``map_period_s`` the places and links are logged at the first change of a period and at its
    last, at the last change's time; a map update logs them at once, and the stop logs what is left."""
    session, _ = hub
    proc = start_recorder(processes, hub, tmp_path, "--param", "map_period_s=10")
    s = Script(session)
    try:
        s.put(topics.places_confirmed(ROBOT), PlaceConfirmed(stamp=0.5, seq=0, place_id=0, x_m=0.0, y_m=0.0))
        s.sync()
        s.put(topics.places_confirmed(ROBOT), PlaceConfirmed(stamp=0.6, seq=1, place_id=1, x_m=2.0, y_m=0.0))
        s.sync()
        s.put(topics.places_predicted(ROBOT), PlacePredicted(stamp=0.7, seq=0, place_id=2, x_m=2.0, y_m=2.0,
                                                             parent_id=1))
        s.sync()  # order holds per key only: the link must come last
        s.put(topics.links_measured(ROBOT), LinkMeasured(stamp=0.8, seq=0, from_id=0, to_id=1, d_m=2.0,
                                                         theta_rad=0.0, steps=20, mean_step_m=0.1))
        s.sync()
        s.put(topics.map_update(ROBOT), MapUpdate(
            stamp=1.0, seq=0, version=1, changed=[PlacePosition(place_id=1, x_m=2.2, y_m=0.1)], full=False,
            places=2, links=1, energy=1.0, iterations=3, method="sweep", noise=NOISE))
        s.sync()
        s.put(topics.places_predicted(ROBOT), PlacePredicted(stamp=1.5, seq=1, place_id=3, x_m=0.0, y_m=2.0,
                                                             parent_id=0))
        s.sync()
        h = health(session)
        assert h.detail["places"] == 2 and h.detail["predicted"] == 2 and h.detail["handler_errors"] == 0, h
    finally:
        s.close()
    assert processes.stop(proc, signal.SIGTERM) == 0, _output(proc)
    result = verify(tmp_path / "recording.rrd")
    assert result.returncode == 0, result.stdout + result.stderr

    rows = read_recording(tmp_path / "recording.rrd")
    confirmed = [(t, v["Points2D:positions"]) for t, v in rows["/map/places/confirmed"] if t is not None]
    # at the first change (0.5), at the last change before the update (0.8), at the update (1.0), and
    # at the change after it (1.5), logged on the way out
    assert [t for t, _ in confirmed] == pytest.approx([0.5, 0.8, 1.0, 1.5])
    np.testing.assert_allclose(confirmed[1][1], [[0, 0], [2.0, 0.0]], atol=1e-6)
    np.testing.assert_allclose(confirmed[2][1], [[0, 0], [2.2, 0.1]], atol=1e-6)
    # the labels in force at each time: a row carries them only when the ids changed
    predicted, labels, relabelled = [], None, []
    for t, v in rows["/map/places/predicted"]:
        if t is not None:
            relabelled.append("Points2D:labels" in v)
            labels = v.get("Points2D:labels", labels)
            predicted.append((t, labels))
    assert predicted[1] == (pytest.approx(0.8), ["2"]) and predicted[-1] == (pytest.approx(1.5), ["2", "3"])
    assert relabelled == [True, True, False, True]  # ids [] (0.5), [2] (0.8), [2] (the update), [2, 3]
    traversed = [t for t, v in rows["/map/links/traversed"] if t is not None and v.get("LineStrips2D:strips")]
    assert traversed and traversed[0] == pytest.approx(0.8)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_recording_stays_valid_after_a_signal(hub, processes, tmp_path, sig):
    session, _ = hub
    proc = start_recorder(processes, hub, tmp_path)
    s = Script(session)
    try:
        for i in range(50):
            s.put(topics.truth_pose(ROBOT), TruthPose(stamp=0.01 * i, seq=i, pose=Pose2(x_m=0.01 * i, y_m=0.0,
                                                                                         heading_rad=0.0)))
        s.sync()
    finally:
        s.close()
    assert processes.stop(proc, sig) == 0, _output(proc)
    result = verify(tmp_path / "recording.rrd")
    assert result.returncode == 0, result.stdout + result.stderr
    rows = read_recording(tmp_path / "recording.rrd")
    assert len([t for t, _ in rows["/map/robot/truth/pose"] if t is not None]) == 50


def test_duration_ends_the_run_with_a_valid_file(processes, tmp_path):
    rrd = tmp_path / "sub" / "run.rrd"
    proc = processes.python("services.recorder", "--robot", ROBOT, "--listen", "tcp/127.0.0.1:0",
                            "--rrd", str(rrd), "--duration-s", "0.5")
    out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out.decode()
    result = verify(rrd)
    assert result.returncode == 0, result.stdout + result.stderr


def test_bad_parameters_are_a_clear_error(processes, tmp_path):
    proc = processes.python("services.recorder", "--out", str(tmp_path), "--param", "sonar_pose=lidar")
    out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 2 and "sonar_pose" in out.decode()
    assert not (tmp_path / "recording.rrd").exists()


def test_max_sim_time_ends_the_run(hub, processes, tmp_path):
    session, _ = hub
    proc = start_recorder(processes, hub, tmp_path, "--max-sim-time", "1.0")
    s = Script(session)
    try:
        s.put(topics.truth_pose(ROBOT), TruthPose(stamp=0.5, seq=0, pose=Pose2(x_m=1.0, y_m=0.0, heading_rad=0.0)))
        s.sync()
        s.put(topics.truth_pose(ROBOT), TruthPose(stamp=1.5, seq=1, pose=Pose2(x_m=2.0, y_m=0.0, heading_rad=0.0)))
        proc.wait(15)
    finally:
        s.close()
    assert proc.returncode == 0, _output(proc)
    assert verify(tmp_path / "recording.rrd").returncode == 0
    rows = read_recording(tmp_path / "recording.rrd")
    assert [t for t, _ in rows["/map/robot/truth/pose"] if t is not None] == [0.5]  # None: its style, static


def test_an_exception_still_leaves_a_valid_file(tmp_path):
    import zenoh

    from services.recorder.core import RecorderParams
    from services.recorder.node import run
    from services.runtime import loopback_config

    session = zenoh.open(loopback_config())
    session.close()  # declaring anything on it fails
    rrd = tmp_path / "recording.rrd"
    with pytest.raises(zenoh.ZError):
        run(session, RecorderParams(), rrd_path=rrd, robot=ROBOT)
    result = verify(rrd)
    assert result.returncode == 0, result.stdout + result.stderr


def test_a_missing_grid_is_counted_not_fatal(hub, processes, tmp_path):
    session, _ = hub
    proc = start_recorder(processes, hub, tmp_path, "--param", "grid_timeout_s=0.3")
    s = Script(session)
    try:
        s.put(topics.map_update(ROBOT), MapUpdate(stamp=1.0, seq=0, version=1, changed=[], full=True, places=0,
                                                  links=0, energy=0.0, iterations=0, method="sweep", noise=NOISE))
        s.sync()
        assert wait_until(lambda: health(session).detail["grid_failures"] == 1, 10), health(session)
        h = health(session)
        assert h.detail["grid_queries"] == 1 and h.detail["grids_logged"] == 0 and proc.poll() is None
    finally:
        s.close()
    assert processes.stop(proc, signal.SIGTERM) == 0
    assert verify(tmp_path / "recording.rrd").returncode == 0
