"""The example scene's step (rtfem simulate --example gallbladder), quiet and with a core busy.

The liver and the gallbladder hung beneath it (two shells, 642 + 162 vertices, 30 modes each with
the static correction of the liver's loads), the cystic plate's 37 springs, a grasper holding and
retracting the fundus and a probe pressing the right lobe: ``--seconds`` of scene time from t = 0
(the last 0.5 s with both tools in contact). Columns: the step's median and 99th percentile over the
whole run and over the steps with both tools in contact, and the share of real time at the scene's
dt = 1 ms. The same run quiet and beside a process spinning on one core, under rtfem's run-time
BLAS limit (rtfem.threads.runtime) as rtfem simulate runs it. ``--stages``: each stage of the step
(the trial steps, the springs, the points of the planes, pairs and probes, the solve) timed.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import busy_core, print_table  # noqa: E402

import rtfem as rt  # noqa: E402
from rtfem.interaction.scene_file import load_scene  # noqa: E402
from rtfem.threads import runtime  # noqa: E402


def run(seconds: float, busy: bool) -> list:
    from importlib import resources

    scene = load_scene(resources.files("rtfem") / "scenes" / "gallbladder.toml")
    times, both = [], []
    with busy_core(busy), runtime():
        for _ in range(int(round(seconds / scene.dt))):
            t0 = time.perf_counter()
            scene.step()
            times.append(time.perf_counter() - t0)
            touching = [np.abs(scene.contacts.get(("gallbladder", "grasper"), 0)).max() > 0,
                        np.abs(scene.contacts.get(("liver", "probe"), 0)).max() > 0]
            if all(touching):
                both.append(times[-1])
    t, b = np.array(times) * 1e3, np.array(both or [np.nan]) * 1e3
    return ["one core busy" if busy else "quiet", len(t), f"{np.median(t):.2f}", f"{np.percentile(t, 99):.2f}",
            len(both), f"{np.median(b):.2f}", f"{np.percentile(b, 99):.2f}", f"{scene.dt * 1e3 / np.median(t):.2f}x"]


STAGES = ("_trial", "_attachment_loads", "_held_trial", "_plane_points", "_pair_points", "_tool_points", "_solve")


def stages(seconds: float) -> list:
    """Each stage of Scene.step timed (a wrapper around each method; the final driver steps and the rest
    are the difference), quiet: [stage, calls a step, median per step (us), share]."""
    from importlib import resources

    from rtfem.interaction.scene import Scene

    spent = {name: 0.0 for name in STAGES}
    saved = {name: Scene.__dict__[name] for name in STAGES}

    def timed(name, fn):
        def wrapper(*args, **kw):
            t0 = time.perf_counter()
            try:
                return fn(*args, **kw)
            finally:
                spent[name] += time.perf_counter() - t0
        return wrapper

    for name, fn in saved.items():
        raw = fn.__func__ if isinstance(fn, staticmethod) else fn
        setattr(Scene, name, staticmethod(timed(name, raw)) if isinstance(fn, staticmethod) else timed(name, raw))
    try:
        scene = load_scene(resources.files("rtfem") / "scenes" / "gallbladder.toml")
        per_step, totals = {name: [] for name in STAGES}, []
        with runtime():
            for _ in range(int(round(seconds / scene.dt))):
                before = dict(spent)
                t0 = time.perf_counter()
                scene.step()
                totals.append(time.perf_counter() - t0)
                for name in STAGES:
                    per_step[name].append(spent[name] - before[name])
    finally:
        for name, fn in saved.items():
            setattr(Scene, name, fn)
    keep = slice(len(totals) // 3, None)  # past the grasp's start
    total = float(np.median(totals[keep]))
    rows = [[name.strip("_"), f"{np.median(per_step[name][keep]) * 1e6:.0f}",
             f"{np.median(per_step[name][keep]) / total:.0%}"] for name in STAGES]
    rest = total - sum(np.median(per_step[name][keep]) for name in STAGES)
    rows.append(["the rest (final steps, tools, joins)", f"{rest * 1e6:.0f}", f"{rest / total:.0%}"])
    rows.append(["the step (median)", f"{total * 1e6:.0f}", "100%"])
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, default=1.5, help="scene time per run (s; default 1.5)")
    ap.add_argument("--stages", action="store_true", help="also each stage's median per step (quiet, timers on)")
    args = ap.parse_args()
    print(f"# rtfem {rt.__version__}, python {platform.python_version()}, {platform.machine()}, {os.cpu_count()} cores; "
          f"the gallbladder example scene, {args.seconds:g} s of scene time per run")
    rows = [run(args.seconds, busy) for busy in (False, True)]
    print_table(["machine", "steps", "step p50 (ms)", "p99", "steps, both tools in contact", "p50", "p99",
                 "real time (p50)"], rows)
    if args.stages:
        print("\nThe step's stages (a timer around each; the timers add a few us a stage):")
        print_table(["stage", "median per step (us)", "share"], stages(args.seconds))


if __name__ == "__main__":
    main()
