"""
Haptic session
==============

A scripted probe presses the liver under a real-time 1 kHz force loop.

Replace ScriptedDevice by CallbackDevice(get_position, set_force) to plug in a real device.

    .venv/bin/python examples/03_haptic_session.py
"""

import numpy as np

import rtfem as rt

mesh = rt.meshes.liver()
model = rt.ShellModel(mesh, rt.Material())
model.fix("attachment")
sim = rt.ModalSimulator(rt.modal_analysis(model, 40), 1e-3, rt.Damping(alpha=8.0), static_correction=True)

node = mesh.groups["probe"][0]  # a vertex on the free edge of the right lobe
X, n = mesh.vertices[node], mesh.vertex_normals()[node]
# 2 mm above the surface, press 5 mm in over 0.5 s, hold, pull out from 1.5 s
device = rt.ScriptedDevice.press(X, n, depth=0.005, duration=2.0, ramp=0.25, release=0.75)
probe = rt.Probe(mesh, sim, stiffness=200.0)  # virtual coupling spring, N/m
probe.prepare(around=X, radius=0.01)  # contact compliances, before the clock starts
stats = rt.HapticLoop(probe, device, rate=1000.0).run(2.0)

forces = np.linalg.norm(np.array(device.forces), axis=1)
hold = int(np.searchsorted(device.times, 1.4))  # the tick at t = 1.4 s (a loaded machine may skip some)
print(stats)
print(f"force during the hold: {forces[hold]:.3f} N; after pulling out: {forces[-1]:.3f} N")
