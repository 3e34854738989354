"""The viewer's scalpel (issue 57): a blade drawn through a solid organ cuts it while it runs.

The first stroke puts the session in scalpel mode. The organ goes full order (a cut opens only there:
a new lagged corotational driver, whatever the method was; the motion it had is left), set at rest at
its static equilibrium under gravity (:func:`rtfem.nonlinear.solve_static`), so that it hangs from its
fixed nodes before the blade touches it and a cut opens under its weight; an :class:`rtfem.Scalpel`
steps it, on the session's own clock (``thread=False``), cutting where the blade sweeps: each cut is
made and assembled in the scalpel's worker process and swapped in between two steps, and the session
takes the cut model as its own (its surface, drawn vertices and region colours; ``generation`` counts
them, for the front end to send the new surface). The blade leaves the tissue with :meth:`lift`; the
organ keeps hanging. A grasp is refused in scalpel mode; :meth:`~rtfem.viewer.session.Session.configure` (the panel's Reset)
leaves it, rebuilding the chosen method on the cut mesh: the cut is kept, undone only by reloading.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .. import validate
from ..errors import ModelError

__all__ = ["Cutting", "GRAVITY"]

GRAVITY = (0.0, 0.0, -9.81)  # m/s^2 on the organ in scalpel mode (the viewer's frame: z up)


class Cutting:
    """The :class:`~rtfem.viewer.session.Session`'s scalpel mode (see the module)."""

    scalpel = None  # the rt.Scalpel stepping the organ in scalpel mode, else None
    _pre_scalpel = None  # the settings before scalpel mode (its method and large-deformation switch)
    generation = 0  # the cut models taken so far (the front end redraws the surface when it changes)
    cut_status = ""  # what the scalpel mode is doing, for the panel

    def cut(self, tip, heel) -> None:
        """The blade from ``heel`` to ``tip`` (m, the organ's frame) for the next steps: the first call
        enters scalpel mode (see the module; its solve runs outside the session's lock, the organ stepping
        and drawn meanwhile), each call after :meth:`lift` starts a new stroke there."""
        tip, heel = validate.point(tip, "blade tip"), validate.point(heel, "blade heel")
        if not np.linalg.norm(tip - heel) > 0:
            raise ModelError("the blade's tip and heel coincide: give a blade of some length")
        with self._entry:  # one entry at a time
            if self.scalpel is None:
                self._enter_scalpel_mode()
        with self._lock:
            self._blade = (tip, heel)

    def lift(self) -> None:
        """The blade out of the tissue (the stroke's end): the organ steps on, hanging, uncut further."""
        with self._lock:
            self._blade = None
            if self.scalpel is not None:
                self.scalpel.lift()

    def _enter_scalpel_mode(self) -> None:
        """A new full-order lagged corotational driver on the model, hung at its static equilibrium under
        gravity (built and solved outside the lock), then the scalpel stepping it installed under the lock."""
        from ..drivers.fullorder import DirectSimulator
        from ..interaction.scalpel import Scalpel

        with self._lock:
            if self.volume is None:
                raise ModelError("a shell cannot be cut yet: open the organ as a solid (rtfem view ORGAN --solid)")
            if self.device is not None:
                raise ModelError("the scalpel follows the mouse: detach the haptic device first")
            model, dt, damping, method = self.model, self.driver.dt, self.damping, self.settings.method
            self._pre_scalpel = self.settings  # what Reset through configure() starts from
        original, element, nodes = model, model.element, model.n_nodes
        if element != "tet4":  # (a cut tet10 liver's next step turned split elements inside out: issue 57)
            model = _corner_model(model)
        driver = DirectSimulator(model, dt, damping, large_deformation=True)
        scalpel = Scalpel(driver, gravity=GRAVITY, thread=False, worker=True)
        try:
            _hang(driver, scalpel.solid.weights)
        except Exception:
            scalpel.close()
            raise
        with self._lock:
            if self.model is not original:  # rebuilt meanwhile (Reset): not this one's scalpel
                scalpel.close()
                raise ModelError("the organ was rebuilt while scalpel mode was being entered: cut again")
            self.node, self.target = None, None
            self.grasp.release()
            self._local_gen += 1  # a patch training for the reduced model is not wanted any more
            if getattr(self, "monitor", None) is not None:
                self.monitor.stop(timeout=0.0)
                self.monitor = None
            self.scalpel, self.driver = scalpel, driver
            if model is not original:  # the tet10 organ's corners: drawn and rebuilt (Reset) as tet4 from now on
                self._take(model)
                self._model_options = dict(self._model_options, element="tet4")
            else:
                self.grasp = self._grasp_on(driver)  # (refused in scalpel mode; on the session's driver all the same)
            scalpel.lift()
            self.settings = replace(self.settings, method="direct", large=True)
            self.cut_status = (f"scalpel mode: the organ on the full order (the {method} model's motion left), hung at "
                               "its equilibrium under gravity; Reset leaves it, keeping the cut"
                               + ("" if element == "tet4" else f"; the {element} organ ({nodes} nodes) is cut as tet4 on its "
                                  f"{model.n_nodes} corner nodes: a cut {element} organ turned its split elements inside "
                                  "out in the steps after"))

    def _scalpel_step(self) -> None:
        """One step in scalpel mode (under the session's lock): the blade placed, the organ stepped, a
        cut ready swapped in (and taken by the session)."""
        sc = self.scalpel
        if sc.error is not None:  # a cut job failed (rt.cut's refusals are sc.refused): said here, whether or not the
            # blade is down (only a tick, the blade's, said it: a stroke's last job failing after the lift went unsaid)
            err, sc.error = sc.error, None
            self.error = f"a cut failed ({type(err).__name__}: {err}); the organ steps on and the next strip cuts again"
        if self._blade is not None:
            sc.update(*self._blade)
        sc.physics_step()
        if sc.model is not self.model:
            self._take(sc.model)
        self.driver = sc.driver
        if sc.refused:
            self.cut_status = f"the last strip was not cut: {sc.refused}"

    def _take(self, model) -> None:
        """The cut model as the session's own: its mesh drawn and touched from now on."""
        from .gltf import region_colours

        model._viewer_E = self.settings.E
        self._fixed = np.flatnonzero(model.fixed.any(axis=1))  # (a rebuild fixes the cut mesh's nodes, copies included)
        self.model, self.volume = model, model.tetmesh
        self.mesh = model.tetmesh.surface
        self.X = np.asarray(self.mesh.vertices)
        self.drawn = self.mesh.used_vertices()
        self.region_colours = region_colours(self.volume, self.drawn)
        self.grasp = self._grasp_on(self.scalpel.driver)
        self.generation += 1
        sc = self.scalpel
        self.cut_status = (f"cut {sc.cuts} time(s): {model.n_nodes} nodes, {model.tetmesh.n_tets} tets; the last strip "
                           f"applied {1e3 * sc.latencies[-1]:.0f} ms after it was swept" if sc.latencies else "")

    def _leave_scalpel_mode(self) -> None:
        """Before a rebuild: the scalpel closed (its worker process too); the cut mesh stays the session's."""
        sc, self.scalpel, self._blade, self._pre_scalpel = self.scalpel, None, None, None
        if sc is not None:
            sc.close()
            self.cut_status = f"the cut organ ({self.model.n_nodes} nodes) rebuilt with the chosen method"


