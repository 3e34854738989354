"""The precompute of a model through the cache (:mod:`rtfem.cache`): its modal basis, and its
reduced nonlinear model (modes + modal derivatives) with the trained cubature, each computed once
per machine and loaded on every later launch (issue 54: ``rtfem view`` recomputed 29-93 s of modes,
derivatives and cubature on each launch of the same organ).

Each artefact is filed under a digest of everything it is computed from: the model's recipe (its
mesh arrays, material or law, every constructor option and the supports: :func:`model_digest`),
its kind, the settings of the stage
(modes asked, eigensolver options; derivatives and the cubature's poses, tolerance and seed; the
modes it was built on) and the file format's version. A file that does not load as it was saved
(the checksums, the mesh fingerprint, the model key, the recorded digest) is computed again and
replaced. What is returned is always the file as loaded, also right after it is computed, so a
first launch and a later one run bit-identical physics.

:func:`precompute` is the one call of the Python API; the command line and the viewer use it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .. import validate
from ..cache import digest, entry
from ..errors import ModelError, RtfemError
from ..fe.protocol import check_model
from .modal import ModalBasis, model_key, modal_analysis

__all__ = ["precompute", "Precomputed", "cached_modes", "cached_reduced", "model_digest"]

FORMAT = 1  # this module's keys: a change in what they cover bumps it (old files are then just unused)


def model_digest(model) -> str:
    """A digest of everything a model's precompute depends on. A ShellModel or SolidModel: its recipe
    (:class:`rtfem.fe.recipe.ModelRecipe`: the mesh's arrays, the material or law, every constructor
    option and the fixed dofs, what rebuilds the same model on a cluster's workers) and the model key:
    the inputs, not the assembled matrices, whose last bits differ between the compiled and the numpy
    assembly (a process that has loaded numba assembles the other way: a K digest missed the cache
    between `rtfem modes` and `rtfem view`). Another model class: its assembled constrained K and M
    (whatever determines them), the mesh's arrays, the fixed dofs, the model key and the law."""
    check_model(model)
    from ..fe.recipe import ModelRecipe

    try:
        recipe = ModelRecipe.of(model)
    except ModelError:  # a user's own model class: what it assembles
        K, dofs = model.constrained_stiffness()
        M, _ = model.constrained_mass()
        tetmesh = getattr(model, "tetmesh", None)
        cells = np.asarray(tetmesh.tets if tetmesh is not None else model.mesh.triangles)
        return digest("model", FORMAT, np.asarray(model.mesh.vertices, dtype=float), cells, np.asarray(model.fixed),
                      K, M, np.asarray(dofs), model_key(model), repr(getattr(model, "law", None)))
    # the material's or law's every parameter at full precision (its repr, in the recipe's key, rounds)
    return digest("recipe", FORMAT, recipe.key, type(model).__name__, model_key(model), _parameters(recipe.material))


def _parameters(obj, depth: int = 0):
    """``obj``'s attributes as JSON-able values (floats exact), recursively: a material's or a law's."""
    if depth > 8 or obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    if isinstance(obj, np.ndarray):
        return [str(obj.dtype), obj.shape, obj.ravel().tolist()]
    if isinstance(obj, (list, tuple)):
        return [_parameters(o, depth + 1) for o in obj]
    if isinstance(obj, dict):
        return {str(k): _parameters(v, depth + 1) for k, v in sorted(obj.items(), key=lambda kv: str(kv[0]))}
    if hasattr(obj, "__dict__"):
        return [type(obj).__name__, _parameters(vars(obj), depth + 1)]
    return repr(obj)


def _report(progress, stage: str, message: str) -> None:
    if progress is not None:
        progress(1, 1, f"{stage}: {message}")


def _cached(kind: str, key: str, load, compute, save, progress, stage: str):
    """The artefact filed under ``key``: loaded, or computed, saved and loaded back (a cache that
    cannot be written: the computed one). Returns (it, whether it came from the cache)."""
    path = entry(kind, key)
    if path.is_file():
        try:
            found = load(path)
            if found.info.get("cache_key") == key:
                _report(progress, stage, f"from the cache ({path})")
                found.info["cache_hit"] = True
                return found, True
        except RtfemError:  # damaged, altered, another format or model: computed again below
            pass
    made = compute()
    made.info["cache_key"] = key
    try:
        save(made, path)
        made = load(path)
    except RtfemError:  # a read-only or full disk: the result stands, only not kept
        pass
    made.info["cache_hit"] = False
    return made, False


def cached_modes(model, n_modes: int = 40, *, progress=None, **options) -> ModalBasis:
    """:func:`rtfem.modal_analysis` through the cache (``options``: its sigma, tol, solver)."""
    key = digest("modes", FORMAT, model_digest(model), n_modes, options)
    basis, _ = _cached("modes", key, lambda p: ModalBasis.load(p, model=model),
                       lambda: modal_analysis(model, n_modes, progress=progress, **options),
                       lambda b, p: b.save(p), progress, "modes")
    return basis


def cached_reduced(model, modes: ModalBasis, derivatives: int = 20, *, cubature: bool = True, poses: int = 16,
                   tol: float = 0.05, progress=None, scheduler=None):
    """A :class:`~rtfem.ReducedNonlinearModel` on ``modes`` with the derivatives of ``derivatives``
    of them and (``cubature``) its cubature trained on ``poses`` poses to ``tol``, through the cache."""
    from .reduced import ReducedNonlinearModel

    if not isinstance(modes, ModalBasis):
        raise ModelError(f"modes={validate.show(modes)} must be an rt.ModalBasis")
    derivatives = validate.count(derivatives, "derivatives", 0, modes.n_modes)
    key = digest("reduced", FORMAT, model_digest(model), modes.omega, modes.shapes, derivatives, bool(cubature),
                 poses, tol, 0)

    def compute():
        red = ReducedNonlinearModel(model, modes, derivatives, progress=progress, scheduler=scheduler)
        if cubature:
            red.train_cubature(poses, tol=tol, scheduler=scheduler)
        return red

    red, _ = _cached("reduced", key, lambda p: ReducedNonlinearModel.load(p, model), compute, lambda r, p: r.save(p),
                     progress, "reduced model")
    return red


@dataclass
class Precomputed:
    """What :func:`precompute` returns: the modal basis, the reduced nonlinear model (None without
    derivatives asked), which of them came from the cache, and the seconds it all took."""

    modes: ModalBasis
    reduced: object | None
    from_cache: dict = field(default_factory=dict)
    seconds: float = 0.0


def precompute(model, n_modes: int = 40, derivatives: int | None = 20, *, cubature: bool = True,
               progress=None, scheduler=None) -> Precomputed:
    """Everything a run of ``model`` needs computed once, through the cache: the lowest ``n_modes``
    modes and, unless ``derivatives`` is None, the reduced nonlinear model with the modal derivatives
    of min(derivatives, n_modes) of them and (``cubature``) its trained cubature (16 poses, 5 %: the
    viewer's and ``rtfem simulate``'s). The first call on a machine computes and keeps them
    (:func:`rtfem.cache.cache_dir`); a later one, in any process, loads them in a fraction of the
    time, bit for bit the same. ``rtfem cache`` lists and clears what is kept.

    Parameters
    ----------
    model : a ShellModel or SolidModel with its fixes.
    n_modes : the modes asked of :func:`rtfem.modal_analysis`.
    derivatives : the modes whose modal derivatives the reduced model adds (None: no reduced model).
    cubature : train the reduced model's cubature (16 poses, 5 %).
    progress : ``progress(done, total, message)`` of each stage (a stage loaded from the cache says so).
    scheduler : the derivatives and the cubature's poses on a Dask cluster (as the reduced model takes it).

    Returns
    -------
    Precomputed
        ``modes``, ``reduced``, ``from_cache`` ({"modes": bool, "reduced": bool}) and ``seconds``.

    Example::

        pre = rt.precompute(model, n_modes=40, derivatives=20)
        sim = rt.ReducedNonlinearSimulator(pre.reduced, dt=1e-3, damping=rt.Damping(alpha=8.0))

    Raises
    ------
    ModelError
        A model that is not one, a bad count; as :func:`rtfem.modal_analysis` and
        :class:`rtfem.ReducedNonlinearModel` raise.
    """
    t0 = time.perf_counter()
    check_model(model)
    n_modes = validate.count(n_modes, "n_modes", 1, what="a number of modes")
    if derivatives is not None:
        derivatives = validate.count(derivatives, "derivatives", 0, 10**4)
    cubature = validate.flag(cubature, "cubature")
    progress = validate.progress(progress)
    modes = cached_modes(model, n_modes, progress=progress)
    reduced = None
    if derivatives is not None:
        reduced = cached_reduced(model, modes, min(derivatives, modes.n_modes), cubature=cubature,
                                 progress=progress, scheduler=scheduler)
    hits = {"modes": _hit(modes)}
    if reduced is not None:
        hits["reduced"] = _hit(reduced)
    return Precomputed(modes, reduced, hits, time.perf_counter() - t0)


def _hit(thing) -> bool:
    return bool(getattr(thing, "info", {}).get("cache_hit", False))
