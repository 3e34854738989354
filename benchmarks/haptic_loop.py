"""The real-time probe loop at 1, 5 and 10 kHz, compiled (every tick in numba without the GIL)
against the Python loop, in one run; and the full-field reconstruction for drawing in float64
and float32.

Scene: the liver at ``--level`` (default 6: 40,962 vertices), fixed at its attachment, r modes
(default 100), static correction on, a point probe (virtual coupling 200 N/m) pressing 4 mm
into the "probe" vertex and backing out once a second, for ``--seconds`` of wall time per row.
With ``--grasp``, also Grasp rows: a jaw of radius 4 mm holding that vertex (37 nodes at level 6)
pulls it 4 mm out along its normal and back once a second. With ``--impedance``, also rows of
the same press on a quasi-static impedance map (paper 4.1) of the vertices within 1 cm of the
probe vertex (static responses kept within 3 cm), built from the same modes: its ticks are the
probe's with nothing to integrate. ``--no-probe`` leaves out the modal probe rows.
"busy viewer" rows run a second thread meanwhile that draws like a viewer: each 1/60 s frame the
float32 field, then 5 ms of pure-Python work (holding the GIL, as a frame's scene update does),
then it sleeps until the next frame. The static-correction columns (they depend on the basis
only) are computed for the first row and shared by the others.

Columns: steps run, achieved rate, ticks skipped (a loop that falls behind skips, it does not
burst), compute time per tick (p50 / p99 / max), period error |interval - period| between
adjacent ticks (p50 / p99 / max), ticks whose compute took over 100 us, and the peak force.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import threading
import time

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import print_table  # noqa: E402

import rtfem as rt  # noqa: E402
from rtfem.drivers import gpu  # noqa: E402
from rtfem.interaction.ticks import _compiled_loop  # noqa: E402
from rtfem.drivers.base import prepare  # noqa: E402


def us(x: float) -> str:
    return f"{x * 1e6:.1f}"


class BusyViewer:
    """A thread that draws like the viewer: the float32 field at 60 Hz, Python work between."""

    def __init__(self, sim) -> None:
        self.sim, self.stop, self.frames = sim, threading.Event(), 0
        self.thread = threading.Thread(target=self.run, daemon=True)

    def run(self) -> None:
        while not self.stop.is_set():
            t0 = time.perf_counter()
            self.sim.displacements(dtype=np.float32)
            self.frames += 1
            while time.perf_counter() - t0 < 0.005:
                sum(i * i for i in range(200))  # pure Python: holds the GIL
            time.sleep(max(0.0, 1 / 60 - (time.perf_counter() - t0)))

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join()


_COLUMNS: dict = {}  # static-correction columns by node, shared by the rows (same basis)


def loop_row(model, basis, node, rate, seconds, compiled, busy, tool="probe", imap=None):
    X, N = np.asarray(model.mesh.vertices), model.mesh.vertex_normals()
    if tool == "impedance":  # the same press on the quasi-static map's driver
        sim = imap.as_driver(1.0 / rate)
    else:
        sim = rt.ModalSimulator(basis, 1.0 / rate, rt.Damping(alpha=8.0), static_correction=True)
        sim._D = _COLUMNS
    if tool in ("impedance", "probe"):
        handle = rt.Probe(model.mesh, sim)
        handle.prepare(around=X[node], radius=0.01)
        device = rt.ScriptedDevice.press(X[node], N[node], 0.004, 1.0, repeat=True)
    else:  # a jaw of radius 4 mm pulls the vertex 4 mm out along its normal and back, once a second
        handle = rt.Grasp(model.mesh, sim, radius=0.004)
        prepare(sim, handle.grab(node))  # the held nodes' static-correction columns, before the clock starts
        x0, n0 = X[node].copy(), N[node].copy()
        device = rt.ScriptedDevice(lambda t: x0 + 0.004 * n0 * (0.5 - 0.5 * np.cos(2 * np.pi * t)))
    loop = rt.HapticLoop(handle, device, rate=rate, compiled=compiled)
    if busy:
        with BusyViewer(sim) as viewer:
            st = loop.run(seconds)
        frames = viewer.frames
    else:
        st = loop.run(seconds)
        frames = None
    c, e = np.asarray(st.compute), st.period_errors()
    if e.size == 0:  # no two adjacent ticks (every other slot skipped)
        e = np.array([np.nan])
    return [("compiled" if compiled else "python") + ("" if tool == "probe" else " " + tool),
            "busy viewer" if busy else "-", f"{rate / 1000:g} kHz", st.steps,
            f"{st.rate:.0f} Hz", st.missed, us(np.median(c)), us(np.percentile(c, 99)), us(c.max()),
            us(np.median(e)), us(np.percentile(e, 99)), us(e.max()), int((c > 1e-4).sum()),
            f"{st.peak_force:.3f} N", "-" if frames is None else f"{frames / seconds:.0f}/s"]


def field_rows(basis, calls=300):
    sim = rt.ModalSimulator(basis, 1e-3)
    sim.step({0: (0.0, 0.0, -0.1)})
    devices = [("cpu", np.float64), ("cpu", np.float32)]
    if gpu.module() is not None:
        devices += [("gpu", np.float64), ("gpu", np.float32)]
    rows = []
    u64 = sim.displacements()
    for device, dtype in devices:
        sim.displacements(dtype=dtype, device=device)  # the GPU's upload happens here, not in a timed call
        ts = []
        for _ in range(calls):
            t0 = time.perf_counter()
            sim.displacements(dtype=dtype, device=device)
            ts.append(time.perf_counter() - t0)
        u = sim.displacements(dtype=dtype, device=device)
        rows.append([basis.n_nodes, basis.n_modes, device, np.dtype(dtype).name, np.median(ts),
                     f"{np.percentile(ts, 99) * 1e3:.2f} ms",
                     "-" if (device, dtype) == ("cpu", np.float64) else f"{np.abs(u - u64).max() / np.abs(u64).max():.1e}"])
    base = rows[0][4]
    for row in rows:
        row.insert(6, f"{base / row[4]:.2f}x")
        row[4] = f"{row[4] * 1e3:.2f} ms"
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--level", type=int, default=6)
    ap.add_argument("--modes", type=int, default=100)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--rates", type=float, nargs="+", default=[1000.0, 5000.0, 10000.0])
    ap.add_argument("--grasp", action="store_true", help="add Grasp rows: a 4 mm jaw pulling the vertex 4 mm "
                    "out and back once a second, compiled and Python, at each rate")
    ap.add_argument("--impedance", action="store_true", help="add rows of the probe on a quasi-static impedance map "
                    "of the vertices within 1 cm of the probe vertex, compiled and Python, at each rate")
    ap.add_argument("--no-probe", action="store_true", help="leave out the modal probe rows")
    args = ap.parse_args()
    model = rt.ShellModel(rt.meshes.liver(args.level), rt.Material()).fix("attachment")
    node = int(model.mesh.groups["probe"][0])
    basis = rt.modal_analysis(model, args.modes)
    print(f"# rtfem {rt.__version__}, python {platform.python_version()}, {platform.machine()}, {os.cpu_count()} cores; "
          f"liver level {args.level}: {model.n_nodes:,} vertices, r = {args.modes}, {args.seconds:g} s per row; "
          f"compiled loop available: {_compiled_loop() is not None}")
    rows = []
    modes = [True, False] if _compiled_loop() is not None else [False]
    if not args.no_probe:
        for rate in args.rates:
            for compiled in modes:
                rows.append(loop_row(model, basis, node, rate, args.seconds, compiled, False))
                print(f"  {rows[-1][0]} {rows[-1][2]}: {rows[-1][4]}", file=sys.stderr, flush=True)
        if _compiled_loop() is not None:
            for compiled in (True, False):
                rows.append(loop_row(model, basis, node, max(args.rates), args.seconds, compiled, True))
    tools = (["grasp"] if args.grasp else []) + (["impedance"] if args.impedance else [])
    imap = None
    if args.impedance:
        X = np.asarray(model.mesh.vertices)
        near = np.flatnonzero(np.linalg.norm(X - X[node], axis=1) <= 0.01)
        t0 = time.perf_counter()
        imap = rt.ImpedanceMap.build(model, rt.Damping(alpha=8.0), nodes=near, radius=0.03, modes=basis)
        print(f"impedance map: {near.size} loaded vertices within 1 cm, {imap.neighbours.size:,} kept responses, "
              f"built in {time.perf_counter() - t0:.1f} s")
    for tool in tools:
        for rate in args.rates:
            for compiled in modes:
                rows.append(loop_row(model, basis, node, rate, args.seconds, compiled, False, tool=tool, imap=imap))
                print(f"  {rows[-1][0]} {rows[-1][2]}: {rows[-1][4]}", file=sys.stderr, flush=True)
    if rows:
        print("\nProbe loop (period error = |tick interval - period| between adjacent ticks; times in us):")
        print_table(["loop", "other thread", "rate", "steps", "achieved", "skipped", "compute p50", "p99", "max",
                     "period err p50", "p99", "max", "ticks > 100 us", "peak force", "viewer frames"], rows)
    print("\nFull-field reconstruction U = Phi q (+ static correction), the viewer's per-frame product:")
    print_table(["vertices", "modes", "device", "dtype", "median", "p99", "speed-up", "max rel. diff"],
                field_rows(basis))
    if gpu.module() is None:
        print(f"(no GPU rows: {gpu.status()})")


if __name__ == "__main__":
    main()
