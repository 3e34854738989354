"""What a multi-rate tool's grab, release and lift take their caller while the physics steps on its thread:
the calls that take the physics' lock between two steps.

Before this script's commit the physics thread, stepping flat out, took the lock again first, step after
step, so a call waited several steps, the hand meanwhile feeling the old tool (a jaw pulling, a blade
cutting). The organ is benchmarks/fullorder.py's tet4 liver (dt 4 ms, rt.Damping(alpha=10)), the ticks at
1 kHz on the calling thread. ``grasp``: rt.MultiRateGrasp (stiffness 200 N/m, a 10 mm jaw) on the vertex at
the free end, pulled 10 mm out over 0.5 s and held to 0.7 s, released, then 0.2 s free: ``--strokes`` times;
``scalpel``: rt.Scalpel drawn 0.8 s along benchmarks/scalpel.py's path and lifted, ``--strokes`` times (the
first stroke of each, which compiles and loads, is not kept). Each
with the code at ``--baseline`` (a temporary git worktree) and with the working tree, in fresh processes,
alternating, quiet and with another process spinning: each call's time (median and max over the runs'
calls) and the physics step's median and 90th percentile.

    python benchmarks/grab_wait.py [--strokes 6] [--runs 1] [--baseline 70902e1]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import baseline_tree, busy_core, child, print_table  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def _ticks(update, seconds: float, at) -> None:
    start = time.perf_counter()
    while (now := time.perf_counter()) < start + seconds:
        update(at(now - start))
        time.sleep(max(0.0, 1e-3 - (time.perf_counter() - now)))


def grasp(model, strokes: int) -> dict:
    import rtfem as rt

    mesh = model.mesh
    X = np.asarray(mesh.vertices)
    v = int(np.argmax(X[:, 0]))
    n = mesh.vertex_normals()[v]
    tool = rt.MultiRateGrasp(mesh, rt.DirectSimulator(model, 4e-3, rt.Damping(alpha=10.0), large_deformation=True),
                             stiffness=200.0, radius=0.01)
    calls: dict = {"grab": [], "release": []}
    try:
        for _ in range(strokes + 1):  # (the first, which compiles and loads, not kept)
            t0 = time.perf_counter()
            tool.grab(v)
            calls["grab"].append(time.perf_counter() - t0)
            _ticks(tool.update, 0.7, lambda t: X[v] + 0.01 * min(1.0, t / 0.5) * n)
            t0 = time.perf_counter()
            tool.release()
            calls["release"].append(time.perf_counter() - t0)
            _ticks(tool.update, 0.2, lambda t: None)
    finally:
        tool.close()
    return {"calls": {k: v[1:] for k, v in calls.items()}, "steps": tool.step_times}


def scalpel(model, strokes: int) -> dict:
    from scalpel import lift_ticks

    lifts, steps = lift_ticks(model, 4e-3, strokes + 1, seconds=0.8)  # (the first stroke's lift not kept)
    return {"calls": {"lift": lifts[1:]}, "steps": steps}


def one(tool: str, strokes: int) -> None:
    """The child: the tool's calls with the rtfem on PYTHONPATH, as a JSON line."""
    from fullorder import organ

    out = {"grasp": grasp, "scalpel": scalpel}[tool](organ()[0], strokes)
    print(json.dumps(out))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--strokes", type=int, default=6)
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--baseline", default="70902e1")
    ap.add_argument("--one", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        return one(args.one, args.strokes)
    print(f"# {args.strokes} strokes a run, {args.runs} fresh processes per cell; {platform.processor() or platform.machine()}",
          flush=True)
    res: dict = {}
    with baseline_tree(args.baseline) as (base, short):
        trees = {f"baseline {short}": base / "src", "now (working tree)": ROOT / "src"}
        for busy in (False, True):
            with busy_core(busy):
                for _ in range(args.runs):
                    for tool in ("grasp", "scalpel"):
                        for code, src in trees.items():
                            run = child("grab_wait.py", src, "--one", tool, "--strokes", str(args.strokes))
                            res.setdefault((tool, busy, code), []).append(run)
    rows = []
    for (tool, busy, code), rs in res.items():
        steps = np.concatenate([r["steps"] for r in rs]) * 1e3
        for call in rs[0]["calls"]:
            t = np.concatenate([r["calls"][call] for r in rs]) * 1e3
            rows.append([tool, "busy" if busy else "quiet", code, call, f"{np.median(t):.2f}", f"{t.max():.2f}",
                         f"{np.median(steps):.1f}", f"{np.percentile(steps, 90):.1f}"])
    print_table(["tool", "machine", "code", "call", "call p50 (ms)", "call max (ms)", "step p50 (ms)", "step p90 (ms)"], rows)


if __name__ == "__main__":
    main()
