"""Full-order large-deformation dynamics against MuJoCo's flex on the same mesh (issue 55): steps per
second of each stepper in one run, under the same load, and where the fast step settles against
rt.nonlinear.solve_static.

The organ: SOFA's liver2 (../shared/data/organs/sofa_liver2.obj, scaled to 0.21 m) filled by fTetWild at
12 mm (about 2,100 nodes, 9,100 tet4; the embedded liver at a spacing of the same size where the
shared data is absent), E 30 kPa, nu 0.45, 1,060 kg/m^3, the tenth of its length at low x held, a
0.5 N pull along z spread on the tenth at high x; dt = 1 ms.

Each stepper is timed twice: over its first 500 steps from rest (the pull just applied, the organ
swinging: the hardest half second; the Newton reference over its first 20), then over --seconds of
wall time from there (the median of --repeat windows; the swing dies out, the organ settles). The
factorizations column counts both parts'.

Steppers:
- MuJoCo flex: a flexcomp of the same nodes and tets (dim 3, elasticity young/poisson: MuJoCo's
  St Venant-Kirchhoff flex, integrator "discrete", its one linearized implicit solve a step), the
  held nodes pinned, the pull on the tip vertices' bodies (needs `pip install mujoco`, not a
  dependency of rtfem);
- rtfem lagged: rt.DirectSimulator(model, 1e-3, damping, large_deformation=True) (chord iterations on
  a lagged tangent, refreshed when its extra iterations have cost about a factorization), with
  refresh=20 (every 20 steps), and with background=True (refreshed on a thread when stale);
- rtfem Newton: the same with solver="newton" (the Newton-converged reference);
- rtfem linear: the linear full order (Newmark, factorized once): the floor of a full-order step.

    python benchmarks/fullorder.py [--repeat 3] [--seconds 3] [--busy] [--sizes 10000 50000]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import busy_core, print_table  # noqa: E402

import rtfem as rt  # noqa: E402

ORGAN = Path(__file__).resolve().parents[2] / "shared" / "data" / "organs" / "sofa_liver2.obj"
E, NU, RHO, PULL, DT = 3e4, 0.45, 1060.0, 0.5, 1e-3
TRANSIENT = 500  # steps: the first half second after the pull is applied, where the organ swings most


def organ(spacing: float = 0.012):
    """The tet4 liver, its held nodes and its tip nodes (see the module)."""
    from rtfem.mesh.meshing import cached_tetrahedralize

    if ORGAN.is_file():
        tets = cached_tetrahedralize(rt.load_mesh(ORGAN, scale=0.1), spacing)
    else:
        tets = rt.meshes.liver(solid=True, spacing=spacing)
    model = rt.SolidModel(tets, rt.Material(E=E, nu=NU, density=RHO), element="tet4")
    X = np.asarray(tets.vertices)
    lo, hi = X.min(axis=0), X.max(axis=0)
    held = np.flatnonzero(X[:, 0] < lo[0] + 0.1 * (hi[0] - lo[0]))
    model.fix(held)
    tip = np.flatnonzero(X[:, 0] > hi[0] - 0.1 * (hi[0] - lo[0]))
    tip = tip[np.isin(tip, model.mesh.used_vertices())]
    F = np.zeros((model.n_nodes, 3))
    F[tip, 2] = PULL / tip.size
    return model, held, tip, F


def rate(step, seconds: float, repeat: int, warm: int = 5) -> float:
    """Steps per second of ``step()`` (the median of ``repeat`` windows of ``seconds``)."""
    for _ in range(warm):
        step()
    return steady(step, seconds, repeat)


def transient(step, n: int = TRANSIENT) -> float:
    """Steps per second over the first ``n`` steps from rest (the pull just applied: the organ swings)."""
    t0 = time.perf_counter()
    for _ in range(n):
        step()
    return n / (time.perf_counter() - t0)


def steady(step, seconds: float, repeat: int) -> float:
    """Steps per second of ``step()``: the median of ``repeat`` windows of ``seconds``."""
    rates = []
    for _ in range(repeat):
        n, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            step()
            n += 1
        rates.append(n / (time.perf_counter() - t0))
    return statistics.median(rates)


def mujoco_stepper(model, held, tip):
    """One mj_step of the same mesh as a MuJoCo flex, or None without mujoco."""
    try:
        import mujoco
    except ImportError:
        return None, "mujoco is not installed (pip install mujoco)"
    X = np.asarray(model.tetmesh.vertices)
    T = np.asarray(model.tetmesh.tets)
    xml = f"""<mujoco><option timestep="{DT}" gravity="0 0 0" integrator="discrete"/><worldbody>
      <flexcomp name="organ" type="direct" dim="3" radius="0.0005" mass="{RHO * model.tetmesh.volume()}"
        point="{' '.join(f'{v:.9g}' for v in X.ravel())}" element="{' '.join(map(str, T.ravel()))}">
        <elasticity young="{E}" poisson="{NU}" damping="0.002"/>
        <contact selfcollide="none" conaffinity="0" contype="0"/><edge equality="false"/>
        <pin id="{' '.join(map(str, held))}"/></flexcomp></worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    bodies = m.flex_vertbodyid[m.flex_vertadr[0] + tip]
    d.xfrc_applied[bodies, 2] = PULL / tip.size
    return (lambda: mujoco.mj_step(m, d)), f"MuJoCo {mujoco.__version__} flex ({m.nv} dof)"


