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


def _free(mesh, E=3e4, modes=20, alpha=20.0, dt=1e-3):
    model = rt.SolidModel(mesh, rt.Material(E=E, nu=0.3, density=1000.0), element="tet4")
    return model, rt.ModalSimulator(rt.modal_analysis(model, modes), dt=dt, damping=rt.Damping(alpha=alpha))


def _moved(mesh, offset):
    return rt.TetMesh(np.asarray(mesh.vertices) + np.asarray(offset, float), np.asarray(mesh.tets))


def test_stacked_bodies_the_lower_carries_both_the_interface_the_upper():
    """Box B (6 x 6 x 3 cm) dropped 1 mm onto box A (10 x 10 x 5 cm) on a table: settled, the table
    carries both weights, A carries B's, and the two bodies' forces on each other are opposite."""
    ma, A = _free(rt.meshes.box(0.1, 0.1, 0.05, nx=4, ny=4, nz=2))
    mb, B = _free(_moved(rt.meshes.box(0.06, 0.06, 0.03, nx=3, ny=3, nz=2), (0.02, 0.02, 0.051)))
    scene = rt.Scene()
    scene.add_body("A", A, ma.mesh)
    scene.add_body("B", B, mb.mesh)
    scene.add_plane("table", (0.0, 0.0, -0.001), (0.0, 0.0, 1.0))
    scene.run(2000)
    g = 9.81
    wa, wb = scene.body("A").mass * g, scene.body("B").mass * g
    assert abs(scene.contacts[("A", "table")][2] - (wa + wb)) < 0.01 * (wa + wb)
    assert abs(scene.contacts[("B", "A")][2] - wb) < 0.01 * wb
    assert np.allclose(scene.contacts[("A", "B")], -scene.contacts[("B", "A")])
    # B rests on A, not in it: each of B's bottom vertices against A's deformed surface beneath it
    from rtfem.interaction.contact_points import closest_points_on_triangles

    xa = np.asarray(ma.mesh.vertices) + A.displacements()
    xb = np.asarray(mb.mesh.vertices) + B.displacements()
    bottom = xb[np.isclose(np.asarray(mb.mesh.vertices)[:, 2], 0.051)]
    tri = np.asarray(ma.mesh.triangles)
    top = tri[np.isclose(np.asarray(ma.mesh.vertices)[tri][:, :, 2], 0.05).all(axis=1)]
    for p in bottom:
        q, _ = closest_points_on_triangles(np.repeat(p[None], len(top), axis=0), xa[top[:, 0]], xa[top[:, 1]],
                                           xa[top[:, 2]])
        below = q[np.argmin(np.linalg.norm(q[:, :2] - p[:2], axis=1))]
        assert p[2] - below[2] > -1e-6


def test_a_frictionless_collision_keeps_the_momentum():
    """Two free boxes, no gravity, no damping: B pushed at A for 20 ms, then let go; their total
    momentum sum m_i v_i is the same before they touch and after the collision (the contact forces
    are equal and opposite; the rigid-body modes carry the translations exactly)."""
    ma, A = _free(rt.meshes.box(0.05, 0.05, 0.05, nx=2, ny=2, nz=2), E=1e5, modes=12, alpha=0.0)
    mb, B = _free(_moved(rt.meshes.box(0.03, 0.03, 0.03, nx=2, ny=2, nz=2), (0.01, 0.01, 0.055)), E=1e5, modes=12,
                  alpha=0.0)
    scene = rt.Scene(gravity=(0.0, 0.0, 0.0))
    a, b = scene.add_body("A", A, ma.mesh), scene.add_body("B", B, mb.mesh)

    def momentum():
        return sum(body.masses @ ((body.driver.displacements() - body.last) / scene.dt) for body in (a, b))

    b.loads[:, 2] = -0.5 * b.masses / b.mass  # 0.5 N down, spread by mass
    for _ in range(20):
        scene.step()
    b.loads[:] = 0.0
    for body in (a, b):
        body.last = body.driver.displacements()
    scene.step()
    before = momentum()
    touched = False
    for _ in range(400):
        for body in (a, b):
            body.last = body.driver.displacements()
        scene.step()
        touched |= bool(np.any(scene.contacts[("B", "A")]))
    after = momentum()
    assert touched and abs(before[2]) > 1e-4
    assert np.abs(after - before).max() < 1e-6 * np.abs(before).max(), (before, after)