def _corner_model(model):
    """The tet4 model on the corner nodes of a tet10 ``model`` (:meth:`TetMesh.linear`): the same material or
    regions, options and fixes (a fixed corner stays fixed)."""
    from ..fe.recipe import ModelRecipe

    recipe = ModelRecipe.of(model)
    mesh = recipe.mesh.linear()
    kept = np.flatnonzero(mesh.vertex_map >= 0)
    fixed = np.zeros((mesh.n_vertices, recipe.fixed.shape[1]), dtype=bool)
    fixed[mesh.vertex_map[kept]] = recipe.fixed[kept]
    return ModelRecipe(mesh, recipe.material, dict(recipe.options, element="tet4"), fixed, "", recipe.kind).build()


def _hang(driver, weights: np.ndarray) -> None:
    """``driver`` (the lagged full-order step) set at rest at the static equilibrium of its model under
    ``weights`` (n, 3): the displacements solve_static finds, no velocity or acceleration, the loads
    held (what the next steps apply) those weights, its HHT residual zero, its factor made there."""
    from ..fe.nonlinear import solve_static

    weights = np.where(driver.model.fixed[:, :3], 0.0, weights)  # (the supports carry their own nodes' weight)
    u = np.asarray(solve_static(driver.model, weights).displacements, dtype=float).ravel()[driver._solved]
    state = driver.get_state()
    zero = np.zeros_like(u)
    state.update(u=u, v=zero, a=zero, g=zero, held=np.asarray(weights, dtype=float).ravel(), ref_u=u.copy(),
                 ref_step=np.array([float(state["steps"])]), chord=np.array([-1.0, 0.0]), u_1=u.copy(), u_2=u.copy(),
                 past=np.zeros(1))
    driver.set_state(state)
