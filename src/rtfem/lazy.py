"""Submodules imported on first use: ``rt.mesh.meshing`` and the like work as attribute reads
although ``import rtfem`` imports almost nothing (issue 54: 0.72 s of imports at start before)."""

from __future__ import annotations

import importlib

__all__ = ["submodules"]


def submodules(package: str):
    """A module ``__getattr__`` for ``package``: an unknown attribute is its submodule of that
    name, imported now (an AttributeError where there is none)."""

    def __getattr__(name: str):
        if name.startswith("__"):
            raise AttributeError(name)
        try:
            return importlib.import_module(f"{package}.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"{package}.{name}":
                raise
            raise AttributeError(f"module {package!r} has no attribute {name!r}") from None

    return __getattr__
