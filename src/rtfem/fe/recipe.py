"""A model's recipe: what rebuilds it in another process (a Dask worker, :mod:`rtfem.cluster`) from the
mesh and the settings, instead of sending its assembled matrices or factorization: the mesh, the
material (or law), the model's options and its fixed dofs."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field

import numpy as np

from .. import validate
from ..errors import ModelError

__all__ = ["ModelRecipe"]


@dataclass(frozen=True)
class ModelRecipe:
    """What :meth:`build` makes the same model of (the same mesh, material, options and fixes).

    Parameters
    ----------
    mesh : the model's TriMesh (a shell) or TetMesh (a solid).
    material : its Material, or a solid's law, or a solid's {label: material or law} of its regions.
    options : the constructor's keyword arguments (a solid's element, mass, constraints, penalty;
        a shell's membrane, rotary_inertia, constraints, penalty).
    fixed : the (n, dofs per node) mask of fixed dofs.
    key : an identity of all of that (the mesh's fingerprint and the model key), the worker's cache key.
    kind : the model's class.

    Raises
    ------
    ModelError
        From :meth:`of`, a model that is not a ShellModel or SolidModel.
    """

    mesh: object
    material: object
    options: dict = field(default_factory=dict)
    fixed: np.ndarray | None = None
    key: str = ""
    kind: type | None = None  # the model's class (pickled by reference)

    @classmethod
    def of(cls, model) -> "ModelRecipe":
        """The recipe of a ShellModel or SolidModel as it is now (its fixes included)."""
        if hasattr(model, "tetmesh") and hasattr(model, "element"):  # a SolidModel
            mesh, options = model.tetmesh, {"element": model.element, "mass": model.mass}
        elif hasattr(model, "membrane") and hasattr(model, "rotary_inertia"):  # a ShellModel
            mesh, options = model.mesh, {"membrane": model.membrane, "rotary_inertia": model.rotary_inertia}
        else:
            raise ModelError(f"model={validate.show(model)} must be an rt.ShellModel or rt.SolidModel to be rebuilt "
                             "on a cluster's workers")
        options.update(constraints=model.constraints, penalty=model.penalty)
        material = getattr(model, "materials", None) or getattr(model, "law", None) or model.material
        fixed = np.array(model.fixed, dtype=bool)
        return cls(mesh, material, options, fixed, _identity(mesh, material, options, fixed), type(model))

    def build(self):
        """The model (assembled on first use, as any model), with the recipe's fixes."""
        model = self.kind(self.mesh, self.material, **self.options)
        model.fixed[:] = self.fixed
        model._supports_changed()
        return model


def _identity(mesh, material, options: dict, fixed: np.ndarray) -> str:
    """A hash of the mesh's arrays, the material's repr, the options and the fixes."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    cells = getattr(mesh, "tets", None)
    h.update(np.ascontiguousarray(mesh.triangles if cells is None else cells, dtype=np.int64).tobytes())
    labels = getattr(mesh, "labels", None)
    if labels is not None and np.asarray(labels).any():
        h.update(np.ascontiguousarray(labels, dtype=np.int64).tobytes())
    h.update(repr(material).encode())
    h.update(json.dumps(options, sort_keys=True, default=str).encode())
    h.update(np.ascontiguousarray(fixed).tobytes())
    return h.hexdigest()[:32]
