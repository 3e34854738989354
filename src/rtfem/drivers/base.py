"""The Driver protocol (DESIGN.md) and what every run-time simulator shares: the Newmark
constants, dt and damping checks, the batched helpers over drivers (predictions, compliances,
displacements at nodes), dead loads (ForceInput), the static correction, and the check that a
driver belongs to a mesh."""


from __future__ import annotations

from typing import Mapping, Protocol, runtime_checkable

import numpy as np

from .. import validate
from ..errors import ModelError
from ..mesh.surface import TriMesh
from ..fe.material import Damping

__all__ = ["Driver", "DRIVER_MEMBERS", "as_driver", "displacements_at", "predictions", "step_compliances", "prepare",
           "ForceInput", "StaticCorrection", "check_driver_mesh", "newmark_coefficients", "newmark_constants"]

_NEWMARK_BETA = 0.25  # eta in the paper
_NEWMARK_GAMMA = 0.5  # delta in the paper


def check_dt(dt) -> float:
    """A driver's time step in seconds (the rule every driver applies)."""
    return validate.time_step(dt, "dt")


def check_damping(damping) -> Damping:
    """A driver's damping: an rt.Damping, or None for none."""
    if damping is None:
        return Damping()
    if not isinstance(damping, Damping):
        raise ModelError(f"damping={validate.show(damping)} must be an rt.Damping (or None)")
    return damping


def newmark_constants(dt: float, beta: float = _NEWMARK_BETA, gamma: float = _NEWMARK_GAMMA) -> tuple[float, ...]:
    """The six constants of Newmark's method (Bathe's a0..a5; the paper's Eq. 12-15):
    c0 = 1/(beta dt^2), c1 = gamma/(beta dt), c2 = 1/(beta dt), c3 = 1/(2 beta) - 1,
    c4 = gamma/beta - 1, c5 = dt/2 (gamma/beta - 2); the one copy used by the modal and
    the full-order Newmark updates."""
    return (1.0 / (beta * dt * dt), gamma / (beta * dt), 1.0 / (beta * dt), 1.0 / (2 * beta) - 1.0,
            gamma / beta - 1.0, 0.5 * dt * (gamma / beta - 2.0))


def newmark_velocity(v, acc, acc_new, dt: float, gamma: float = _NEWMARK_GAMMA):
    """v_{t+dt} = v_t + dt ((1 - gamma) a_t + gamma a_{t+dt})."""
    return v + dt * ((1 - gamma) * acc + gamma * acc_new)


def newmark_coefficients(lam, a, dt, beta: float = _NEWMARK_BETA, gamma: float = _NEWMARK_GAMMA):
    """Newmark's scalar update as a linear map (Eq. 12-15).

    For x'' + a x' + lam x = f, with the acceleration at t eliminated through the equation of
    motion at t (a_t = f_t - a v_t - lam x_t), returns Phi (..., 2, 2), G0 (..., 2), G1 (..., 2):
    [x, v]_{t+dt} = Phi [x, v]_t + G0 f_t + G1 f_{t+dt}.
    """
    lam, a = np.broadcast_arrays(np.asarray(lam, float), np.asarray(a, float))
    c0, c1, c2, c3, c4, c5 = newmark_constants(dt, beta, gamma)
    khat = lam + a * c1 + c0

    def advance(x, v, f0, f1):
        acc = f0 - a * v - lam * x
        fhat = f1 + c0 * x + c2 * v + c3 * acc + a * (c1 * x + c4 * v + c5 * acc)
        xn = fhat / khat
        an = c0 * (xn - x) - c2 * v - c3 * acc
        vn = newmark_velocity(v, acc, an, dt, gamma)
        return xn, vn

    one, zero = np.ones_like(lam), np.zeros_like(lam)
    cols = [advance(one, zero, zero, zero), advance(zero, one, zero, zero)]
    Phi = np.stack([np.stack([cols[0][0], cols[1][0]], -1), np.stack([cols[0][1], cols[1][1]], -1)], -2)
    G0 = np.stack(advance(zero, zero, one, zero), -1)
    G1 = np.stack(advance(zero, zero, zero, one), -1)
    return Phi, G0, G1


