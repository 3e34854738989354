"""Haptic session: a scripted probe presses the liver under a real-time 1 kHz force loop.

Replace ScriptedDevice by CallbackDevice(get_position, set_force) to plug in a real device.

    .venv/bin/python examples/03_haptic_session.py
"""

import numpy as np

import rtfem as rt

mesh = rt.meshes.liver()
model = rt.ShellModel(mesh, rt.Material())
model.fix("attachment")
sim = rt.ModalSimulator(rt.modal_analysis(model, 40), 1e-3, rt.Damping(alpha=8.0), static_correction=True)

node = mesh.nearest_vertex([0.055, 0.05, 0.0])
X, n = mesh.vertices[node], mesh.vertex_normals()[node]


def trajectory(t):  # 2 mm above the surface, press 5 mm in over 0.5 s, hold, pull out at 1.5 s
    depth = -0.002 + 0.007 * min(t / 0.5, 1.0) if t < 1.5 else -0.002
    return X - depth * n


device = rt.ScriptedDevice(trajectory)
probe = rt.Probe(mesh, sim, stiffness=200.0)  # virtual coupling spring, N/m
probe.prepare(around=X, radius=0.01)  # contact compliances, before the clock starts
stats = rt.HapticLoop(probe, device, rate=1000.0).run(2.0)

forces = np.linalg.norm(np.array(device.forces), axis=1)
print(stats)
print(f"force during the hold: {forces[1400]:.3f} N; after pulling out: {forces[-1]:.3f} N")
