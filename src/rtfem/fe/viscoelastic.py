"""Viscoelastic soft tissue: a Prony series on the isochoric part of a hyperelastic law
(quasi-linear viscoelasticity; Simo 1987, the form of Abaqus' ``*VISCOELASTIC, TIME=PRONY`` and
FEBio's viscoelastic solid).

The law's isochoric second Piola-Kirchhoff stress S_iso relaxes with the normalized relaxation
function g(t) = g_inf + sum_i g_i exp(-t / tau_i) (g_inf = 1 - sum_i g_i > 0); the volumetric part
does not relax:

    S(t) = S_vol(t) + S_iso(t) - sum_i Q_i(t),   dQ_i/dt + Q_i / tau_i = (g_i / tau_i) S_iso(t),

so that a deformation applied suddenly and held gives S_vol + g(t) S_iso, the law's own stress at
first (the instantaneous response) and g_inf S_iso once relaxed (the long-term law). Over a time
step dt, with S_iso taken linear in time between the step's ends (x = dt / tau_i, a = exp(-x)):

    Q_i(n+1) = a Q_i(n) + g_i (1 - a) S_iso(n) + g_i (1 - (1 - a) / x) (S_iso(n+1) - S_iso(n)),

the hereditary integral's exact value for that interpolation (unconditionally stable, any dt). The
internal variables Q_i and S_iso(n) are kept at every quadrature point of every element by the
simulator that steps them (the model is shared; the history is the simulation's).

Without time (a static solve, the linear solvers, the modal route) a :class:`Prony` law is its
long-term law, :meth:`Prony.long_term`: the equilibrium a held load relaxes to.
"""

from __future__ import annotations

import numpy as np

from .. import validate
from ..errors import ModelError
from .hyperelastic import LAWS, Hyperelastic, _cofactor, _det, law_from_text, make_law
from .solid import HyperelasticTets, _tangent_point

__all__ = ["Prony", "ViscoelasticTets", "material_from_text", "material_from_table", "prony_step", "prony_commit",
           "history_size"]