@runtime_checkable
class Driver(Protocol):
    """What Probe, Grasp, HapticLoop and the viewer ask of anything that advances in time.

    ``step(forces)`` advances one step of ``dt`` under ``forces`` ({node: (fx, fy, fz)} or an
    (n, 3) array; None for no load) and, like every member, refuses bad input before changing
    any state. ``predict(node)`` is where the node would be after one more step with no load and
    ``step_compliance(node)`` the 3x3 W with u(k+1) = predict(node) + W f for a force f on it.
    Implemented by :class:`ModalSimulator`, the full-order simulators of :class:`DirectSimulator`
    and the impedance map's driver (:meth:`ImpedanceMap.as_driver`); a user's own class with
    these members works with every consumer. Optional, with a fallback on the members:
    ``displacements_at(nodes)`` (a batched query), ``prepare(nodes)`` (precompute what loads on
    those nodes will need; see :func:`prepare`), ``fingerprint`` (the mesh hash, checked by the
    consumers when present), ``predict_at(nodes)`` ((k, 3) predictions, batched) and
    ``step_compliances(nodes, loaded)`` (the cross compliances of a contact set: block (a, b) is
    d u_a(k+1) / d f_b; see :func:`step_compliances`).
    """

    dt: float
    time: float
    n_nodes: int

    def step(self, forces=None) -> None: ...
    def predict(self, node: int) -> np.ndarray: ...
    def step_compliance(self, node: int) -> np.ndarray: ...
    def displacement(self, node: int) -> np.ndarray: ...
    def displacements(self) -> np.ndarray: ...
    def reset(self) -> None: ...
    def get_state(self) -> dict: ...
    def set_state(self, state) -> None: ...


DRIVER_MEMBERS = ("step", "predict", "step_compliance", "displacement", "displacements", "reset", "get_state",
                  "set_state", "dt", "time", "n_nodes")


def as_driver(obj, what: str = "probe"):
    """``obj`` as a Driver: objects with ``as_driver()`` (an ImpedanceMap) are converted; anything
    lacking a protocol member is refused, naming what it lacks."""
    if hasattr(obj, "as_driver") and callable(obj.as_driver):
        obj = obj.as_driver()
    missing = [m for m in DRIVER_MEMBERS if not hasattr(obj, m)]
    if missing:
        raise ModelError(f"the {what} drives a ModalSimulator, a Newmark DirectSimulator, an ImpedanceMap or any Driver "
                         f"(a class with {', '.join(DRIVER_MEMBERS)}); {validate.show(obj)} lacks {', '.join(missing)}")
    return obj


