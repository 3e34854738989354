"""Saving and loading a reduced nonlinear model (:class:`rtfem.reduction.reduced.ReducedNonlinearModel`):
its basis (modes and modal derivatives, stiffness-orthonormal on the free dofs) and its cubature
(the elements and their weights), in a versioned ``.npz`` (no pickle) that records the mesh's
fingerprint and the model key. Loading rebuilds the rest (the nonlinear system, the rest stiffness
and its factorization, the cubature elements' rows) from the model given, so a batch precomputes
the derivatives once and a session loads them in seconds. Also here, beside the other code that
rebuilds a reduced model's pieces from its model (and so kept out of the reduced model's module, which
imports this one): the cubature's training poses on a Dask cluster (:func:`cluster_poses`)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import ModelError
from ..fe.protocol import check_model
from ..storage import load_versioned, save_versioned
from .modal import check_model_key, mesh_fingerprint, model_key

__all__ = ["save_reduced", "load_reduced", "FORMAT_VERSION"]

FORMAT_VERSION = 1
_ARRAYS = ["basis", "n_modes", "elements", "weights", "fingerprint"]


def save_reduced(reduced, path: str | os.PathLike) -> Path:
    """Save ``reduced``'s basis and cubature (see the module's docstring).

    Parameters
    ----------
    reduced : a ReducedNonlinearModel (not a localized copy: its patch belongs to a session).
    path : the file (``.npz`` is added when missing).

    Returns
    -------
    Path
        The file written (atomically: an interrupted save leaves an older file whole).

    Raises
    ------
    ModelError
        A localized model, or a path that is a directory.
    """
    if reduced.local is not None:
        raise ModelError("a localized reduced model is not saved (its patch follows a grasp): save the model it was "
                         "localized from and localize it again after loading")
    elements = getattr(reduced, "_cubature_elements", None)
    has = getattr(reduced, "_cubature", None) is not None and elements is not None
    arrays = {"basis": reduced.basis, "n_modes": np.array(reduced.n_modes),
              "elements": elements if has else np.zeros(0, int),
              "weights": reduced._cubature[1] if has else np.zeros(0),
              "fingerprint": np.array(mesh_fingerprint(reduced.model.mesh))}
    info = dict(reduced.info, model_key=model_key(reduced.model), law=repr(reduced.law))
    return save_versioned(path, "rtfem.ReducedNonlinearModel", FORMAT_VERSION, arrays, info)


def load_reduced(cls, path: str | os.PathLike, model):
    """The reduced model saved at ``path`` on ``model`` (:meth:`ReducedNonlinearModel.load`).

    Parameters
    ----------
    cls : the ReducedNonlinearModel class.
    path : a file :func:`save_reduced` wrote.
    model : the ShellModel or SolidModel it was computed for (the same mesh, supports, material
        and law).

    Returns
    -------
    ReducedNonlinearModel

    Raises
    ------
    ModelError
        A file that is not one, is damaged or altered (each field named), or belongs to another mesh,
        other supports, material or law.
    """
    check_model(model)
    z, info = load_versioned(path, "rtfem.ReducedNonlinearModel", FORMAT_VERSION, _ARRAYS, "reduced model")
    where = repr(str(path))
    fp = z["fingerprint"]
    if fp.dtype.kind != "U" or fp.ndim != 0 or str(fp) != mesh_fingerprint(model.mesh):
        raise ModelError(f"{where} was computed for another mesh (field 'fingerprint'): rebuild it with "
                         "rt.ReducedNonlinearModel(model, modes, ...)")
    check_model_key(info, model, where)
    if info.get("law") != repr(getattr(model, "law", None)):
        raise ModelError(f"{where} was computed with the law {info.get('law')}, the model has "
                         f"{getattr(model, 'law', None)!r}: rebuild it for this law")
    out = object.__new__(cls)
    out._setup(model)
    basis, n_modes, elements, weights = z["basis"], z["n_modes"], z["elements"], z["weights"]
    bad = _check_arrays(basis, n_modes, elements, weights, out.free.size, out.system.cells.shape[0])
    if bad:
        raise ModelError(f"{where}: {bad}; the file is damaged or altered")
    out.basis, out.n_modes = np.ascontiguousarray(basis, dtype=float), int(n_modes)
    out.n_derivatives = out.basis.shape[1] - out.n_modes
    out.info = {k: v for k, v in info.items() if k not in ("model_key", "law")}
    if elements.size:
        out._cubature_pinned = 0
        out._cubature = (out._element_data(elements), np.asarray(weights, float))
        out._cubature_elements = np.asarray(elements, int)
        out._cubature_remainder = bool(out.info.get("cubature", {}).get("remainder", False))
        if out._cubature_remainder:  # as train_cubature(remainder=True) keeps it: the exact rest stiffness
            K = out.basis.T @ (out._K0 @ out.basis)
            out._cubature_rest = (out._cubature, out._rest_tangents(out._cubature[0]), 0.5 * (K + K.T))
    return out


def _check_arrays(basis, n_modes, elements, weights, free: int, cells: int) -> str:
    """What is wrong with a saved model's arrays ("" when nothing)."""
    if basis.ndim != 2 or basis.shape[0] != free or basis.dtype.kind != "f" or not np.isfinite(basis).all():
        return f"field 'basis' must be a finite ({free}, r) array for the model's {free} free dofs"
    if n_modes.ndim != 0 or n_modes.dtype.kind not in "iu" or not 1 <= int(n_modes) <= basis.shape[1]:
        return "field 'n_modes' must be a count of the basis's columns"
    if elements.ndim != 1 or elements.dtype.kind not in "iu" or weights.shape != elements.shape:
        return "fields 'elements' and 'weights' must be one weight per element index"
    if elements.size and (elements.min() < 0 or elements.max() >= cells or np.unique(elements).size != elements.size):
        return f"field 'elements' must hold distinct element indices 0..{cells - 1}"
    if weights.size and (weights.dtype.kind != "f" or not np.isfinite(weights).all() or weights.min() < 0):
        return "field 'weights' must be finite and non-negative"
    return ""


