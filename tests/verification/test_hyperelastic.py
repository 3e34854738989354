"""Hyperelastic laws (issue 41): neo-Hookean, Mooney-Rivlin, Ogden against closed forms written
here from each law's energy alone, and the FE solids built on them.

- Uniaxial compression of a unit cube, sides free: any tet mesh is exact for the homogeneous
  field, so the reaction equals the closed-form nominal stress, found here from the scalar energy
  W(lambda, t) of F = diag(lambda, t, t) (the lateral stretch t where dW/dt = 0, the stress
  dW/dlambda; derivatives by complex step of that scalar formula, not of the laws' code).
- Simple shear, J = 1: sigma_12 = mu gamma for neo-Hookean and Mooney-Rivlin, and the neo-Hookean
  normal stresses 2 mu gamma^2 / 3, -mu gamma^2 / 3 (Ogden, Non-linear Elastic Deformations, 1984).
- Invariants: P is the energy's gradient and dP/dF the gradient of P (central differences),
  objectivity P(QF) = Q P(F), isotropy W(FQ) = W(F), the rest tangent equal to the linear
  isotropic tensor of mu and kappa; Ogden with alpha = 2 equals neo-Hookean, with (2, -2)
  Mooney-Rivlin.
"""

import numpy as np
import pytest
from scipy.optimize import brentq

import rtfem as rt
from rtfem.errors import ModelError

MU, KAPPA = 2000.0, 100000.0


def _laws():
    return {
        "neo-hookean": rt.NeoHookean(mu=MU, kappa=KAPPA, density=1000.0),
        "mooney-rivlin": rt.MooneyRivlin(c10=700.0, c01=300.0, kappa=KAPPA, density=1000.0),
        "ogden": rt.Ogden(mu=[1500.0, 500.0], alpha=[8.0, -2.0], kappa=KAPPA, density=1000.0),
    }


def _scalar_energy(law, lam, t):
    """W of F = diag(lam, t, t), written from the law's definition (complex-safe)."""
    J = lam * t * t
    if isinstance(law, rt.Ogden):
        lb, tb = J ** (-1 / 3) * lam, J ** (-1 / 3) * t
        iso = sum(2 * m / a**2 * (lb**a + 2 * tb**a - 3) for m, a in zip(law.mus, law.alphas))
    else:
        I1, I2 = lam**2 + 2 * t**2, 2 * lam**2 * t**2 + t**4
        iso = law.c10 * (J ** (-2 / 3) * I1 - 3) + law.c01 * (J ** (-4 / 3) * I2 - 3)
    return iso + 0.5 * law.kappa * (J - 1) ** 2


def _d(f, x, h=1e-30):
    return f(x + 1j * h).imag / h


def uniaxial(law, lam):
    """(lateral stretch, nominal axial stress) of uniaxial stress at axial stretch lam."""
    t = brentq(lambda t: _d(lambda s: _scalar_energy(law, lam, s), t), 0.5, 2.0, xtol=1e-15)
    return t, _d(lambda s: _scalar_energy(law, s, t), lam)


def _cube(law, element):
    mesh = rt.meshes.box(1.0, 1.0, 1.0, nx=2, ny=2, nz=2)
    model = rt.SolidModel(mesh, law, element=element)
    X = np.asarray(model.tetmesh.vertices)
    base, top = np.flatnonzero(X[:, 2] == 0.0), np.flatnonzero(X[:, 2] == 1.0)
    model.fix(base, "z")  # the base held in its normal direction ...
    model.fix(np.flatnonzero((X == 0.0).all(axis=1)), "xyz")  # ... one corner fully
    model.fix(np.flatnonzero((X[:, 0] == 1.0) & (X[:, 1] == 0.0) & (X[:, 2] == 0.0)), "y")  # the turn about z
    model.fix(top, "z")
    return model, X, top


@pytest.mark.parametrize("name,element", [("neo-hookean", "tet4"), ("neo-hookean", "tet10"),
                                          ("mooney-rivlin", "tet4"), ("ogden", "tet4")])
