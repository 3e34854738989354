"""Tools touching a model: the probe, the grasp, patch contact with friction, haptic loops and
devices."""

from ..lazy import submodules  # noqa: E402

__getattr__ = submodules(__name__)  # submodules on first use (rt.mesh.meshing)
