"""The command line (``rtfem``), the demo, the benchmark tables and the pictures."""

from ..lazy import submodules  # noqa: E402

__getattr__ = submodules(__name__)  # submodules on first use (rt.mesh.meshing)