def test_a_cube_compressed_30_percent_carries_the_closed_form_uniaxial_stress(name, element):
    """Issue 41's case: a unit cube, base held normally (one corner fully, one more against the
    turn about the axis), the top face moved down 30 % with the sides free: the top's reaction is
    the closed-form nominal stress times the area (1 m^2) within 1e-8 (the issue asks 0.5 %; the
    field is homogeneous, so any tet mesh is exact: measured 2-4e-13), and the sides move out by
    the closed-form stretch."""
    law = _laws()[name]
    model, X, top = _cube(law, element)
    prescribed = np.zeros((model.n_nodes, 3))
    prescribed[top, 2] = -0.3
    result = rt.nonlinear.solve_static(model, prescribed=prescribed, steps=3)
    t, P11 = uniaxial(law, 0.7)
    assert P11 < 0 and t > 1.0  # compressed, bulging
    reaction = result.reactions[top, 2].sum()
    assert abs(reaction - P11) <= 1e-8 * abs(P11), (reaction, P11)  # the issue asks 0.5 %; measured 4e-13
    u = result.displacements
    side = np.flatnonzero(X[:, 0] == 1.0)
    assert np.allclose(u[side, 0], t - 1.0, rtol=1e-6, atol=1e-9)


def test_simple_shear_closed_forms():
    """sigma = P F^T / J under F = I + gamma e1 e2^T (J = 1): neo-Hookean sigma_12 = mu gamma,
    sigma_11 = 2 mu gamma^2 / 3, sigma_22 = sigma_33 = -mu gamma^2 / 3; Mooney-Rivlin sigma_12 =
    2 (C10 + C01) gamma; for every law sigma_12 at small gamma -> mu gamma and sigma_13 = 0."""
    laws = _laws()
    for gamma in (0.05, 0.3, 1.0):
        F = np.eye(3)[None].copy()
        F[0, 0, 1] = gamma
        sig = {k: (law.stress(F, False)[0][0] @ F[0].T) for k, law in laws.items()}
        s = sig["neo-hookean"]
        np.testing.assert_allclose([s[0, 1], s[0, 0], s[1, 1], s[2, 2]],
                                   [MU * gamma, 2 * MU * gamma**2 / 3, -MU * gamma**2 / 3, -MU * gamma**2 / 3],
                                   rtol=1e-12, atol=1e-9 * MU)
        mr = laws["mooney-rivlin"]
        assert abs(sig["mooney-rivlin"][0, 1] - 2 * (mr.c10 + mr.c01) * gamma) < 1e-10 * MU
    for law in laws.values():
        F = np.eye(3)[None].copy()
        F[0, 0, 1] = 1e-5
        s = law.stress(F, False)[0][0] @ F[0].T
        assert abs(s[0, 1] - law.mu * 1e-5) < 1e-9 * law.mu and abs(s[0, 2]) < 1e-12 * law.mu


@pytest.mark.parametrize("name", ["neo-hookean", "mooney-rivlin", "ogden"])
def test_stress_tangent_energy_objectivity(name):
    """At random gradients with J > 0 (stretches 0.6-1.6): P equals the central-difference
    gradient of the energy, dP/dF the central-difference gradient of P; P(QF) = Q P(F),
    W(QF) = W(FQ) = W(F) for rotations Q; at rest P = 0 and dP/dF = kappa d.d + mu (d.d + d.d - 2/3 d.d)
    (the linear isotropic tensor of mu and kappa), the law's linearized Material the same E, nu."""
    law = _laws()[name]
    rng = np.random.default_rng(3)
    U = np.linalg.qr(rng.normal(size=(20, 3, 3)))[0]
    F = U @ (np.exp(rng.uniform(np.log(0.6), np.log(1.6), (20, 3)))[:, :, None] * np.linalg.qr(rng.normal(size=(20, 3, 3)))[0])
    F *= np.sign(np.linalg.det(F))[:, None, None]
    P, W, dP = law.stress(F)
    h = 1e-6
    gW, gP = np.empty_like(P), np.empty_like(dP)
    for c in range(3):
        for d in range(3):
            Fp, Fm = F.copy(), F.copy()
            Fp[:, c, d] += h
            Fm[:, c, d] -= h
            (Pp, Wp, _), (Pm, Wm, _) = law.stress(Fp, False), law.stress(Fm, False)
            gW[:, c, d] = (Wp - Wm) / (2 * h)
            gP[:, :, :, c, d] = (Pp - Pm) / (2 * h)
    scale = np.abs(P).max()
    assert np.abs(gW - P).max() < 1e-6 * scale
    assert np.abs(gP - dP).max() < 1e-6 * np.abs(dP).max()
    Q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    Q *= np.sign(np.linalg.det(Q))
    PQ, WQ, _ = law.stress(Q @ F, False)
    assert np.abs(PQ - Q @ P).max() < 1e-10 * scale and np.abs(WQ - W).max() < 1e-10 * np.abs(W).max()
    assert np.abs(law.stress(F @ Q, False)[1] - W).max() < 1e-10 * np.abs(W).max()
    P0, W0, C0 = law.stress(np.eye(3)[None])
    d = np.eye(3)
    lam = law.kappa - 2 * law.mu / 3
    C = lam * np.einsum("ab,cd->abcd", d, d) + law.mu * (np.einsum("ac,bd->abcd", d, d) + np.einsum("ad,bc->abcd", d, d))
    assert np.abs(P0).max() < 1e-9 * law.mu and abs(W0[0]) < 1e-9 * law.mu
    assert np.abs(C0[0] - C).max() < 1e-6 * law.kappa
    m = law.linearized()
    assert np.isclose(m.G, law.mu, rtol=1e-12) and np.isclose(m.E / (3 * (1 - 2 * m.nu)), law.kappa, rtol=1e-9)


