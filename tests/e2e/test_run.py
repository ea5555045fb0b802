"""``relaxmap run`` end to end: every service as a process, the outputs written and readable."""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from services.launch.evaluate import place_errors_m
from services.relaxer.g2o import read_g2o
from services.relaxer.mapjson import read_map_json

RERUN = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")


def _run(out: Path, *extra: str, timeout_s: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "services.cli", "run", "--port", "0", "--headless", "--out",
                           str(out), *extra], capture_output=True, text=True, timeout=timeout_s,
                          start_new_session=True)


def _check_outputs(out: Path) -> dict:
    summary = json.loads((out / "summary.json").read_text())
    for key in ("world", "seed", "places", "links_traversed", "links_inferred", "sim_time_s", "wall_time_s",
                "exploration_complete", "energy", "ate_relaxed_m", "ate_dead_reckoning_m", "iterations",
                "links_measured", "links_lost", "map_scale", "map_turn_deg", "ate_relaxed_similarity_m"):
        assert key in summary, key
    assert 0.9 < summary["map_scale"] < 1.1 and abs(summary["map_turn_deg"]) < 10, summary
    assert summary["ate_relaxed_similarity_m"] <= summary["ate_relaxed_m"]  # a turn of 0 and a scale of 1 are candidates
    m = read_map_json(out / "map.json")
    assert m.graph.n_places == summary["places"] and m.graph.n_links == summary["links_traversed"]
    g2o = read_g2o(out / "map.g2o")
    assert g2o.graph.n_poses == summary["places"]
    yaml = (out / "grid.yaml").read_text()
    assert "image: grid.png" in yaml and "resolution: 0.15" in yaml
    for png in ("grid.png", "grid_dead_reckoning.png"):
        img = np.asarray(Image.open(out / png))
        assert img.ndim == 2 and img.size > 1
        occ = (255.0 - img) / 255.0  # map_server's reading (negate 0) against grid.yaml's thresholds
        assert (occ > 0.65).any() and (occ < 0.196).any(), f"{png} shows no wall or no free space"
    assert RERUN is not None, "the rerun command comes with rerun-sdk"
    verify = subprocess.run([RERUN, "rrd", "verify", str(out / "recording.rrd")], capture_output=True, text=True,
                            timeout=120)
    assert verify.returncode == 0, verify.stderr
    return summary


def test_run_writes_every_output(tmp_path):
    out = tmp_path / "run"
    done = _run(out, "--world", "orebro-office", "--seed", "1", "--max-sim-time", "90")
    assert done.returncode == 0, done.stderr[-3000:]
    summary = _check_outputs(out)
    assert summary["world"] == "orebro-office" and summary["seed"] == 1
    assert summary["sim_time_s"] >= 89.0
    assert summary["places"] >= 10 and summary["links_traversed"] >= summary["places"] - 1
    assert summary["links_lost"] == 0, summary
    assert all(n == 0 for n in summary["restarts"].values())
    for log in (out / "logs").iterdir():
        assert "Traceback" not in log.read_text(), log.read_text()[-2000:]


