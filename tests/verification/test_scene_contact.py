"""Scenes (rt.Scene): bodies under gravity on rigid planes, against closed forms and invariants.

- A free body resting on a plane carries its weight (the plane's force = m g; momentum balance),
  with no surface point behind the plane.
- Coulomb on an incline (angle theta; the plane level and gravity tilted, so that the box's flat
  bottom lies on it): with mu > tan theta the body sticks and the friction is m g sin theta, the
  normal force m g cos theta; with mu < tan theta it slides with |F_t| = mu F_n.
"""

from __future__ import annotations

import numpy as np
import pytest

import rtfem as rt


def _free_box(lx=0.1, ly=0.1, lz=0.05, n=(4, 4, 2), E=3e4, element="tet4"):
    mesh = rt.meshes.box(lx, ly, lz, nx=n[0], ny=n[1], nz=n[2])
    return rt.SolidModel(mesh, rt.Material(E=E, nu=0.3, density=1000.0), element=element)


def test_a_free_body_on_a_plane_carries_its_weight():
    model = _free_box()
    modes = rt.modal_analysis(model, 20)  # six rigid-body modes first
    assert np.allclose(modes.frequencies[:6], 0.0, atol=1e-3)
    scene = rt.Scene()
    scene.add_body("box", rt.ModalSimulator(modes, dt=1e-3, damping=rt.Damping(alpha=20.0)), model.mesh)
    scene.add_plane("table", (0.0, 0.0, -0.002), (0.0, 0.0, 1.0), friction=0.3)  # 2 mm below: it falls first
    scene.run(1500)
    weight = scene.body("box").mass * 9.81
    f = scene.contacts[("box", "table")]
    assert abs(f[2] - weight) < 1e-3 * weight and np.abs(f[:2]).max() < 1e-4 * weight
    x = np.asarray(model.mesh.vertices) + scene.body("box").driver.displacements()
    assert x[:, 2].min() > -0.002 - 1e-9  # nothing behind the plane (20 modes: parts of the bottom stand off a little)


@pytest.mark.parametrize("mu, sticks", [(0.5, True), (0.1, False)])
def test_coulomb_on_an_incline(mu, sticks):
    theta = np.radians(15.0)  # tan 15 deg = 0.268
    model = _free_box(E=1e5)
    modes = rt.modal_analysis(model, 20)
    scene = rt.Scene(gravity=9.81 * np.array([np.sin(theta), 0.0, -np.cos(theta)]))
    scene.add_body("box", rt.ModalSimulator(modes, dt=1e-3, damping=rt.Damping(alpha=20.0)), model.mesh)
    scene.add_plane("incline", (0.0, 0.0, -1e-4), (0.0, 0.0, 1.0), friction=mu)
    scene.run(1200)
    f = scene.contacts[("box", "incline")]
    weight = scene.body("box").mass * 9.81
    fn, ft = f[2], np.linalg.norm(f[:2])
    if sticks:
        assert abs(fn - weight * np.cos(theta)) < 0.01 * weight and abs(ft - weight * np.sin(theta)) < 0.01 * weight
    else:
        assert abs(ft - mu * fn) < 0.01 * fn