def test_ogden_reduces_to_neo_hookean_and_mooney_rivlin():
    """Ogden's alpha = 2 term is neo-Hookean (mu_1 = mu), alpha = (2, -2) Mooney-Rivlin (mu_1 =
    2 C10, mu_2 = 2 C01): the principal-stretch code against the invariant code, to round-off."""
    rng = np.random.default_rng(5)
    F = np.eye(3) + 0.25 * rng.normal(size=(30, 3, 3))
    F = F[np.linalg.det(F) > 0.2]
    pairs = [(rt.Ogden([MU], [2.0], KAPPA), rt.NeoHookean(MU, KAPPA)),
             (rt.Ogden([1400.0, 600.0], [2.0, -2.0], KAPPA), rt.MooneyRivlin(700.0, 300.0, KAPPA))]
    for og, ref in pairs:
        (P, W, dP), (Pr, Wr, dPr) = og.stress(F), ref.stress(F)
        assert np.abs(P - Pr).max() < 1e-12 * np.abs(Pr).max()
        assert np.abs(W - Wr).max() < 1e-12 * np.abs(Wr).max()
        assert np.abs(dP - dPr).max() < 1e-7 * np.abs(dPr).max()  # Ogden's by differences


def test_bad_laws_and_unsupported_uses_are_refused():
    """Clear errors: non-positive moduli, mismatched Ogden lists, a kappa/mu with no linear twin;
    an inverted element gives NaN stresses and an infinite energy rather than a number."""
    for make, match in [(lambda: rt.NeoHookean(-1.0, KAPPA), "mu"), (lambda: rt.NeoHookean(MU, 0.0), "kappa"),
                        (lambda: rt.MooneyRivlin(-600.0, 100.0, KAPPA), "shear modulus"),
                        (lambda: rt.Ogden([1.0, 2.0], [2.0], KAPPA), "same length"),
                        (lambda: rt.Ogden([1.0], [0.0], KAPPA), "alpha_i != 0"),
                        (lambda: rt.Ogden([1.0], [1e300], KAPPA), "each exponent must be within"),
                        (lambda: rt.NeoHookean(MU, 1e4 * MU), "kappa / mu"),
                        (lambda: rt.NeoHookean(MU, KAPPA, density=float("nan")), "density")]:
        with pytest.raises(ModelError, match=match):
            make()
    P, W, dP = rt.NeoHookean(MU, KAPPA).stress(np.diag([1.0, 1.0, -0.5])[None])
    assert np.isnan(P).all() and np.isinf(W).all() and np.isnan(dP).all()
    F = np.eye(3)[None] + np.array([[[0.1, 0.2, 0.0], [0.0, -0.1, 0.05], [0.0, 0.0, 0.2]]])
    for law in _laws().values():  # scaled(f): every stress times f, the law itself unchanged; a bad f refused
        before = repr(law)
        np.testing.assert_allclose(law.scaled(2.5).stress(F, False)[0], 2.5 * law.stress(F, False)[0], rtol=1e-12)
        with pytest.raises(ModelError, match="factor"):
            law.scaled(-1.0)
        assert repr(law) == before