def test_a_run_on_the_bus_is_the_in_process_loop(tmp_path):
    """Six processes exchanging messages in whatever order zenoh delivers them measure the same links,
    to the last bit, as the in-process loop stepping the same cores in its fixed order, and end with
    the same map: a run is a function of the world, the parameters and the seed."""
    from services.launch.inprocess import InProcessParams, run_world

    out = tmp_path / "run"
    done = _run(out, "--world", "orebro-office", "--seed", "2", "--max-sim-time", "300")
    assert done.returncode == 0, done.stderr[-3000:]
    bus = [json.loads(line) for line in (out / "links_measured.jsonl").read_text().splitlines()]
    loop = run_world("orebro-office", InProcessParams(seed=2, max_sim_time_s=300.0))
    logs = "\n".join(line for log in (out / "logs").iterdir() for line in log.read_text().splitlines()
                     if "timeouts" in line or "WARNING" in line)
    assert len(loop.links) > 50, "too short a run to say anything"
    assert [(b["from_id"], b["to_id"], b["d_m"], b["theta_rad"], b["steps"]) for b in bus] == [
        (lk.from_id, lk.to_id, lk.d_m, lk.theta_rad, lk.steps) for lk in loop.links], logs[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["places"] == len(loop.places)
    written = {p["id"]: (p["x"], p["y"]) for p in json.loads((out / "map.json").read_text())["places"]}
    assert written == loop.relaxed  # and the map at rest is the same minimum of those links


# two rooms joined by a door: explored to the end in about 250 s of simulated time
TWO_ROOMS = {"name": "two-rooms", "walls": [[0, 0, 8, 0], [8, 0, 8, 5], [8, 5, 0, 5], [0, 5, 0, 0], [4, 0, 4, 2],
                                            [4, 3, 4, 5]],
             "start": [1.5, 2.5, 0.0], "magnetic_disturbances": [], "routes": {}}


def test_a_run_on_the_bus_ends_where_the_loop_does(tmp_path):
    """The explorer's last command ends the simulation at the tick the exploration became complete:
    no tick, scan or link after it, so the whole run is the loop's, to its end."""
    from services.launch.inprocess import InProcessParams, run_world

    world = tmp_path / "two-rooms.json"
    world.write_text(json.dumps(TWO_ROOMS))
    out = tmp_path / "run"
    done = _run(out, "--world", str(world), "--seed", "0")
    assert done.returncode == 0, done.stderr[-3000:]
    loop = run_world(str(world), InProcessParams(seed=0, max_sim_time_s=3000.0))
    assert loop.complete and len(loop.links) > 20
    summary = json.loads((out / "summary.json").read_text())
    assert summary["exploration_complete"] and summary["sim_time_s"] == pytest.approx(
        loop.complete_tick * InProcessParams().sim.dt_s)
    bus = [json.loads(line) for line in (out / "links_measured.jsonl").read_text().splitlines()]
    assert [(b["from_id"], b["to_id"], b["d_m"], b["theta_rad"], b["steps"]) for b in bus] == [
        (lk.from_id, lk.to_id, lk.d_m, lk.theta_rad, lk.steps) for lk in loop.links]
    written = {p["id"]: (p["x"], p["y"]) for p in json.loads((out / "map.json").read_text())["places"]}
    assert written == loop.relaxed


def _stored_places(store: Path) -> int:
    """Places the relaxer has stored so far (read-only; 0 while the store does not exist yet)."""
    if not store.exists():
        return 0
    try:
        with sqlite3.connect(f"file:{store}?mode=ro", uri=True, timeout=1) as db:
            return db.execute("SELECT count(*) FROM places").fetchone()[0]
    except sqlite3.OperationalError:  # the schema is not written yet
        return 0


def _interrupt_once_mapped(out: Path, places: int, *extra: str) -> tuple[int, str]:
    """Start a run, Ctrl-C it (SIGINT to its process group) once the store holds ``places`` places;
    return its exit code and standard error."""
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", "--port", "0", "--headless", "--out",
                             str(out), "--max-sim-time", "100000", *extra], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and _stored_places(out / "map.sqlite") < places:
            time.sleep(0.2)
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return proc.returncode, err


def test_ctrl_c_stops_cleanly_and_writes_outputs(tmp_path):
    out = tmp_path / "run"
    code, err = _interrupt_once_mapped(out, 2)
    assert code == 0, err[-3000:]
    assert "stopped by signal" in err
    summary = _check_outputs(out)
    assert summary["exploration_complete"] is False and summary["places"] >= 1


def test_a_service_that_cannot_start_fails_the_run(tmp_path):
    graph = json.loads((Path(__file__).resolve().parents[2] / "deploy" / "graph.json").read_text())
    for s in graph["services"]:
        if s["name"] == "relaxer":
            s["args"] = ["--store", "/proc/no/such/dir/map.sqlite"]
            s["restart"]["max_restarts"] = 1
            s["restart"]["backoff_s"] = 0.1
    bad = tmp_path / "graph.json"
    bad.write_text(json.dumps(graph))
    done = _run(tmp_path / "run", "--graph", str(bad), "--max-sim-time", "30", "--start-timeout-s", "30",
                timeout_s=120)
    assert done.returncode == 1
    assert "relaxer" in done.stderr and "was not restarted" in done.stderr


def test_bad_world_is_a_clear_error(tmp_path):
    world = tmp_path / "w.json"
    world.write_text('{"name": "x", "walls": [], "start": [0, 0, 0]}')
    done = _run(tmp_path / "run", "--world", str(world), timeout_s=60)
    assert done.returncode == 1 and "no walls" in done.stderr
    done = _run(tmp_path / "run", "--world", "atlantis", timeout_s=60)
    assert done.returncode == 1 and "neither a built-in world" in done.stderr


# Simulated seconds of the long run: CI runs it at this small size; RELAXMAP_E2E_SIM_S=7200 runs a
# whole exploration.
LONG_RUN_SIM_S = float(os.environ.get("RELAXMAP_E2E_SIM_S", "1200"))


