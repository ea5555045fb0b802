"""``relaxmap run`` end to end: every service as a process, the outputs written and readable."""

from __future__ import annotations

import json
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
                "links_measured", "links_lost"):
        assert key in summary, key
    m = read_map_json(out / "map.json")
    assert m.graph.n_places == summary["places"] and m.graph.n_links == summary["links_traversed"]
    g2o = read_g2o(out / "map.g2o")
    assert g2o.graph.n_poses == summary["places"]
    yaml = (out / "grid.yaml").read_text()
    assert "image: grid.png" in yaml and "resolution: 0.15" in yaml
    for png in ("grid.png", "grid_dead_reckoning.png"):
        img = np.asarray(Image.open(out / png))
        assert img.ndim == 2 and img.size > 1
        assert (img < 100).any() and (img > 250).any(), f"{png} shows no wall or no free space"
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


def _stored_places(store: Path) -> int:
    """Places the relaxer has stored so far (read-only; 0 while the store does not exist yet)."""
    if not store.exists():
        return 0
    try:
        with sqlite3.connect(f"file:{store}?mode=ro", uri=True, timeout=1) as db:
            return db.execute("SELECT count(*) FROM places").fetchone()[0]
    except sqlite3.OperationalError:  # the schema is not written yet
        return 0


def test_ctrl_c_stops_cleanly_and_writes_outputs(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", "--port", "0", "--headless", "--out",
                             str(out), "--max-sim-time", "100000"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and _stored_places(out / "map.sqlite") < 2:
            time.sleep(0.5)
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 0, err[-3000:]
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
def test_long_run_relaxed_map_beats_dead_reckoning(tmp_path):
    out = tmp_path / "run"
    done = _run(out, "--world", "orebro-office", "--seed", "0", "--max-sim-time", f"{LONG_RUN_SIM_S:g}",
                timeout_s=60 + LONG_RUN_SIM_S)
    assert done.returncode == 0, done.stderr[-3000:]
    summary = _check_outputs(out)
    assert summary["links_lost"] == 0, summary
    assert summary["places"] >= LONG_RUN_SIM_S / 20, summary
    assert summary["ate_relaxed_m"] < summary["ate_dead_reckoning_m"], summary


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