class _PoseTerms:
    """On a worker: what :meth:`rtfem.reduction.element_terms.ElementTerms._pose_rows` needs of a reduced model (its
    elements' rows and forces), from the model's recipe and the basis, without the factorization."""

    def __init__(self, model, basis: np.ndarray, remainder: bool) -> None:
        from .element_terms import ElementTerms

        class Terms(ElementTerms):
            size = basis.shape[1]

        self.terms = terms = Terms()
        terms.model, terms.law, terms.system = model, getattr(model, "law", None), model.nonlinear()
        terms.dpn, terms.free, terms.basis = model.dofs_per_node, terms.system.free, basis
        self.data = terms._element_data()
        self.Ke = terms._rest_tangents(self.data) if remainder else None


def _pose_task(recipe, basis: np.ndarray, remainder: bool, reach: float, qs: list) -> list:
    import hashlib

    from ..cluster import worker_cached

    key = recipe.key + hashlib.sha256(np.ascontiguousarray(basis).tobytes()).hexdigest() + str(remainder)
    owner = worker_cached(key, lambda: _PoseTerms(recipe.build(), basis, remainder))
    return [(i, owner.terms._pose_rows(q, owner.data, owner.Ke, reach)) for i, q in qs]


def cluster_poses(reduced, qs: list, remainder: bool, reach: float, scheduler) -> list:
    """:meth:`ReducedNonlinearModel.train_cubature`'s poses on a Dask cluster (one pose a task, each
    worker building the elements' rows once): [(rows, target, halvings)] in the poses' order.

    Parameters
    ----------
    reduced : the reduced model.
    qs : the poses' reduced coordinates.
    remainder : the rest-linear part subtracted (``train_cubature(remainder=True)``).
    reach : the poses' reach (for the message of a pose that cannot be evaluated).
    scheduler : as :func:`rtfem.cluster.connect` takes it.

    Returns
    -------
    list

    Raises
    ------
    ModelError, SolverError
        An unreachable scheduler; a pose that failed, or the run stopped.
    """
    from ..cluster import connect, run_tasks
    from ..errors import SolverError
    from ..fe.recipe import ModelRecipe

    out: list = [None] * len(qs)

    def collect(batch) -> None:
        for i, found in batch:
            out[i] = found

    with connect(scheduler) as client:
        why = run_tasks(client, _pose_task, (ModelRecipe.of(reduced.model), reduced.basis, remainder, reach),
                        [[(i, q)] for i, q in enumerate(qs)], collect)
    if why:
        raise KeyboardInterrupt if why == "interrupted" else SolverError(f"cubature training on the cluster stopped: "
                                                                         f"{why}")
    return out
