"""rtfem.interaction.contact and the cross compliances: each driver's block against a second route (stepping the
driver under unit loads from its saved state), the contact solver against closed forms, and the
refusals of bad arguments (nothing changes on a refusal)."""

from __future__ import annotations

import numpy as np
import pytest

import rtfem as rt
from rtfem.cli.main import main
from rtfem.interaction import compliance, contact_points, friction
from rtfem.interaction.contact import hold_patch
from rtfem.interaction.contact_points import closest_points_on_triangles
from rtfem.interaction.friction import pgs
from rtfem.drivers.base import predictions, step_compliances
from rtfem.viewer.session import Settings


def frames(n: np.ndarray) -> np.ndarray:
    """(k, 3, 3) contact frames of unit normals n, by the kernel the contact set uses."""
    F = np.empty((n.shape[0], 3, 3))
    for k in range(n.shape[0]):
        contact_points._frame_into(n[k, 0], n[k, 1], n[k, 2], F, k)
    return F


@pytest.fixture(scope="module")
def plate():
    mesh = rt.meshes.plate(0.2, 0.2, 8, 8)
    model = rt.ShellModel(mesh, rt.Material())
    model.fix(mesh.boundary_vertices())
    return model, rt.modal_analysis(model, 12)


class Stepped:
    """A driver that hides its batched members: the consumers fall back on the protocol."""

    def __init__(self, driver) -> None:
        self.d = driver

    def __getattr__(self, name):
        if name in ("step_compliances", "predict_at"):
            raise AttributeError(name)
        return getattr(self.d, name)


def drivers(model, modes):
    return {
        "modal": rt.ModalSimulator(modes, 1e-3, rt.Damping(alpha=5.0), static_correction=True),
        "warped": rt.ModalSimulator(modes, 1e-3, rt.Damping(alpha=5.0), static_correction=True, warping=True),
        "newmark": rt.DirectSimulator(model, 1e-3, rt.Damping(alpha=5.0)),
        "newmark HHT": rt.DirectSimulator(model, 1e-3, rt.Damping(alpha=5.0, beta=1e-3), numerical_damping=0.1),
        "central": rt.DirectSimulator(model, 1e-5, rt.Damping(alpha=5.0), method="central"),
        "corotational": rt.DirectSimulator(model, 1e-3, rt.Damping(alpha=5.0), large_deformation=True),
    }


# the linear drivers to round-off; the warped and corotational ones are linearizations, and the
# stepped route is a 1 N finite difference of them
TOL = {"modal": 1e-12, "newmark": 1e-12, "newmark HHT": 1e-12, "central": 1e-12, "warped": 1e-3, "corotational": 1e-3}


@pytest.mark.parametrize("name", list(TOL))
def test_each_drivers_cross_compliances_equal_stepping_it_under_unit_loads(plate, name):
    model, modes = plate
    d = drivers(model, modes)[name]
    nodes = np.array([30, 31, 40])
    for _ in range(3):
        d.step({30: (0.0, 0.0, 0.3)})
    state = d.get_state()
    W = step_compliances(d, nodes)
    Wf = step_compliances(Stepped(d), nodes)
    assert np.abs(W - Wf).max() < TOL[name] * np.abs(W).max()
    np.testing.assert_allclose(predictions(d, nodes), predictions(Stepped(d), nodes), rtol=1e-12, atol=1e-20)
    after = d.get_state()  # the stepped route put the driver back where it was
    assert after.keys() == state.keys()
    for key, value in state.items():
        if isinstance(value, np.ndarray):
            np.testing.assert_allclose(after[key], value, rtol=1e-12, atol=1e-300)  # set_state round-off
    # one node: the Driver's own 3x3
    np.testing.assert_allclose(step_compliances(d, [40]), d.step_compliance(40), rtol=1e-12, atol=0)


