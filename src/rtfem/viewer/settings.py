"""What the viewer's panel controls (:class:`Settings`), checked, and the model's material in words."""

from __future__ import annotations

from dataclasses import dataclass

from .. import validate
from ..errors import ModelError

METHODS = ("modal", "impedance", "direct", "nonlinear")
#: response samples of the maps the impedance method builds per grabbed vertex (s)
MAP_TIMES = (0.005, 0.01, 0.02, 0.035, 0.05, 0.075, 0.1, 0.15, 0.2, 0.3, 0.5, 0.75, 1.0)


@dataclass
class Settings:
    """What the panel controls."""

    method: str = "modal"
    n_modes: int = 40
    dt: float = 1e-3  # s
    alpha: float = 8.0  # mass-proportional damping (1/s)
    E: float | None = None  # Young's modulus (Pa); None: the material's
    grasp_stiffness: float = 200.0  # N/m
    grab_radius: float = 0.01  # m: the jaw holds the surface within this radius of the picked vertex (0: one vertex)
    max_force: float = 10.0  # N: what a desktop haptic device renders (a Touch X: 7.9 N peak); the panel says when it clips
    large: bool = False  # large deformation: modal warping (modal), corotational Newton (direct)
    local: float = 0.0  # m: each grab adds every dof within this of the held nodes to the basis (0: off; method "nonlinear" only)
    # method "nonlinear" (issue 56): while a grasp is held and the error estimate exceeds ``adapt`` (m; 0: never),
    # the basis is localized once around it, every dof within ``adapt_radius`` (m) of the held nodes
    adapt: float = 5e-4
    adapt_radius: float = 0.01
    derivatives: int = 10  # method "nonlinear": the modal derivatives of the lowest this many modes
    spread: int = 1  # method "nonlinear": cubature element groups, one re-evaluated per step (1: all every step, stable)

    def check(self) -> "Settings":
        """Validate every field; returns a checked copy (numbers as floats, n_modes as an int)."""
        return Settings(
            method=validate.choice(self.method, "method", METHODS),
            n_modes=validate.count(self.n_modes, "n_modes", 1, 2000, what="modes in use"),
            dt=validate.in_range(self.dt, "dt", 1e-5, 0.05, what="the viewer's time step in s"),
            alpha=validate.nonnegative(self.alpha, "alpha", "mass-proportional damping in 1/s"),
            E=None if self.E is None else validate.positive(self.E, "E", "Young's modulus in Pa"),
            grasp_stiffness=validate.positive(self.grasp_stiffness, "grasp_stiffness", "the grasp spring in N/m"),
            grab_radius=validate.in_range(self.grab_radius, "grab_radius", 0.0, 1.0, what="the grab radius in m"),
            max_force=validate.positive(self.max_force, "max_force", "the force cap in N"),
            large=_large(self.method, self.large),
            local=validate.in_range(self.local, "local", 0.0, 1.0, what="the radius in m of the patch a grab adds"),
            adapt=validate.in_range(self.adapt, "adapt", 0.0, 1.0, what="the error estimate in m above which the basis "
                                    "is localized around the grasp (0: never)"),
            adapt_radius=validate.in_range(self.adapt_radius, "adapt_radius", 0.0, 0.05, lo_open=True,
                                           what="the radius in m of the patch an estimate above adapt adds; a 0.5 m "
                                           "patch of the 1,701-node block trained for minutes in 4.8 GB"),
            derivatives=validate.count(self.derivatives, "derivatives", 0, 200, what="modes whose derivatives are kept"),
            spread=validate.count(self.spread, "spread", 1, 64, what="cubature element groups"),
        )

    @property
    def label(self) -> str:
        """The method in words, with the large-deformation variant when on."""
        if self.method == "nonlinear":
            patch = (f", localized per grab ({self.local * 1e3:g} mm)" if self.local > 0 else
                     f", {self.adapt_radius * 1e3:g} mm patch above a {self.adapt * 1e3:g} mm estimate" if self.adapt > 0
                     else "")
            return f"reduced nonlinear (modes + derivatives{patch})"
        if not self.large:
            return self.method
        return {"modal": "modal (warped)", "direct": "direct (corotational)"}.get(self.method, self.method)


def describe_material(model) -> str:
    """The model's material in words: a hyperelastic law with its moduli, or the linear one's E and nu
    (a shell's thickness too)."""
    law = getattr(model, "law", None)
    if law is not None:
        return f"{law.name} {law!r}"
    if getattr(model, "materials", None):
        return "; ".join(f"region {k}: {v!r}" for k, v in model.materials.items())
    m = model.material
    text = f"linear elastic, E = {m.E / 1e3:g} kPa, nu = {m.nu:g}, density {m.density:g} kg/m^3"
    return text + (f", thickness {m.thickness * 1e3:g} mm" if getattr(model, "element", None) is None else "")


def _large(method: str, large) -> bool:
    large = validate.flag(large, "large")
    if large and method == "impedance":
        raise ModelError("large deformation: the impedance map superposes linear responses; use the modal method (modal "
                         "warping) or direct (the corotational full order)")
    return large
