"""Hyperelastic laws of soft tissue for solids: neo-Hookean, Mooney-Rivlin and Ogden, with the
isochoric / volumetric split of the FE codes users compare with.

    W = W_iso(I1bar, I2bar or the stretches lambda_a bar) + kappa / 2 (J - 1)^2

with J = det F, Cbar = J^(-2/3) F^T F, I1bar = tr Cbar, I2bar = (I1bar^2 - tr Cbar^2) / 2 and
lambda_a bar = J^(-1/3) lambda_a (Abaqus Theory Manual 4.6.1 and CalculiX's ``*HYPERELASTIC``, which
write the volumetric part as (J - 1)^2 / D1: kappa = 2 / D1).

- neo-Hookean: W_iso = mu / 2 (I1bar - 3) (C10 = mu / 2);
- Mooney-Rivlin: W_iso = C10 (I1bar - 3) + C01 (I2bar - 3) (mu = 2 (C10 + C01));
- Ogden: W_iso = sum_i 2 mu_i / alpha_i^2 (sum_a lambda_a bar^alpha_i - 3) (mu = sum_i mu_i;
  N = 1, alpha = 2 is neo-Hookean; alpha = (2, -2) is Mooney-Rivlin with C10 = mu_1 / 2,
  C01 = mu_2 / 2, since lambda_1bar^-2 + lambda_2bar^-2 + lambda_3bar^-2 = I2bar).

Each law gives the first Piola-Kirchhoff stress P(F), the energy density and the tangent dP/dF
for a batch of deformation gradients. Neo-Hookean and Mooney-Rivlin write P in closed form from
the invariants; their tangent is the complex-step derivative of that P (Squire & Trapp, SIAM
Review 40 (1998) 110: Im P(F + i h E_cd) / h, exact to round-off for any h as small as 1e-30,
with no difference to cancel), nine evaluations in complex arithmetic. Ogden's P comes from the
principal stretches (the eigenvectors of C; Simo & Taylor 1991's principal Kirchhoff stresses
tau_a = dev(lambda bar d W_iso / d lambda bar)_a + J p, p = kappa (J - 1)), its tangent from
central differences of P (an eigen-decomposition has no complex step; ~1e-9 relative).

At rest every law is the linear isotropic material of shear modulus mu and bulk modulus kappa
(E = 9 kappa mu / (3 kappa + mu), nu = (3 kappa - 2 mu) / (2 (3 kappa + mu))): :meth:`linearized`
is the :class:`~rtfem.Material` the linear solvers and the modal route use.
"""

from __future__ import annotations

import numpy as np

from .. import validate
from ..errors import ModelError
from .material import Material

__all__ = ["Hyperelastic", "NeoHookean", "MooneyRivlin", "Ogden", "law_from_text", "make_law", "LAWS"]


def _det(F):
    return (F[:, 0, 0] * (F[:, 1, 1] * F[:, 2, 2] - F[:, 1, 2] * F[:, 2, 1])
            - F[:, 0, 1] * (F[:, 1, 0] * F[:, 2, 2] - F[:, 1, 2] * F[:, 2, 0])
            + F[:, 0, 2] * (F[:, 1, 0] * F[:, 2, 1] - F[:, 1, 1] * F[:, 2, 0]))


def _cofactor(F):
    """cof F = det(F) F^-T, written out (holomorphic: the complex step goes through it)."""
    C = np.empty_like(F)
    for i in range(3):
        i1, i2 = (i + 1) % 3, (i + 2) % 3
        for j in range(3):
            j1, j2 = (j + 1) % 3, (j + 2) % 3
            C[:, i, j] = F[:, i1, j1] * F[:, i2, j2] - F[:, i1, j2] * F[:, i2, j1]
    return C


