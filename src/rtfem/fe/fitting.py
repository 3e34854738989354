"""Fitting a hyperelastic law to uniaxial test data (``rt.fit_material``).

A uniaxial tension or compression test of tissue gives the nominal (first Piola-Kirchhoff) stress
P against the stretch lambda = l / l0. Tissue is nearly incompressible and tested with its sides
free, so the fit uses the incompressible uniaxial closed forms of the laws' isochoric parts
(Ogden, Non-linear Elastic Deformations, 1984, ch. 7; the same as Abaqus' test-data fitting):

- neo-Hookean: P = mu (lambda - lambda^-2)
- Mooney-Rivlin: P = 2 (C10 + C01 / lambda) (lambda - lambda^-2)
- Ogden: P = sum_i (2 mu_i / alpha_i) (lambda^(alpha_i - 1) - lambda^(-alpha_i / 2 - 1))

by nonlinear least squares on the stresses (scipy's trust-region reflective method; Ogden from
several starting exponents, the best kept), and returns the law with a bulk modulus of ``kappa``,
or of ``kappa_ratio`` times the fitted shear modulus (default 50: nu = 0.49 at rest).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from .. import validate
from ..errors import ModelError
from .hyperelastic import MAX_OGDEN_ALPHA, MooneyRivlin, NeoHookean, Ogden

__all__ = ["fit_material", "uniaxial_stress"]

FITS = ("neo-hookean", "mooney-rivlin", "ogden")


def uniaxial_stress(name: str, params, stretch) -> np.ndarray:
    """The incompressible uniaxial nominal stress of law ``name`` with ``params`` (neo-Hookean: [mu];
    Mooney-Rivlin: [C10, C01]; Ogden: [mu_1, alpha_1, mu_2, alpha_2, ...]) at ``stretch``."""
    lam = np.asarray(stretch, float)
    p = np.asarray(params, float)
    if name == "neo-hookean":
        return p[0] * (lam - lam**-2)
    if name == "mooney-rivlin":
        return 2 * (p[0] + p[1] / lam) * (lam - lam**-2)
    out = np.zeros_like(lam)
    for m, a in zip(p[0::2], p[1::2]):
        out += (2 * m / a) * (lam ** (a - 1) - lam ** (-a / 2 - 1))
    return out


def fit_material(stretch, stress, law: str = "neo-hookean", *, terms: int = 1, kappa: float | None = None,
                 kappa_ratio: float = 50.0, density: float = 1000.0):
    """Fit a hyperelastic law to uniaxial data by least squares on the incompressible closed forms
    (module docstring).

    Parameters
    ----------
    stretch : the stretches lambda = l / l0 of the test (> 0, not all 1).
    stress : the nominal stresses in Pa (the force over the undeformed area), as many.
    law : "neo-hookean", "mooney-rivlin" or "ogden".
    terms : Ogden's number of terms, 1..3.
    kappa : the fitted law's bulk modulus in Pa; default ``kappa_ratio`` times its shear modulus.
    kappa_ratio : kappa / mu when ``kappa`` is not given (default 50: nu = 0.49 at rest).
    density : the fitted law's density in kg/m^3.

    Returns
    -------
    tuple
        (the fitted law, {"law", "parameters", "rms" (Pa), "relative_rms" (rms over the rms stress)}).

    Raises
    ------
    ModelError
        Data that are not finite, of different lengths, fewer points than parameters,
        non-positive stretches, or a fit with no stable initial shear modulus.
    """
    name = validate.choice(str(law).lower(), "law", FITS)
    lam = np.asarray(stretch, float).ravel()
    P = np.asarray(stress, float).ravel()
    if lam.shape != P.shape or not (np.isfinite(lam).all() and np.isfinite(P).all()):
        raise ModelError(f"fit_material: stretch ({lam.size}) and stress ({P.size}) must be finite arrays of the same "
                         "length")
    if (lam <= 0).any() or np.all(np.abs(lam - 1) < 1e-12):
        raise ModelError("fit_material: stretches must be > 0 and not all 1 (l / l0 of a tension or compression test)")
    terms = validate.count(terms, "terms", 1, 3)
    kappa = None if kappa is None else validate.positive(kappa, "kappa", "the bulk modulus in Pa")
    kappa_ratio = validate.positive(kappa_ratio, "kappa_ratio", "kappa / mu, e.g. 50")  # before any fitting
    n_params = {"neo-hookean": 1, "mooney-rivlin": 2, "ogden": 2 * terms}[name]
    if lam.size < n_params:
        raise ModelError(f"fit_material: {lam.size} data points for {n_params} parameters: give more")
    scale = float(np.sqrt(np.mean(P**2))) or 1.0
    g = np.abs(lam - lam**-2)
    mu0 = float(np.sum(np.abs(P) * g) / max(np.sum(g * g), 1e-300))  # the neo-Hookean slope: the starting modulus

    def residual(p):
        return (uniaxial_stress(name, p, lam) - P) / scale

    if name == "neo-hookean":
        starts = [[mu0]]
    elif name == "mooney-rivlin":
        starts = [[0.5 * mu0, 0.0], [0.25 * mu0, 0.25 * mu0]]
    else:
        exps = [2.0, 5.0, 8.0, -2.0, 12.0, -5.0]
        starts = []
        for k in range(6):
            alphas = [exps[(k + j) % len(exps)] for j in range(terms)]
            starts.append([v for a in alphas for v in (mu0 / terms, a)])
    best = None
    lo = np.full(len(starts[0]), -np.inf)
    if name == "ogden":  # the exponents within what rt.Ogden takes
        lo[1::2] = -MAX_OGDEN_ALPHA
    for x0 in starts:
        r = least_squares(residual, x0, method="trf", x_scale="jac", max_nfev=2000, bounds=(lo, -lo))
        if best is None or r.cost < best.cost:
            best = r
    p = best.x
    rms = float(np.sqrt(np.mean((uniaxial_stress(name, p, lam) - P) ** 2)))
    mu = {"neo-hookean": lambda: p[0], "mooney-rivlin": lambda: 2 * (p[0] + p[1]),
          "ogden": lambda: float(np.sum(p[0::2]))}[name]()
    if not mu > 0:
        raise ModelError(f"fit_material: the best {name} fit has an initial shear modulus of {mu:g} Pa (unstable): "
                         "try another law, fewer terms, or data over a wider stretch range")
    k = kappa if kappa is not None else kappa_ratio * mu
    if name == "neo-hookean":
        fitted = NeoHookean(float(p[0]), k, density)
    elif name == "mooney-rivlin":
        fitted = MooneyRivlin(float(p[0]), float(p[1]), k, density)
    else:
        fitted = Ogden(p[0::2].tolist(), p[1::2].tolist(), k, density)
    return fitted, {"law": name, "parameters": p.tolist(), "rms": rms, "relative_rms": rms / scale}
