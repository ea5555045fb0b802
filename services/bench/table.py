"""Printing benchmark tables (rich) and timing helpers shared by every benchmark."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import numpy as np
from rich.console import Console
from rich.table import Table


def print_table(title: str, columns: Sequence[str], rows: Sequence[Sequence[object]],
                *, console: Console | None = None, note: str | None = None) -> None:
    """Print one table; floats are shown with 4 significant digits."""
    table = Table(title=title, title_justify="left")
    for i, col in enumerate(columns):
        table.add_column(col, justify="left" if i == 0 else "right")
    for row in rows:
        table.add_row(*(_fmt(v) for v in row))
    console = console or Console(width=None if Console().is_terminal else 160)
    console.print(table)
    if note:
        console.print(note)


def _fmt(v: object) -> str:
    if isinstance(v, float | np.floating):
        if v != v:
            return "-"
        return f"{v:.4g}"
    return str(v)


def time_call(fn: Callable[[], object], *, repeat: int = 5, min_time_s: float = 0.05) -> float:
    """Median seconds per call of ``fn`` over ``repeat`` batches of at least ``min_time_s`` each."""
    fn()  # warm up
    n = 1
    while True:
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        dt = time.perf_counter() - t0
        if dt >= min_time_s or n >= 1 << 20:
            break
        n *= 2
    samples = [dt / n]
    for _ in range(repeat - 1):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        samples.append((time.perf_counter() - t0) / n)
    return float(np.median(samples))