def test_a_body_hung_on_springs_bounces_at_sqrt_nk_over_m_and_keeps_its_energy():
    """A stiff free box (E = 10 MPa: its first elastic mode at 261 Hz) hung from the world by n = 25
    springs of k = 500 N/m on its top face, released unstretched under gravity without damping: a
    rigid body on n springs, it bounces at omega = sqrt(n k / m) (25.2 Hz) about the sag m g / (n k),
    the springs' force between 0 and 2 m g. Newmark's period elongation at omega dt = 0.16 is 0.2 %;
    implicit springs keep the amplitude (explicit ones, the force from the start of the step, grew it
    20-fold in 0.6 s)."""
    model = _free_box(E=1e7)
    scene = rt.Scene()
    scene.add_body("box", rt.ModalSimulator(rt.modal_analysis(model, 20), dt=1e-3, integrator="newmark"), model.mesh)
    spring = scene.attach("ligament", "box", "z>0.049", stiffness=500.0)
    n, m, g = spring.nodes_a.size, scene.body("box").mass, 9.81
    assert n == 25
    F = []
    for _ in range(600):
        scene.step()
        F.append(scene.contacts[("box", "ligament")][2] - m * g)
    F = np.array(F)
    i = np.flatnonzero(np.sign(F[1:]) != np.sign(F[:-1]))
    crossings = (i + 1 + F[i] / (F[i] - F[i + 1])) * 1e-3
    period = 2.0 * np.median(np.diff(crossings))
    assert abs(period / (2 * np.pi * np.sqrt(m / (n * 500.0))) - 1.0) < 0.006
    assert abs(np.ptp(F[:80]) / (2 * m * g) - 1.0) < 0.01 and abs(np.ptp(F[-80:]) / (2 * m * g) - 1.0) < 0.01


def test_a_chain_of_bodies_on_springs_carries_the_weights_below():
    """Box A hung from the world by its top face, box B hung from A's bottom face (each of B's top
    nodes to the nearest node of A), with damping: settled, the world's springs carry both weights,
    the A-B springs B's weight, and A and B feel opposite forces from them (1e-6)."""
    ma, A = _free(rt.meshes.box(0.1, 0.1, 0.05, nx=4, ny=4, nz=2), E=1e5)
    mb, B = _free(_moved(rt.meshes.box(0.06, 0.06, 0.03, nx=3, ny=3, nz=2), (0.02, 0.02, -0.035)), E=1e5)
    scene = rt.Scene()
    scene.add_body("A", A, ma.mesh)
    scene.add_body("B", B, mb.mesh)
    scene.attach("top", "A", "z>0.049", stiffness=2000.0)
    link = scene.attach("link", "B", "z>-0.0051", "A", stiffness=2000.0)
    assert np.all(ma.mesh.vertices[link.nodes_b][:, 2] < 1e-9)  # the nearest nodes of A: on its bottom face
    scene.run(1500)
    g = 9.81
    wa, wb = scene.body("A").mass * g, scene.body("B").mass * g
    assert abs(scene.contacts[("A", "top")][2] - (wa + wb)) < 0.01 * (wa + wb)
    assert abs(scene.contacts[("B", "link")][2] - wb) < 0.01 * wb
    assert np.allclose(scene.contacts[("A", "link")], -scene.contacts[("B", "link")], atol=1e-6 * wb)
    assert np.abs(scene.contacts[("A", "top")][:2]).max() < 1e-3 * wa


def _hertz_block(h0, q, n, upper=False, d=0.0, R=0.005):
    """A quarter of a block of n^3 Kuhn-split hexes whose edges grow from h0 at the corner (0, 0, 0)
    by q per cell (as test_tool_contact's): below z = 0, or (``upper``) its mirror above with the
    bottom face bent into the paraboloid z = r^2 / 2R - d (Hertz's gap). Symmetry planes x = 0 and
    y = 0, the far faces clamped; E = 1e4 Pa, nu = 0.3."""
    box = rt.meshes.box(1.0, 1.0, 1.0, n, n, n)
    g = h0 * (q ** np.arange(n + 1) - 1) / (q - 1)
    i = np.rint(np.asarray(box.vertices) * n).astype(int)
    x, y = g[i[:, 0]], g[i[:, 1]]
    z = g[i[:, 2]] + (x**2 + y**2) / (2 * R) - d if upper else -g[n - i[:, 2]]
    model = rt.SolidModel(rt.TetMesh(np.column_stack([x, y, z]), np.asarray(box.tets)),
                          rt.Material(E=1e4, nu=0.3, density=1000.0), element="tet4")
    Y = np.asarray(model.mesh.vertices)
    far = np.isclose(Y[:, 2], Y[:, 2].max()) if upper else np.isclose(Y[:, 2], Y[:, 2].min())
    model.fix(far | (Y[:, 0] == g[-1]) | (Y[:, 1] == g[-1]), dofs="xyz")
    model.fix(Y[:, 0] == 0.0, dofs="x")
    model.fix(Y[:, 1] == 0.0, dofs="y")
    return model