class Hyperelastic:
    """A hyperelastic law (isochoric part + kappa / 2 (J - 1)^2); see the module's docstring.
    ``mu``: the initial shear modulus, ``kappa``: the bulk modulus (Pa), ``density`` (kg/m^3)."""

    name = "hyperelastic"
    mu: float
    kappa: float
    density: float

    def _check_common(self, kappa, density) -> None:
        if not self.mu > 0:
            raise ModelError(f"{type(self).__name__}: the initial shear modulus mu = {self.mu:g} Pa must be > 0 (a "
                             "stable law)")
        self.kappa = validate.positive(kappa, f"{type(self).__name__} kappa", "the bulk modulus in Pa, e.g. 1e5")
        self.density = validate.positive(density, f"{type(self).__name__} density", "the mass density in kg/m^3")
        try:
            self.linearized()
        except ModelError as exc:
            raise ModelError(f"{self!r}: kappa / mu = {self.kappa / self.mu:.4g} has no linear twin the linear solvers "
                             f"can use ({exc}); keep kappa / mu below 5000 (nu <= 0.4999)") from None

    def linearized(self) -> Material:
        """The linear isotropic material of this law at rest (same mu and kappa, same density)."""
        mu, kappa = self.mu, self.kappa
        return Material(E=9 * kappa * mu / (3 * kappa + mu), nu=(3 * kappa - 2 * mu) / (2 * (3 * kappa + mu)),
                        density=self.density)

    def scaled(self, factor: float) -> "Hyperelastic":
        """The same law with every modulus times ``factor`` (the same shape of the stress-stretch
        curve, stiffer or softer: what the viewer's E control does to a law)."""
        factor = validate.positive(factor, "factor", "a stiffness scale such as 2.0")
        out = object.__new__(type(self))
        out.__dict__.update(self.__dict__)
        for name in ("mu", "kappa", "c10", "c01"):
            if name in out.__dict__:
                out.__dict__[name] = out.__dict__[name] * factor
        if "mus" in out.__dict__:
            out.mus = out.mus * factor
        return out

    # ---------------------------------------------------------------- the law
    def _stress(self, F: np.ndarray):
        """P (m, 3, 3) and the energy density (m,) at deformation gradients F (m, 3, 3)."""
        raise NotImplementedError

    def _tangent(self, F: np.ndarray) -> np.ndarray:
        """dP_ab / dF_cd (m, 3, 3, 3, 3) by central differences of P (step 1e-6)."""
        h = 1e-6
        out = np.empty(F.shape + (3, 3))
        for c in range(3):
            for d in range(3):
                Fp, Fm = F.copy(), F.copy()
                Fp[:, c, d] += h
                Fm[:, c, d] -= h
                out[:, :, :, c, d] = (self._stress(Fp)[0] - self._stress(Fm)[0]) / (2 * h)
        return out

    def stress(self, F: np.ndarray, tangent: bool = True):
        """First Piola-Kirchhoff stress P (m, 3, 3), energy density (m,) and, if ``tangent``,
        dP/dF (m, 3, 3, 3, 3) ([a, b, c, d] = dP_ab / dF_cd) at deformation gradients F (m, 3, 3).
        An inverted or degenerate F (det F <= 0) gives NaN stresses and an infinite energy (a
        Newton step or a trust-region step then refuses it)."""
        F = np.asarray(F, dtype=float)
        P, psi = self._stress(F)
        bad = ~(_det(F) > 0)
        if bad.any():
            P[bad], psi[bad] = np.nan, np.inf
        if not tangent:
            return P, psi, None
        dP = self._tangent(F)
        if bad.any():
            dP[bad] = np.nan
        return P, psi, dP

    def tets(self, X: np.ndarray, element: str):
        """This law's element kernel on tets X (m, k, 3) (:class:`rtfem.fe.solid.HyperelasticTets`)."""
        from .solid import HyperelasticTets

        return HyperelasticTets(X, self, element)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(mu={self.mu:g}, kappa={self.kappa:g}, density={self.density:g})"


class _Invariants(Hyperelastic):
    """A law W_iso = C10 (I1bar - 3) + C01 (I2bar - 3): P in closed form, the tangent by complex step."""

    c10: float
    c01: float

    def _stress(self, F):
        J = _det(F)
        cof = _cofactor(F)  # J F^-T
        C = np.einsum("mki,mkj->mij", F, F)
        I1 = np.einsum("mii->m", C)
        I2 = 0.5 * (I1 * I1 - np.einsum("mij,mji->m", C, C))
        with np.errstate(invalid="ignore", divide="ignore"):
            j23 = J ** (-2.0 / 3.0)
            FinvT = cof / J[:, None, None]
        P = self.c10 * j23[:, None, None] * (2 * F - (2.0 / 3.0) * I1[:, None, None] * FinvT)
        if self.c01:
            FC = np.einsum("mik,mkj->mij", F, C)
            P = P + self.c01 * (j23 * j23)[:, None, None] * (
                2 * I1[:, None, None] * F - 2 * FC - (4.0 / 3.0) * I2[:, None, None] * FinvT)
        P = P + (self.kappa * (J - 1.0))[:, None, None] * cof
        psi = self.c10 * (j23 * I1 - 3.0) + self.c01 * (j23 * j23 * I2 - 3.0) + 0.5 * self.kappa * (J - 1.0) ** 2
        return P, psi

    def _tangent(self, F):
        h = 1e-30
        out = np.empty(F.shape + (3, 3))
        Fc = F.astype(complex)
        for c in range(3):
            for d in range(3):
                Fc[:, c, d] += 1j * h
                out[:, :, :, c, d] = self._stress(Fc)[0].imag / h
                Fc[:, c, d] = F[:, c, d]
        return out


