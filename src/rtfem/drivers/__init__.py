"""Run-time simulators behind the Driver protocol: modal, warped modal, full order, static,
reduced nonlinear (built in reduction), the impedance map; compiled step kernels; the GPU field."""

from . import warping  # noqa: F401,E402  (registers WarpedModalSimulator as ModalSimulator(warping=True))
