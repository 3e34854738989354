"""Material parameters of the shell (SI units)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import validate
from ..errors import ModelError

__all__ = ["Material", "Damping"]


def finite_positive(name: str, value: float, what: str, owner: str = "Material ") -> float:
    """``value`` as a float, or a ModelError naming it when it is not a finite number > 0."""
    return validate.positive(value, f"{owner}{name}", what)


@dataclass(frozen=True)
class Material:
    """Linear isotropic elastic material of shells and solids (frozen).

    Parameters
    ----------
    E : Young's modulus in Pa, 1e-6 .. 1e13 (soft tissue: 1e3 .. 1e6 Pa).
    nu : Poisson's ratio, -1 < nu <= 0.4999 (tissue is nearly incompressible: 0.45 .. 0.49).
    thickness : shell thickness in m (ignored by solids).
    density : mass density in kg/m^3 (tissue: about 1000 .. 1100).

    Raises
    ------
    ModelError
        A value that is not a finite number, or outside those ranges.
    """

    E: float = 3.0e4
    nu: float = 0.45
    thickness: float = 4.0e-3
    density: float = 1060.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "E", finite_positive("E", self.E, "Young's modulus in Pa"))
        if not 1e-6 <= self.E <= 1e13:
            raise ModelError(f"Material E={self.E!r} Pa is outside 1e-6 .. 1e13 Pa (soft tissue: 1e3 .. 1e6 Pa, steel "
                             "2e11): give Young's modulus in pascals")
        object.__setattr__(
            self, "thickness", finite_positive("thickness", self.thickness, "the shell thickness in m")
        )
        object.__setattr__(
            self, "density", finite_positive("density", self.density, "the mass density in kg/m^3")
        )
        nu = validate.number(self.nu, "Material nu", "Poisson's ratio, -1 < nu < 0.5")
        if not (-1.0 < nu < 0.5):
            raise ModelError(
                f"Material nu={self.nu!r} is outside (-1, 0.5): an isotropic elastic material "
                "needs -1 < nu < 0.5 (soft tissue: 0.45 .. 0.49)."
            )
        if nu > 0.4999:
            raise ModelError(f"Material nu={self.nu!r} is within 1e-4 of 0.5: the bulk modulus is then "
                             f"{1 / (3 * (1 - 2 * nu)):.3g} times E and the stiffness singular to working precision. "
                             "Give nu <= 0.4999 (soft tissue: 0.45 .. 0.49, with element='tet10')")
        object.__setattr__(self, "nu", nu)

    @property
    def G(self) -> float:
        """Shear modulus E / (2 (1 + nu))."""
        return self.E / (2.0 * (1.0 + self.nu))

    @property
    def bending_rigidity(self) -> float:
        """Plate bending rigidity D = E t^3 / (12 (1 - nu^2))."""
        return self.E * self.thickness**3 / (12.0 * (1.0 - self.nu**2))

    def plane_stress(self) -> np.ndarray:
        """3x3 plane-stress constitutive matrix per unit thickness (engineering shear strain)."""
        c = self.E / (1.0 - self.nu**2)
        return c * np.array(
            [[1.0, self.nu, 0.0], [self.nu, 1.0, 0.0], [0.0, 0.0, 0.5 * (1.0 - self.nu)]]
        )


@dataclass(frozen=True)
class Damping:
    """Viscous damping, mapped to one damping coefficient per mode (Eq. 9). The three kinds add
    up: mode i gets alpha_i = alpha + beta w_i^2 + 2 zeta_i w_i, so that
    x_i'' + alpha_i x_i' + w_i^2 x_i = f_i.

    Parameters
    ----------
    alpha : mass-proportional, B = alpha M (the paper's choice), in 1/s; >= 0.
    beta : stiffness-proportional, B = alpha M + beta K (Rayleigh), in s; >= 0.
    zeta : modal damping ratios >= 0: a scalar for all modes, or one per mode (modal drivers
        only: there is no full-system matrix for them).

    Raises
    ------
    ModelError
        A negative or non-finite value, or zeta that is not ratios.
    """

    alpha: float = 0.0
    beta: float = 0.0
    zeta: float | tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        for name in ("alpha", "beta"):
            v = validate.nonnegative(getattr(self, name), f"Damping {name}",
                                     "1/s" if name == "alpha" else "s")
            object.__setattr__(self, name, v)
        if self.zeta is not None:
            if isinstance(self.zeta, (bool, np.bool_)):
                raise ModelError(f"Damping zeta={self.zeta!r} must be damping ratios >= 0")
            z = np.atleast_1d(validate.real_array(self.zeta, "Damping zeta", finite=False))
            if z.ndim != 1 or z.size == 0 or not np.all(np.isfinite(z)) or np.any(z < 0):
                raise ModelError(f"Damping zeta={validate.show(self.zeta)} must be finite damping ratios >= 0")
            object.__setattr__(self, "zeta", float(z[0]) if z.size == 1 and np.ndim(self.zeta) == 0 else tuple(z.tolist()))

    @property
    def is_modal_only(self) -> bool:
        """True when the damping has no full-system matrix (modal damping ratios)."""
        return self.zeta is not None and (np.ndim(self.zeta) > 0 or self.zeta != 0.0)

    def modal_alpha(self, omega: np.ndarray) -> np.ndarray:
        """Per-mode damping coefficients alpha_i = alpha + beta w_i^2 + 2 zeta_i w_i (Eq. 9): the one
        copy of the formula (SLDM evaluates it at Ritz values through :meth:`alpha_of_eigenvalue`)."""
        w = np.asarray(omega, dtype=float)
        a = self.alpha + self.beta * w**2
        if self.zeta is not None:
            z = np.asarray(self.zeta, dtype=float)
            if z.ndim == 1 and z.size not in (1, w.size):
                raise ModelError(f"Damping has {z.size} modal damping ratios but the basis has {w.size} modes")
            a = a + 2.0 * z * w
        return a

    def alpha_of_eigenvalue(self, lam: np.ndarray) -> np.ndarray:
        """:meth:`modal_alpha` at w = sqrt(lam) (lam = w^2 >= 0; round-off negatives clipped)."""
        return self.modal_alpha(np.sqrt(np.clip(np.asarray(lam, dtype=float), 0.0, None)))

    def matrix(self, M, K):
        """The full-system damping matrix B = alpha M + beta K (refused for modal ratios)."""
        if self.is_modal_only:
            raise ModelError(
                "modal damping ratios (zeta) define no full-system damping matrix; "
                "use alpha (B = alpha M) and/or beta (B = alpha M + beta K) for a full-order solver"
            )
        return self.alpha * M + self.beta * K