class NeoHookean(_Invariants):
    """Neo-Hookean: W = mu / 2 (I1bar - 3) + kappa / 2 (J - 1)^2 (Abaqus / CalculiX ``NEO HOOKE``
    with C10 = mu / 2, D1 = 2 / kappa).

    Parameters
    ----------
    mu : the shear modulus in Pa (soft tissue: 1e2 .. 1e5).
    kappa : the bulk modulus in Pa; kappa / mu below 5000 (nu <= 0.4999 at rest).
    density : the mass density in kg/m^3.

    Raises
    ------
    ModelError
        A mu, kappa or density that is not a finite number > 0, or a kappa / mu with no linear twin.
    """

    name = "neo-hookean"

    def __init__(self, mu: float, kappa: float, density: float = 1000.0) -> None:
        self.mu = validate.positive(mu, "NeoHookean mu", "the shear modulus in Pa, e.g. 2000")
        self.c10, self.c01 = 0.5 * self.mu, 0.0
        self._check_common(kappa, density)


class MooneyRivlin(_Invariants):
    """Mooney-Rivlin: W = C10 (I1bar - 3) + C01 (I2bar - 3) + kappa / 2 (J - 1)^2 (Abaqus /
    CalculiX ``MOONEY-RIVLIN``, D1 = 2 / kappa); initial shear modulus mu = 2 (C10 + C01).

    Parameters
    ----------
    c10, c01 : the moduli C10 and C01 in Pa (C01 may be negative if C10 + C01 > 0).
    kappa : the bulk modulus in Pa; kappa / mu below 5000.
    density : the mass density in kg/m^3.

    Raises
    ------
    ModelError
        Values that are not finite numbers, a kappa or density not > 0, or C10 + C01 <= 0 (no
        stable initial shear modulus).
    """

    name = "mooney-rivlin"

    def __init__(self, c10: float, c01: float, kappa: float, density: float = 1000.0) -> None:
        self.c10 = validate.number(c10, "MooneyRivlin c10", "C10 in Pa")
        self.c01 = validate.number(c01, "MooneyRivlin c01", "C01 in Pa")
        self.mu = 2.0 * (self.c10 + self.c01)
        self._check_common(kappa, density)

    def __repr__(self) -> str:
        return f"MooneyRivlin(c10={self.c10:g}, c01={self.c01:g}, kappa={self.kappa:g}, density={self.density:g})"


MAX_OGDEN_ALPHA = 100.0  # the largest |alpha_i| an Ogden law takes


