"""The static compliance between surface nodes (:meth:`rtfem.fe.model.FEModel.surface_compliance`): the
columns of K^-1 by blocks of solves, or Bro-Nielsen & Cotin's condensation (the Schur complement of the
other dofs and its dense inverse); the blocks of columns here, or on a Dask cluster's workers
(:mod:`rtfem.cluster`), each rebuilding the model from its recipe and factorizing once."""

from __future__ import annotations

import numpy as np

from .. import validate
from ..errors import ModelError
from .linalg import factorize

__all__ = ["surface_compliance"]

_DENSE_LIMIT = 6000  # largest condensed size (3n) formed densely without allow_large=True


def surface_compliance(model, nodes, method: str, memory: float, allow_large: bool, scheduler=None):
    """(nodes, C): see :meth:`rtfem.fe.model.FEModel.surface_compliance`.

    Parameters
    ----------
    model : the model (restrained).
    nodes : the nodes (None: the surface's not fully held).
    method : "solves" or "condensation".
    memory : bytes of right-hand sides per block of columns.
    allow_large : form C above 6,000 rows.
    scheduler : None (here) or a Dask scheduler (:func:`rtfem.cluster.connect`).

    Returns
    -------
    tuple
        (nodes, C (3s, 3s)).

    Raises
    ------
    ModelError
        A bad method, memory or nodes, a C too large, a model with nothing fixed, an unreachable
        scheduler.
    """
    from scipy.linalg import cho_factor, cho_solve

    method = validate.choice(method, "method", ("solves", "condensation"))
    memory = validate.positive(memory, "memory", "a size in bytes")
    allow_large = validate.flag(allow_large, "allow_large")
    if nodes is None:
        used = model.mesh.used_vertices()
        nodes = used[~model.held_nodes[used]]
    else:
        nodes = np.unique(validate.nodes(nodes, model.n_nodes))
    if 3 * nodes.size > _DENSE_LIMIT and not allow_large:
        raise ModelError(f"the dense surface compliance would be {3 * nodes.size} x {3 * nodes.size} "
                         f"({(3 * nodes.size) ** 2 * 8 / 2**30:.1f} GiB); pass fewer nodes or allow_large=True")
    model.check_restrained()
    rows = (model.dofs_per_node * nodes[:, None] + np.arange(3)).reshape(-1)  # global dofs of the nodes
    C = np.zeros((rows.size, rows.size))
    if method == "solves":
        live = np.flatnonzero(~model.fixed.reshape(-1)[rows])
        per = max(1, int(memory // (8 * model.n_dofs)))
        blocks = [live[i:i + per] for i in range(0, live.size, per)]
        for cols, block in _blocks(model, nodes, blocks, "solves", scheduler):
            C[:, cols] = block
        return nodes, C
    cond = _Condensation(model, nodes, factor=scheduler is None)  # the cluster's workers factorize K_II
    K_SS = cond.dense_SS()
    per = max(1, int(memory // (8 * max(cond.inner_size, 1))))
    blocks = [np.arange(i, min(i + per, cond.size)) for i in range(0, cond.size, per)]
    for cols, block in _blocks(model, nodes, blocks, "condensation", scheduler, cond):  # K* = K_SS - K_SI K_II^-1 K_IS
        K_SS[:, cols] -= block
    inverse = cho_solve(cho_factor(K_SS, lower=True), np.eye(cond.size))
    keep = np.flatnonzero(np.isin(rows, cond.here))
    C[np.ix_(keep, keep)] = inverse
    return nodes, C


class _Condensation:
    """The condensation of a model's ``nodes``: their free translations ``here`` (with penalty
    constraints the held dofs are condensed out with the rest), K_IS, K_SI and, with ``factor``,
    K_II's factorization (a worker's; K_SS, dense, only where it is formed: :meth:`dense_SS`)."""

    def __init__(self, model, nodes: np.ndarray, factor: bool = True) -> None:
        rows = (model.dofs_per_node * nodes[:, None] + np.arange(3)).reshape(-1)
        Kc, dofs = model.constrained_stiffness()
        self.here = rows[~model.fixed.reshape(-1)[rows]]
        S = np.searchsorted(dofs, self.here)
        inner = np.setdiff1d(np.arange(dofs.size), S)
        self.size, self.inner_size = S.size, inner.size
        Kc = Kc.tocsc()
        self._Kc, self._S = Kc, S
        self.K_IS = Kc[inner][:, S].tocsc()
        self.K_SI = self.K_IS.T.tocsr()
        self.K_II = factorize(Kc[inner][:, inner].tocsr(), spd=True, what="K_II (the dofs condensed out)",
                              order=lambda: model.dof_order(dofs[inner])) if factor else None

    def dense_SS(self) -> np.ndarray:
        """K_SS, dense (the start of K*)."""
        return self._Kc[self._S][:, self._S].toarray()

    def block(self, cols: np.ndarray) -> np.ndarray:
        """K_SI K_II^-1 K_IS[:, cols]."""
        return self.K_SI @ self.K_II.solve(self.K_IS[:, cols].toarray())


def _solves_block(model, nodes: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """The rows of ``nodes``' translations of K^-1's columns ``cols`` (positions among those rows)."""
    rows = (model.dofs_per_node * nodes[:, None] + np.arange(3)).reshape(-1)
    F = np.zeros((model.n_dofs, cols.size))
    F[rows[cols], np.arange(cols.size)] = 1.0
    return model._solve(F).reshape(model.n_nodes * 3, cols.size)[(3 * nodes[:, None] + np.arange(3)).reshape(-1)]


def _blocks(model, nodes: np.ndarray, blocks: list, method: str, scheduler, condensation=None):
    """(cols, block) for every block of columns: here, in order (the condensation's with
    ``condensation``), or from the cluster as they come."""
    if scheduler is None:
        for cols in blocks:
            yield cols, (condensation.block(cols) if condensation is not None else _solves_block(model, nodes, cols))
        return
    from ..cluster import connect, run_tasks
    from .recipe import ModelRecipe

    done: list = []
    with connect(scheduler) as client:
        why = run_tasks(client, _block_task, (ModelRecipe.of(model), nodes, method), [[c] for c in blocks], done.extend)
    if why:
        raise KeyboardInterrupt if why == "interrupted" else ModelError(f"the surface compliance on the cluster "
                                                                        f"stopped: {why}")
    yield from done


def _block_task(recipe, nodes: np.ndarray, method: str, blocks: list) -> list:
    """On a worker: [(cols, block)], the model (and K_II's factorization) built once per worker."""
    import hashlib

    from ..cluster import worker_cached

    model = worker_cached(recipe.key, recipe.build)
    if method == "solves":
        return [(cols, _solves_block(model, nodes, cols)) for cols in blocks]
    key = recipe.key + hashlib.sha256(np.ascontiguousarray(nodes).tobytes()).hexdigest()
    condensation = worker_cached(key, lambda: _Condensation(model, nodes))
    return [(cols, condensation.block(cols)) for cols in blocks]
