"""How an impedance map's columns are computed (:meth:`rtfem.ImpedanceMap.build`): the build's checks,
the loaded nodes and their neighbourhoods (a radius, Euclidean or geodesic), the size estimate, the
response engines (the modal route with its static correction, SLDM; the static limits solved or from
the surface's condensed compliance) and the run over the loaded nodes (threads, progress, Ctrl-C
keeping what is done)."""

from __future__ import annotations

import time

import numpy as np
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from .. import validate
from ..errors import ModelError
from ..fe.material import Damping
from ..reduction.modal import mesh_fingerprint, modal_analysis
from ..reduction.oscillator import step_response


def _check_build(damping, times, metric, radius, threshold, method, n_modes, tol) -> tuple:
    """:meth:`ImpedanceMap.build`'s options checked: (damping, times, radius, threshold, n_modes, tol)."""
    if damping is not None and not isinstance(damping, Damping):
        raise ModelError(f"damping={validate.show(damping)} must be an rt.Damping (or None)")
    damping = damping if damping is not None else Damping()
    t = validate.times(times, "times")
    validate.choice(metric, "metric", ("euclidean", "geodesic"))
    if radius is not None:
        radius = validate.positive(radius, "radius", "a radius of influence in m, or None")
    if threshold is not None:
        threshold = validate.in_range(threshold, "threshold", 0.0, 1.0, hi_open=True,
                                      what="a fraction of each column's peak, or None")
    validate.choice(method, "method", ("modal", "sldm"))
    n_modes = validate.count(n_modes, "n_modes", 1, what="modes of the modal route")
    tol = validate.in_range(tol, "tol", 0.0, 1.0, lo_open=True, hi_open=True, what="SLDM's relative accuracy")
    return damping, t, radius, threshold, n_modes, tol


def _check_modes(model, modes) -> None:
    """Refuse a modal basis (given to :meth:`ImpedanceMap.build`) computed for another model."""
    if modes is None:
        return
    from ..reduction.modal import ModalBasis

    if (not isinstance(modes, ModalBasis) or modes.n_nodes != model.n_nodes
            or modes.fingerprint != mesh_fingerprint(model.mesh)
            or (modes.model is not None and modes.model is not model)):
        raise ModelError("modes must be a ModalBasis computed for this model (rt.modal_analysis(model, r))")


def _condensed_static(model, engine, loaded: np.ndarray) -> np.ndarray:
    """The engine's static limits from the surface's condensed compliance (Bro-Nielsen & Cotin);
    returns the mask of the surface nodes it covers (the map keeps those only)."""
    t_cond = time.perf_counter()
    nodes_s, C = model.surface_compliance(np.union1d(_free_surface(model), loaded), method="condensation")
    engine.static = _CondensedStatic(model.n_nodes, nodes_s, C)
    engine.setup_seconds += time.perf_counter() - t_cond
    surface = np.zeros(model.n_nodes, dtype=bool)
    surface[nodes_s] = True
    return surface


def _column_task(engine, within, surface: np.ndarray | None, threshold: float | None):
    """The work for one loaded node j: its response columns, kept within the radius (on the surface,
    where the static limit is known there only) and above the threshold of the column's peak."""

    def one(j: int):
        cols = engine.columns(j)  # (n, n_t + 1, 3, 3)
        keep = within(j)
        if surface is not None:
            keep = keep[surface[keep]]
        if threshold is not None and threshold > 0:
            mag = np.abs(cols[keep]).max(axis=(1, 2, 3))
            keep = keep[mag >= threshold * mag.max()]
        return j, keep, cols[keep], cols[j].copy()  # a copy: a view would keep all of cols alive

    return one


def _free_surface(model) -> np.ndarray:
    """The surface's nodes that can move (all free nodes on a shell; a solid is touched on its surface)."""
    surface = model.mesh.used_vertices()
    return surface[~model.held_nodes[surface]]


def _loaded_nodes(model, nodes) -> tuple[np.ndarray, np.ndarray]:
    """The nodes to load (default every free surface node) and those given that are held (skipped: a
    load on a fixed node moves nothing)."""
    if nodes is None:
        loaded = _free_surface(model)
    else:
        loaded = np.unique(model.select_nodes(nodes))
    held = loaded[model.held_nodes[loaded]]
    loaded = np.setdiff1d(loaded, held)
    if loaded.size == 0:
        raise ModelError("no free nodes to load (every node given is fixed)")
    return loaded, held


def _estimate(loaded: np.ndarray, within, n_times: int) -> tuple[float, float]:
    """(bytes, mean kept nodes per loaded node) of a map's responses, its kept neighbourhoods
    sampled at 20 loaded nodes (before any threshold, which keeps fewer)."""
    sample = loaded[np.linspace(0, loaded.size - 1, min(20, loaded.size)).astype(int)]
    mean_kept = float(np.mean([within(j).size for j in sample]))
    return loaded.size * mean_kept * (n_times + 1) * 9 * 8, mean_kept


