"""Run-time simulators behind the Driver protocol: modal, warped modal, full order, static,
reduced nonlinear (built in reduction), the impedance map; compiled step kernels; the GPU field."""

# the variants the base classes make (ModalSimulator(warping=True), DirectSimulator(large_deformation=True))
# register themselves when imported
from . import nonlinear_newmark, warping  # noqa: F401,E402
