"""Shared helpers of the benchmark scripts: timing medians, table printing, a busy core, a baseline's code."""

from __future__ import annotations

import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

from rtfem.cli.bench import format_table


def median_time(fn: Callable[[], object], repeat: int = 3) -> tuple[float, object]:
    """Median wall time of ``repeat`` calls of fn, and the last result."""
    times, out = [], None
    for _ in range(max(1, repeat)):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def print_table(headers: list[str], rows: list[list[object]]) -> None:
    print(format_table(headers, rows))


def fmt_s(t: float | None) -> str:
    if t is None:
        return "-"
    if t < 1e-3:
        return f"{t * 1e6:.1f} us"
    if t < 1.0:
        return f"{t * 1e3:.1f} ms"
    return f"{t:.2f} s"


@contextlib.contextmanager
def busy_core(on: bool = True):
    """Another process keeping one core busy (a Python spin loop) while the block runs; nothing
    when ``on`` is false: the "busy" column of the run-time tables."""
    spinner = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if on else None
    try:
        yield
    finally:
        if spinner is not None:
            spinner.kill()
            spinner.wait()


@contextlib.contextmanager
def baseline_tree(ref: str):
    """The repository at ``ref`` ("merge-base": the merge base of HEAD with main) checked out in a temporary
    git worktree for the block (its ``src`` run beside the working tree's, in fresh processes); yields (the
    folder, the short ref) and removes the worktree after."""
    root = Path(__file__).resolve().parents[1]
    if ref == "merge-base":
        ref = subprocess.run(["git", "merge-base", "HEAD", "main"], cwd=root, capture_output=True, text=True,
                             check=True).stdout.strip()
    folder = Path(tempfile.mkdtemp(prefix="rtfem-baseline-"))
    subprocess.run(["git", "worktree", "add", "--detach", str(folder), ref], cwd=root, capture_output=True, check=True)
    try:
        yield folder, ref[:7]
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(folder)], cwd=root, capture_output=True)


def child(script: str, src: Path, *args: str) -> dict:
    """The last JSON line a fresh process of ``benchmarks/<script> args`` prints, with the rtfem of ``src`` (a
    checkout's src: the working tree's or a baseline_tree's) first on its path."""
    here = Path(__file__).resolve().parent
    env = dict(os.environ, PYTHONPATH=f"{src}{os.pathsep}{here}")
    out = subprocess.run([sys.executable, str(here / script), *args], env=env, capture_output=True, text=True,
                         timeout=1800, cwd=tempfile.gettempdir())
    line = [x for x in out.stdout.splitlines() if x.startswith("{")]
    if not line:
        raise RuntimeError(f"the child failed: {out.stderr[-2000:]}")
    return json.loads(line[-1])