@pytest.mark.parametrize("name", ["neo-hookean", "ogden"])
def test_the_reduced_nonlinear_model_runs_the_law(name):
    """A reduced nonlinear model of a hyperelastic cantilever (tet4, 12 modes + derivatives of 4):
    its element kernel summed over all tets equals the full order's assembled forces projected,
    U^T g(U q), and its element tangents U^T K(U q) U (two codes: the batched law kernel against
    the full order's HyperelasticTets); its static equilibrium under a tip load is within 2 % of
    the full order's (the basis' error; measured 0.4 %; the linear tip is over 10 % further), and
    the simulator settles on its cubature's equilibrium."""
    from rtfem.drivers.reduced_nonlinear import ReducedNonlinearSimulator
    from rtfem.reduction.reduced import ReducedNonlinearModel

    E, nu = 1e5, 0.3
    mu, kappa = E / (2 * (1 + nu)), E / (3 * (1 - 2 * nu))
    law = rt.NeoHookean(mu, kappa, 10.0) if name == "neo-hookean" else rt.Ogden([0.8 * mu, 0.2 * mu], [6.0, -2.0], kappa, 10.0)
    model = rt.SolidModel(rt.meshes.box(1.0, 0.1, 0.1, nx=16, ny=2, nz=2), law)
    model.fix("x0")
    red = ReducedNonlinearModel(model, rt.modal_analysis(model, 12), 4)
    rng = np.random.default_rng(2)
    q = rng.normal(size=red.size)
    q *= 0.3 / np.abs(red.displacements(q)).max()
    data = red._element_data()
    n_el = data[0].shape[0]
    g, K = red.reduced_forces(q)
    assert np.abs(red._element_forces(q, data, np.ones(n_el), False)[0] - g).max() < 1e-10 * np.abs(g).max()
    from rtfem.reduction import tet_kernels

    V = (data[0].reshape(-1, red.size) @ q).reshape(n_el, -1)
    V[0, :3] = 3 * (data[1][0, 1:].mean(axis=0) - data[1][0, 0])  # element 0 inside out: NaN, not a number
    Fc, Fn = np.empty(V.shape), np.empty(V.shape)
    tet_kernels.law_forces(V, *data[1:4], law, Fc)  # compiled (numba) for both laws
    tet_kernels.law_forces_numpy(V, *data[1:4], law, Fn)
    assert np.isnan(Fc[0]).all() and np.isnan(Fn[0]).all()
    assert np.abs(Fc[1:] - Fn[1:]).max() < 1e-12 * np.abs(Fn[1:]).max()
    V = (data[0].reshape(-1, red.size) @ q).reshape(n_el, -1)
    Ke = red._element_tangents(V, data)
    Kr = np.einsum("eir,eij,ejs->rs", data[0], Ke, data[0])
    assert np.abs(Kr - K).max() < 1e-7 * np.abs(K).max()
    tip = model.select_nodes("x1")
    F = np.zeros((model.n_nodes, 3))
    F[tip, 2] = 1.0
    F *= 0.4 / model.solve_static(F)[tip, 2].mean()  # a linear tip deflection of 40 % of the length
    full = rt.nonlinear.solve_static(model, F, steps=2).displacements[tip, 2].mean()
    reduced = red.solve_static(F).displacements[tip, 2].mean()
    assert abs(reduced - full) < 0.02 * abs(full) and full < 0.9 * 0.4, (reduced, full)
    red.train_cubature(8, tol=0.02)
    sim = ReducedNonlinearSimulator(red, 2e-3, rt.Damping(zeta=1.0))
    sim.run(F, 1500)
    static = red.solve_static(F, cubature=True, max_iterations=60).displacements
    assert np.abs(sim.displacements() - static).max() < 1e-3 * np.abs(static).max()


def test_cubature_training_halves_poses_that_turn_elements_inside_out():
    """A hyperelastic law has no energy for an inverted element (NaN forces): random training poses
    large enough to invert tets are halved until every force is finite (the corotated material,
    which has an energy there, keeps them), and the cubature is trained, not left empty; training
    forces that are not finite are refused by the trainer itself."""
    from rtfem.reduction import cubature
    from rtfem.reduction.reduced import ReducedNonlinearModel

    out = {}
    for name, material in (("law", rt.NeoHookean(MU, KAPPA, 10.0)), ("corotated", rt.NeoHookean(MU, KAPPA).linearized())):
        model = rt.SolidModel(rt.meshes.box(1.0, 0.1, 0.1, nx=8, ny=1, nz=1), material)
        model.fix("x0")
        red = ReducedNonlinearModel(model, rt.modal_analysis(model, 8), 2)
        out[name] = red.train_cubature(8, tol=0.05, reach=3.0)
        q = np.random.default_rng(1).normal(size=red.size) * 1e-3
        assert np.isfinite(red.cubature_forces(q)).all()
    assert out["law"]["halved_poses"] > 0 and out["law"]["elements"].size > 0 and out["law"]["training_error"] <= 0.05
    assert out["corotated"]["halved_poses"] == 0
    with pytest.raises(ModelError, match="not finite"):
        cubature.train(np.array([[1.0, np.nan], [0.5, 1.0]]), np.array([1.0, 1.0]))