@pytest.mark.slow
def test_long_run_keeps_every_link_and_no_place_strays(tmp_path):
    """A long run keeps every measured link; its relaxed places lie within 3 m RMS of the truth and none
    6 m or more from its true position: the bounds catch a map gone wrong as a whole (a 12% stretch
    made 3.7 m) and a place confirmed after a jump to a look-alike (8-10 m), not the run-to-run spread.

    Measured (orebro-office, seed 0, 1200 simulated s; runs differ with the timing of the relaxed
    coordinates fed back), with the recognizer's arrival gate: six runs on an idle machine
    ``ate_relaxed_m`` 0.35-0.69 m against compass dead reckoning's 0.52-0.75 m; in CI once 2.14 m (one
    wrong loop-closing link, 2.8 m off, bent a branch by 3.3 m; dead reckoning 0.61 m). Before the
    gate, two CI runs ended at 2.4 and 3.3 m, each with a place 8-10 m astray. The figure of a run that
    is a function of its seed is asserted in process (tests/unit/test_inprocess_runs.py, 0.34 m).
    """
    out = tmp_path / "run"
    done = _run(out, "--world", "orebro-office", "--seed", "0", "--max-sim-time", f"{LONG_RUN_SIM_S:g}",
                timeout_s=120 + LONG_RUN_SIM_S)
    assert done.returncode == 0, done.stderr[-3000:]
    summary = _check_outputs(out)
    assert summary["links_lost"] == 0, summary
    assert summary["links_measured"] >= summary["links_traversed"] > 0, summary
    assert summary["places"] >= LONG_RUN_SIM_S / 20, summary
    relaxed = {p["id"]: (p["x"], p["y"]) for p in json.loads((out / "map.json").read_text())["places"]}
    truth = {p["id"]: (p["x"], p["y"]) for p in json.loads((out / "truth.json").read_text())["places"]}
    assert set(truth) == set(relaxed)
    assert summary["ate_relaxed_m"] < 3.0, summary
    astray = place_errors_m(relaxed, truth, min(relaxed))
    assert max(astray.values()) < 6.0, sorted(astray.items(), key=lambda e: -e[1])[:5]


def test_killed_relaxer_is_restarted_and_loses_nothing(tmp_path):
    """SIGKILL the relaxer mid-run: the supervisor restarts it, it resumes from its store and hears the
    events it missed again (history), and the final map holds every measured link."""
    import zenoh

    from messages.types import Health, MapStats
    from services.runtime import QueryFailed, loopback_config, query
    from tests.conftest import free_port

    port = free_port()
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", "--port", str(port), "--headless",
                             "--out", str(out), "--max-sim-time", "400"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    session = zenoh.open(loopback_config(connect=[f"tcp/127.0.0.1:{port}"]))
    try:
        def places() -> int:
            try:
                return query(session, "relaxmap/robot0/map/stats", type_=MapStats, timeout_s=1).places
            except QueryFailed:
                return 0

        deadline = time.monotonic() + 120
        while places() < 15 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert places() >= 15
        pid = query(session, "relaxmap/robot0/health/relaxer", type_=Health).pid
        os.kill(pid, signal.SIGKILL)
        _, err = proc.communicate(timeout=300)
    finally:
        session.close()
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 0, err[-3000:]
    assert "relaxer ended (killed by SIGKILL)" in err
    summary = _check_outputs(out)
    assert summary["restarts"]["relaxer"] == 1
    assert summary["links_lost"] == 0, summary


