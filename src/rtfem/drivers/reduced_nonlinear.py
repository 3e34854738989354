"""The run-time driver of a reduced nonlinear model (:class:`rtfem.reduction.reduced.ReducedNonlinearModel`):
its reduced coordinates integrated by the average-acceleration Newmark rule, linearized once per
step, with the tangent refreshed in the background, the static correction and patch stiffening."""

from __future__ import annotations

from typing import Callable, Mapping

import numpy as np

from .. import validate
from ..errors import ModelError, SolverError
from ..fe.material import Damping
from .base import ForceInput, StaticCorrection
from .tangent import Linearization

from ..reduction.element_terms import _projection_rows
from ..reduction.reduced import ReducedNonlinearModel, check_build_memory

__all__ = ["ReducedNonlinearSimulator", "reduced_nonlinear_driver"]


class ReducedNonlinearSimulator(Linearization, StaticCorrection, ForceInput):
    """A Driver on a :class:`ReducedNonlinearModel`: its reduced coordinates integrated by the
    average-acceleration Newmark rule, linearized once per step about the predictor (one cubature
    force evaluation and one r x r product, no Newton iterations: a linearly implicit step). At
    rest the state is the reduced nonlinear equilibrium exactly, whatever the linearization. By
    default the linearization is the cubature forces' tangent at a recent state (``tangent``,
    ``refresh``, ``background``): the step is then implicit in the reduced coordinates to first
    order, stable wherever the tangent changes little between refreshes (a tet10 cantilever swung
    to 60 % of its length at 1 kHz, tests/verification/test_reduced_nonlinear.py). Linearized about
    the rest tangent (``tangent="rest"``, the step before) the nonlinearity is explicit, stable
    only while the true tangent stays near the rest one: that cantilever diverged at 60 %.

    With a relaxing law (``rt.Prony``) the simulator carries each force element's history (the
    cubature's, or every element's; each point's Q_i and S_iso(n), in ``get_state()["visc"]``)
    and takes the step's algorithmic forces and the history it leaves at the predictor, in one
    compiled pass (:mod:`rtfem.reduction.prony_kernels`); the step is linearized about the
    instantaneous law's tangent (at least as stiff as the algorithmic one: the long-term tangent
    would leave the step unstable for g_inf < 1/2). It needs ``spread=1``. The static correction is
    the long-term law's (the local dent taken relaxed); a state without "visc" starts with no
    history (as if reached suddenly), and so does a localized copy (:meth:`localized`).

    Parameters
    ----------
    reduced : the model, with :meth:`ReducedNonlinearModel.train_cubature` called (the forces are
        the cubature's; ``cubature=False`` sums every element: exact, ~100 times slower).
    dt, damping : the step (s) and :class:`~rtfem.Damping`; alpha, beta and a scalar zeta act on
        the reduced model's own linear modes (the eigenvectors of its rest mass and stiffness).
    spread : split the cubature elements into this many groups and re-evaluate one group per step
        (multirate, after Cavusoglu & Tendick 2000): the forces are the cubature's rest-linear part
        K_c q, exact every step, plus each group's nonlinear remainder g_e(v) - K_e v as last
        evaluated (at most ``spread - 1`` steps old). A step then costs about 1/spread of the
        cubature; the static equilibrium is the same (every group is current at rest). Default 1:
        every element every step. The lagged remainders are explicit with a delay, so spread > 1
        is conditionally stable: it needs the reduced model's high modes damped (a zeta; mass-
        proportional alpha alone leaves them free) and a coupling the basis does not have to take
        whole. Measured on the level-4 liver (40 modes + derivatives of 20, zeta 1): a 200 N/m
        probe at 1 kHz settles with spread 8. A Grasp 1e5 times stiffer than the organ, jumped
        1-5 cm: without the static correction it diverges with spread 6-8 and keeps a ripple of
        ~6 % of the pull with spread 2 and 4; with it (the grasped dent taken by D, not forced
        into the basis) spreads 1-6 settle, single precision, to a ripple of ~2e-6 of the pull
        over 5,000 steps (vertex 1, 2, 5 cm; 1 cm jaw 2, 5 cm), and spread 8 diverged on the 5 cm
        jaw. So ``static_correction=True, spread=4`` is the setting for a 1 kHz loop. A diverged
        state raises SolverError.
    precision : "double" (default) or "single": the two products with the cubature elements'
        basis rows (13.5 MB in double on the default liver, read twice a step: the step's limit)
        in single precision, the element forces and the integration in double. Half the memory
        read: the cubature forces 1.3 against 1.6 ms, the 1 kHz probe tick 0.64 times
        (benchmarks/reduced_nonlinear.py); the forces within ~1e-6 relative and the settled
        state within ~1e-6 of the double one (tested to 1e-5).

    static_correction : add the static response the basis cannot hold, D f with
        D = K^-1 - U U^T (U stiffness-orthonormal, so U U^T is the basis's own static compliance),
        for the current loads f, as the linear ModalSimulator's static correction does: the local
        dent under a grasped or probed vertex, which a basis of global modes and their derivatives
        misses. At small load the displacement is then the exact linear static one, K^-1 f; at
        large load the basis carries the nonlinearity and D the linear local part. Measured on
        the default liver's pulls (``benchmarks/reduced_nonlinear.py``) it cuts the error against
        the corotational full order by 1.4-6 times; ``reduced_nonlinear_driver`` turns it on.
        Three sparse solves per loaded vertex the first time (``prepare`` does them ahead).
    stiffening : on a localized model (:meth:`ReducedNonlinearModel.localize`), the factor on the patch
        coordinates' rest stiffness in the step's linearization (default 100; the current tangent gets the
        margin added). The step linearizes about the predictor with a constant tangent and takes the rest of
        the forces explicitly; for a stiff, light coordinate that is a fixed-point
        iteration, which converges only while the true tangent stays below twice the one used.
        A patch pulled centimetres stiffens far more than that (its elements stretched: a strong
        geometric stiffness), so the patch coordinates are linearized with an over-stiff
        reference: stable while their true tangent stays below 2 x stiffening times the rest one,
        the same equilibrium, and still affine in the loads. Measured on the solid liver under a
        stiff Grasp (spread 4): a vertex jumped 5 cm with a 2 cm patch diverged with factor 3 and
        settled with 10-30; a 1 cm jaw (4 nodes) with the patch within 2 cm of it kept a ripple of
        6e-5 of the pull at 2 cm with 10-30 and diverged at 5 cm, and settled with 100 (ripple
        5e-11). The price is a slower patch where it does not stiffen: with 100 a 200 N/m probe
        and a 1 mm pull settle as fast as without a patch (1 % of the final field after 455 / 180
        steps), the 2 cm jaw pull in 295 steps against 185 (300: the same, 0.1 % later).

    patch_zeta : on a localized model, the damping ratio at least given to the reduced modes that
        lie mostly in the patch's coordinates (more than half of their stiffness norm; default 1,
        ignored otherwise). Linearized over-stiff (``stiffening``), those light, stiff modes are
        integrated without numerical damping, and mass-proportional damping (``alpha``, the
        viewer's) leaves them nearly free: a grasp's 0.6 N on a localized beam kept a ripple of
        0.04-0.06 N (alpha 20, zeta 0), 7e-6 N with them damped critically. On that beam the first
        such mode is at 177 Hz and the twelve lowest carry none of the patch, so the organ's
        swing keeps the damping given.

    tangent : "current" (default): the step's matrix S = M + dt/2 C + dt^2/4 T with T the
        cubature forces' tangent (element tangents by forward differences of the compiled kernel,
        projected on the basis; every element's with ``cubature=False``) at the predictor of the
        step it was refreshed at, kept positive definite (negative eigenvalues clipped: only the
        step's stability depends on it); with ``spread`` > 1 each group's lagged remainder is also
        carried to the predictor along the group's tangent (nearly second order in the lag).
        "rest": T the rest stiffness, fixed. A patch's part is over-stiff with either (``stiffening``).
    refresh : steps between tangent refreshes (default 10; a refresh costs ~13 ms on the default
        liver: element tangents and an r x r projection; the swung cantilever of the tests settles
        to the same field with 10, 50 or 200). Synchronous, in the step: reproducible.
    background : refresh on a thread instead, at the normal priority (the real-time setting): the step asks
        with its predictor every ``refresh`` steps and takes the newest result at a later step,
        never waiting; all such threads hold BLAS to the cores a step leaves, through one shared
        limit. Results then depend on the timing (the equilibrium does not). A worker starved by
        a busy machine is not waited for past
        ``MAX_TANGENT_AGE`` steps (200): the step then refreshes the tangent itself (counted in
        ``sync_refreshes``; a starved worker let a swung cantilever diverge at step 2,394).

    The step is affine in the loads: ``predict(node)`` is the no-load step and
    ``step_compliance(node)`` dt^2/4 U_i S^-1 U_i^T (+ D_ii), constant between tangent refreshes
    (``compliance_changes`` is True with the current tangent), so Probe and Grasp work as on a
    linear driver. Loads are dead forces on the translations.

    Raises
    ------
    ModelError
        A reduced model that is not one or has no cubature (with ``cubature=True``), a bad dt,
        damping, precision, tangent, refresh, spread, stiffening or patch_zeta, or options that
        do not go together (``background`` with ``tangent="rest"``, single precision without
        cubature, a Prony law with ``spread`` > 1).
    SolverError
        At run time: the state diverged (forces no longer finite), or the background tangent
        refresh failed.
    """

    compliance_changes = False
    warping = False
    #: displacements_at may run on another thread beside step() (the viewer's frames): a step replaces
    #: its coordinates and its loads, never writes into them, so a reader sees one step's (the field
    #: and the correction at most one step apart)
    concurrent_reads = True

    def __init__(self, reduced: ReducedNonlinearModel, dt: float, damping: Damping | None = None, *,
                 cubature: bool = True, spread: int = 1, precision: str = "double",
                 static_correction: bool = False, stiffening: float = 100.0, patch_zeta: float = 1.0,
                 tangent: str = "current", refresh: int = 10, background: bool = False) -> None:
        from .base import check_dt

        if not isinstance(reduced, ReducedNonlinearModel):
            raise ModelError(f"reduced={validate.show(reduced)} must be a ReducedNonlinearModel")
        cubature = validate.flag(cubature, "cubature")
        if cubature and getattr(reduced, "_cubature", None) is None:
            raise ModelError("the reduced model has no cubature yet: call reduced.train_cubature() first, or pass "
                             "cubature=False (every element each step: exact, slow)")
        self.reduced = reduced
        self.cubature = bool(cubature)
        self.single = validate.choice(precision, "precision", ("double", "single")) == "single"
        if self.single and not self.cubature:
            raise ModelError("precision='single' is for the cubature's basis rows: it needs cubature=True")
        self.dt = check_dt(dt)
        damping = Damping() if damping is None else damping
        if not isinstance(damping, Damping):
            raise ModelError(f"damping={validate.show(damping)} must be an rt.Damping")
        if isinstance(damping.zeta, tuple):
            raise ModelError("the reduced nonlinear simulator takes one damping ratio zeta for all its modes")
        model = reduced.model
        self.n_nodes = model.n_nodes
        U = reduced.basis
        self._U = U
        local = reduced.local
        self.patch_zeta = validate.in_range(patch_zeta, "patch_zeta", 0.0, 10.0, what="a damping ratio")
        self._reduced_matrices(damping)
        factor = validate.number(stiffening, "stiffening")
        if not 1.0 <= factor <= 1e6:
            raise ModelError(f"stiffening={validate.show(stiffening)} must be a factor from 1 to 1e6 (default 100)")
        self.tangent = validate.choice(tangent, "tangent", ("current", "rest"))
        self.refresh = validate.count(refresh, "refresh", 1, 10**6)
        self.background = validate.flag(background, "background")
        if self.background and self.tangent == "rest":
            raise ModelError("background=True refreshes the step's tangent on a thread: it needs tangent='current'")
        self.compliance_changes = self.tangent == "current"  # W follows the tangent: consumers must not cache it
        self.stiffening = 1.0 if local is None else factor
        self._stiffening, self.damping = factor, damping  # as given: for localized()
        Kref = self._K0r.copy()
        if self.stiffening != 1.0:  # the patch's coordinates linearized with an over-stiff reference (see the class)
            c = local["columns"]
            Kref[c:, c:] *= self.stiffening
        self._patch_margin, Kref = (Kref - self._K0r, self._K0r) if self.tangent == "current" and self.stiffening != 1 \
            else (None, Kref)  # (the current tangent gets the margin: tangent.Linearization._step_inverse)
        self._trans = self._translation_rows()
        self._init_correction(validate.flag(static_correction, "static_correction"), model,
                              self._trans.reshape(-1, U.shape[1]), np.ones(U.shape[1]))
        self.spread = validate.count(spread, "spread", 1, 1024)
        self._spread_groups()
        self._worker = None
        self._last_compliances = None  # (Sinv, nodes, loaded, W): W changes only with the tangent
        self._viscous_terms()
        if self._visc_terms is not None:  # a Prony law: linearized about its instantaneous law (stiffer)
            Kref = self._Kc = self._visc_terms.Kc
        # about rest: the force model's own rest tangent (the cubature's), or the reference of tangent="rest"
        self._rest_linearization = (None, self._step_inverse(self._Kc if self.tangent == "current" and self.cubature
                                                             else Kref))
        self.reset()

    def _reduced_matrices(self, damping: Damping) -> None:
        """The reduced mass and rest stiffness, and the damping: alpha M + beta K plus zeta on each of
        the reduced model's linear modes (at least ``patch_zeta`` on the modes mostly in a localized
        patch's coordinates)."""
        reduced, U = self.reduced, self._U
        m = reduced.model.mass_diagonal[reduced.free]
        M = U.T @ (m[:, None] * U)
        K = U.T @ (reduced._K0 @ U)
        self._M, self._K0r = 0.5 * (M + M.T), 0.5 * (K + K.T)
        # the reduced model's linear modes: K y = w^2 M y; with K = L L^T, L^-1 M L^-T = V diag(mu) V^T
        L = np.linalg.cholesky(self._K0r)
        Linv = np.linalg.inv(L)
        mu, V = np.linalg.eigh(Linv @ self._M @ Linv.T)
        mu = np.clip(mu, 0.0, None)
        zeta = np.full(mu.shape, float(damping.zeta or 0.0))
        local = reduced.local
        if local is not None and self.patch_zeta > 0:
            # the reduced modes mostly in the patch's coordinates (more than half of their
            # stiffness norm: the basis is stiffness-orthonormal), damped at least by patch_zeta
            Phi = np.linalg.solve(L.T, V)
            share = (Phi[local["columns"]:] ** 2).sum(axis=0) / (Phi**2).sum(axis=0)
            zeta = np.where(share > 0.5, np.maximum(zeta, self.patch_zeta), zeta)
        c = damping.alpha * mu + damping.beta + 2.0 * zeta * np.sqrt(mu)  # alpha_i mu_i (finite as mu -> 0)
        self._C = L @ (V * c) @ V.T @ L.T

    def _spread_groups(self) -> None:
        """With spread > 1, the cubature elements in ``spread`` groups refreshed in turn (a localized
        model's patch elements every step); the cubature's rest tangent where the step uses it."""
        reduced = self.reduced
        self._groups, self._always = [], None
        if self.spread > 1:
            if not self.cubature:
                raise ModelError("spread > 1 refreshes the cubature forces a group at a time: it needs cubature=True")
            data, w = reduced._cubature
            Ke, self._Kc = reduced.cubature_rest()
            p = reduced._cubature_pinned  # a localized model's patch elements: every step
            if self.spread > w.size - p:
                raise ModelError(f"spread={self.spread} is more than the {w.size - p} cubature elements outside the "
                                 f"patch: pass at most {w.size - p}")
            cut = np.linspace(p, w.size, self.spread + 1).astype(int)
            self._groups = [(tuple(a[lo:hi] for a in data), w[lo:hi], Ke[lo:hi],
                             *_projection_rows(data[0][lo:hi], self.single)) for lo, hi in zip(cut[:-1], cut[1:])]
            if p:
                self._always = (tuple(a[:p] for a in data), w[:p], Ke[:p], *_projection_rows(data[0][:p], self.single))
        elif self.cubature and self.tangent == "current":
            self._Kc = reduced.cubature_rest()[1]

    def _viscous_terms(self) -> None:
        """With a :class:`~rtfem.Prony` law, or regions of which some relax: the elements whose history the
        step carries (:class:`rtfem.reduction.viscous_terms.ViscousTerms`); else None."""
        from ..reduction.viscous_terms import viscous_terms

        self._visc_terms = viscous_terms(self.reduced, self.cubature)
        if self._visc_terms is not None and self.spread > 1:
            raise ModelError(f"spread={self.spread}: a Prony law's history is stepped on every element each step; "
                             "pass spread=1")

    def _translation_rows(self) -> np.ndarray:
        """(n, 3, r): the basis rows of each node's translations (zero at fixed dofs)."""
        red = self.reduced
        out = np.zeros((self.n_nodes * red.dpn, red.size))
        out[red.free] = self._U
        return np.ascontiguousarray(out.reshape(self.n_nodes, red.dpn, red.size)[:, :3])

    # ---------------------------------------------------------------- state
    def reset(self) -> None:
        r = self.reduced.size
        self._q, self._v, self._a = np.zeros(r), np.zeros(r), np.zeros(r)
        self.time = 0.0
        self.steps = 0
        self._lag = np.zeros((self.spread, r))  # each group's remainder, as last evaluated (zero at rest)
        self._lag_q = np.zeros((self.spread, r))  # and the coordinates it was evaluated at
        self._tangent_step = None  # the step the tangent was last refreshed at (None: at the next step)
        self._tangent_at = 0  # the step the linearization in use was taken up at
        self.sync_refreshes = 0  # background=True: refreshes made here because the worker was too late
        self._use_rest()
        self._free = None  # (steps, q*, v*, S^-1 (-C v* - g(q*)), (group, its new remainder)) of the next step
        self._loads, self._load_array = {}, None
        self._visc = None if self._visc_terms is None else np.zeros(self._visc_terms.size)  # a Prony law's history

    def get_state(self) -> dict:
        state = {"q": self._q.copy(), "qdot": self._v.copy(), "qddot": self._a.copy(), "steps": np.array(self.steps)}
        if self.spread > 1:
            state["lag"], state["lag_q"] = self._lag.copy(), self._lag_q.copy()
        if self._visc is not None:
            state["visc"] = self._visc.copy()
        if self.tangent == "current":  # the linearization, as where it was computed and its age: a replay is exact
            state["tangent_q"] = np.zeros(0) if self._tangent_q is None else self._tangent_q.copy()
            state["tangent_age"] = np.array(-1 if self._tangent_step is None else self.steps - self._tangent_step)
        return state

    def set_state(self, state) -> None:
        r = self.reduced.size
        if not isinstance(state, Mapping) or "q" not in state:
            raise ModelError(f"state={validate.show(state)} must be a mapping with 'q', 'qdot', 'qddot' (and "
                             "'steps'), as get_state() returns")
        arrays = {}
        for key in ("q", "qdot", "qddot"):
            a = validate.real_array(state.get(key, np.zeros(r)), f"state[{key!r}]", 1)
            if a.shape != (r,):
                raise ModelError(f"state[{key!r}] must have shape ({r},), got {a.shape}")
            arrays[key] = a.copy()
        steps = state.get("steps", 0)
        steps = validate.count(steps[()] if isinstance(steps, np.ndarray) else steps, "state['steps']", 0)
        lag = lag_q = None
        if self.spread > 1 and state.get("lag") is not None:
            lag = validate.real_array(state["lag"], "state['lag']", 2)
            lag_q = validate.real_array(state.get("lag_q", np.tile(arrays["q"], (self.spread, 1))), "state['lag_q']", 2)
            for key, a in (("lag", lag), ("lag_q", lag_q)):
                if a.shape != (self.spread, r):
                    raise ModelError(f"state[{key!r}] must have shape ({self.spread}, {r}) (one row per group), got "
                                     f"{a.shape}")
        elif self.spread > 1:  # no lags saved: every group evaluated at q
            lag = np.stack([self._remainder(c, arrays["q"]) for c in range(self.spread)])
            lag_q = np.tile(arrays["q"], (self.spread, 1))
        visc = None
        if self._visc is not None:  # a Prony law's history; none saved: no strain before this state
            visc = validate.real_array(state.get("visc", np.zeros(self._visc.size)), "state['visc']", 1)
            if visc.size != self._visc.size:
                raise ModelError(f"state['visc'] holds {visc.size} values; this simulator's Prony history has "
                                 f"{self._visc.size} (another cubature or law)")
        tangent_q, age = None, -1
        if self.tangent == "current" and state.get("tangent_q") is not None:
            tangent_q = validate.real_array(state["tangent_q"], "state['tangent_q']", 1)
            if tangent_q.shape not in ((0,), (r,)):
                raise ModelError(f"state['tangent_q'] must have shape ({r},) or (0,) (rest), got {tangent_q.shape}")
            a = state.get("tangent_age", -1)
            age = int(validate.number(a[()] if isinstance(a, np.ndarray) else a, "state['tangent_age']"))
        self._q, self._v, self._a = arrays["q"], arrays["qdot"], arrays["qddot"]
        if lag is not None:
            self._lag, self._lag_q = lag.copy(), lag_q.copy()
        if visc is not None:
            self._visc = visc.copy()
        self._use_rest()  # (and no refresh in flight)
        if tangent_q is not None and tangent_q.size:
            self._use(self._linearization(tangent_q), tangent_q)
        self._tangent_step = steps - age if tangent_q is not None and age >= 0 else None
        self._tangent_at = steps  # the linearization just installed
        self.steps = steps
        self.time = steps * self.dt
        self._free = None

    def localized(self, nodes, radius: float, *, tol: float = 0.05) -> "ReducedNonlinearSimulator":
        """This simulator on its model localized around ``nodes`` (:meth:`ReducedNonlinearModel.localize`:
        every dof within ``radius`` m of them added to the basis, a new cubature trained to ``tol``; 20 s
        on the solid liver), with the same settings, continuing from this one's state (:meth:`continue_from`).
        Its patch is linearized over-stiff (``stiffening``) with either tangent: with the bare current one a
        10 mm patch of the tet10 block pulled 2.25 cm at once diverged in 41-220 steps, on the rest one the
        tet10 cantilever lifted 30 % of L did; both settle with it. Nothing of this simulator changes."""
        red = self.reduced.localize(nodes, radius)
        if self.cubature:
            red.train_cubature(16, tol=tol)
        new = ReducedNonlinearSimulator(red, self.dt, self.damping, cubature=self.cubature, spread=self.spread,
                                        precision="single" if self.single else "double",
                                        static_correction=self.static_correction, stiffening=self._stiffening,
                                        patch_zeta=self.patch_zeta, tangent=self.tangent, refresh=self.refresh,
                                        background=self.background)
        new.continue_from(self)
        return new

    def continue_from(self, other: "ReducedNonlinearSimulator", *, tangent: str = "here") -> None:
        """Take over the state of ``other``, a simulator of the same model on another basis (one
        localized around other nodes, or not): the displacement (with the static correction of
        its current loads), velocity and acceleration projected on this basis in the stiffness
        inner product (both bases are stiffness-orthonormal), its loads, step count and time.
        Exact (the displacement field unchanged) where this basis holds the other one's, as a
        localized basis holds its parent's; from another patch, the old patch's share this basis
        cannot hold is dropped (the closest field in the energy norm).

        With the current tangent, the step goes on linearized at the state taken over (``tangent``
        "here", computed now: milliseconds), or at the state of this simulator's last ``continue_from``
        ("kept": a swap under a lock, linearized beforehand; from the rest tangent instead, a patch of
        the tet10 block swapped in under a 2 cm jaw diverged within 50-80 steps in most runs)."""
        tangent = validate.choice(tangent, "tangent", ("here", "kept"))
        if not isinstance(other, ReducedNonlinearSimulator) or other.reduced.model is not self.reduced.model:
            raise ModelError(f"other={validate.show(other)} must be a ReducedNonlinearSimulator of the same model")
        if other.static_correction != self.static_correction:
            raise ModelError("continue_from needs both simulators with the static correction or both without (the "
                             "field of one cannot be matched by the other's without a full solve)")
        red, kept = self.reduced, getattr(self, "_projection", (None, None))
        # (r, r_other): this basis's coordinates of the other's columns (kept: a swap under a lock is quick)
        P = kept[1] if kept[0] is other._U else self._U.T @ (red._K0 @ other._U)
        self._projection = (other._U, P)
        q = P @ other._q
        loads = {int(k): np.array(f, float) for k, f in other._loads.items()}
        load_array = None if other._load_array is None else other._load_array.copy()
        if self.static_correction:
            # the corrections differ by (U_o U_o^T - U U^T) f: U q' + D f = U_o q_o + D_o f for
            # q' = P q_o + U^T f - P U_o^T f (the translation rows give U^T f on the loaded nodes)
            def reduced_load(rows):
                if load_array is not None:
                    return np.einsum("nir,ni->r", rows, load_array)
                return sum((rows[k].T @ f for k, f in loads.items()), np.zeros(rows.shape[2]))

            q += reduced_load(self._trans) - P @ reduced_load(other._trans)
        state = {"q": q, "qdot": P @ other._v, "qddot": P @ other._a, "steps": other.steps}
        kept = (self._dK, self._Sinv, self._tangent_q) if tangent == "kept" and self._tangent_q is not None else None
        if self.tangent == "current" and kept is None:
            state.update(tangent_q=q, tangent_age=0)
        self.set_state(state)
        if kept is not None and self.tangent == "current":
            self._dK, self._Sinv, self._tangent_q = kept
            self._tangent_step = self._tangent_at = self.steps
        self._loads, self._load_array = (loads, load_array) if self.static_correction else ({}, None)

    from .reduced_carry import reduced_carry_over as carry_over, reduced_take_over as take_over  # a cut organ: full and back

    @property
    def fingerprint(self) -> str:
        from ..reduction.modal import mesh_fingerprint

        return mesh_fingerprint(self.reduced.model.mesh)

    # ---------------------------------------------------------------- the step
    def _forces_at(self, q: np.ndarray) -> np.ndarray:
        red = self.reduced
        if self._visc_terms is not None:  # the step's algorithmic forces, and the history it leaves
            g, self._visc_next = self._visc_terms.forces(red, q, self._visc, self.dt)
            return g
        return red.cubature_forces(q, single=self.single) if self.cubature else red.reduced_forces(q, tangent=False)[0]

    def _remainder(self, c: int, q: np.ndarray) -> np.ndarray:
        """Group c's nonlinear remainder sum_e w_e U_e^T (g_e(U_e q) - K_e U_e q) (c = -1: the
        patch elements of a localized model, refreshed every step)."""
        data, w, Ke, U, UT = self._always if c < 0 else self._groups[c]
        return self.reduced._element_forces(q, data, w, False, rest=Ke, UT=UT, U=U)[0]

    def _free_step(self):
        """The predictor and the no-load acceleration of the next step (cached until it is taken)."""
        if self._free is None or self._free[0] != self.steps:
            h = self.dt
            qs = self._q + h * self._v + 0.25 * h * h * self._a
            vs = self._v + 0.5 * h * self._a
            fresh = None
            if self.tangent == "current":
                self._refresh_tangent(qs)
            if self.spread == 1:
                g = self._forces_at(qs)
            else:  # one group refreshed at the predictor, the others as last evaluated
                c = self.steps % self.spread
                fresh = (c, self._remainder(c, qs), qs)
                g = self._Kc @ qs + (self._lag.sum(axis=0) - self._lag[c] + fresh[1])
                if self._dK is not None:  # the lagged remainders carried to qs along their tangents
                    dq = qs - self._lag_q
                    dq[c] = 0.0
                    g += self._dK @ dq.reshape(-1)
                if self._always is not None:
                    g += self._remainder(-1, qs)
            a0 = self._Sinv @ (-(self._C @ vs) - g)
            if not np.isfinite(a0).all():
                raise SolverError(f"the reduced nonlinear simulation diverged at step {self.steps} (t = {self.time:g} s): "
                                  "the forces are no longer finite; reset() it, and take a smaller dt or spread "
                                  f"(now {self.spread}), or more damping")
            self._free = (self.steps, qs, vs, a0, fresh)
        return self._free

    def step(self, forces=None) -> None:
        """Advance one step of dt under dead ``forces`` ({node: f} or (n, 3); None for none)."""
        Fr, loads, load_array = None, {}, None
        if forces is not None:
            if isinstance(forces, Mapping):
                nodes, P = self._parse_loads(forces)
                Fr = np.einsum("kir,ki->r", self._trans[nodes], P)
                if self.static_correction:
                    for i, f in zip(nodes.tolist(), P):
                        loads[i] = loads[i] + f if i in loads else f.copy()
            else:
                A = self._as_array(forces)
                Fr = np.einsum("nir,ni->r", self._trans, A)
                load_array = A.copy() if self.static_correction and A.any() else None
        _, qs, vs, a0, fresh = self._free_step()
        if fresh is not None:
            self._lag[fresh[0]], self._lag_q[fresh[0]] = fresh[1], fresh[2]
        a = a0 if Fr is None else a0 + self._Sinv @ Fr
        h = self.dt
        self._q = qs + 0.25 * h * h * a
        self._v = vs + 0.5 * h * a
        self._a = a
        if self._visc is not None:  # the history at the predictor, where the step's forces were taken
            self._visc = self._visc_next
        self._loads, self._load_array = loads, load_array
        self.steps += 1
        self.time = self.steps * self.dt
        self._free = None

    def run(self, forces, n_steps: int) -> None:
        for _ in range(self._n_steps(n_steps)):
            self.step(forces)

    # ---------------------------------------------------------------- outputs and the one-step contract
    def displacements(self) -> np.ndarray:
        u = self.reduced.displacements(self._q)
        if self.static_correction:
            self._add_correction(u)
        return u

    def displacements_at(self, nodes) -> np.ndarray:
        nodes = validate.nodes(nodes, self.n_nodes)
        u = self._trans[nodes] @ self._q
        return self._correction_at(nodes, u) if self.static_correction else u

    def displacement(self, node: int) -> np.ndarray:
        i = self._node(node)
        u = self._trans[i] @ self._q
        c = self._point_correction(i) if self.static_correction else None
        return u if c is None else u + c

    def predict_at(self, nodes) -> np.ndarray:
        nodes = validate.nodes(nodes, self.n_nodes)
        _, qs, _, a0, _ = self._free_step()
        return self._trans[nodes] @ (qs + 0.25 * self.dt**2 * a0)

    def predict(self, node: int) -> np.ndarray:
        return self.predict_at(np.array([self._node(node)]))[0]

    def step_compliances(self, nodes, loaded=None) -> np.ndarray:
        nodes = validate.nodes(nodes, self.n_nodes)
        loaded = nodes if loaded is None else validate.nodes(loaded, self.n_nodes)
        self._free_step()  # the next step's tangent
        key = (self._Sinv, nodes.tobytes(), loaded.tobytes())
        last = self._last_compliances
        if last is not None and last[0] is key[0] and last[1:3] == key[1:]:  # the same tangent and nodes
            return last[3].copy()
        Ua = self._trans[nodes].reshape(-1, self.reduced.size)
        Ub = self._trans[loaded].reshape(-1, self.reduced.size)
        W = 0.25 * self.dt**2 * (Ua @ self._Sinv @ Ub.T)
        if self.static_correction and loaded.size:
            W += self._correction_block(nodes, loaded)
        self._last_compliances = (*key, W)
        return W.copy()

    def step_compliance(self, node: int) -> np.ndarray:
        return self.step_compliances(np.array([self._node(node)]))


