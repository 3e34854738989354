"""Run-time paths quiet and beside a busy process, with and without the run-time BLAS limit.

Each path runs in a fresh process (the limit, ``RTFEM_RUNTIME_THREADS``, is read at import):
with the default limit (one BLAS thread while a run-time loop runs: :func:`rtfem.threads.runtime`)
and without it (``RTFEM_RUNTIME_THREADS=0``: BLAS's own thread count, every core), each once on a
quiet machine and once while another process keeps one core busy (a Python spin loop). Paths:

* ``modal r=100``: the linear modal step of the default (shell) liver with r = 100 modes and the
  static correction, one vertex read back (the haptic step), 3,000 steps;
* ``field r=50``: the full field of a 15,000-vertex organ from r = 50 modes, float32 (the
  viewer's drawing product; random shapes of that size), 300 products;
* ``nonlinear shell``: the reduced nonlinear step (40 modes + derivatives of 20, cubature,
  static correction, single precision, spread 1) under a Grasp pulled 2 cm, 2,000 steps;
* ``view``: ``rtfem view --benchmark 5``: the default scene (the liver as a solid of tet10, the
  reduced nonlinear model) stepped by the viewer's session with frames drawn at up to 30/s;
* ``view-local``: the same for 10 s with ``--local 20``: the grab trains a 20 mm patch in the
  background (the end of the row: what became of it).

Medians and 99th percentiles per step; the ratio busy / quiet of the medians in the same run.

    python benchmarks/runtime_load.py [--paths modal field nonlinear view] [--seconds 5]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

ROOT = Path(__file__).resolve().parents[1]


def _times(fn, n: int) -> list[float]:
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def worker(path: str, seconds: float) -> dict:
    import rtfem as rt
    from rtfem.threads import runtime

    if path == "modal":
        mesh = rt.meshes.liver()
        model = rt.ShellModel(mesh, rt.Material())
        model.fix("attachment")
        sim = rt.ModalSimulator(rt.modal_analysis(model, 100), 1e-3, rt.Damping(alpha=8.0), static_correction=True)
        node = mesh.groups["probe"][0]

        def step():
            sim.step({node: (0.0, 0.0, -0.1)})
            sim.displacement(node)

        with runtime():
            t = _times(step, 3000)
    elif path == "field":
        rng = np.random.default_rng(0)
        shapes = rng.standard_normal((15_000 * 3, 50)).astype(np.float32)
        q = rng.standard_normal(50).astype(np.float32)
        with runtime():
            t = _times(lambda: shapes @ q, 300)
    elif path == "nonlinear":
        from rtfem.drivers.reduced_nonlinear import reduced_nonlinear_driver

        mesh = rt.meshes.liver()
        model = rt.ShellModel(mesh, rt.Material())
        model.fix("attachment")
        sim = reduced_nonlinear_driver(model, rt.modal_analysis(model, 40), 1e-3, rt.Damping(alpha=8.0),
                                       precision="single", background=True)
        node = mesh.groups["probe"][0]
        g = rt.Grasp(mesh, sim, stiffness=200.0, radius=0.01)
        g.grab(node)
        target = mesh.vertices[node] + 0.02 * mesh.vertex_normals()[node]
        with runtime():
            t = _times(lambda: g.update(target), 2000)[200:]
    else:
        raise SystemExit(f"unknown path {path}")
    t = np.array(t) * 1e6
    return {"p50_us": float(np.median(t)), "p99_us": float(np.percentile(t, 99))}


def run_path(path: str, limit: bool, busy: bool, seconds: float) -> dict:
    env = dict(os.environ, RTFEM_RUNTIME_THREADS="1" if limit else "0")
    from _common import busy_core

    with busy_core(busy):
        if path == "view":
            cmd = [sys.executable, "-m", "rtfem.cli.main", "view", "--benchmark", str(seconds)]
        elif path == "view-local":
            cmd = [sys.executable, "-m", "rtfem.cli.main", "view", "--benchmark", str(2 * seconds), "--local", "20"]
        else:
            cmd = [sys.executable, __file__, "--worker", path, "--seconds", str(seconds)]
        r = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    line = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
    if r.returncode != 0 or not line:
        return {"error": (r.stderr or r.stdout).strip().splitlines()[-1:]}
    out = json.loads(line[-1])
    if path.startswith("view"):
        out = {"p50_us": out["step_p50_us"], "p99_us": out["step_p99_us"], "realtime": out["realtime"],
               "fps": out["frames_per_s"], "local": out.get("local")}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--paths", nargs="+", default=["modal", "field", "nonlinear", "view", "view-local"])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--worker")
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(worker(args.worker, args.seconds)))
        return
    from _common import print_table

    names = {"modal": "modal r=100, haptic step", "field": "field 15k vertices r=50 float32",
             "nonlinear": "reduced nonlinear shell, Grasp step", "view": "rtfem view --benchmark (solid tet10 nonlinear)",
             "view-local": "same, --local 20 (a patch trained per grab), twice as long"}
    rows = []
    for path in args.paths:
        for limit in (True, False):
            res = {busy: run_path(path, limit, busy, args.seconds) for busy in (False, True)}

            def cell(r: dict) -> str:
                if "error" in r:
                    return f"failed: {r['error']}"
                extra = f", {r['realtime']:.2f} x real time, {r['fps']:.0f} frames/s" if "realtime" in r else ""
                if r.get("local"):
                    extra += f" ({r['local'].split(':')[0]})"
                return f"{r['p50_us']:,.0f} / {r['p99_us']:,.0f} us{extra}"

            ratio = (f"{res[True]['p50_us'] / res[False]['p50_us']:.2f}"
                     if "error" not in res[True] and "error" not in res[False] else "-")
            rows.append([names[path], "1 thread (default)" if limit else "none (all cores)", cell(res[False]),
                         cell(res[True]), ratio])
            print(rows[-1], flush=True)
    print()
    print_table(["path", "run-time BLAS limit", "quiet: step p50 / p99", "one core busy: p50 / p99",
                 "busy / quiet (p50)"], rows)


if __name__ == "__main__":
    main()