def test_two_elastic_bodies_pressed_together_follow_hertz():
    """Hertz for two bodies: a paraboloid of radius R = 5 mm (a sphere's tip) on a flat block, both
    elastic, the same material, pressed d into each other (quarters by symmetry, static drivers: a
    critically damped modal simulator with the static correction and a 100 s step). Hertz:
    F = 4/3 E* sqrt(R) d^1.5 with 1/E* = 2 (1 - nu^2) / E, contact radius a = sqrt(R d) = 0.5 mm at
    d = 50 um. The scene's body-body contact (both directions, the two compliances added) on graded
    meshes of h0 = a/5 at the contact: measured 0.6 % and 1.5 % above Hertz at 50 and 100 um, the
    force growing as d^1.51; the same at h0 = a/2.5 was 8.5 % above at 100 um."""
    R, E_star = 0.005, 1e4 / (2 * (1 - 0.3**2))

    def ratio(h0, q, n, d):
        A, B = _hertz_block(h0, q, n), _hertz_block(h0, q, n, upper=True, d=d, R=R)
        scene = rt.Scene(gravity=(0.0, 0.0, 0.0))
        for name, model in (("A", A), ("B", B)):
            sim = rt.ModalSimulator(rt.modal_analysis(model, 4), 100.0, rt.Damping(zeta=1.0), static_correction=True)
            scene.add_body(name, sim, model.mesh)
        scene.run(8)  # the contact set and the geometry settle in a few steps
        f_b, f_a = scene.contacts[("B", "A")], scene.contacts[("A", "B")]
        assert np.allclose(f_a, -f_b) and f_b[2] > 0
        return 4 * f_b[2] / (4 / 3 * E_star * np.sqrt(R) * d**1.5)  # the whole contact: four quarters

    a = np.sqrt(R * 5e-5)
    coarse = ratio(0.4 * a, 1.44, 10, 1e-4)
    fine = np.array([ratio(0.2 * a, 1.2, 20, d) for d in (5e-5, 1e-4)])  # every coarse hex split in 8
    assert np.all(np.abs(fine - 1) < 0.02)  # measured 0.6 %, 1.5 %
    assert abs(fine[1] - 1) < abs(coarse - 1) / 3  # measured 8.5 % -> 1.5 %: converging to Hertz
    slope = 1.5 + np.log(fine[1] / fine[0]) / np.log(2)
    assert abs(slope - 1.5) < 0.05  # measured 1.513: the contact area grows as Hertz's


def test_a_nonlinear_body_on_stiff_springs_settles_to_the_static_spring_equilibrium():
    """A full-order corotational cantilever (the lagged step) held at its free end by 25 springs of 500 N/m
    to the world, settled under gravity with damping: the springs' force is k times their stretch (to 1e-9;
    each step's spring forces are the last step's and a correction that vanishes at rest: from the weight
    alone, through the compliance of a step far from the one made, they held 0.20 N where their stretch said
    0.15 N, and drifted) and the static equilibrium's of the beam with the springs in its stiffness, solved
    linearly (the sag is 16 um: the corotated law's is the same to 1e-3)."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    L, W = 0.1, 0.02
    model = rt.SolidModel(rt.meshes.box(L, W, W, nx=20, ny=4, nz=4), rt.Material(E=3e4, nu=0.45, density=1060.0),
                          element="tet4").fix("x0")
    scene = rt.Scene(gravity=(0.0, 0.0, -9.81))
    sim = rt.DirectSimulator(model, 5e-3, rt.Damping(alpha=60.0), large_deformation=True)
    scene.add_body("beam", sim, model.mesh)
    X = np.asarray(model.tetmesh.vertices)
    tip = scene.attach("tip", "beam", np.flatnonzero(X[:, 0] > L - 1e-9), stiffness=500.0)
    scene.run(400)
    U = sim.displacements()
    held = scene.contacts[("beam", "tip")]
    assert np.abs(held + 500.0 * U[tip.nodes_a].sum(axis=0)).max() <= 1e-9 * np.linalg.norm(held)
    springs = np.zeros((model.n_nodes, 3))
    springs[tip.nodes_a] = 500.0
    free = model.free_dofs
    weight = (scene.body("beam").masses[:, None] * np.array([0.0, 0.0, -9.81])).ravel()
    u = spla.spsolve((model.K + sp.diags(springs.ravel()))[free][:, free].tocsc(), weight[free])
    full = np.zeros(model.n_dofs)
    full[free] = u
    ref = -500.0 * full.reshape(-1, 3)[tip.nodes_a].sum(axis=0)
    assert held[2] == pytest.approx(ref[2], rel=1e-3)