class Ogden(Hyperelastic):
    """Ogden: W = sum_i 2 mu_i / alpha_i^2 (lambda_1bar^alpha_i + lambda_2bar^alpha_i +
    lambda_3bar^alpha_i - 3) + kappa / 2 (J - 1)^2 (Abaqus / CalculiX ``OGDEN``, N = 1..6 terms);
    initial shear modulus mu = sum_i mu_i.

    In this form a term with mu_i > 0 is convex in the logarithmic stretches (Ogden's own form's
    condition mu_p alpha_p > 0, with mu_p = 2 mu_i / alpha_i); fitted tissue parameters often mix
    signs, which is accepted as long as mu = sum mu_i > 0, and whose stability then holds over the
    strain range of the fit only.

    Parameters
    ----------
    mu : the moduli mu_i in Pa, 1 to 6 of them (a list, or one number).
    alpha : the exponents alpha_i, as many.
    kappa : the bulk modulus in Pa; kappa / sum(mu) below 5000.
    density : the mass density in kg/m^3.

    Raises
    ------
    ModelError
        Lists of different lengths, more than 6 terms, an alpha or a mu_i of 0, an |alpha_i| over 100, or
        sum mu_i <= 0
        (no stable initial shear modulus).
    """

    name = "ogden"

    def __init__(self, mu, alpha, kappa: float, density: float = 1000.0) -> None:
        mus = np.atleast_1d(np.asarray(mu, dtype=float))
        alphas = np.atleast_1d(np.asarray(alpha, dtype=float))
        if mus.ndim != 1 or alphas.shape != mus.shape or not 1 <= mus.size <= 6:
            raise ModelError(f"Ogden mu={validate.show(mu)}, alpha={validate.show(alpha)}: give 1 to 6 terms, as "
                             "two lists of the same length (e.g. mu=[2000.0], alpha=[8.0])")
        if not (np.isfinite(mus).all() and np.isfinite(alphas).all()):
            raise ModelError("Ogden mu and alpha must be finite numbers")
        if (np.abs(alphas) > MAX_OGDEN_ALPHA).any():
            raise ModelError(f"Ogden alpha={alphas.tolist()}: each exponent must be within +-{MAX_OGDEN_ALPHA:g} (fitted "
                             "soft tissue uses |alpha| up to about 30; a stretch of 1.5 to the power 1e3 is 1e176)")
        if (alphas == 0).any() or (mus == 0).any():
            raise ModelError(f"Ogden mu={mus.tolist()}, alpha={alphas.tolist()}: every term needs mu_i != 0 and "
                             "alpha_i != 0 (drop a term that is zero)")
        self.mus, self.alphas = mus, alphas
        self.mu = float(mus.sum())
        self._check_common(kappa, density)

    def _stress(self, F):
        J = _det(F)
        C = np.einsum("mki,mkj->mij", F, F)
        lam2, N = np.linalg.eigh(C)
        with np.errstate(invalid="ignore", divide="ignore"):
            jb = np.abs(J) ** (-1.0 / 3.0)
            lb = np.sqrt(np.maximum(lam2, 0.0)) * jb[:, None]  # lambda_a bar
            beta = np.zeros_like(lb)  # lambda_a bar dW_iso / d lambda_a bar
            W = np.zeros(J.shape)
            for m, a in zip(self.mus, self.alphas):
                p = lb ** a
                beta += (2 * m / a) * p
                W += (2 * m / a**2) * (p.sum(axis=1) - 3.0)
            tau = beta - beta.mean(axis=1)[:, None] + (self.kappa * J * (J - 1.0))[:, None]  # principal Kirchhoff
            S = np.einsum("mia,ma,mja->mij", N, tau / lam2, N)  # second Piola-Kirchhoff
        P = np.einsum("mik,mkj->mij", F, S)
        return P, W + 0.5 * self.kappa * (J - 1.0) ** 2

    def __repr__(self) -> str:
        return (f"Ogden(mu={self.mus.tolist()}, alpha={self.alphas.tolist()}, kappa={self.kappa:g}, "
                f"density={self.density:g})")


LAWS = ("linear", "neo-hookean", "mooney-rivlin", "ogden")