def test_services_stop_when_the_launcher_is_killed(tmp_path):
    """SIGKILL the launcher alone (it cannot stop anything then): every service notices that its
    launcher is gone and ends by itself, the relaxer's store keeps what was mapped."""
    import psutil
    import zenoh

    from messages.types import Health, MapStats
    from services.launch.graph import load_graph
    from services.runtime import QueryFailed, deploy_file, loopback_config, query
    from services.runtime.procs import free_port

    names = load_graph(deploy_file("graph.json")).names()
    port = free_port()
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", "--port", str(port), "--headless",
                             "--out", str(out), "--max-sim-time", "100000"], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    pids: dict[str, int] = {}
    session = zenoh.open(loopback_config(connect=[f"tcp/127.0.0.1:{port}"]))
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            try:
                if query(session, "relaxmap/robot0/map/stats", type_=MapStats, timeout_s=1).places >= 3:
                    break
            except QueryFailed:
                pass
            time.sleep(0.1)
        for name in names:
            pids[name] = query(session, f"relaxmap/robot0/health/{name}", type_=Health, timeout_s=2).pid
        proc.kill()
        proc.wait()

        def running(pid: int) -> bool:
            try:
                return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
            except psutil.NoSuchProcess:
                return False

        deadline = time.monotonic() + 30
        while any(running(pid) for pid in pids.values()) and time.monotonic() < deadline:
            time.sleep(0.1)
        left = {name: pid for name, pid in pids.items() if running(pid)}
    finally:
        session.close()
        for pid in [proc.pid, *pids.values()]:
            try:
                os.killpg(pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
    assert not left, f"still running after their launcher was killed: {left}"
    assert _stored_places(out / "map.sqlite") >= 3
    for name in names:
        assert "launcher (pid" in (out / "logs" / f"{name}.log").read_text(), name


def _map(out: Path) -> tuple[dict[int, tuple[float, float]], dict[tuple[int, int], dict]]:
    """Places (id -> coordinates) and links (unordered pair -> link) of ``out/map.json``."""
    m = json.loads((out / "map.json").read_text())
    places = {p["id"]: (p["x"], p["y"]) for p in m["places"]}
    return places, {(min(lk["from"], lk["to"]), max(lk["from"], lk["to"])): lk for lk in m["links"]}


def _rigid_fit(a: list, b: list):
    """The rotation and translation taking points ``a`` closest to ``b`` (least squares), and the residuals."""
    A, B = np.asarray(a, float), np.asarray(b, float)
    ca, cb = A.mean(axis=0), B.mean(axis=0)
    u, _, vt = np.linalg.svd((A - ca).T @ (B - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rot = vt.T @ np.diag([1.0, d]) @ u.T

    def fit(p):
        return tuple(rot @ (np.asarray(p, float) - ca) + cb)

    return fit, [math.dist(fit(p), q) for p, q in zip(a, b, strict=True)]


def test_resume_continues_the_saved_run(tmp_path):
    """Stop a run with Ctrl-C, continue it from its directory: no place or link of the first part is
    lost, its coordinates move little, new places get new ids and join the old ones, simulated time
    and the summary's counts go on, and both parts' recordings are readable."""
    out = tmp_path / "run"
    code, err = _interrupt_once_mapped(out, 12, "--seed", "2")
    assert code == 0, err[-3000:]
    first = _check_outputs(out)
    saved = json.loads((out / "run.json").read_text())
    places1, links1 = _map(out)
    truth1 = (out / "truth.json").read_text()
    assert saved["parts"] == 1 and saved["seed"] == 2 and saved["world"] == "orebro-office"
    assert saved["sim_time_s"] == pytest.approx(first["sim_time_s"]) and len(places1) == first["places"] >= 12
    assert saved["monitor"]["robot"]["tick"] == round(saved["monitor"]["robot"]["stamp"] * 10)
    assert saved["monitor"]["max_place_id"] >= max(places1)
    assert saved["monitor"]["robot"]["fix"]["place_id"] in places1  # where the recognizer last had it

    # what contradicts the saved run is refused before anything starts, and the directory stays as it was
    for extra, why in ((["--seed", "3"], "contradicts the saved run's seed 2"),
                       (["--world", "manchester-corridors"], "contradicts the saved run's world"),
                       (["--max-sim-time", "1"], "must go beyond it")):
        done = subprocess.run([sys.executable, "-m", "services.cli", "run", "--port", "0", "--headless",
                               "--resume", str(out), *extra], capture_output=True, text=True, timeout=60)
        assert done.returncode == 1 and why in done.stderr, done.stderr[-2000:]
    assert json.loads((out / "run.json").read_text()) == saved

    end_s = first["sim_time_s"] + 90
    done = subprocess.run([sys.executable, "-m", "services.cli", "run", "--port", "0", "--headless", "--resume",
                           str(out), "--seed", "2", "--max-sim-time", f"{end_s:g}"], capture_output=True,
                          text=True, timeout=300, start_new_session=True)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "continuing the run" in done.stderr
    second = _check_outputs(out)
    places2, links2 = _map(out)
    # nothing of the first part is lost: every place, and every link between the same two places
    assert set(places1) <= set(places2)
    assert set(links1) <= set(links2)
    # relaxation moves the first part's places a little, not away
    moved = [math.dist(places1[i], places2[i]) for i in places1]
    assert max(moved) < 1.0, sorted(moved)[-5:]
    # new places, with ids beyond every id the first part used, joined to the first part's by links
    new = set(places2) - set(places1)
    assert len(new) >= 3 and min(new) > saved["monitor"]["max_place_id"]
    across = [lk for (a, b), lk in links2.items() if (a in new) != (b in new)]
    assert across, "no link joins the second part's places to the first's"
    for lk in across:  # coordinates continue: a link across the parts agrees with the relaxed map
        a, b = places2[lk["from"]], places2[lk["to"]]
        assert abs(math.dist(a, b) - lk["d"]) < 0.5, lk
    # simulated time, counts and truth go on
    assert second["sim_time_s"] >= end_s - 1.0 > first["sim_time_s"]
    assert second["links_lost"] == 0, second
    assert second["links_measured"] >= len(links2) and second["parts"] == 2
    assert second["wall_time_s"] > first["wall_time_s"]
    truth2 = {p["id"]: (p["x"], p["y"]) for p in json.loads((out / "truth.json").read_text())["places"]}
    assert all(truth2[p["id"]] == (p["x"], p["y"]) for p in json.loads(truth1)["places"])
    # the robot went on from where it truly was: fitted on the first part's places, the map puts the
    # second part's first places where they truly are, about as well as it puts the first part's
    old_ids = sorted(places1)
    fit, old_err = _rigid_fit([places2[i] for i in old_ids], [truth2[i] for i in old_ids])
    new_err = [math.dist(fit(places2[i]), truth2[i]) for i in sorted(new)[:3]]
    assert max(new_err) < max(old_err) + 0.75, (new_err, max(old_err))
    run2 = json.loads((out / "run.json").read_text())
    assert run2["parts"] == 2 and run2["recordings"] == ["recording.rrd", "recording-2.rrd"]
    assert run2["recording_id"] == saved["recording_id"]
    verify = subprocess.run([RERUN, "rrd", "verify", str(out / "recording.rrd"), str(out / "recording-2.rrd")],
                            capture_output=True, text=True, timeout=120)
    assert verify.returncode == 0, verify.stderr
    for log in (out / "logs").iterdir():
        assert "Traceback" not in log.read_text(), log.read_text()[-2000:]


def test_resume_refuses_a_directory_without_a_run(tmp_path):
    def resume(directory: Path, *extra: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "services.cli", "run", "--port", "0", "--headless", "--resume",
                               str(directory), *extra], capture_output=True, text=True, timeout=60)

    done = resume(tmp_path / "nowhere")
    assert done.returncode == 1 and "cannot resume" in done.stderr and "is not a directory" in done.stderr
    empty = tmp_path / "empty"
    empty.mkdir()
    done = resume(empty)
    assert done.returncode == 1 and "holds no saved run (run.json is missing" in done.stderr
    assert list(empty.iterdir()) == []  # nothing started, nothing written
    (empty / "run.json").write_text("{not json")
    done = resume(empty)
    assert done.returncode == 1 and "is not a run relaxmap saved" in done.stderr
    done = resume(empty, "--out", str(tmp_path / "elsewhere"))
    assert done.returncode == 1 and "a continued run writes into the directory" in done.stderr
    # a run that cannot go on: its exploration is complete, or it confirmed no place
    from services.launch.monitor import MonitorState, RobotState
    from services.launch.resume import RUN_FORMAT, RunRecord, write_run_record

    robot = RobotState(stamp=1.0, tick=10, truth=(0.0, 0.0, 0.0), dr_xy=(0.0, 0.0), dr_raw=(0.0, 0.0, 0.0), steps=10,
                       path_length_m=0.1)
    monitor = MonitorState(sim_time_s=1.0, max_place_id=0, places=[], deleted_places=[], measured=[], inferred=[],
                           deleted_links=[], robot=robot)
    record = RunRecord(format=RUN_FORMAT, world="orebro-office", world_ref="orebro-office", seed=0, parts=1,
                       sim_time_s=1.0, wall_time_s=1.0, exploration_complete=False, places=3, recording_id="x",
                       recordings=["recording.rrd"], monitor=monitor)
    write_run_record(empty, record)
    done = resume(empty)
    assert done.returncode == 1 and "has no map store (map.sqlite)" in done.stderr
    (empty / "map.sqlite").write_bytes(b"")
    for change, why in (({"exploration_complete": True}, "completed its exploration"),
                        ({"places": 0}, "confirmed no place"), ({"format": 99}, "has format 99")):
        import msgspec

        write_run_record(empty, msgspec.structs.replace(record, **change))
        done = resume(empty)
        assert done.returncode == 1 and why in done.stderr, done.stderr[-2000:]