def test_impedance_cross_compliances_are_the_static_inverse(plate):
    model, modes = plate
    nodes = np.array([30, 31, 40])
    d = rt.ImpedanceMap.build(model, rt.Damping(alpha=5.0), nodes=nodes, radius=0.2, modes=modes).as_driver()
    W = step_compliances(d, nodes)
    K_inv = np.concatenate([np.stack([model.unit_load_response(j, k)[nodes] for k in range(3)], 2).reshape(-1, 3)
                            for j in nodes], axis=1)
    assert np.abs(W - K_inv).max() < 1e-12 * np.abs(K_inv).max()
    assert np.abs(W - W.T).max() < 1e-12 * np.abs(W).max()


def test_a_patch_load_steps_and_reads_back_as_the_entry_by_entry_path(plate):
    """A contact patch's load (12 vertices, the one-product path) gives the state of the same loads
    parsed one by one (an insertion order the fast path refuses: numpy integer nodes), and the
    displacements read at a set of nodes (the gathered static-correction path, kept between calls)
    equal the full field's, also after the loads change; cross compliances of a few nodes against many
    equal the transpose of the many against the few."""
    model, modes = plate
    rng = np.random.default_rng(8)
    free = np.flatnonzero(~model.held_nodes)
    nodes = rng.choice(free, 12, replace=False)
    ask = np.sort(rng.choice(free, 30, replace=False))
    a = rt.ModalSimulator(modes, 1e-3, rt.Damping(alpha=5.0), static_correction=True)
    b = rt.ModalSimulator(modes, 1e-3, rt.Damping(alpha=5.0), static_correction=True)
    for step in range(4):
        loads = {int(v): rng.normal(size=3) * 1e-3 for v in nodes[:12 - step]}
        a.step(loads)
        b.step({np.int64(v): tuple(f) for v, f in loads.items()})
        np.testing.assert_allclose(a.q, b.q, rtol=1e-12, atol=1e-15 * np.abs(b.q).max())
        for _ in range(2):  # the second call reads the kept gather
            np.testing.assert_allclose(a.displacements_at(ask), b.displacements()[ask], rtol=1e-10,
                                       atol=1e-12 * np.abs(b.displacements()).max())
    # a few rows against many loads come from the few's own columns (D symmetric): the same block as
    # the many rows against the few loads, transposed (one load's column per load)
    few, many = nodes[:3], ask
    a.prepare(many)
    W = a.step_compliances(few, many)
    np.testing.assert_allclose(W, a.step_compliances(many, few).T, rtol=0, atol=1e-9 * np.abs(W).max())


