"""Interactive web viewer (viser): push and pull the organ with the mouse.

``rtfem view [MESH]`` or :func:`rtfem.viewer.app.serve`. Needs the ``viewer`` extra
(``pip install rtfem[viewer]``); :class:`~rtfem.viewer.session.Session` (the simulation
behind it) needs nothing beyond the core.
"""

from .session import METHODS, Session, Settings

__all__ = ["METHODS", "Session", "Settings"]

from ..lazy import submodules  # noqa: E402

__getattr__ = submodules(__name__)  # submodules on first use (rt.mesh.meshing)
