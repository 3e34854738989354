"""The cutting example scene headless (``rtfem simulate --example cut``; issue 57): what a step costs when
the scalpel cuts nothing and when a cut is applied in it.

The shipped solid liver (tet4, 1,152 nodes) hanging from its bare area, full order (a lagged corotational
step), a scalpel drawn 4 cm into its right lobe from 0.5 s to 1.5 s; the scene stepped at its file's
dt (5 ms) for 2 s, each cut finished within its step (the default: a run is the same every time). Columns:
the steps; the median and 99th percentile of the steps that applied no cut; the steps that did (the first
one's time apart: in a fresh process it compiles the cut's kernels) with their median and largest time;
the nodes added; the scene's simulated seconds per wall second. Run it quiet and with a core kept busy.

    python benchmarks/scene_cut.py [--busy] [--seconds 2]
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from importlib import resources

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import busy_core, print_table  # noqa: E402

from rtfem.interaction.scene_file import load_scene  # noqa: E402


def run(seconds: float) -> list:
    scene = load_scene(str(resources.files("rtfem") / "scenes" / "cut.toml"))
    knife, n0 = scene.scalpels[0], scene.bodies[0].driver.n_nodes
    plain, cutting = [], []
    t_start = time.perf_counter()
    while scene.time < seconds - 1e-9:
        cuts, t0 = knife.cuts, time.perf_counter()
        scene.step()
        (cutting if knife.cuts != cuts else plain).append(time.perf_counter() - t0)
    wall = time.perf_counter() - t_start
    later = np.asarray(cutting[1:]) if len(cutting) > 1 else np.array([np.nan])
    return [len(plain) + len(cutting), f"{np.median(plain) * 1e3:.1f} ms", f"{np.percentile(plain, 99) * 1e3:.1f} ms",
            len(cutting), f"{cutting[0] * 1e3:.0f} ms" if cutting else "-", f"{np.median(later) * 1e3:.0f} ms",
            f"{np.max(later) * 1e3:.0f} ms", scene.bodies[0].driver.n_nodes - n0, f"{scene.time / wall:.2f}"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--busy", action="store_true", help="also with a core kept busy by another process")
    ap.add_argument("--seconds", type=float, default=2.0)
    args = ap.parse_args()
    print(f"rtfem simulate --example cut: {args.seconds:g} s of scene time at its dt (5 ms); "
          f"{platform.processor() or platform.machine()}")
    rows = []
    for busy in ([False, True] if args.busy else [False]):
        with busy_core(busy):
            rows.append(["busy" if busy else "quiet", *run(args.seconds)])
    print_table(["machine", "steps", "no cut: p50", "p99", "steps that cut", "the first", "the others: p50", "max",
                 "nodes added", "sim s / s"], rows)


if __name__ == "__main__":
    main()
