"""
A scene: the gallbladder hung beneath the liver
===============================================

Two organs in one :class:`rtfem.Scene`: the liver held at its bare area, the gallbladder hung from
its bed by springs (the cystic plate), both under gravity; after they settle a probe pushes the
gallbladder up from below. The cystic plate carries the gallbladder's weight, then the weight less
the push. (``rtfem view --example gallbladder`` shows the same organs with the mouse as tools.)

    .venv/bin/python examples/04_scene.py
"""

from pathlib import Path

import numpy as np

import rtfem as rt

dt = 0.002
liver = rt.ShellModel(rt.meshes.liver(3), rt.Material(E=1e6, nu=0.45, thickness=0.01, density=1060.0))
liver.fix("attachment")
gallbladder = rt.ShellModel(rt.meshes.gallbladder(), rt.Material(E=2e5, nu=0.45, thickness=0.002, density=1030.0))

scene = rt.Scene(gravity=(0.0, 0.0, -9.81))
scene.add_body("liver", rt.ModalSimulator(rt.modal_analysis(liver, 30), dt, rt.Damping(alpha=10.0),
                                          static_correction=True), liver.mesh)
# nothing fixed: the gallbladder's six rigid-body modes are among its 30; the springs hold it
scene.add_body("gallbladder", rt.ModalSimulator(rt.modal_analysis(gallbladder, 30), dt, rt.Damping(alpha=10.0)),
               gallbladder.mesh)
scene.attach("cystic plate", "gallbladder", "bed", "liver", stiffness=40.0)  # each bed node to the liver's nearest

# a 5 mm probe under the gallbladder's lowest point: from 1 cm below, up to 4 mm into it from 1.0 s to 1.3 s
X = np.asarray(gallbladder.mesh.vertices)
low = X[np.argmin(X[:, 2])]
path = [[0.0, *(low - [0, 0, 0.015])], [1.0, *(low - [0, 0, 0.015])], [1.3, *(low - [0, 0, 0.001])]]
scene.add_tool("probe", rt.Keyframes(path).device(), radius=0.005, stiffness=200.0)

weight = scene.body("gallbladder").mass * 9.81
t, plate, push = [], [], []
for _ in range(int(1.6 / dt)):
    scene.step()
    t.append(scene.time)
    plate.append(scene.contacts[("gallbladder", "cystic plate")][2])
    push.append(scene.contacts[("gallbladder", "probe")][2])
rest = int(0.95 / dt) - 1  # settled, before the probe arrives
print(f"the gallbladder weighs {weight:.4f} N; at rest the cystic plate carries {plate[rest]:.4f} N")
print(f"pushed: the probe {push[-1]:.4f} N, the plate {plate[-1]:.4f} N, together {push[-1] + plate[-1]:.4f} N")

try:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
except ImportError:  # the plots extra: pip install 'rtfem[plots]'
    plt = None
if plt is not None:
    fig, ax = plt.subplots(figsize=(6, 3.2))
    ax.plot(t, plate, label="cystic plate on the gallbladder")
    ax.plot(t, push, label="probe on the gallbladder")
    ax.axhline(weight, color="grey", ls=":", label="its weight")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("upward force (N)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    Path("out/examples").mkdir(parents=True, exist_ok=True)
    fig.savefig("out/examples/scene.png", dpi=120)
    print("wrote out/examples/scene.png")