def test_fit_material_recovers_known_laws_and_its_fit_holds_in_the_solver():
    """rt.fit_material on uniaxial data made from known parameters (stretches 0.7-1.4, the
    incompressible closed forms): neo-Hookean and Mooney-Rivlin recovered to 1e-9, a one-term
    Ogden to 1e-6; with 1 % noise the relative rms is ~1 %. The closed forms are checked against
    the compressible laws' uniaxial stress from their energies at kappa / mu = 4000 (within 1e-3),
    and a fitted Mooney-Rivlin law in a tet cube compressed 30 % carries the data's stress within
    0.3 % at kappa = 1000 mu and 3 % at 50 mu (nu 0.49): bounds of O(mu / kappa), the
    compressibility the incompressible fit leaves out (measured 0.035 % and 0.7 %)."""
    from rtfem.fe.fitting import uniaxial_stress

    lam = np.linspace(0.7, 1.4, 15)
    cases = [("neo-hookean", [2000.0], 1), ("mooney-rivlin", [700.0, 300.0], 1), ("ogden", [1500.0, 6.0], 1)]
    for name, params, terms in cases:
        data = uniaxial_stress(name, params, lam)
        law, report = rt.fit_material(lam, data, name, terms=terms, kappa_ratio=4000.0)
        np.testing.assert_allclose(report["parameters"], params, rtol=1e-6 if name == "ogden" else 1e-9)
        assert report["relative_rms"] < 1e-8
        for stretch in (0.7, 1.3):  # the incompressible form against the nearly incompressible law
            assert abs(uniaxial(law, stretch)[1] / uniaxial_stress(name, params, stretch) - 1) < 1e-3
    noisy = uniaxial_stress("neo-hookean", [2000.0], lam) * (1 + 0.01 * np.random.default_rng(0).normal(size=lam.size))
    law, report = rt.fit_material(lam, noisy, "neo-hookean", kappa_ratio=50.0)
    assert 0.002 < report["relative_rms"] < 0.02 and abs(law.mu / 2000.0 - 1) < 0.01
    exact = uniaxial_stress("mooney-rivlin", [700.0, 300.0], lam)
    for ratio, tol in ((1000.0, 0.003), (50.0, 0.03)):  # the incompressible fit in a nearly incompressible solid
        law, _ = rt.fit_material(lam, exact, "mooney-rivlin", kappa_ratio=ratio)
        model, X, top = _cube(law, "tet4")
        prescribed = np.zeros((model.n_nodes, 3))
        prescribed[top, 2] = -0.3
        reaction = rt.nonlinear.solve_static(model, prescribed=prescribed, steps=3).reactions[top, 2].sum()
        assert abs(reaction / uniaxial_stress("mooney-rivlin", [700.0, 300.0], 0.7) - 1) < tol, (ratio, reaction)
    for bad, match in [((lam, noisy[:-1]), "same length"), ((lam * 0 + 1, noisy), "not all 1"),
                       ((-lam, noisy), "> 0"), ((lam[:1], noisy[:1], "mooney-rivlin"), "more")]:
        with pytest.raises(ModelError, match=match):
            rt.fit_material(*bad)
    for bad_kwargs in ({"kappa": -1.0}, {"kappa_ratio": 0.0}):
        with pytest.raises(ModelError, match="kappa"):
            rt.fit_material(lam, noisy, **bad_kwargs)


