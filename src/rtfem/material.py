"""Material parameters of the shell (SI units)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import ModelError

__all__ = ["Material"]


def _finite_positive(name: str, value: float, what: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ModelError(f"Material {name}={value!r} is not a number; give {what}.") from None
    if not math.isfinite(v) or v <= 0.0:
        raise ModelError(f"Material {name}={value!r} must be a finite number > 0 ({what}).")
    return v


@dataclass(frozen=True)
class Material:
    """Linear isotropic elastic shell material.

    Parameters
    ----------
    E : Young's modulus in Pa (soft tissue: 1e3 .. 1e6 Pa).
    nu : Poisson's ratio, -1 < nu < 0.5 (tissue is nearly incompressible: 0.45 .. 0.49).
    thickness : shell thickness in m.
    density : mass density in kg/m^3 (tissue: about 1000 .. 1100).
    """

    E: float = 3.0e4
    nu: float = 0.45
    thickness: float = 4.0e-3
    density: float = 1060.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "E", _finite_positive("E", self.E, "Young's modulus in Pa"))
        object.__setattr__(
            self, "thickness", _finite_positive("thickness", self.thickness, "the shell thickness in m")
        )
        object.__setattr__(
            self, "density", _finite_positive("density", self.density, "the mass density in kg/m^3")
        )
        try:
            nu = float(self.nu)
        except (TypeError, ValueError):
            raise ModelError(f"Material nu={self.nu!r} is not a number; give -1 < nu < 0.5.") from None
        if not math.isfinite(nu) or not (-1.0 < nu < 0.5):
            raise ModelError(
                f"Material nu={self.nu!r} is outside (-1, 0.5): an isotropic elastic material "
                "needs -1 < nu < 0.5 (soft tissue: 0.45 .. 0.49)."
            )
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
