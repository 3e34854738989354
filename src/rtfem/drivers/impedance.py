"""The impedance map: precomputed responses to unit loads, superposed at run time (paper 4.1).

For each selected node j and direction k, the displacement response to a unit step load
switched on at t = 0 is computed at the requested time samples plus its static limit, and
kept only where it matters: within a radius of influence of j (Euclidean or geodesic), or
where it is larger than a fraction of its peak (``threshold``; a radius fails for a load
near the free end of an organ held at the other end, where the largest motion lies far
from the load). At run time, the field of any set of loads switched on at given times is
the superposition of those columns, delayed to their onsets (Duhamel), and the 3x3 point
compliance at a contact node renders the force.

Responses come from the modal route (``method="modal"``: r modes, exact closed form in time,
plus the static correction so that the static limit is exact) or from SLDM (one Krylov basis
per load vector; exact to ``tol`` at every sample, costlier to build).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from .. import validate
from ..errors import ModelError
from ..storage import load_versioned, save_versioned
from ..fe.material import Damping
from ..fe.protocol import check_model
from ..reduction.modal import check_model_key, mesh_fingerprint, model_key

from .impedance_columns import (_check_build, _check_memory, _check_modes, _estimate, _loaded_nodes, _NeighbourFinder,
                                _run_cluster, _run_here)

__all__ = ["ImpedanceMap", "Load"]

FORMAT_VERSION = 1


@dataclass(frozen=True)
class Load:
    """A force switched on at ``onset`` and held: the loads of :meth:`ImpedanceMap.response`.

    Parameters
    ----------
    node : the loaded node.
    force : (fx, fy, fz) in N.
    onset : when it is switched on (s).

    Raises
    ------
    ModelError
        From the map's methods, for a node it does not load or a non-finite force.
    """

    node: int
    force: tuple[float, float, float]
    onset: float = 0.0


class ImpedanceMap:
    """Precomputed unit-load responses (see the module docstring); build with :meth:`build`, read
    with :meth:`load`. The constructor takes the arrays as :meth:`save` writes them.

    Parameters
    ----------
    n_nodes : nodes of the mesh the map belongs to.
    times : (nt,) increasing sample times (s) of the step responses.
    loaded : (L,) the loaded nodes, each once.
    offsets : (L + 1,) each loaded node's slice of ``neighbours`` (rising from 0).
    neighbours : the nodes whose responses are kept for each loaded node.
    responses : (len(neighbours), 3, 3, nt + 1) the responses at the sample times and the static one.
    point : (L, 3, 3, nt + 1) each loaded node's own (point) response, kept exactly.
    fingerprint : the mesh's fingerprint.
    info : what :meth:`build` recorded (radius, damping, model key, ...).

    Raises
    ------
    ModelError
        Arrays that do not fit together (each message names the array and what it must be).
    """

    def __init__(self, n_nodes: int, times: np.ndarray, loaded: np.ndarray, offsets: np.ndarray,
                 neighbours: np.ndarray, responses: np.ndarray, point: np.ndarray, fingerprint: str,
                 info: dict | None = None) -> None:
        n = validate.count(n_nodes, "n_nodes", 1)
        times = validate.times(times, "times")
        loaded = validate.int_array(loaded, "loaded")
        offsets = validate.int_array(offsets, "offsets")
        neighbours = validate.int_array(neighbours, "neighbours")
        L, nt = loaded.size, times.size + 1
        if L == 0:
            raise ModelError("loaded is empty: a map needs at least one loaded node")
        if loaded.min() < 0 or loaded.max() >= n:
            raise ModelError(f"loaded holds node {loaded.max() if loaded.max() >= n else loaded.min()} outside "
                             f"0..{n - 1} (n_nodes = {n})")
        if np.unique(loaded).size != L:
            raise ModelError("loaded lists a node twice")
        if offsets.size != L + 1 or offsets[0] != 0 or np.any(np.diff(offsets) < 0) or offsets[-1] != neighbours.size:
            raise ModelError(f"offsets must rise from 0 to {neighbours.size} (the length of neighbours) in {L + 1} "
                             f"entries, one slot per loaded node; got {offsets.size} entries from "
                             f"{offsets[0] if offsets.size else '-'} to {offsets[-1] if offsets.size else '-'}")
        if neighbours.size and (neighbours.min() < 0 or neighbours.max() >= n):
            bad = neighbours.max() if neighbours.max() >= n else neighbours.min()
            raise ModelError(f"neighbours holds node {bad} outside 0..{n - 1} (n_nodes = {n})")
        inner = np.ones(neighbours.size, bool)
        inner[offsets[:-1][offsets[:-1] < neighbours.size]] = False  # first entry of each slot
        if neighbours.size > 1 and np.any(np.diff(neighbours)[inner[1:]] <= 0):
            raise ModelError("neighbours are not strictly increasing within each loaded node's slot")
        responses = validate.real_array(responses, "responses", 4)
        if responses.shape != (neighbours.size, nt, 3, 3):
            raise ModelError(f"responses must have shape ({neighbours.size}, {nt}, 3, 3) for {neighbours.size} kept "
                             f"nodes and {times.size} times + the static limit, got {responses.shape}")
        point = validate.real_array(point, "point", 4)
        if point.shape != (L, nt, 3, 3):
            raise ModelError(f"point must have shape ({L}, {nt}, 3, 3), got {point.shape}")
        if not isinstance(fingerprint, str):
            raise ModelError(f"fingerprint={validate.show(fingerprint)} must be a string (the mesh hash)")
        if info is not None and not isinstance(info, dict):
            raise ModelError(f"info={validate.show(info)} must be a dict")
        self.n_nodes = n
        self.times = times  # (n_t,) samples; the static limit is appended
        self.loaded = loaded  # (L,) loaded nodes
        self.offsets = offsets  # (L + 1,) into neighbours/responses
        self.neighbours = neighbours  # (N,) kept nodes per loaded node, increasing
        self.responses = responses  # (N, n_t + 1, 3, 3): [kept node, time, u comp, load dir]
        self.point = point  # (L, n_t + 1, 3, 3): exact responses at the loaded node itself
        self.fingerprint = fingerprint
        self.info = dict(info or {})
        self._slot = np.full(self.n_nodes, -1, dtype=np.int64)
        self._slot[self.loaded] = np.arange(self.loaded.size)

    # ---------------------------------------------------------------- building
    @classmethod
    def build(cls, model, damping: Damping | None = None, *, nodes=None, radius: float | None = None,
              metric: str = "euclidean", threshold: float | None = None,
              times: Sequence[float] = (0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5), method: str = "modal",
              n_modes: int = 100, tol: float = 1e-6, memory_limit: float = 4 * 2**30,
              progress: Callable[[int, int, str], None] | None = None, workers: int = 1, modes=None,
              static: str = "solves", scheduler=None) -> "ImpedanceMap":
        """Precompute the map.

        Parameters
        ----------
        model : a restrained ShellModel.
        damping : the damping of the responses.
        nodes : loaded nodes (indices, mask or group name); default every free node of the surface.
        radius : radius of influence in metres (None: no radius).
        metric : "euclidean" or "geodesic" (shortest path along mesh edges).
        threshold : keep only nodes whose response exceeds ``threshold`` times the largest
            response of that column (at any time); combines with ``radius``.
        times : response samples (s), increasing, > 0; the static limit is kept as well.
        method : "modal" (``n_modes`` modes + static correction) or "sldm" (tolerance ``tol``).
        memory_limit : refuse to start if the estimate exceeds it (bytes).
        progress : ``progress(done, total, message)`` after each loaded node (nodes done, nodes asked
            for, a message with the node and the seconds so far).
        workers : loaded nodes computed in parallel by this many threads (the sparse solves
            and the BLAS products release the interpreter lock).
        modes : a :class:`~rtfem.ModalBasis` of this model to use instead of computing
            ``n_modes`` modes (method "modal").
        static : where the static limits (and the modal route's static correction) come from:
            "solves" (three sparse solves per loaded node, default) or "condensation" (Bro-Nielsen
            & Cotin: the surface's whole static compliance at once, :meth:`surface_compliance`
            with its Schur complement; the map then keeps surface nodes only, which is what is
            drawn and touched). Condensation pays for maps over a large part of a solid's surface
            (``benchmarks/condensation.py``); it is dense, (3 s)^2 for s surface nodes.
        scheduler : the columns on a Dask cluster (:mod:`rtfem.cluster`): "tcp://HOST:PORT",
            "local:N" or a ``distributed.Client``; each worker rebuilds the model and factorizes it
            once, the modes are computed here and sent once, a task carries a few loaded nodes; the
            same map (tests/test_cluster.py). Tasks of a worker that dies are rerun; a failure Dask
            gives up on keeps, as Ctrl-C does, the nodes that came back (``info["error"]`` says why).
            Not with ``static="condensation"``.

        Raises
        ------
        ModelError
            A bad option (each named), a model with nothing fixed, modes of another model, a map
            above ``memory_limit``, a scheduler that cannot be reached.

        A KeyboardInterrupt stops the build cleanly: the map holds the nodes finished so far
        (``info["complete"]`` is False, ``info["requested_nodes"]`` says how many were asked
        for) and can be saved; an interruption before the first node is re-raised.
        """
        check_model(model)
        damping, t, radius, threshold, n_modes, tol = _check_build(damping, times, metric, radius, threshold, method,
                                                                     n_modes, tol)
        memory_limit = validate.positive(memory_limit, "memory_limit", "a size in bytes")
        progress, workers = validate.progress(progress), validate.count(workers, "workers", 1, 256)
        static = validate.choice(static, "static", ("solves", "condensation"))
        _check_modes(model, modes)
        model.check_restrained()
        loaded, held = _loaded_nodes(model, nodes)
        within = _NeighbourFinder(model.mesh, radius, metric)
        _check_memory(loaded, within, t.size, memory_limit)
        t0, why = time.perf_counter(), ""
        settings = (method, damping, t, n_modes, tol, radius, metric, threshold)
        if scheduler is not None:
            results, complete, why, setup = _run_cluster(scheduler, model, settings, modes, loaded, progress,
                                                         static=static)
        else:
            results, complete, setup = _run_here(model, settings, modes, static, loaded, within, workers, progress)
        info = {"method": method, "radius": float(radius) if radius is not None else -1.0, "metric": metric,
                "threshold": float(threshold) if threshold is not None else -1.0,
                "seconds": time.perf_counter() - t0 - setup, "complete": complete, "alpha": damping.alpha,
                "beta": damping.beta, "n_modes": n_modes if method == "modal" else -1,
                "tol": tol if method == "sldm" else -1.0, "precompute_seconds": setup,
                "skipped_fixed_nodes": int(held.size), "static": static, "requested_nodes": int(loaded.size),
                "error": why, "scheduler": "" if scheduler is None else str(getattr(scheduler, "scheduler", scheduler)),
                "model_key": model_key(model)}
        offsets = np.r_[0, np.cumsum([r[1].size for r in results])]
        return cls(model.n_nodes, t, np.array([r[0] for r in results]), offsets,
                   np.concatenate([r[1] for r in results]), np.concatenate([r[2] for r in results]),
                   np.array([r[3] for r in results]), mesh_fingerprint(model.mesh), info)

    # ---------------------------------------------------------------- sizes
    @staticmethod
    def estimate_bytes(model, *, nodes=None, radius: float | None = None, metric: str = "euclidean",
                       times: Sequence[float] = (0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5)) -> dict:
        """What :meth:`build` with these settings would hold (and :meth:`save` write), before
        any work: ``{"bytes", "loaded", "kept_per_node", "samples"}`` (the kept neighbourhoods
        sampled at 20 loaded nodes; a ``threshold`` keeps fewer)."""
        check_model(model)
        t = validate.times(times, "times")
        validate.choice(metric, "metric", ("euclidean", "geodesic"))
        if radius is not None:
            radius = validate.positive(radius, "radius", "a radius of influence in m, or None")
        loaded, _ = _loaded_nodes(model, nodes)
        nbytes, kept = _estimate(loaded, _NeighbourFinder(model.mesh, radius, metric), t.size)
        return {"bytes": nbytes, "loaded": int(loaded.size), "kept_per_node": kept, "samples": int(t.size + 1)}

    @property
    def nbytes(self) -> int:
        return int(self.responses.nbytes + self.point.nbytes + self.neighbours.nbytes + self.offsets.nbytes)

    @property
    def bytes_per_node(self) -> float:
        """Memory per loaded node (bytes)."""
        return self.nbytes / max(1, self.loaded.size)

    def __repr__(self) -> str:
        kept = np.diff(self.offsets).mean() if self.loaded.size else 0
        return (f"ImpedanceMap({self.loaded.size} loaded nodes, {kept:.0f} kept per node, {self.times.size} samples "
                f"+ static, {self.nbytes / 2**20:.1f} MiB, method={self.info.get('method')!r})")

    # ---------------------------------------------------------------- run time
    def _slot_of(self, node, name: str = "node") -> int:
        node = validate.node(node, self.n_nodes, name)
        if self._slot[node] < 0:
            raise ModelError(f"node {node} is not a loaded node of this impedance map")
        return int(self._slot[node])

    def _sample(self, R: np.ndarray, tau: float) -> np.ndarray | None:
        """R (k, n_t + 1, 3, 3) at a delay tau, linear in time between samples.

        Before the first sample the response grows linearly from 0 at tau = 0; past the last
        sample the static limit is used (choose the samples to cover the settling time).
        """
        t = self.times
        if tau <= 0:
            return None
        if tau > t[-1]:
            return R[:, -1]
        i1 = int(np.searchsorted(t, tau))
        if i1 == 0:
            return R[:, 0] * (tau / t[0])
        w = (tau - t[i1 - 1]) / (t[i1] - t[i1 - 1])
        return (1 - w) * R[:, i1 - 1] + w * R[:, i1]

    def displacements(self, loads: Iterable[Load | tuple], t: float) -> np.ndarray:
        """Superposed (n, 3) displacement field at time ``t`` of loads switched on at their onsets.

        ``loads``: :class:`Load` objects or ``(node, (fx, fy, fz), onset)`` tuples; a load that
        ends is a second load of opposite sign at the release time.
        """
        t = validate.instant(t, "t")
        if isinstance(loads, (str, bytes)) or not hasattr(loads, "__iter__"):
            raise ModelError(f"loads={validate.show(loads)} must be a list of Load or (node, (fx, fy, fz), onset)")
        parsed = []
        for ld in loads:
            if isinstance(ld, Load):
                node, f, onset = ld.node, ld.force, ld.onset
            elif isinstance(ld, (tuple, list)) and len(ld) in (2, 3):
                node, f, onset = ld[0], ld[1], ld[2] if len(ld) > 2 else 0.0
            else:
                raise ModelError(f"load {validate.show(ld)} must be a Load or a (node, (fx, fy, fz), onset) tuple")
            self._slot_of(node, "load node")
            f = validate.vector(f, f"force on node {node}", 3)
            onset = validate.instant(onset, "onset")
            parsed.append((int(node), f, onset))
        u = np.zeros((self.n_nodes, 3))
        for node, f, onset in parsed:
            self._superpose(u, node, f, t - onset)
        return u

    def _superpose(self, u: np.ndarray, node: int, f: np.ndarray, delay: float) -> None:
        """u += the field of a step load f switched on at a loaded node ``delay`` seconds ago
        (inf: its static limit); checked arguments (the run-time path)."""
        s = int(self._slot[node])
        lo, hi = self.offsets[s], self.offsets[s + 1]
        Rt = self._sample(self.responses[lo:hi], delay)
        if Rt is not None:
            u[self.neighbours[lo:hi]] += Rt @ f

    def compliance_at(self, loaded: int, nodes: np.ndarray, t: float | None = None) -> np.ndarray:
        """(k, 3, 3) responses at ``nodes`` per unit force at ``loaded`` (static when t is None).

        O(k log kept): what a haptic update needs (the field near the contact), without
        superposing the whole map. Nodes outside the kept set get zeros.
        """
        self._slot_of(loaded, "loaded")
        nodes = validate.nodes(nodes, self.n_nodes)
        if t is not None:
            t = validate.instant(t, "t")
        return self._columns(int(loaded), nodes, t)

    def _columns(self, loaded: int, nodes: np.ndarray, t: float | None) -> np.ndarray:
        """:meth:`compliance_at` on checked arguments (the run-time path)."""
        s = int(self._slot[loaded])
        lo, hi = self.offsets[s], self.offsets[s + 1]
        kept = self.neighbours[lo:hi]  # sorted
        pos = np.clip(np.searchsorted(kept, nodes), 0, max(kept.size - 1, 0))
        hit = kept[pos] == nodes
        out = np.zeros((nodes.size, 3, 3))
        R = self.responses[lo + pos[hit]]
        if t is None:
            out[hit] = R[:, -1]
        else:
            Rt = self._sample(R, t)
            if Rt is not None:
                out[hit] = Rt
        return out

    def point_compliance(self, node: int, t: float | None = None) -> np.ndarray:
        """3x3 compliance at a loaded node: displacement there per unit force there.

        ``t=None`` gives the static compliance (G_pp = [K^-1]_pp), otherwise the step-response
        compliance after a delay ``t``. Exact (it does not depend on the truncation).
        """
        s = self._slot_of(node)
        if t is not None:
            t = validate.instant(t, "t")
        P = self.point[s][None]
        if t is None:
            return self.point[s, -1].copy()
        out = self._sample(P, t)
        return np.zeros((3, 3)) if out is None else out[0]

    def as_driver(self, dt: float = 1e-3, *, dynamic: bool = False):
        """This map as a Driver (what Probe and Grasp use when given the map): quasi-static, or with
        ``dynamic=True`` its field follows the force history (:class:`ImpedanceDriver`)."""
        return ImpedanceMap._driver(self, dt, dynamic=dynamic)

    _driver = None  # ImpedanceDriver: rtfem.drivers.impedance_driver registers it (the package imports it)

    # ---------------------------------------------------------------- files
    _ARRAYS = ["times", "loaded", "offsets", "neighbours", "responses", "point"]

    def save(self, path: str | os.PathLike) -> Path:
        """Save as a versioned ``.npz`` (no pickle)."""
        arrays = {k: getattr(self, k) for k in self._ARRAYS}
        arrays.update(n_nodes=np.array(self.n_nodes), fingerprint=np.array(self.fingerprint))
        return save_versioned(path, "rtfem.ImpedanceMap", FORMAT_VERSION, arrays, self.info)

    @classmethod
    def load(cls, path: str | os.PathLike, model=None) -> "ImpedanceMap":
        """Load a saved map; with ``model`` it must belong to that model's mesh."""
        z, info = load_versioned(path, "rtfem.ImpedanceMap", FORMAT_VERSION, cls._ARRAYS + ["n_nodes", "fingerprint"],
                                  "impedance map")
        fp, n = z.pop("fingerprint"), z.pop("n_nodes")
        where = repr(str(path))
        if fp.dtype.kind != "U" or fp.ndim != 0:
            raise ModelError(f"{where}: field 'fingerprint' is not a string: the file is damaged or altered")
        if n.ndim != 0 or not np.issubdtype(n.dtype, np.integer):
            raise ModelError(f"{where}: field 'n_nodes' is not an integer: the file is damaged or altered")
        fp, n = str(fp), int(n)
        if model is not None:
            check_model(model)
            if n != model.n_nodes:
                raise ModelError(f"{where}: field 'n_nodes' = {n} but the model has {model.n_nodes} nodes: "
                                 "the map was built for a different mesh (or the file was altered)")
            if fp != mesh_fingerprint(model.mesh):
                raise ModelError(f"{where} was built for a different mesh (field 'fingerprint'); rebuild it with "
                                 "ImpedanceMap.build")
            check_model_key(info, model, where)  # maps saved before it was recorded have none
        try:
            return cls(n, fingerprint=fp, info=info, **z)
        except ModelError as exc:
            raise ModelError(f"{where}: {exc}; the file is damaged or altered") from None