def settle(model, F) -> tuple[float, float, float]:
    """(|u - u_static| / |u_static| after 25 / w1 and after 50 / w1 of the lagged step, critically damped,
    the linear answer's same measure)."""
    w1 = float(rt.modal_analysis(model, 1).omega[0])
    sim = rt.DirectSimulator(model, 2e-3, rt.Damping(alpha=2 * w1), large_deformation=True)
    static = rt.nonlinear.solve_static(model, F).displacements
    scale = np.abs(static).max()
    gaps = []
    for _ in range(2):  # 25 / w1 each: 12 time constants of the critically damped lowest mode
        for _ in range(int(np.ceil(25.0 / w1 / 2e-3))):
            sim.step(F)
        gaps.append(np.abs(sim.displacements() - static).max() / scale)
    return gaps[0], gaps[1], np.abs(model.solve_static(F) - static).max() / scale


def run(repeat: int, seconds: float, busy: bool, sizes: list[int]) -> None:
    model, held, tip, F = organ()
    damping = rt.Damping(alpha=30.0)
    rows, base = [], None
    mj, what = mujoco_stepper(model, held, tip)
    print(f"organ: {model.n_nodes} nodes, {model.tetmesh.n_tets} tet4, {model.free_dofs.size} free dofs; "
          f"{what}; {platform.processor() or platform.machine()}, {'one core busy' if busy else 'quiet'}", flush=True)
    steppers = []
    if mj is not None:
        steppers.append(("MuJoCo flex (discrete, its implicit solve)", mj, None))
    for name, options in (("rtfem lagged (the default: refreshed when stale)", {}),
                          ("rtfem lagged (refreshed every 20 steps)", {"refresh": 20}),
                          ("rtfem lagged (refreshed on a thread when stale)", {"background": True}),
                          ("rtfem Newton (the reference)", {"solver": "newton"})):
        sim = rt.DirectSimulator(model, DT, damping, large_deformation=True, **options)
        steppers.append((name, lambda s=sim: s.step(F), sim))
    linear = rt.DirectSimulator(model, DT, damping)
    steppers.append(("rtfem linear full order (factorized once)", lambda: linear.step(F), None))
    with busy_core(busy):
        for name, step, sim in steppers:
            newton = "Newton" in name
            first = transient(step, 20 if newton else TRANSIENT)  # the Newton step: its first 20 steps only
            factorizations = getattr(sim, "refreshes", None)
            r = steady(step, max(seconds, 5.0) if newton else seconds, 1 if newton else repeat)
            base = (first, r) if base is None else base
            extra = "" if sim is None else f"{sim.iterations} its last step"
            if factorizations is not None:
                extra += f", {factorizations} + {sim.refreshes - factorizations} factorizations"
            if sim is not None and getattr(sim, "newton_steps", 0):
                extra += f", {sim.newton_steps} Newton steps"
            rows.append([name, f"{first:.1f}", f"{first / base[0]:.2f}", f"{r:.1f}", f"{r / base[1]:.2f}", extra])
        ref = "x MuJoCo" if mj is not None else "x first"
        print_table(["stepper", f"first {TRANSIENT} steps/s", ref, "then steps/s", ref, "notes"], rows)
        big = []
        for n_tets in sizes:
            spacing = 0.012 * (9100 / n_tets) ** (1 / 3)
            m2, _, _, F2 = organ(spacing)
            sim = rt.DirectSimulator(m2, DT, damping, large_deformation=True)
            t0 = time.perf_counter()
            sim.step(F2)
            first = time.perf_counter() - t0
            r = rate(lambda s=sim, f=F2: s.step(f), seconds, 1)
            big.append([f"{m2.tetmesh.n_tets:,}", f"{m2.n_nodes:,}", f"{first:.2f} s", f"{r:.1f}"])
        if big:
            print_table(["tet4", "nodes", "first step (factorization)", "lagged steps/s"], big)
    gap, later, linear_gap = settle(model, F)
    print(f"settled: the lagged step's state against rt.nonlinear.solve_static: {gap:.2e} of the motion after "
          f"25 / w1, {later:.2e} after 50 / w1 (the linear answer: {linear_gap:.2e})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--busy", action="store_true", help="another process keeps one core busy meanwhile")
    ap.add_argument("--sizes", type=int, nargs="*", default=[], help="also these numbers of tets (about)")
    args = ap.parse_args()
    run(args.repeat, args.seconds, args.busy, args.sizes)


if __name__ == "__main__":
    main()
