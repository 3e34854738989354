"""Run-time simulators behind the Driver protocol: modal, warped modal, full order, static,
reduced nonlinear (built in reduction), the impedance map; compiled step kernels; the GPU field."""

# the classes others make (ModalSimulator(warping=True), DirectSimulator(large_deformation=True),
# ImpedanceMap.as_driver()) register themselves when imported
from . import impedance_driver, lagged_newmark, nonlinear_newmark, warping  # noqa: F401,E402

from ..lazy import submodules  # noqa: E402

__getattr__ = submodules(__name__)  # submodules on first use (rt.mesh.meshing)