def _check_memory(loaded: np.ndarray, within, n_times: int, memory_limit: float) -> None:
    """Refuse before starting when the map would exceed ``memory_limit``."""
    estimate, mean_kept = _estimate(loaded, within, n_times)
    if estimate > memory_limit:
        raise ModelError(
            f"the map would need about {estimate / 2**30:.1f} GiB ({mean_kept:.0f} nodes kept per loaded "
            f"node, {n_times + 1} samples, {loaded.size} loaded nodes), above memory_limit = "
            f"{memory_limit / 2**30:.1f} GiB; use a smaller radius, a threshold, fewer times or fewer nodes"
        )


def _run_nodes(one, loaded: np.ndarray, workers: int, progress) -> tuple[list, bool]:
    """``one(j)`` for every loaded node, in order, on ``workers`` threads; a KeyboardInterrupt
    keeps the finished nodes (complete = False) unless there are none (re-raised)."""
    # one append per finished node: a Ctrl-C between two bytecodes cannot leave the
    # partial results inconsistent
    results: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []
    t0 = time.perf_counter()
    complete = True

    def collect(result) -> None:
        results.append(result)
        if progress is not None:
            progress(len(results), loaded.size, f"node {result[0]}, {time.perf_counter() - t0:.1f} s")

    try:
        if workers == 1:
            for j in loaded:
                collect(one(int(j)))
        else:
            from concurrent.futures import ThreadPoolExecutor

            with ThreadPoolExecutor(max_workers=workers) as pool:
                pending = []  # in order, a window of 2 x workers in flight
                for j in loaded:
                    pending.append(pool.submit(one, int(j)))
                    if len(pending) >= 2 * workers:
                        collect(pending.pop(0).result())
                while pending:
                    collect(pending.pop(0).result())
    except KeyboardInterrupt:
        complete = False
    if not results:
        raise KeyboardInterrupt  # nothing to keep: an ordinary interruption
    return results, complete


def _run_here(model, settings: tuple, modes, static: str, loaded: np.ndarray, within, workers: int,
              progress) -> tuple[list, bool, float]:
    """The loaded nodes' columns here, on ``workers`` threads (``settings`` as :func:`_cluster_columns`
    takes them; the neighbourhoods are ``within``'s): (results, complete, the engine's setup seconds:
    the modes or SLDM's factorization, the condensed compliance)."""
    method, damping, t, n_modes, tol, _, _, threshold = settings
    engine = (_ModalColumns(model, damping, t, n_modes, modes) if method == "modal"
              else _SLDMColumns(model, damping, t, tol))
    surface = _condensed_static(model, engine, loaded) if static == "condensation" else None
    return (*_run_nodes(_column_task(engine, within, surface, threshold), loaded, workers, progress),
            engine.setup_seconds)


def _run_cluster(scheduler, model, settings: tuple, modes, loaded: np.ndarray, progress,
                 chunk: int | None = None, static: str = "solves") -> tuple[list, bool, str, float]:
    """The loaded nodes' columns on a Dask cluster (:mod:`rtfem.cluster`), connected before anything
    is computed: the modes here (method "modal", unless given), then every worker rebuilds the model
    from its recipe and the engine once (:func:`_cluster_columns`), tasks carry ``chunk`` nodes each.
    Returns (results in the loaded nodes' order, complete, why not, the modes' seconds)."""
    from ..cluster import connect

    if static == "condensation":
        raise ModelError("static='condensation' is computed here: with a scheduler use static='solves' (each worker "
                         "solves its own nodes' static limits)")
    with connect(scheduler) as client:  # a wrong address is said before the modes
        t0 = time.perf_counter()
        if settings[0] == "modal" and modes is None:
            modes = modal_analysis(model, settings[3])
        setup = time.perf_counter() - t0
        return (*_cluster_nodes(client, model, settings, modes, loaded, progress, chunk), setup)


def _cluster_nodes(client, model, settings, modes, loaded, progress, chunk) -> tuple[list, bool, str]:
    from ..cluster import run_tasks
    from ..fe.recipe import ModelRecipe

    recipe = ModelRecipe.of(model)
    light = None if settings[0] != "modal" else (np.asarray(modes.shapes), np.asarray(modes.omega))  # not matrices
    results: list = []
    t0 = time.perf_counter()

    def collect(batch) -> None:
        for r in batch:
            results.append(r)
            if progress is not None:
                progress(len(results), loaded.size, f"node {r[0]}, {time.perf_counter() - t0:.1f} s")

    workers = max(1, sum(client.nthreads().values()))
    size = chunk or int(np.clip(np.ceil(loaded.size / (4 * workers)), 1, 32))
    chunks = [loaded[i:i + size] for i in range(0, loaded.size, size)]
    stage = None if progress is None else (lambda message: progress(len(results), loaded.size, message))
    why = run_tasks(client, _cluster_columns, (recipe, light, settings), chunks, collect, stage=stage)
    slot = np.full(model.n_nodes, -1)
    slot[loaded] = np.arange(loaded.size)
    results.sort(key=lambda r: slot[r[0]])
    return results, not why, why