@pytest.mark.parametrize("element", ["tet4", "tet10"])
def test_the_compiled_ogden_forces_equal_the_laws_at_repeated_stretches(element):
    """The compiled Ogden kernel takes the principal stretches by Jacobi rotations: at rest (three
    equal stretches), in uniaxial stretch (two equal) and in a general pose its forces equal the
    law's own P contracted in numpy (numpy's eigh), to round-off."""
    from rtfem.reduction import tet_kernels

    if tet_kernels.compiled_ogden_forces() is None:
        pytest.skip("numba is not installed")
    law = rt.Ogden(mu=[1500.0, 500.0], alpha=[8.0, -2.0], kappa=KAPPA, density=1000.0)
    mesh = rt.meshes.box(0.1, 0.05, 0.05, nx=4, ny=2, nz=2)
    tets = rt.SolidModel(mesh, law, element=element).tetmesh
    X, T = np.asarray(tets.vertices), np.asarray(tets.tets)
    kernel = law.tets(X[T], element)
    G, w = np.ascontiguousarray(np.stack(kernel.G, axis=1)), np.ascontiguousarray(np.stack(kernel.wdet, axis=1))
    Xe = np.ascontiguousarray(X[T])
    rng = np.random.default_rng(5)
    poses = [np.eye(3), np.diag([1.3, 0.9, 0.9]), np.diag([0.7, 1.2, 1.2]), np.eye(3) + 0.2 * rng.normal(size=(3, 3))]
    for Fd in poses:
        V = (Xe @ Fd.T - Xe).reshape(T.shape[0], -1)
        if Fd is poses[-1]:  # and a general pose, off the homogeneous field
            V = V + 1e-4 * rng.normal(size=V.shape)
        V = np.ascontiguousarray(V)
        Fc, Fn = np.empty(V.shape), np.empty(V.shape)
        tet_kernels.law_forces(V, Xe, G, w, law, Fc)
        tet_kernels.law_forces_numpy(V, Xe, G, w, law, Fn)
        scale = max(np.abs(Fn).max(), law.mu * w.max() * np.abs(G).max())  # at rest: a unit strain's force
        assert np.abs(Fc - Fn).max() < 1e-12 * scale, (Fd, np.abs(Fc - Fn).max())


def test_the_compiled_ogden_tangents_equal_the_laws_differences():
    """The reduced model's Ogden tangents (the law's dP/dF by central differences, compiled) equal the
    numpy law's differences contracted with the shape gradients, and the central differences of the
    compiled forces, on a general pose."""
    from rtfem.fe.solid import _tangent_point
    from rtfem.reduction import tet_kernels

    if tet_kernels.compiled_ogden_dP() is None:
        pytest.skip("numba is not installed")
    law = rt.Ogden(mu=[1500.0, 500.0], alpha=[8.0, -2.0], kappa=KAPPA, density=1000.0)
    tets = rt.SolidModel(rt.meshes.box(0.1, 0.05, 0.05, nx=2, ny=1, nz=1), law, element="tet10").tetmesh
    X, T = np.asarray(tets.vertices), np.asarray(tets.tets)
    kernel = law.tets(X[T], "tet10")
    G, w = np.ascontiguousarray(np.stack(kernel.G, axis=1)), np.ascontiguousarray(np.stack(kernel.wdet, axis=1))
    Xe = np.ascontiguousarray(X[T])
    E, nq, k = G.shape[:3]
    V = np.ascontiguousarray(0.004 * np.random.default_rng(8).normal(size=(E, 3 * k)))
    K = np.empty((E, 3 * k, 3 * k))
    tet_kernels.law_tangents(V, Xe, G, w, law, K)
    dP = law.stress(tet_kernels._gradients(V, Xe, G))[2] * w.reshape(-1)[:, None, None, None, None]
    Kn = _tangent_point(np.ascontiguousarray(G.reshape(E * nq, k, 3)), dP).reshape(E, nq, 3 * k, 3 * k).sum(axis=1)
    Kn = 0.5 * (Kn + Kn.transpose(0, 2, 1))
    assert np.abs(K - Kn).max() < 1e-7 * np.abs(Kn).max()
    h = 1e-7
    for j in (0, 7, 20):
        Vp, Vm = V.copy(), V.copy()
        Vp[:, j] += h
        Vm[:, j] -= h
        Fp, Fm = np.empty(V.shape), np.empty(V.shape)
        tet_kernels.law_forces(Vp, Xe, G, w, law, Fp)
        tet_kernels.law_forces(Vm, Xe, G, w, law, Fm)
        assert np.abs((Fp - Fm) / (2 * h) - K[:, :, j]).max() < 1e-5 * np.abs(K).max()
