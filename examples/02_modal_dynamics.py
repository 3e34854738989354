"""
Modal dynamics
==============

40 modes, a push held for 0.2 s and released, plotted against direct integration.

    .venv/bin/python examples/02_modal_dynamics.py
"""

import time
from pathlib import Path

import numpy as np

import rtfem as rt

mesh = rt.meshes.liver()
model = rt.ShellModel(mesh, rt.Material())
model.fix("attachment")

modes = rt.modal_analysis(model, 40)  # K phi = w^2 M phi, the 40 lowest
print("lowest frequencies (Hz):", np.round(modes.frequencies[:6], 3))

dt, damping = 1e-3, rt.Damping(alpha=8.0)  # B = alpha M
node = mesh.groups["probe"][0]
push = tuple(-0.2 * mesh.vertex_normals()[node])

modal = rt.ModalSimulator(modes, dt, damping, static_correction=True)
direct = rt.DirectSimulator(model, dt, damping)  # the paper's baseline: every dof, every step
t, u_modal, u_direct, cost = [], [], [], {"modal": 0.0, "direct": 0.0}
for k in range(500):
    load = {node: push} if k < 200 else None
    for name, sim, out in (("modal", modal, u_modal), ("direct", direct, u_direct)):
        t0 = time.perf_counter()
        sim.step(load)
        out.append(np.linalg.norm(sim.displacement(node)) * 1e3)
        cost[name] += time.perf_counter() - t0
    t.append((k + 1) * dt)

print(f"time per step: modal {cost['modal'] / 500 * 1e6:.1f} us, direct {cost['direct'] / 500 * 1e3:.2f} ms "
      f"({cost['direct'] / cost['modal']:.0f} x)")
print(f"at the end of the push: modal {u_modal[199]:.3f} mm, direct {u_direct[199]:.3f} mm")

try:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
except ImportError:
    print("matplotlib is not installed: no plot (pip install 'rtfem[plots]')")
else:
    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    ax.plot(t, u_direct, "k", lw=2.5, label="direct Newmark (all dof)")
    ax.plot(t, u_modal, "C1", label="40 modes + static correction")
    ax.axvline(0.2, color="grey", ls=":", label="release")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("|u| at the pushed vertex (mm)")
    ax.legend()
    fig.tight_layout()
    Path("out/examples").mkdir(parents=True, exist_ok=True)
    fig.savefig("out/examples/modal_dynamics.png", dpi=110)
    print("wrote out/examples/modal_dynamics.png")
