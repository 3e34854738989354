"""A full-order body nothing can touch takes no trial step in a scene (rtfem.interaction.scene_reach): the
trial is the contact search's look ahead, a whole nonlinear step. Skipping it must change nothing: the
same steps, bit for bit, with a probe coming down onto the body (the trials come back before it
touches), beside a plane, and hung on a spring (never skipped: the trial carries the spring's response).
(The cut example's liver alone, 200 steps: the same displacements bit for bit, 3.16 -> 1.37 s.)"""

from __future__ import annotations

import numpy as np

import rtfem as rt
import rtfem.interaction.scene as scene_module
from rtfem.interaction import scene_reach
from rtfem.interaction.scene_tools import Keyframes

from test_scalpel import L, W


def _run(skip: bool, spring: bool):
    model = rt.SolidModel(rt.meshes.box(L, W, W, nx=10, ny=2, nz=2), rt.Material(E=3e5, nu=0.45, density=1060.0),
                          element="tet4").fix("x0")
    scene = rt.Scene()
    scene.add_body("beam", rt.DirectSimulator(model, 5e-3, rt.Damping(alpha=40.0), large_deformation=True), model.mesh)
    scene.add_plane("floor", (0.0, 0.0, -0.2), (0.0, 0.0, 1.0))
    if spring:
        scene.attach("tip", "beam", "x1", stiffness=20.0)
    scene.add_tool("probe", Keyframes([[0.0, 0.8 * L, W / 2, 0.3], [0.4, 0.8 * L, W / 2, W - 0.004]]).device(),
                   kind="probe", radius=0.004, stiffness=300.0)
    scene.skip_trials = skip
    U, forces = [], []
    for _ in range(100):
        scene.step()
        U.append(np.asarray(scene.bodies[0].driver.displacements()).copy())
        forces.append(scene.contacts[("beam", "probe")].copy())
    return np.array(U), np.array(forces)


def test_skipping_the_trials_of_an_untouched_body_changes_nothing(monkeypatch):
    U0, F0 = _run(False, False)
    skipped = []

    def counting(*args):
        out = scene_reach.untouched(*args)
        skipped.append(sum(u is not None for u in out))
        return out
    monkeypatch.setattr(scene_module, "untouched", counting)
    U1, F1 = _run(True, False)
    assert sum(skipped) > 20  # the probe far above at first: the beam's trials skipped
    assert np.linalg.norm(F0, axis=1).max() > 0.05  # and then it presses
    assert np.array_equal(U0, U1) and np.array_equal(F0, F1)
    skipped.clear()
    U2, _ = _run(True, True)  # hung on a spring: the trial carries the spring's response, never skipped
    assert sum(skipped) == 0 and np.array_equal(U2, _run(False, True)[0])
