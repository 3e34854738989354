"""The reduced model's error indicator while the viewer's default organ runs (issue 56): the physics
thread's step times with the ErrorMonitor off and on (rt.error_estimate of the state every --period
s, on a thread at nice 10), alternating, in one run; and what one estimate costs.

The organ: `rtfem view`'s default session (the liver as tet10, the reduced nonlinear model, 1 kHz),
its top vertex grabbed and dragged 2 cm up; each phase steps it in real time for --seconds.

    python benchmarks/error_monitor.py [--period 2] [--seconds 8] [--rounds 2] [--busy]
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import busy_core, print_table  # noqa: E402

from rtfem.viewer.session import default_session  # noqa: E402


def phase(s, period, seconds):
    keep = s.monitor
    if period:
        s.monitor.period = period
        s.monitor.cost.clear()
    else:
        s.monitor = None
    s.stats.computes.clear()
    s.start()
    time.sleep(seconds)
    s.stop()
    c = np.array(s.stats.computes)
    costs = list(keep.cost) if period else []
    s.monitor = keep
    return [f"{period:g} s" if period else "off", len(c), f"{np.median(c) * 1e6:.0f} us",
            f"{np.percentile(c, 99) * 1e6:.0f} us", f"{c.max() * 1e3:.1f} ms", f"{s.stats.realtime:.2f}",
            len(costs), f"{np.median(costs):.2f} s" if costs else "-",
            f"{keep.latest.max_error * 1e3:.3f} mm" if period and keep.latest is not None else "-"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--period", type=float, default=2.0)
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--busy", action="store_true", help="also with a core kept busy by another process")
    args = ap.parse_args()
    s = default_session()
    X = s.X
    node = s.grab(X[s.drawn[np.argmax(X[s.drawn, 2])]])
    s.drag(X[node] + [0.0, 0.0, 0.02])
    print(f"organ: {s.kind}, {s.model.n_nodes:,} nodes, {s.settings.label}, dt {s.settings.dt * 1e3:g} ms; grabbed {node}")
    rows = []
    for busy in ([False, True] if args.busy else [False]):
        with busy_core(busy):
            for _ in range(args.rounds):
                for period in (0.0, args.period):
                    rows.append(["busy" if busy else "quiet"] + phase(s, period, args.seconds))
    print_table(["machine", "monitor", "steps", "step p50", "step p99", "step max", "sim s / s", "estimates",
                 "estimate cost", "last estimate"], rows)


if __name__ == "__main__":
    main()