def rows_times(A: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(k, 3, r) times (r,) -> (k, 3) as one matrix-vector product (numpy's stacked matmul of the
    (k, 3, r) array is 4-6x slower: 1.5 ms against 0.23 ms for 10,242 nodes and r = 40)."""
    return (A.reshape(-1, A.shape[-1]) @ x).reshape(-1, 3)


def prepare(driver, nodes) -> None:
    """Let the driver compute what it needs at ``nodes`` before they are loaded (its optional
    ``prepare(nodes)``: static-correction or compliance columns, impedance maps); a no-op for
    drivers without one. Consumers call it when a node is first touched, outside the force loop."""
    fn = getattr(driver, "prepare", None)
    if fn is not None:
        fn(nodes)


def displacements_at(driver, nodes: np.ndarray) -> np.ndarray:
    """(k, 3) displacements of some nodes: the driver's batched query when it has one."""
    fn = getattr(driver, "displacements_at", None)
    return fn(nodes) if fn is not None else np.asarray(driver.displacements())[nodes]


def predictions(driver, nodes: np.ndarray) -> np.ndarray:
    """(k, 3) :meth:`Driver.predict` of some nodes: the driver's batched ``predict_at`` when it has one."""
    fn = getattr(driver, "predict_at", None)
    if fn is not None:
        return fn(nodes)
    return np.array([driver.predict(int(i)) for i in np.asarray(nodes).tolist()]).reshape(-1, 3)


def trial_displacements(driver, forces, nodes: np.ndarray) -> np.ndarray:
    """(k, 3) displacements of ``nodes`` after one step under ``forces`` from the driver's present
    state, which is left as it is (a scene's trial step): the driver's own ``trial_displacements``
    when it has one, else :func:`stepped_trial`."""
    fn = getattr(driver, "trial_displacements", None)
    return fn(forces, nodes) if fn is not None else stepped_trial(driver, forces, nodes)


def stepped_trial(driver, forces, nodes: np.ndarray) -> np.ndarray:
    """:func:`trial_displacements` by the protocol: a step, the displacements, the state restored."""
    state = driver.get_state()
    try:
        driver.step(forces)
        return displacements_at(driver, nodes)
    finally:
        driver.set_state(state)


def step_compliances(driver, nodes, loaded=None) -> np.ndarray:
    """The one-step cross compliances of a contact set, (3k, 3l): block (a, b) is the displacement
    of ``nodes[a]`` after one step per unit force on ``loaded[b]`` (default: ``nodes``), so that
    u_S(k+1) = predict_S + W_SS f_S (James & Pai's capacitance matrix).

    The driver's own ``step_compliances`` when it has one; otherwise, for one node its
    ``step_compliance``, and for a set the block is measured by stepping the driver from its
    saved state under unit loads (3 l steps, state restored: a user's driver needs only the
    protocol)."""
    nodes = validate.nodes(nodes, driver.n_nodes)
    loaded = nodes if loaded is None else validate.nodes(loaded, driver.n_nodes)
    fn = getattr(driver, "step_compliances", None)
    if fn is not None:
        return fn(nodes, loaded)
    if nodes.size == 1 and loaded.size == 1 and nodes[0] == loaded[0]:
        return np.asarray(driver.step_compliance(int(nodes[0])), dtype=float)
    state = driver.get_state()
    base = predictions(driver, nodes).reshape(-1)
    W = np.zeros((3 * nodes.size, 3 * loaded.size))
    try:
        for b, j in enumerate(loaded.tolist()):
            for k in range(3):
                f = [0.0, 0.0, 0.0]
                f[k] = 1.0
                driver.set_state(state)
                driver.step({j: tuple(f)})
                W[:, 3 * b + k] = displacements_at(driver, nodes).reshape(-1) - base
    finally:
        driver.set_state(state)
    return W


class ForceInput:
    """For driver classes: the two load formats, {node: (fx, fy, fz)} or an (n, 3) array, and the
    node and count rules, checked the same way in every driver."""

    n_nodes: int

    def _as_array(self, forces) -> np.ndarray:
        if forces is None:
            return np.zeros((self.n_nodes, 3))
        return validate.forces(forces, self.n_nodes)

    def _node(self, node) -> int:
        return validate.node(node, self.n_nodes)

    @staticmethod
    def _vec(node, f) -> np.ndarray:
        return validate.vector(f, f"force on node {node}", 3)

    @staticmethod
    def _n_steps(n_steps) -> int:
        return validate.count(n_steps, "n_steps", 0, 10**9)

    def _parse_loads(self, forces: Mapping) -> tuple[np.ndarray, np.ndarray]:
        """{node: f} as (nodes, (k, 3)): in one pass where it can (a grasp loads tens of nodes per
        tick), else entry by entry, which names a bad entry."""
        parsed = self._load_arrays(forces)
        if parsed is not None:
            return parsed
        items = [(self._node(k), self._vec(k, f)) for k, f in forces.items()]
        return np.array([i for i, _ in items], dtype=np.int64), np.array([f for _, f in items]).reshape(-1, 3)

    def _load_arrays(self, forces: Mapping):
        """A {node: f} mapping as (nodes (k,), forces (k, 3)) in one pass, when every key is a plain
        int node on the mesh and every value three finite numbers (a contact patch's or a grasp's
        loads); None for anything else, which the caller parses entry by entry (naming a bad one)."""
        nodes = list(forces)
        if not all(type(v) is int for v in nodes):
            return None
        try:
            F = np.array(list(forces.values()), dtype=float)
        except (TypeError, ValueError):
            return None
        idx = np.array(nodes, dtype=np.int64)
        if F.shape != (idx.size, 3) or not np.isfinite(F).all() or idx.min() < 0 or idx.max() >= self.n_nodes:
            return None
        return idx, F


class StaticCorrection:
    """The static correction of a driver on a truncated basis (mode-acceleration method): the
    displacement the basis cannot hold, D f with D = K^-1 - P G P^T, added quasi-statically for
    the current loads f. P (3n, r) are the basis rows of the node translations and G (r,) the
    basis's static compliance (1 / w^2 for mass-normalized modes; 1 for a stiffness-orthonormal
    basis), so that at small load P q + D f is the exact linear static answer K^-1 f. The driver
    calls :meth:`_init_correction` and keeps ``_loads`` ({node: f}) or ``_load_array`` ((n, 3))
    as its last step's loads."""

    static_correction = False

    def _init_correction(self, on: bool, model, rows: np.ndarray, weights: np.ndarray) -> None:
        self.static_correction = bool(on)
        self._sc_model, self._sc_rows, self._sc_weights = model, rows, weights
        self._sc_supports = getattr(model, "supports_version", 0)  # the supports the basis was computed on
        self._loads: dict[int, np.ndarray] = {}
        self._load_array: np.ndarray | None = None
        self._D: dict[int, np.ndarray] = {}
        self._patch_rows: tuple | None = None  # (nodes, loaded nodes, their D rows at nodes) of the last patch read
        self._D_array: dict[bytes, np.ndarray] = {}  # static corrections of (n, 3) loads, last few kept

    def _correction_column(self, node: int) -> np.ndarray:
        """D for the 3 load directions of ``node``: (n, 3, 3) (displacement, load direction)."""
        D = self._D.get(node)
        if D is None:
            self._check_correction_supports()
            cols = [self._sc_model.unit_load_response(node, k) for k in range(3)]
            Kinv = np.stack(cols, axis=2)
            D = Kinv - self._modal_statics(np.array([node]))[0]
            self._D[node] = D
        return D

    def _check_correction_supports(self) -> None:
        """The correction's solves use the model's current supports: refuse them once the model
        was fixed otherwise than the basis was computed on (the two would not match)."""
        from ..fe.protocol import check_supports

        check_supports(self._sc_model, self._sc_supports, f"{type(self).__name__}'s static correction")

    def _modal_statics(self, nodes: np.ndarray) -> np.ndarray:
        """P G P^T for unit loads on ``nodes``: (k, n, 3, 3), one matrix product."""
        P = self._sc_rows
        Pk = P.reshape(-1, 3, P.shape[1])[nodes].reshape(3 * nodes.size, -1)
        G = (P * self._sc_weights) @ Pk.T
        return G.reshape(-1, 3, nodes.size, 3).transpose(2, 0, 1, 3)

    #: an (n, 3) load that differs from a kept one at no more than this many nodes is corrected as
    #: the kept one's correction plus the difference's columns (a body's weight plus its contacts)
    DIFF_NODES = 96

    def _array_correction(self, F: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """D F for an (n, 3) load: one static solve per distinct load, kept for the next call
        (a load schedule repeats a few patterns; haptic loads are dicts on prepared nodes). A load
        within a few nodes of a kept one (a scene body's weight and this step's contact and
        attachment forces) is that one's correction plus the columns of the nodes that differ
        (D is linear; the columns are kept), and is kept as the last answer only. With ``rows``
        (node indices), only (D F)[rows] (k, 3): for a few nodes, without the whole field."""
        key = F.tobytes()
        hit = self._D_array.get(key)
        if hit is None:
            last = getattr(self, "_D_last", None)
            hit = last[1] if last is not None and last[0] == key else None
        if hit is not None:
            return hit if rows is None else hit[rows]
        for base_key, base in reversed(list(self._D_array.items())):
            diff = F - np.frombuffer(base_key, dtype=F.dtype).reshape(F.shape)
            nz = diff != 0.0
            nodes = np.flatnonzero(nz[:, 0] | nz[:, 1] | nz[:, 2])  # (n, 3): faster than any(axis=1)
            if nodes.size <= self.DIFF_NODES:
                slots = self._pooled(nodes)
                z = np.zeros(self._pool_used)
                z[(3 * slots[:, None] + np.arange(3)).ravel()] = diff[nodes].reshape(-1)
                if rows is not None:  # the rows asked for only (not kept)
                    at = (3 * np.asarray(rows)[:, None] + np.arange(3)).ravel()
                    return base[rows] + (self._pool[at, :self._pool_used] @ z).reshape(-1, 3)
                hit = base + (self._pool[:, :self._pool_used] @ z).reshape(-1, 3)
                self._D_last = (key, hit)
                return hit
        self._check_correction_supports()
        Kinv_f = self._sc_model.solve_static(F, warn=False)
        P = self._sc_rows
        modal = (P @ ((P.T @ F.reshape(-1)) * self._sc_weights)).reshape(-1, 3)
        if len(self._D_array) >= 8:
            self._D_array.pop(next(iter(self._D_array)))
        hit = self._D_array[key] = Kinv_f - modal
        return hit if rows is None else hit[rows]

    def _pooled(self, nodes: np.ndarray) -> np.ndarray:
        """The slots of ``nodes``' correction columns in one (3n, 3 slots) pool (columns added once,
        the pool grown by doubling), so that a load on any of them is one matrix-vector product."""
        pool_slot = self.__dict__.setdefault("_pool_slot", {})
        missing = [j for j in nodes.tolist() if j not in pool_slot]
        if missing:
            self.prepare(np.array(missing, dtype=np.int64))
            used = 3 * len(pool_slot)
            need = used + 3 * len(missing)
            pool = getattr(self, "_pool", None)
            if pool is None or pool.shape[1] < need:
                grown = np.zeros((3 * self.n_nodes, max(need, 2 * (0 if pool is None else pool.shape[1]), 48)))
                if pool is not None:
                    grown[:, :used] = pool[:, :used]
                self._pool = pool = grown
            for j in missing:
                pool[:, 3 * len(pool_slot):3 * len(pool_slot) + 3] = self._D[j].reshape(-1, 3)
                pool_slot[j] = len(pool_slot)
            self._pool_used = 3 * len(pool_slot)
        return np.array([pool_slot[j] for j in nodes.tolist()], dtype=np.int64)

    def prepare(self, nodes) -> None:
        """Precompute the static-correction columns of the nodes that will be loaded (the missing
        ones together: multi-column solves when the model has ``unit_load_responses``)."""
        nodes = validate.nodes(nodes, self.n_nodes)
        if not self.static_correction:
            return
        missing = np.array([n for n in dict.fromkeys(nodes.tolist()) if n not in self._D], dtype=np.int64)
        batched = getattr(self._sc_model, "unit_load_responses", None)
        if missing.size < 2 or batched is None:
            for n in missing.tolist():
                self._correction_column(n)
            return
        self._check_correction_supports()
        Kinv = batched(missing)  # (k, n, 3, 3)
        modal = self._modal_statics(missing)
        for i, n in enumerate(missing.tolist()):
            self._D[n] = Kinv[i] - modal[i]

    def _current_loads(self):
        """(loads {node: f}, load array or None) as one step left them. A step replaces both (never
        mutates them), so the references taken here stay one step's loads while another thread
        steps the driver (a loop stepping it while a bridge or a viewer reads its field)."""
        return self._loads, self._load_array

    def _add_correction(self, u: np.ndarray) -> None:
        """Add the static correction of the current loads to the field u (n, 3), in place (a
        float32 field takes the float64 sum rounded). Each loaded node's columns are one BLAS
        matrix-vector product over the (3n, 3) column block: numpy's stacked (n, 3, 3) @ (3,)
        product ran 5 times slower (36 against 6.7 ms for 114 loads on 15,000 nodes;
        benchmarks/viewer_step.py)."""
        loads, array = self._current_loads()
        if array is not None:
            u += self._array_correction(array)
        if loads:
            total = np.zeros(u.size)
            for node, f in loads.items():
                total += self._correction_column(node).reshape(-1, 3) @ f
            u += total.reshape(u.shape)

    def _point_correction(self, i: int):
        """The static correction (3,) of the current loads at node i, or None with no loads."""
        loads, array = self._current_loads()
        if array is not None:
            return self._array_correction(array)[i]
        c = None
        for j, f in loads.items():
            c = self._correction_column(j)[i] @ f if c is None else c + self._correction_column(j)[i] @ f
        return c

    def _correction_at(self, nodes: np.ndarray, u: np.ndarray) -> np.ndarray:
        """u (k, 3) at ``nodes`` plus the static correction of the current loads there."""
        loads, array = self._current_loads()
        if array is not None:  # a few nodes of a large field: their rows only
            if 8 * nodes.size < array.shape[0]:
                return u + self._array_correction(array, nodes)
            return u + self._array_correction(array)[nodes]
        if len(loads) > 2:  # a contact patch, asked again about the same nodes next tick
            G = self._gathered(nodes, tuple(loads))
            return u + (G @ np.array(list(loads.values())).reshape(-1)).reshape(-1, 3)
        for j, f in loads.items():
            u = u + self._correction_column(j)[nodes] @ f
        return u

    def _correction_block(self, nodes: np.ndarray, loaded: np.ndarray) -> np.ndarray:
        """D_ab (3k, 3l) for ``nodes`` against ``loaded`` (columns computed the first time, as
        :meth:`prepare` does). D does not change: the last block is kept, for a driver whose step
        compliances are asked again at each tangent refresh about the same grasped patch (a gather
        of k columns' l rows each time: 1 ms for a 114-node patch)."""
        key = (nodes.tobytes(), loaded.tobytes())
        kept = self.__dict__.get("_block_kept")
        if kept is not None and kept[0] == key:
            return kept[1]
        block = self._gather_block(nodes, loaded)
        self._block_kept = (key, block)
        return block

    def _gather_block(self, nodes: np.ndarray, loaded: np.ndarray) -> np.ndarray:
        if nodes.size < loaded.size and all(v in self._D for v in nodes.tolist()):
            # D is symmetric (K^-1 minus the basis's part): rows of a few nodes against many loads
            # are the transposed columns of those few (one gather each, not one per load)
            return np.concatenate([self._D[j][loaded].reshape(-1, 3) for j in nodes.tolist()], axis=1).T
        return np.concatenate([self._correction_column(j)[nodes].reshape(-1, 3) for j in loaded.tolist()], axis=1)

    def _gathered(self, nodes: np.ndarray, keys: tuple) -> np.ndarray:
        """The static-correction columns of the loaded nodes ``keys`` at ``nodes`` as one (3k, 3 loads)
        matrix, kept while the loaded nodes and the nodes asked about stay the same (a tool resting
        on a patch: one matrix-vector product instead of a gather per load each tick)."""
        hit = self._patch_rows
        same = hit is not None and hit[0].size == nodes.size and np.array_equal(hit[0], nodes)
        if same and hit[1] == keys:
            return hit[2]
        cols = hit[3] if same and len(hit[3]) < 256 else {}  # each load's rows, for the loads to come
        for j in keys:
            if j not in cols:
                cols[j] = self._correction_column(j)[nodes].reshape(-1, 3)
        G = np.concatenate([cols[j] for j in keys], axis=1)
        self._patch_rows = (nodes.copy(), keys, G, cols) if G.size <= 4_000_000 else None
        return G


def check_driver_mesh(mesh, driver, what: str) -> None:
    """Refuse a driver computed for another mesh (size or fingerprint), when it says which."""
    from ..reduction.modal import mesh_fingerprint

    if not isinstance(mesh, TriMesh):
        raise ModelError(f"mesh={validate.show(mesh)} must be an rtfem TriMesh (the organ the {what} touches)")
    n, fp = driver.n_nodes, getattr(driver, "fingerprint", None)
    if n != mesh.n_vertices:
        raise ModelError(f"the {what}'s driver was computed for a mesh of {n} nodes, not this mesh of "
                         f"{mesh.n_vertices}: give the mesh it was computed for")
    if fp is not None and fp != mesh_fingerprint(mesh):
        raise ModelError(f"the {what}'s driver was computed for another mesh of the same size (fingerprint "
                         f"{str(fp)[:8]}, this mesh {mesh_fingerprint(mesh)[:8]}): give the mesh it was computed for")
