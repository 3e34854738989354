"""Compiled kernels (the reduced models', the assembly's): a kernel and the helpers it calls, compiled by numba once
(cached on disk) with one shared globals dict, so that a helper calling another calls its compiled
twin; None where numba is absent or cannot compile it (the callers then take a numpy path)."""

from __future__ import annotations

_COMPILED: dict = {}


def compiled(key: str, kernel, *helpers):
    """``kernel`` compiled by numba with its helper functions compiled too (cached), or None
    where numba is absent or cannot compile it."""
    if key not in _COMPILED:
        try:
            import numba

            opts = dict(cache=True, nogil=True, fastmath=False, error_model="numpy")
            g = dict(kernel.__globals__)  # shared: a helper calling another finds its compiled twin
            for h in helpers:
                g[h.__name__] = numba.njit(**opts)(type(h)(h.__code__, g, h.__name__))
            _COMPILED[key] = numba.njit(**opts)(type(kernel)(kernel.__code__, g, kernel.__name__))
        except Exception:  # pragma: no cover - numba absent or unable to compile here
            _COMPILED[key] = None
    return _COMPILED[key]