class Prony(Hyperelastic):
    """A hyperelastic law whose isochoric stress relaxes by a Prony series (see the module's docstring).

    Parameters
    ----------
    law : the instantaneous law (:class:`~rtfem.NeoHookean`, :class:`~rtfem.MooneyRivlin` or
        :class:`~rtfem.Ogden`): the response to a sudden deformation.
    g : the relaxation fractions g_i (each > 0, their sum < 1).
    tau : the relaxation times tau_i (s, each > 0), one per g_i.

    Raises
    ------
    ModelError
        A law that is not a hyperelastic one, fractions that are not positive or sum to 1 or more,
        times that are not positive, lengths that differ.
    """

    name = "prony"

    def __init__(self, law, g, tau) -> None:
        if not isinstance(law, Hyperelastic) or isinstance(law, Prony):
            raise ModelError(f"law={validate.show(law)} must be a hyperelastic law (rt.NeoHookean, rt.MooneyRivlin, "
                             "rt.Ogden): the instantaneous response whose isochoric part relaxes")
        g = validate.real_array(np.atleast_1d(g) if _numeric(g) else g, "g", 1)
        tau = validate.real_array(np.atleast_1d(tau) if _numeric(tau) else tau, "tau", 1)
        if g.size == 0 or g.shape != tau.shape:
            raise ModelError(f"g and tau must be one relaxation fraction per relaxation time, got {g.size} and {tau.size}")
        if np.any(g <= 0) or g.sum() >= 1.0:
            raise ModelError(f"g = {g.tolist()}: each fraction must be > 0 and their sum < 1 (the long-term part "
                             "g_inf = 1 - sum g must stay positive)")
        if np.any(tau <= 0):
            raise ModelError(f"tau = {tau.tolist()}: each relaxation time must be > 0 s")
        self.instantaneous, self.g, self.tau = law, g, tau
        self.g_inf = float(1.0 - g.sum())
        relaxed = self.long_term()
        try:
            relaxed.linearized()
        except ModelError as exc:
            raise ModelError(f"the long-term law {relaxed!r} (g_inf = {self.g_inf:.3g}) has no linear twin: {exc}; "
                             "keep its kappa / (g_inf mu) below 5000") from None
        self.mu, self.kappa, self.density = relaxed.mu, relaxed.kappa, relaxed.density
        self._relaxed = relaxed

    def long_term(self) -> Hyperelastic:
        """The relaxed law: the instantaneous one with its isochoric moduli times g_inf, the same bulk
        modulus."""
        out = self.instantaneous.scaled(self.g_inf)
        out.kappa = self.instantaneous.kappa
        return out

    def relaxation(self, t) -> np.ndarray:
        """g(t) = g_inf + sum_i g_i exp(-t / tau_i) at times t (s)."""
        t = np.asarray(t, dtype=float)
        return self.g_inf + np.sum(self.g * np.exp(-t[..., None] / self.tau), axis=-1)

    def _stress(self, F):
        return self._relaxed._stress(F)

    def _tangent(self, F):
        return self._relaxed._tangent(F)

    def tets(self, X: np.ndarray, element: str) -> "ViscoelasticTets":
        return ViscoelasticTets(X, self, element)

    def coefficients(self, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(a, b, c) per term for a step dt: Q(n+1) = a Q(n) + b S_iso(n) + c S_iso(n+1)."""
        x = validate.positive(dt, "dt", "a time step in s") / self.tau
        a = np.exp(-x)
        c = self.g * (1.0 - (-np.expm1(-x)) / x)
        return a, self.g * (-np.expm1(-x)) - c, c

    def __repr__(self) -> str:
        return f"Prony({self.instantaneous!r}, g={self.g.tolist()}, tau={self.tau.tolist()})"


def _numeric(value) -> bool:
    return isinstance(value, (int, float, np.floating, np.integer))


def _split(law, F, tangent: bool):
    """The instantaneous law at F (m, 3, 3): (P, psi, dP, P_vol, psi_vol, dP_vol), the volumetric
    part kappa / 2 (J - 1)^2: P_vol = kappa (J - 1) cof F,
    dP_vol_abcd = kappa cof_ab cof_cd + kappa (J - 1) / J (cof_ab cof_cd - cof_ad cof_cb)."""
    P, psi, dP = law.stress(F, tangent)
    J, cof, kappa = _det(F), _cofactor(F), law.kappa
    P_vol = kappa * (J - 1.0)[:, None, None] * cof
    psi_vol = 0.5 * kappa * (J - 1.0) ** 2
    dP_vol = None
    if tangent:
        outer = np.einsum("mab,mcd->mabcd", cof, cof)
        dP_vol = kappa * outer + (kappa * (J - 1.0) / J)[:, None, None, None, None] * (
            outer - np.einsum("mad,mcb->mabcd", cof, cof))
    return P, psi, dP, P_vol, psi_vol, dP_vol


class ViscoelasticTets(HyperelasticTets):
    """The tets of one mesh with a :class:`Prony` law. :meth:`evaluate` without a history gives the
    long-term law; with ``history=(h, dt)`` (``h``: :attr:`history_size` floats, each quadrature point's Q_i
    and S_iso(n), from :meth:`committed`) the step's algorithmic response: for x the end of the step,
    S = S_vol + (1 - sum c) S_iso - H, H = sum_i (a_i Q_i + b_i S_iso(n)) held, its consistent tangent
    (1 - sum c) dP + sum c dP_vol - d(F H)/dF and the step's potential psi_vol + (1 - sum c) psi_iso
    - (C - I) : H / 2."""

    def __init__(self, X: np.ndarray, law: Prony, element: str) -> None:
        super().__init__(X, law, element)
        self.n_points, self.n_elements = len(self.G), X.shape[0]
        self.history_size = history_size(law, self.n_points, self.n_elements)

    def evaluate(self, x: np.ndarray, tangent: bool = True, history=None):
        if history is None:
            return super().evaluate(x, tangent)
        h, dt = history
        if h.size != self.history_size:
            raise ModelError(f"a viscoelastic history of {h.size} values for a kernel of {self.history_size}")
        return prony_step(self.law, x, self.G, self.wdet, h, dt, tangent)

    def committed(self, x: np.ndarray, history) -> np.ndarray:
        """The history after a step that ended at deformed nodes x (m, k, 3): Q_i(n+1) and S_iso(n+1)."""
        h, dt = history
        return prony_commit(self.law, x, self.G, h, dt)


def history_size(law: Prony, points: int, elements: int) -> int:
    """The floats of a history of ``elements`` elements with ``points`` quadrature points each:
    per point, the Q_i of each term and S_iso(n), each 3 x 3."""
    return points * elements * (law.g.size + 1) * 9


def _views(law: Prony, h: np.ndarray, points: int):
    """(Q (points, m, terms, 3, 3), S_iso(n) (points, m, 3, 3)) as views of a flat history h."""
    n = law.g.size
    block = h.reshape(points, -1, n + 1, 3, 3)
    return block[:, :, :n], block[:, :, n]


def prony_step(law: Prony, x: np.ndarray, G, wdet, h: np.ndarray, dt: float, tangent: bool = False):
    """The step's algorithmic response of tets with a :class:`Prony` law (see
    :class:`ViscoelasticTets`): for deformed nodes x (m, k, 3) at the end of a step dt from the
    history h, the forces (m, 3k), the tangents (m, 3k, 3k; None unless ``tangent``) and the
    step's potential (m). G: each quadrature point's shape gradients (m, k, 3); wdet: its
    weights times the Jacobian (m,) (a subset of a mesh's elements: the rows of those)."""
    a, b, c = law.coefficients(dt)
    Q, Sn = _views(law, h, len(G))
    m, k = x.shape[:2]
    f = np.zeros((m, k, 3))
    K = np.zeros((m, k, 3, k, 3)) if tangent else None
    energy = np.zeros(m)
    keep = 1.0 - c.sum()
    for q, (Gq, wq) in enumerate(zip(G, wdet)):
        F = np.einsum("mka,mkb->mab", x, Gq)
        P, psi, dP, P_vol, psi_vol, dP_vol = _split(law.instantaneous, F, tangent)
        H = np.einsum("i,miab->mab", a, Q[q]) + b.sum() * Sn[q]
        P_alg = P_vol + keep * (P - P_vol) - F @ H
        C = np.einsum("mka,mkb->mab", F, F)
        psi_alg = psi_vol + keep * (psi - psi_vol) - 0.5 * np.einsum("mab,mab->m", C - np.eye(3), H)
        f += wq[:, None, None] * np.einsum("mab,mib->mia", P_alg, Gq)
        energy += wq * psi_alg
        if tangent:
            dP_alg = keep * dP + (1.0 - keep) * dP_vol - np.einsum("ac,mdb->mabcd", np.eye(3), H)
            K += wq[:, None, None, None, None] * _tangent_point(Gq, dP_alg)
    return f.reshape(m, 3 * k), (K.reshape(m, 3 * k, 3 * k) if tangent else None), energy


def prony_commit(law: Prony, x: np.ndarray, G, h: np.ndarray, dt: float) -> np.ndarray:
    """The history after a step dt from h that ended at deformed nodes x (m, k, 3) (G as
    :func:`prony_step`'s): each point's Q_i(n+1) and S_iso(n+1)."""
    a, b, c = law.coefficients(dt)
    out = np.array(h, dtype=float, copy=True)
    Q, Sn = _views(law, h, len(G))
    Q1, S1 = _views(law, out, len(G))
    for q, Gq in enumerate(G):
        F = np.einsum("mka,mkb->mab", x, Gq)
        P, _, _, P_vol, _, _ = _split(law.instantaneous, F, False)
        S_new = np.linalg.solve(F, P - P_vol)  # F^-1 P_iso
        Q1[q] = a[None, :, None, None] * Q[q] + b[None, :, None, None] * Sn[q][:, None] \
            + c[None, :, None, None] * S_new[:, None]
        S1[q] = S_new
    return out


def material_from_text(text: str, material):
    """The material a command line names (``--material``): a sourced tissue set
    (:func:`rtfem.fe.tissues.tissue_from_text`: "liver", "liver#2", "skin"), or what
    :func:`rtfem.fe.hyperelastic.law_from_text` reads, optionally followed by
    "+prony:g1,tau1[,g2,tau2,...]" (a :class:`Prony` series on that law: fractions of its isochoric
    stress and their relaxation times in s).

    Parameters
    ----------
    text : e.g. "neo-hookean", "ogden:2000,8", "neo-hookean+prony:0.5,0.1".
    material : the linear Material whose E, nu and density a law takes.

    Returns
    -------
    Material, Hyperelastic or Prony
        The material, law or relaxing law.

    Raises
    ------
    ModelError
        Text that names no law, or a Prony series that is not pairs of numbers, or not on a
        hyperelastic law.
    """
    from .tissues import tissue_from_text

    text = str(text).strip()
    found = tissue_from_text(text, material)  # a sourced tissue set ("liver", "liver#2", "skin")
    if found is not None:
        return found.material
    base, plus, prony = text.partition("+")
    if not plus:
        return law_from_text(text, material)
    if tissue_from_text(base.strip(), material) is not None:
        raise ModelError(f"--material {text!r}: a sourced tissue set ({base.strip()}) is taken as its source gives it; "
                         "a Prony series goes on a law: LAW+prony:g1,tau1 (e.g. neo-hookean+prony:0.5,0.1, with --E and "
                         "--nu of the set)")
    kind, _, values = prony.partition(":")
    try:
        numbers = [float(v) for v in values.split(",")] if values.strip() else []
    except ValueError:
        numbers = []
    if kind.strip().lower() != "prony" or len(numbers) < 2 or len(numbers) % 2:
        raise ModelError(f"--material {text!r}: a relaxing law is LAW+prony:g1,tau1[,g2,tau2,...] (fractions of the "
                         "isochoric stress and their times in s), e.g. neo-hookean+prony:0.5,0.1")
    law = law_from_text(base, material)
    if not isinstance(law, Hyperelastic):
        raise ModelError(f"--material {text!r}: a Prony series relaxes a hyperelastic law: give neo-hookean, "
                         "mooney-rivlin:... or ogden:... before +prony")
    return Prony(law, numbers[0::2], numbers[1::2])


#: the keys of a material table for each law (``law`` itself besides): E and nu stand in for the
#: moduli a table leaves out, as --E and --nu do for --material
TABLE_KEYS = {
    "linear": ("E", "nu", "density", "thickness"),
    "neo-hookean": ("mu", "kappa", "E", "nu", "density", "prony"),
    "mooney-rivlin": ("c10", "c01", "kappa", "nu", "density", "prony"),
    "ogden": ("mu", "alpha", "kappa", "nu", "density", "prony"),
}
#: what each key is, for the messages
TABLE_WHAT = {"E": "Young's modulus in Pa", "nu": "Poisson's ratio", "density": "the mass density in kg/m^3",
              "thickness": "a shell's thickness in m", "mu": "the shear modulus in Pa", "kappa": "the bulk modulus in Pa",
              "c10": "C10 in Pa", "c01": "C01 in Pa", "alpha": "Ogden's exponents"}


def _tissue_of_table(table: dict):
    """``{ tissue = "liver#2" }``: a sourced set (:func:`rtfem.tissue`) with, besides it, only the
    nu it lacks, a density or a shell's thickness."""
    from .material import Material
    from .tissues import tissue_from_text

    extra = sorted(set(table) - {"tissue", "nu", "density", "thickness"})
    if extra:
        raise ModelError(f"{', '.join(extra)}: a sourced tissue set gives its own law and moduli; beside tissue give "
                         "only nu (where the set has none), density or thickness")
    text = table["tissue"]
    if not isinstance(text, str) or not text.strip():
        raise ModelError(f"tissue = {validate.show(text)}: give a tissue set's name, e.g. 'liver' or 'liver#2'")
    base = Material(**{k: validate.number(table[k], k, TABLE_WHAT[k]) for k in ("nu", "density", "thickness")
                       if k in table})
    found = tissue_from_text(text, base, nu_given="nu" in table)
    if found is None:
        from .tissues import tissues

        names = sorted({t["name"] for t in tissues()})
        raise ModelError(f"tissue = {text!r} names no set of the table: {', '.join(names)} (rt.tissue)")
    return found.material


def material_from_table(table):
    """The material a table names (a scene file's ``material = {...}``): any law ``--material``
    takes, with its parameters as keys, built by :func:`rtfem.fe.hyperelastic.make_law` as the
    command line's are.

    ``law`` (default "linear") and its keys: linear: E, nu, density, thickness; neo-hookean: mu and
    kappa, or E and nu; mooney-rivlin: c10, c01 (Pa), kappa or nu; ogden: mu = [mu_1, ...], alpha =
    [alpha_1, ...], kappa or nu; each hyperelastic law optionally ``prony = {g = [...], tau = [...]}``
    (:class:`Prony`). A modulus left out comes from E and nu (default :class:`~rtfem.Material`'s) as
    --E and --nu give it: a neo-Hookean mu = E / (2 (1 + nu)), every law's kappa keeps nu's ratio
    kappa / mu; density defaults to Material's. ``tissue = "liver"`` (or "liver#2") instead of a
    law: a sourced set (:func:`rtfem.tissue`), with only nu (where the set has none), density or
    thickness beside it.

    Parameters
    ----------
    table : a dict, e.g. ``{"law": "neo-hookean", "mu": 2000.0, "kappa": 50000.0, "density": 1060.0}``.

    Returns
    -------
    Material, Hyperelastic or Prony

    Raises
    ------
    ModelError
        Not a table, an unknown law or a key the law does not take, a key given twice over (mu and E,
        kappa and nu), a value that is not a finite number of its range (the message names the key).
    """
    from .material import Material

    if not isinstance(table, dict):
        raise ModelError(f"{validate.show(table)} must be a table, e.g. {{ law = 'neo-hookean', mu = 2000, kappa = "
                         "50000, density = 1060 }")
    if "tissue" in table:
        return _tissue_of_table(table)
    law = validate.choice(table.get("law", "linear"), "law", LAWS)
    keys = TABLE_KEYS[law]
    for key in table:
        if key != "law" and key not in keys:
            hint = (": a Prony series relaxes a hyperelastic law (neo-hookean, mooney-rivlin, ogden)" if key == "prony"
                    else f": {law}'s shear modulus is its own ({', '.join(keys[:2])}); nu or kappa give its bulk modulus"
                    if key == "E" else f" (law {law!r} takes {', '.join(keys)})")
            raise ModelError(f"{key}: not a key of law {law!r}{hint}")
    for a, b in (("mu", "E"), ("kappa", "nu")):
        if a in table and b in table:
            raise ModelError(f"{a} and {b}: give one (without {a}, {b} gives it, as --{b} does for --material)")
    base = {k: validate.number(table[k], k, TABLE_WHAT[k]) for k in ("E", "nu", "density", "thickness") if k in table}
    material = Material(**base)
    moduli = {k: table[k] for k in ("mu", "kappa", "c10", "c01", "alpha") if k in table}
    for k in ("kappa", "c10", "c01"):
        if k in moduli:
            moduli[k] = validate.number(moduli[k], k, TABLE_WHAT[k])
    if "kappa" in moduli:
        validate.positive(moduli["kappa"], "kappa", TABLE_WHAT["kappa"])
    out = make_law(law, material, **moduli)
    if "prony" not in table:
        return out
    prony = table["prony"]
    if not isinstance(prony, dict) or set(prony) != {"g", "tau"}:
        raise ModelError("prony must be { g = [g_1, ...], tau = [tau_1, ...] } (fractions of the isochoric stress and "
                         "their relaxation times in s)")
    return Prony(out, prony["g"], prony["tau"])
