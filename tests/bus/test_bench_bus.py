"""``relaxmap bench bus`` runs end to end at a small size and prints both tables (no timing asserted)."""

from __future__ import annotations

import subprocess
import sys


def test_bench_bus_prints_its_tables():
    out = subprocess.run(
        [sys.executable, "-m", "services.cli", "bench", "bus", "--messages", "300", "--queries", "30",
         "--rate-hz", "500"],
        capture_output=True, text=True, timeout=180,
    )
    assert out.returncode == 0, out.stderr
    for row in ("raw bytes put", "typed pub/sub", "query round trip", "SonarScan", "DeadReckonedPose"):
        assert row in out.stdout, out.stdout
