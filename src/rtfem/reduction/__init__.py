"""Model reduction: modal analysis (Lanczos), SLDM, the modal oscillator's closed forms,
cubature and the reduced nonlinear models (modes + modal derivatives)."""

from ..lazy import submodules  # noqa: E402

__getattr__ = submodules(__name__)  # submodules on first use (rt.mesh.meshing)
