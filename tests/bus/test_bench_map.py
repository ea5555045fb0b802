"""``relaxmap bench map`` runs end to end at a small size and prints its table (no timing asserted)."""

from __future__ import annotations

import subprocess
import sys


def test_bench_map_prints_its_table():
    out = subprocess.run([sys.executable, "-m", "services.cli", "bench", "map", "--places", "30", "--measure", "6"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "link measurement -> map update" in out.stdout
    row = [line for line in out.stdout.splitlines() if line.startswith("│ 3")]
    assert row, out.stdout  # 36 places: the 30 filled and the 6 measured