def make_law(name: str, material: Material, *, mu=None, kappa=None, c10=None, c01=None, alpha=None):
    """The law ``name`` of :data:`LAWS`, its moduli those given and the rest from ``material`` as the
    command line's ``--E``, ``--nu`` and ``--density`` give them: the one builder behind ``--material``
    (:func:`law_from_text`) and a scene file's ``material`` table
    (:func:`rtfem.fe.viscoelastic.material_from_table`).

    Parameters
    ----------
    name : "linear" (``material`` itself), "neo-hookean", "mooney-rivlin" or "ogden".
    material : the linear Material: its density, its E and nu for what is not given.
    mu : neo-Hookean: its shear modulus (default ``material``'s, E / (2 (1 + nu))); Ogden: the
        moduli mu_i (a list).
    kappa : the bulk modulus (Pa); default: the law's shear modulus at rest times ``material``'s
        kappa / mu, i.e. the same Poisson's ratio at rest.
    c10, c01 : Mooney-Rivlin's moduli (Pa), both needed.
    alpha : Ogden's exponents, one per mu_i.

    Returns
    -------
    Material or Hyperelastic

    Raises
    ------
    ModelError
        An unknown name, a Mooney-Rivlin or Ogden law without its moduli, what the law's
        constructor refuses (a modulus that is not a finite number, kappa <= 0, ...).
    """
    E, nu = material.E, material.nu
    mu_0, kappa_0 = E / (2 * (1 + nu)), E / (3 * (1 - 2 * nu))  # material's; a law keeps kappa_0 / mu_0
    if name == "linear":
        return material
    if name == "neo-hookean":
        if mu is None:
            return NeoHookean(mu_0, kappa_0 if kappa is None else kappa, material.density)
        mu = validate.positive(mu, "mu", "the shear modulus in Pa, e.g. 2000")
        return NeoHookean(mu, mu * kappa_0 / mu_0 if kappa is None else kappa, material.density)
    if name == "mooney-rivlin":
        if c10 is None or c01 is None:
            raise ModelError("mooney-rivlin needs both its moduli, c10 and c01 (Pa)")
        c10, c01 = validate.number(c10, "c10", "C10 in Pa"), validate.number(c01, "c01", "C01 in Pa")
        return MooneyRivlin(c10, c01, 2 * (c10 + c01) * kappa_0 / mu_0 if kappa is None else kappa, material.density)
    if name == "ogden":
        if mu is None or alpha is None:
            raise ModelError("ogden needs its moduli mu = [mu_1, ...] (Pa) and exponents alpha = [alpha_1, ...], as "
                             "many of each")
        mu = np.atleast_1d(validate.real_array(mu, "mu"))
        alpha = np.atleast_1d(validate.real_array(alpha, "alpha"))
        return Ogden(mu.tolist(), alpha.tolist(), float(mu.sum()) * kappa_0 / mu_0 if kappa is None else kappa,
                     material.density)
    raise ModelError(f"law {validate.show(name)}: choose one of {', '.join(LAWS)}")


def law_from_text(text: str, material: Material):
    """The material a command line names (``--material``): "linear" (``material`` itself),
    "neo-hookean" (mu and kappa of ``material``'s E and nu; "linear:E[,nu]" and
    "neo-hookean:E[,nu]" with their own), "mooney-rivlin:C10,C01" or
    "ogden:mu1,alpha1[,mu2,alpha2,...]" (moduli in Pa; kappa keeps ``material``'s ratio kappa / mu,
    i.e. the same Poisson's ratio at rest); the density is ``material``'s (a relaxing law:
    :func:`rtfem.fe.viscoelastic.material_from_text`; the law built by :func:`make_law`). Raises
    ModelError naming what is wrong."""
    text = str(text).strip()
    name, _, values = text.partition(":")
    name = name.strip().lower()
    if name not in LAWS:
        raise ModelError(f"--material {text!r}: choose one of {', '.join(LAWS)} (mooney-rivlin and ogden with their "
                         "parameters: mooney-rivlin:C10,C01, ogden:mu1,alpha1[,mu2,alpha2...], in Pa), or a sourced tissue "
                         "set: brain, fat, gallbladder, liver, muscle, skin, stomach (rt.tissue; TISSUE#N its N-th set)")
    try:
        numbers = [float(v) for v in values.split(",")] if values.strip() else []
    except ValueError:
        raise ModelError(f"--material {text!r}: the parameters after ':' must be numbers separated by commas") from None
    if name in ("linear", "neo-hookean"):
        if numbers:  # its own E[, nu]: a region stiffer than the rest
            if len(numbers) > 2:
                raise ModelError(f"--material {text!r}: {name} takes --E and --nu's moduli, or its own as {name}:E[,nu] "
                                 "(Pa and a ratio)")
            material = Material(E=numbers[0], nu=numbers[1] if len(numbers) == 2 else material.nu,
                                thickness=material.thickness, density=material.density)
        return make_law(name, material)
    if name == "mooney-rivlin":
        if len(numbers) != 2:
            raise ModelError(f"--material {text!r}: give mooney-rivlin:C10,C01 (two moduli in Pa)")
        return make_law(name, material, c10=numbers[0], c01=numbers[1])
    if len(numbers) < 2 or len(numbers) % 2:
        raise ModelError(f"--material {text!r}: give ogden:mu1,alpha1[,mu2,alpha2,...] (pairs of a modulus in Pa and "
                         "an exponent)")
    return make_law(name, material, mu=numbers[0::2], alpha=numbers[1::2])