def test_the_kept_compliance_block_equals_a_fresh_one_as_the_contact_set_changes(plate):
    """ToolContact keeps the cross compliances of the vertices touched lately in one pool and reads
    a contact set's block through their slots: over a sequence of sets that overflows the pool (it
    then keeps the current set and lets the rest go, or grows), each set's block equals the driver's
    fresh step_compliances, and only vertices not in the pool were computed."""
    model, modes = plate
    d = rt.ModalSimulator(modes, 1e-3, rt.Damping(alpha=5.0), static_correction=True)
    d.step({30: (0.0, 0.0, 0.3)})
    pool = compliance._ComplianceBlock(d, slots=16)
    rng = np.random.default_rng(3)
    free = np.flatnonzero(~model.held_nodes)
    caps, computed = set(), 0
    for size in (5, 9, 3, 12, 14, 6, 30, 8, 40, 2, 25, 33):
        nodes = np.sort(rng.choice(free, size, replace=False))
        missing = int(np.count_nonzero(pool.slot[nodes] < 0))
        W, slots = pool.block(nodes)
        idx = (3 * slots[:, None] + np.arange(3)).reshape(-1)
        ref = step_compliances(d, nodes)
        assert np.abs(W[np.ix_(idx, idx)] - ref).max() <= 1e-13 * np.abs(ref).max()
        assert pool.new_rows == missing
        computed += missing
        caps.add(W.shape[0] // 3)
    assert len(caps) >= 2 and computed < 187  # it grew, and kept rows it had (187 = every set in full)


def test_closest_points_on_triangles_against_a_brute_force_sampling():
    rng = np.random.default_rng(3)
    A, B, C = (rng.normal(size=(40, 3)) for _ in range(3))
    P = rng.normal(size=(40, 3)) * 2
    Q, bary = closest_points_on_triangles(P, A, B, C)
    np.testing.assert_allclose(bary.sum(axis=1), 1.0, rtol=0, atol=1e-12)
    assert bary.min() >= -1e-12
    s, t = np.meshgrid(np.linspace(0, 1, 201), np.linspace(0, 1, 201))
    s, t = s[s + t <= 1], t[s + t <= 1]
    for i in range(40):
        samples = A[i] + s[:, None] * (B[i] - A[i]) + t[:, None] * (C[i] - A[i])
        best = np.linalg.norm(samples - P[i], axis=1).min()
        d = np.linalg.norm(Q[i] - P[i])
        assert d <= best + 1e-12 and d > best - 1e-2  # never beaten by a sample, and the grid comes close


def test_compiled_geometry_equals_the_vectorized_definitions():
    """The force loop's kernels against the numpy definitions: gaps and push directions against
    Tool.distance for a sphere, a capsule and a jaw (points outside, inside, behind the surface);
    each triangle's closest point against closest_points_on_triangles; frames orthonormal with n
    first."""
    rng = np.random.default_rng(5)
    P = rng.normal(size=(300, 3)) * 0.006
    O = rng.normal(size=(300, 3))
    O /= np.linalg.norm(O, axis=1)[:, None]
    c = np.array([0.001, -0.002, 0.0005])
    for tool in (rt.Tool.sphere(0.004), rt.Tool.capsule(0.002, 0.012, axis=(1, 1, 0)),
                 rt.Tool.jaw(0.01, 0.02, 0.002, normal=(0.2, 0.1, 1.0))):
        d_ref, n_ref = tool.distance(P, c, O)
        d, n = np.empty(300), np.empty((300, 3))
        contact_points._gaps(P, P, O, np.zeros(300), c, tool.orientation, tool.half_extents, tool.radius, d, n)
        np.testing.assert_allclose(d, d_ref, rtol=0, atol=1e-15)
        np.testing.assert_allclose(n, n_ref, rtol=0, atol=1e-12)
        assert (d < 0).sum() > 10 and (d > 0).sum() > 10  # both sides met
    A, B, C = (rng.normal(size=(60, 3)) for _ in range(3))
    Q_ref, bary_ref = closest_points_on_triangles(P[:60] * 100, A, B, C)
    for i in range(60):
        q, bary = np.empty(3), np.empty(3)
        contact_points._closest_on_triangle(P[i] * 100, A[i], B[i], C[i], q, bary)
        np.testing.assert_allclose(q, Q_ref[i], atol=1e-12)
        np.testing.assert_allclose(bary, bary_ref[i], atol=1e-12)
    F = frames(O)
    np.testing.assert_allclose(np.einsum("kia,kib->kab", F, F), np.broadcast_to(np.eye(3), (300, 3, 3)), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(F), 1.0, atol=1e-14)
    np.testing.assert_array_equal(F[:, :, 0], O)


def test_contact_operator_equals_the_matrix_products_and_the_solve_needs_only_pressed_columns():
    """A = F^T (B W B^T + E E^T / k) F from the kernel's 3x3 blocks equals the dense matrix products
    (vertex and face points, a nonsymmetric W); the solve that fills A's columns only for contacts
    that get a force (at some sweep) gives the forces of the solve on the whole A, bit for bit."""
    rng = np.random.default_rng(6)
    s, nv, nf = 30, 20, 25
    m = nv + nf
    L = rng.normal(size=(3 * s, 3 * s))
    W = 1e-3 * (L @ L.T / (3 * s) + 0.3 * np.eye(3 * s)) + 1e-5 * rng.normal(size=(3 * s, 3 * s))
    Bi = np.zeros((m, 3), dtype=np.int64)
    Bv = np.zeros((m, 3))
    Bi[:nv] = rng.choice(s, nv, replace=False)[:, None]
    Bv[:nv, 0] = 1.0
    Bi[nv:] = np.array([rng.choice(s, 3, replace=False) for _ in range(nf)])
    Bv[nv:] = rng.dirichlet(np.ones(3), nf)
    n = rng.normal(size=(m, 3))
    F = frames(n / np.linalg.norm(n, axis=1)[:, None])
    B = np.zeros((m, s))
    np.add.at(B, (np.repeat(np.arange(m), 3), Bi.reshape(-1)), Bv.reshape(-1))
    B3, Fd = np.kron(B, np.eye(3)), np.zeros((3 * m, 3 * m))
    Fd.reshape(m, 3, m, 3)[np.arange(m), :, np.arange(m), :] = F
    for inv_k in (0.0, 1e-3):
        A, full = np.empty((3 * m, 3 * m)), np.zeros(m, dtype=bool)
        for d in range(m):
            friction._column(W, Bi, Bv, F, inv_k, d, A, full)
        C = B3 @ W @ B3.T + inv_k * np.tile(np.eye(3), (m, m))
        ref = Fd.T @ C @ Fd
        # and the tangential diagonal's 1e-9 of each point's compliance (a held direction stays invertible)
        eps = 1e-9 * np.einsum("cii->c", C.reshape(m, 3, m, 3)[np.arange(m), :, np.arange(m), :])
        ref[3 * np.arange(m) + 1, 3 * np.arange(m) + 1] += eps
        ref[3 * np.arange(m) + 2, 3 * np.arange(m) + 2] += eps
        np.testing.assert_allclose(A, ref, rtol=0, atol=1e-14 * np.abs(ref).max())
        b = np.zeros(3 * (nv + nf))
        b[::3] = rng.normal(size=nv + nf) * 1e-5 + 2e-6  # some points pressed, most apart
        b[1::3] = rng.normal(size=nv + nf) * 1e-6
        mu = np.full(m, 0.4)
        r_full, sweeps_full = pgs(A, b, mu)
        have = np.zeros(m, dtype=bool)
        lazy = np.full_like(A, np.nan)
        r, sweeps = friction._solve(lazy, have, W, Bi, Bv, F, inv_k, b.copy(), mu, np.zeros_like(b), 500, 1e-10)
        np.testing.assert_array_equal(r, r_full)
        assert sweeps == sweeps_full
        pressed = r[::3] > 0
        assert have[pressed].all() and 0 < pressed.sum() <= have.sum() < m  # columns of the points
        # pressed at some sweep (22 and 30 of 45 with the spring), not all


def test_pgs_solves_one_contact_in_closed_form():
    """One contact, A = diag(a): r_n = -b_n / a_n when penetrating; stick r_t = -b_t / a_t inside the
    cone, else mu r_n along -b_t."""
    A = np.diag([2.0, 4.0, 4.0])
    r, _ = pgs(A, np.array([-1.0, 0.4, 0.0]), 0.5)
    np.testing.assert_allclose(r, [0.5, -0.1, 0.0], rtol=1e-12)  # |r_t| 0.1 < 0.25: stick
    r, _ = pgs(A, np.array([-1.0, 4.0, 0.0]), 0.5)
    np.testing.assert_allclose(r, [0.5, -0.25, 0.0], rtol=1e-12)  # slip at mu r_n
    r, _ = pgs(A, np.array([1.0, 4.0, 0.0]), 0.5)
    np.testing.assert_array_equal(r, 0.0)  # apart: no force


def coupled_contacts(m: int, seed: int, extra: int = 0):
    """The contact operator of m points on a soft, strongly coupled body (a shell under a rigid jaw:
    every point's compliance mostly shared), in random frames, and ``extra`` more points
    interpolating pairs of the first (a face point between its corners: A is then singular)."""
    rng = np.random.default_rng(seed)
    L = rng.normal(size=(3 * m, 3 * m))
    W = 1.0 + 0.02 * (L @ L.T) / (3 * m)  # all points move together, 2 % apart
    W = W * np.kron(np.ones((m, m)), np.eye(3)) + 0.02 * (L @ L.T) / (3 * m)
    B = np.eye(m)
    for _ in range(extra):
        i, j = rng.choice(m, 2, replace=False)
        t = rng.uniform(0.2, 0.8)
        row = np.zeros(m)
        row[i], row[j] = 1 - t, t
        B = np.vstack([B, row])
    B3 = np.kron(B, np.eye(3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    F = np.kron(np.eye(B.shape[0]), q)  # one frame per point
    return F.T @ B3 @ W @ B3.T @ F, B3.T @ F, rng


def check_signorini_coulomb(A, b, mu, r, atol):
    """The solution's conditions, point by point: w_n >= 0, r_n >= 0, w_n r_n = 0; |r_t| <= mu r_n;
    stuck (|r_t| < mu r_n): w_t = 0; sliding: r_t = -mu r_n w_t / |w_t|."""
    w = b + A @ r
    scale = np.abs(r).max()
    for c in range(b.size // 3):
        (wn, *wt), (rn, *rt_) = w[3 * c:3 * c + 3], r[3 * c:3 * c + 3]
        wt, rt_ = np.array(wt), np.array(rt_)
        assert rn >= 0 and wn >= -atol and min(rn / scale, wn) <= atol
        assert np.linalg.norm(rt_) <= mu * rn * (1 + 1e-9) + 1e-15
        if rn > 0 and mu > 0 and np.linalg.norm(rt_) < mu * rn * (1 - 1e-6):
            np.testing.assert_allclose(wt, 0.0, atol=atol)
        elif rn > 0 and mu > 0 and np.linalg.norm(wt) > atol:
            np.testing.assert_allclose(rt_, -mu * rn * wt / np.linalg.norm(wt), atol=1e-6 * scale)


def test_pgs_equals_the_active_set_enumeration_on_strongly_coupled_contacts():
    """Frictionless, 8 points sharing most of their compliance (where plain projected Gauss-Seidel
    crawls): the forces equal those of the one active set, found by trying all 256, whose forces are
    nonnegative and leave no gap negative; with the subspace steps in tens of sweeps."""
    A, _, rng = coupled_contacts(8, 1)
    An = A[::3, ::3]
    for trial in range(5):
        b = np.zeros(24)
        b[::3] = rng.normal(size=8) * 2e-5 - 5e-4  # the jaw pressed nearly evenly: 2-3 points carry it
        r, sweeps = pgs(A, b, 0.0, max_sweeps=500, tol=1e-12)
        assert sweeps <= 40  # plain projected Gauss-Seidel: 321-517 sweeps on these five
        found = []
        for mask in range(256):
            act = np.flatnonzero([(mask >> i) & 1 for i in range(8)])
            rn = np.zeros(8)
            rn[act] = np.linalg.solve(An[np.ix_(act, act)], -b[::3][act]) if act.size else []
            if (rn >= -1e-15).all() and (b[::3] + An @ rn >= -1e-12).all():
                found.append(rn)
        assert len(found) == 1  # A is positive definite: one solution
        np.testing.assert_allclose(r[::3], found[0], rtol=1e-8, atol=1e-10 * np.abs(found[0]).max())
        np.testing.assert_array_equal(r[1::3], 0.0)
        np.testing.assert_array_equal(r[2::3], 0.0)


@pytest.mark.parametrize("mu", [0.0, 0.3, 1.0])
def test_pgs_meets_signorini_coulomb_on_dependent_points(mu):
    """Twelve coupled points and five more between pairs of them (singular A: their forces are not
    unique): every point meets the contact and friction conditions; without friction the forces on
    the body (B^T F r, unique) are the same from another start."""
    A, BF, rng = coupled_contacts(12, 2, extra=5)
    for trial in range(4):
        b = rng.normal(size=A.shape[0]) * 1e-3
        b[::3] -= 5e-4
        r, sweeps = pgs(A, b, mu, max_sweeps=2000, tol=1e-12)
        assert sweeps <= 2000, "not converged"
        check_signorini_coulomb(A, b, mu, r, atol=1e-9 * np.abs(b).max())
        if mu:
            continue
        body = BF @ r
        again, _ = pgs(A, b, mu, r + rng.uniform(0, 1e-3, r.size) * (np.arange(r.size) % 3 == 0),
                       max_sweeps=2000, tol=1e-12)
        np.testing.assert_allclose(BF @ again, body, atol=1e-7 * np.abs(body).max())  # another start

def test_hold_patch_of_one_vertex_is_the_single_spring_grab():
    W = np.array([[2.0, 0.1, 0.0], [0.1, 1.0, 0.0], [0.0, 0.0, 3.0]])
    h, g, k = np.zeros(3), 5.0 * np.array([0.1, -0.2, 0.3]), 5.0
    f, _ = hold_patch(W, h, g, k, grip=1e15)
    np.testing.assert_allclose(f[0], np.linalg.solve(np.eye(3) + k * W, g), rtol=1e-9)


def test_a_patch_grasp_leaves_out_the_vertices_the_supports_hold(plate):
    """A jaw closed next to the clamped edge: the footprint covers clamped vertices, but a grip on
    them would anchor the jaw to the support (the pull would go into the support and the plate
    would barely move), so the jaw holds only the free ones, and the settled plate is the static
    response to the forces on them."""
    model, modes = plate
    X = np.asarray(model.mesh.vertices)
    node = int(np.argmin(np.linalg.norm(X - [0.025, 0.1, 0.0], axis=1)))  # one row in from the edge x = 0
    d = rt.ModalSimulator(modes, 1e-3, rt.Damping(alpha=12.0), static_correction=True)  # ~critical for 1 Hz
    g = rt.Grasp(model.mesh, d, stiffness=50.0, radius=0.03)
    footprint = g.patch(node)
    assert model.held_nodes[footprint].any()  # the footprint reaches the clamped edge
    held = g.grab(node)
    assert node in held and held.size > 3 and not model.held_nodes[held].any()
    for _ in range(3000):
        g.update(X[node] + [0.0, 0.0, 0.005])
    static = model.solve_static({int(v): f for v, f in zip(held, g.forces)})
    u = d.displacements()
    np.testing.assert_allclose(u, static, atol=1e-6 * np.abs(static).max())
    assert u[node, 2] > 0.2 * 0.005  # the pull lifts the plate: the spring is not held by the edge


def test_a_point_tool_behind_a_concave_crease_is_in_contact():
    """A point tool (R = 0) just behind the crease of a valley, between two of its vertices: its
    closest surface point is on the crease edge, where neither face's normal line passes through
    it; judged by the edge's normal (the cone of its faces' normals) it has passed the surface, so
    the constraint pushes the crease onto it. (Judged by a face's normal it was 'beside' the
    surface: no contact, and a point tool sank into the dent of a pressed organ.)"""
    flat = rt.meshes.plate(0.2, 0.2, 8, 8)
    V = np.asarray(flat.vertices).copy()
    V[:, 2] = 0.5 * np.abs(V[:, 0] - 0.1)  # a valley along x = 0.1, concave seen from +z
    mesh = rt.TriMesh(V, flat.triangles)
    model = rt.ShellModel(mesh, rt.Material()).fix(mesh.boundary_vertices())
    d = rt.ModalSimulator(rt.modal_analysis(model, 12), 1e-3, rt.Damping(alpha=5.0), static_correction=True)
    c = np.array([0.1, 0.1125, -0.0002])  # 0.2 mm behind the crease, half-way between two vertices
    tc = rt.ToolContact(mesh, d, rt.Tool.sphere(0.0), coupling="constraint")
    force = tc.update(c)
    assert tc.contacts == 1 and force[2] > 0  # the device is pushed back out of the valley
    ends = np.flatnonzero(np.linalg.norm(V[:, :2] - [0.1, 0.1125], axis=1) < 0.0126)  # the crease edge
    assert ends.size == 2
    y = (V[ends] + d.displacements()[ends]).mean(axis=0)  # the edge's midpoint after the step
    np.testing.assert_allclose(tc.contact_normals, [[0.0, 0.0, -1.0]], atol=1e-12)  # the edge's normal, inward
    assert abs(y[2] - c[2]) < 1e-9  # on the tool (frictionless: it may slide along the crease)


def test_a_rigid_jaw_over_the_clamped_edge_presses_only_the_free_vertices(plate):
    """A jaw held at the device (constraint coupling) pressed over the plate's clamped edge: the
    clamped vertices cannot move, so no force can be solved for them (zero compliance); they are
    left out (no error in the force loop), and every contact point left is pressed onto the jaw.
    (A rigid jaw over a support cannot be satisfied everywhere: a face point whose other corners
    are clamped is put on the jaw by pushing its free corner past it.)"""
    model, modes = plate
    d = rt.ModalSimulator(modes, 1e-3, rt.Damping(alpha=5.0), static_correction=True)
    tc = rt.ToolContact(model.mesh, d, rt.Tool.jaw(0.06, 0.06, 0.002), coupling="constraint")
    c = np.array([0.02, 0.1, 0.001 - 0.0005])  # the jaw's face 0.5 mm below the plate, over x = 0 .. 0.05
    force = tc.update(c)
    assert tc.contacts >= 3 and force[2] > 0
    X = np.asarray(model.mesh.vertices)
    np.testing.assert_allclose(tc.points[:, 2], -0.0005, atol=1e-9)
    inner = (np.abs(X[:, 0] - 0.02) <= 0.03) & (np.abs(X[:, 1] - 0.1) <= 0.03) & (X[:, 0] > 0.03)
    np.testing.assert_allclose(X[inner, 2] + d.displacements()[inner, 2], -0.0005, atol=1e-9)  # away from the edge


def slide_over(mesh, modes, lookahead, wait=False, driver=None):
    """A 1 cm sphere lowered onto the plate and slid 8 cm across it (forces (k, 3), nodes the loop
    prepared itself, the contact); ``wait``: the background preparation finishes after the first
    step, which names the vertices ahead while the sphere is still 15 mm above the plate."""
    sim = driver or rt.ModalSimulator(modes, 1e-3, rt.Damping(alpha=5.0), static_correction=True)
    tc = rt.ToolContact(mesh, sim, rt.Tool.sphere(0.01), lookahead=lookahead)
    forces, in_loop = [], 0
    for k in range(300):
        x = 0.06 + 0.08 * max(k - 100, 0) / 200
        forces.append(tc.update([x, 0.1, 0.025 - 0.018 * min(k, 100) / 100]).copy())
        in_loop += tc._block.prepared_here
        if k == 0 and wait:
            tc._block.preparer._thread.join(10.0)  # it ends after a second with nothing left to do
    return np.array(forces), in_loop, tc


def test_lookahead_prepares_the_vertices_ahead_in_the_background_and_changes_no_number(plate):
    """The vertices within the lookahead are prepared by a background thread before the tool touches
    them, so the loop prepares none itself; the forces are those of preparing them in the loop."""
    model, modes = plate
    F0, loop0, tc0 = slide_over(model.mesh, modes, 0.0)
    F1, loop1, tc1 = slide_over(model.mesh, modes, 0.1, wait=True)  # 10 cm ahead: the whole path
    assert F0[:, 2].max() > 0.01  # it pressed
    assert tc0._block.preparer.background == 0 and loop0 >= 10
    assert tc1._block.preparer.background >= 10 and loop1 == 0
    assert np.abs(F1 - F0).max() < 1e-9 * np.abs(F0).max()  # batched or not, in the loop or not
    F2, _, tc2 = slide_over(model.mesh, modes, None)  # the default (2 edges), not waited for
    assert np.abs(F2 - F0).max() < 1e-9 * np.abs(F0).max()
    # two tools on one driver take turns on one lock (their threads would prepare the same vertices
    # at once); tools on different drivers do not wait for each other
    other = rt.ToolContact(model.mesh, tc2.driver, rt.Tool.sphere(0.002))
    assert other._block.preparer.lock is tc2._block.preparer.lock
    assert tc1._block.preparer.lock is not tc2._block.preparer.lock


def test_a_failing_background_preparation_is_raised_by_the_loop(plate):
    """A driver whose preparation fails: the background thread stops, and the loop, preparing the
    vertex itself, raises the driver's error (nothing is swallowed)."""
    model, modes = plate

    class Failing(Stepped):
        def prepare(self, nodes):
            raise rt.ModelError("cannot prepare these nodes")

    driver = Failing(rt.ModalSimulator(modes, 1e-3, rt.Damping(alpha=5.0), static_correction=True))
    with pytest.raises(rt.ModelError, match="cannot prepare"):
        slide_over(model.mesh, modes, 0.05, wait=True, driver=driver)


def test_bad_arguments_are_refused_and_change_nothing(plate, capsys):
    model, modes = plate
    mesh = model.mesh
    with pytest.raises(rt.ModelError, match="radius"):
        rt.Tool.sphere(-1.0)
    with pytest.raises(rt.ModelError, match="length"):
        rt.Tool.capsule(0.01, 0.0)
    with pytest.raises(rt.ModelError, match="parallel"):
        rt.Tool.jaw(0.01, 0.02, 0.002, normal=(0, 0, 1), along=(0, 0, 2))
    with pytest.raises(rt.ModelError, match="nonzero"):
        rt.Tool.capsule(0.01, 0.02, axis=(0, 0, 0))
    with pytest.raises(rt.ModelError, match="rotation"):
        rt.Tool(0.01, orientation=np.diag([1.0, 1.0, -1.0]))
    sim = rt.ModalSimulator(modes, 1e-3, rt.Damping(alpha=5.0))
    for bad in (dict(coupling="glue"), dict(stiffness=0.0), dict(friction=-0.1), dict(margin=np.nan),
                dict(max_sweeps=0), dict(tol=-1.0), dict(surface_point="yes"), dict(lookahead=-0.01)):
        with pytest.raises(rt.ModelError):
            rt.ToolContact(mesh, sim, **bad)
    with pytest.raises(rt.ModelError, match="rt.Tool"):
        rt.ToolContact(mesh, sim, tool="sphere")
    with pytest.raises(rt.ModelError, match="drives"):
        rt.ToolContact(mesh, object())
    tc = rt.ToolContact(mesh, sim, rt.Tool.sphere(0.01))
    for _ in range(5):
        tc.update([0.1, 0.1, 0.005])
    before = (sim.get_state(), tc.proxy.copy(), tc.force.copy())
    for bad in ([0.1, np.nan, 0.0], [0.1, 0.2], "here"):
        with pytest.raises(rt.ModelError):
            tc.update(bad)
    with pytest.raises(rt.ModelError, match="around"):
        tc.prepare()
    with pytest.raises(rt.ModelError):
        tc.prepare([10**6])
    after = sim.get_state()
    assert after["steps"] == before[0]["steps"] and np.array_equal(after["q"], before[0]["q"])
    assert np.array_equal(tc.proxy, before[1]) and np.array_equal(tc.force, before[2])
    # the cross compliances and the solver
    with pytest.raises(rt.ModelError):
        step_compliances(sim, [10**6])
    with pytest.raises(rt.ModelError):
        step_compliances(Stepped(sim), [-1, 3])
    with pytest.raises(rt.ModelError, match="3m"):
        pgs(np.eye(3), np.zeros(4), 0.1)
    with pytest.raises(rt.ModelError, match="held"):
        pgs(np.zeros((3, 3)), np.zeros(3), 0.1)
    # the patch grasp
    for bad in (dict(radius=-0.01), dict(grip=0.0), dict(radius=np.inf)):
        with pytest.raises(rt.ModelError):
            rt.Grasp(mesh, sim, **bad)
    g = rt.Grasp(mesh, sim, radius=0.03)
    held = g.grab(40)
    state = sim.get_state()
    for call in (lambda: g.grab(10**6), lambda: g.grab(40, radius=-1.0), lambda: g.update([np.nan, 0, 0])):
        with pytest.raises(rt.ModelError):
            call()
    assert np.array_equal(g.nodes, held) and sim.get_state()["steps"] == state["steps"]
    # the viewer's setting and the command line
    with pytest.raises(rt.ModelError, match="grab_radius"):
        Settings(grab_radius=-0.01).check()
    assert main(["view", "--grab-radius", "-1"]) == 2
    assert "--grab-radius" in capsys.readouterr().err