def reduced_nonlinear_driver(model, modes, dt: float, damping: Damping | None = None, *, derivatives: int = 20,
                             spread: int = 1, precision: str = "double", static_correction: bool = True,
                             local: tuple | None = None, refresh: int = 20, background: bool = False,
                             progress: Callable[[int, int, str], None] | None = None, scheduler=None,
                             cache: bool = False):
    """The reduced nonlinear Driver in one call, as ``rtfem simulate --method nonlinear`` and the
    viewer build it: a :class:`ReducedNonlinearModel` on ``modes`` and the modal derivatives of the
    lowest min(derivatives, r) of them, its cubature (16 poses, 5 % training error) and a
    :class:`ReducedNonlinearSimulator` with ``spread`` element groups (1: every element every
    step, stable under any damping; 4 with a zeta damping is the 1 kHz setting, see the class) and the
    basis rows' ``precision`` ("single": 0.64 times the probe tick, the viewer's), with the
    ``static_correction`` (default on, as the linear modal driver's). ``local`` = (nodes, radius):
    the basis also holds every dof within radius (m) of those nodes (:meth:`ReducedNonlinearModel.localize`:
    where a grasp or probe will pull far; its cubature keeps the patch's elements exact). The step is
    linearized about the cubature's tangent, refreshed every ``refresh`` steps (20: reproducible,
    for offline runs; on the default liver a refresh costs ~13 ms) or, with ``background``, on a
    thread so that the step never waits (the real-time setting: the viewer's). Shells and solids:
    the compiled cubature kernels are the corotational triangle's and the corotated tet's. ``scheduler``:
    the modal derivatives on a Dask cluster (:meth:`ReducedNonlinearModel.derivatives`). ``cache``: the
    reduced model and its cubature through the precompute cache (:func:`rtfem.reduction.precompute.cached_reduced`;
    a patch is localized and trained afresh on the cached model), as ``rtfem view`` and ``simulate`` do."""
    if local is not None:
        if not isinstance(local, (tuple, list)) or len(local) != 2:
            raise ModelError(f"local={validate.show(local)} must be (nodes, radius in m), e.g. ([node], 0.02)")
        local = (validate.nodes(local[0], model.n_nodes), validate.positive(local[1], "local radius", "a distance in m"))
    derivatives = validate.count(derivatives, "derivatives", 0, 10**4)
    validate.choice(precision, "precision", ("double", "single"))  # before the precompute
    static_correction = validate.flag(static_correction, "static_correction")
    refresh = validate.count(refresh, "refresh", 1, 10**6)
    background = validate.flag(background, "background")
    derivatives = min(derivatives, getattr(modes, "n_modes", derivatives))
    if hasattr(modes, "n_modes") and callable(getattr(model, "nonlinear", None)):  # else the build says what is wrong
        check_build_memory(model, modes.n_modes + derivatives * (derivatives + 1) // 2, local)  # before the derivatives
    if validate.flag(cache, "cache"):
        from ..reduction.precompute import cached_reduced

        red = cached_reduced(model, modes, derivatives, cubature=local is None, progress=progress, scheduler=scheduler)
    else:
        red = ReducedNonlinearModel(model, modes, derivatives, progress=progress, scheduler=scheduler)
    if local is not None:
        red = red.localize(*local)
    if local is not None or not cache:
        red.train_cubature(16, tol=0.05)
    return ReducedNonlinearSimulator(red, dt, damping, spread=spread, precision=precision,
                                     static_correction=static_correction, refresh=refresh, background=background)