def _cluster_columns(recipe, light, settings: tuple, nodes: np.ndarray) -> list:
    """On a worker: the columns of ``nodes`` (as :func:`_column_task`'s), with the model, its
    factorization and the engine built once per worker process for this recipe and settings."""
    import hashlib
    import types

    from ..cluster import worker_cached

    method, damping, times, n_modes, tol, radius, metric, threshold = settings
    h = hashlib.sha256(repr(settings).encode())
    if light is not None:
        h.update(np.ascontiguousarray(light[1]).tobytes())

    def build():
        model = recipe.build()
        if method == "modal":
            engine = _ModalColumns(model, damping, times, n_modes, types.SimpleNamespace(shapes=light[0], omega=light[1]))
        else:
            engine = _SLDMColumns(model, damping, times, tol)
        return _column_task(engine, _NeighbourFinder(model.mesh, radius, metric), None, threshold)

    one = worker_cached(recipe.key + h.hexdigest(), build)
    return [one(int(j)) for j in nodes]


class _NeighbourFinder:
    def __init__(self, mesh, radius, metric):
        self.mesh, self.radius, self.metric = mesh, radius, metric
        self.X = np.asarray(mesh.vertices)
        self.all = np.arange(mesh.n_vertices)
        if radius is not None and metric == "euclidean":
            self.tree = cKDTree(self.X)

    def __call__(self, j: int) -> np.ndarray:
        if self.radius is None:
            return self.all
        if self.metric == "euclidean":
            return np.array(sorted(self.tree.query_ball_point(self.X[j], self.radius)), dtype=np.int64)
        d = dijkstra(self.mesh.adjacency(), directed=False, indices=j, limit=self.radius)
        return np.flatnonzero(np.isfinite(d))


class _ModalColumns:
    """Unit-step columns from r modes with the static correction (mode acceleration)."""

    def __init__(self, model, damping, times, n_modes, modes=None):
        t0 = time.perf_counter()
        self.model = model
        self.basis = modal_analysis(model, n_modes) if modes is None else modes
        lam = self.basis.omega**2
        self.lam = lam
        g = step_response(lam[:, None], damping.modal_alpha(self.basis.omega)[:, None], times[None, :])
        self.g = np.concatenate([g, (1.0 / lam)[:, None]], axis=1)  # (r, n_t + 1): samples + static
        self.static = _SolvedStatic(model)
        self.setup_seconds = time.perf_counter() - t0

    def columns(self, j: int) -> np.ndarray:
        phi = self.basis.shapes  # (n, 3, r)
        pj = phi[j]  # (3, r): load direction k -> modal force pj[k]
        # modal part: u(t) = sum_i phi_i g_i(t) phi_i(j)^T e_k
        cols = np.einsum("nir,rt,kr->ntik", phi, self.g, pj, optimize=True)
        # static correction: D = K^-1 e_jk - Phi Lambda^-1 Phi^T e_jk, added at every time
        static = self.static(j)
        modal_static = cols[:, -1]
        cols += (static - modal_static)[:, None]
        return cols


class _SLDMColumns:
    """Unit-step columns from SLDM, three Krylov bases per loaded node."""

    def __init__(self, model, damping, times, tol):
        from ..reduction.sldm import SLDM

        t0 = time.perf_counter()
        self.model = model
        self.sldm = SLDM(model, damping, tol=tol)
        self.times = times
        self.static = _SolvedStatic(model)
        self.setup_seconds = time.perf_counter() - t0

    def columns(self, j: int) -> np.ndarray:
        n = self.model.n_nodes
        cols = np.zeros((n, self.times.size + 1, 3, 3))
        F = np.zeros((n, 6))
        static = self.static(j)
        for k in range(3):
            if self.model.fixed[j, k]:
                continue  # a load on a fixed dof goes into the support: a zero column
            F[:] = 0.0
            F[j, k] = 1.0
            U = self.sldm.step_response(F[:, :3], self.times)  # (n_t, n, 3)
            cols[:, :-1, :, k] = U.transpose(1, 0, 2)
            cols[:, -1, :, k] = static[:, :, k]
        return cols


class _SolvedStatic:
    """A loaded node's static responses (n, 3, 3) by three sparse solves."""

    def __init__(self, model) -> None:
        self.model = model

    def __call__(self, j: int) -> np.ndarray:
        static = np.empty((self.model.n_nodes, 3, 3))
        for k in range(3):
            static[:, :, k] = self.model.unit_load_response(j, k)
        return static


class _CondensedStatic:
    """A loaded node's static responses from the condensed surface compliance (zero off the surface,
    where the map then keeps nothing)."""

    def __init__(self, n_nodes: int, nodes: np.ndarray, C: np.ndarray) -> None:
        self.n, self.nodes, self.C = n_nodes, nodes, C
        self.pos = np.full(n_nodes, -1, dtype=np.int64)
        self.pos[nodes] = np.arange(nodes.size)

    def __call__(self, j: int) -> np.ndarray:
        static = np.zeros((self.n, 3, 3))
        b = 3 * self.pos[j]
        static[self.nodes] = self.C[:, b:b + 3].reshape(-1, 3, 3)
        return static
