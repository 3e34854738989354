"""The drawn field on a GPU, through CuPy (optional).

The viewer's per-frame product U = Phi q reads the whole (3n, r) shape matrix: 49 MB in float32
for the 40,962-vertex liver at r = 100, which a CPU reads at memory speed (benchmarks/
haptic_loop.py). On a CUDA GPU the shapes stay resident in device memory, uploaded once per
dtype, and a frame is one matrix-vector product there plus the (n, 3) result copied back for
drawing; the static correction (a few loaded nodes) is added on the host as before.

CuPy is not installed by ``make``: it needs a CUDA GPU and the wheel that matches its CUDA
(``pip install cupy-cuda12x`` or ``cupy-cuda13x``; run on an H100 with CuPy 14.2 for CUDA 13:
benchmarks/results/haptic_loop_gpu_h100.txt). :func:`module` finds it, and checks that it can run a product,
once per process; :func:`status` says what was found and, when nothing is, why.
"""

from __future__ import annotations

import numpy as np

from ..errors import ModelError

__all__ = ["module", "status", "Field"]

_FOUND: dict = {}


def module():
    """CuPy, when it imports and runs a small product on a CUDA device; else None (see :func:`status`)."""
    if "xp" not in _FOUND:
        try:
            import cupy

            a = cupy.arange(6, dtype=cupy.float32).reshape(2, 3)
            if not np.array_equal(cupy.asnumpy(a @ cupy.ones(3, dtype=cupy.float32)), [3.0, 12.0]):
                raise RuntimeError("a 2 x 3 product gave a wrong answer")
            name = cupy.cuda.runtime.getDeviceProperties(cupy.cuda.Device().id)["name"]
            _FOUND.update(xp=cupy, why=f"CuPy {cupy.__version__} on {name.decode() if isinstance(name, bytes) else name}")
        except ImportError:
            _FOUND.update(xp=None, why="CuPy is not installed (pip install cupy-cuda12x or cupy-cuda13x, with a CUDA GPU)")
        except Exception as exc:  # a CuPy without a usable device or driver
            _FOUND.update(xp=None, why=f"CuPy found no usable CUDA device ({type(exc).__name__}: {exc})")
    return _FOUND["xp"]


def status() -> str:
    """What :func:`module` found: the CuPy version and device, or why there is none."""
    module()
    return _FOUND["why"]


class Field:
    """Shapes P (3n, r) resident on the GPU, one copy per dtype asked for; :meth:`product` is
    P q brought back to the host as (n, 3)."""

    def __init__(self, P: np.ndarray) -> None:
        self.xp = module()
        if self.xp is None:
            raise ModelError(f"device='gpu' needs CuPy and a CUDA GPU: {status()}; draw with device='cpu'")
        self._host = P
        self._resident: dict = {}

    def product(self, q: np.ndarray, dtype, out: np.ndarray | None = None) -> np.ndarray:
        xp, dtype = self.xp, np.dtype(dtype)
        P = self._resident.get(dtype)
        if P is None:  # uploaded once (49 MB in float32 for 40,962 vertices at r = 100)
            P = self._resident[dtype] = xp.asarray(np.ascontiguousarray(self._host, dtype=dtype))
        u = xp.asnumpy(P @ xp.asarray(np.asarray(q, dtype=dtype))).reshape(-1, 3)
        if out is not None:
            out[...] = u
            return out
        return u
