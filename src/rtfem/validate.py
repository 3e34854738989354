"""Argument checks shared by every public entry point.

Each helper turns a user value into the type the numerics need or raises an
:class:`~rtfem.errors.RtfemError` subclass (``ModelError`` unless told otherwise) whose one-line
message names the argument, shows the value and says what is expected. The rules are the same
everywhere: a node index is a Python or numpy integer (never a bool, a float or a string); a
number is a finite real (never a bool or a string); a point is three finite numbers.
"""

from __future__ import annotations

import math
import numbers
from typing import Any, Iterable, Sequence

import numpy as np

from .errors import ModelError

__all__ = [
    "one_line", "show", "number", "positive", "nonnegative", "in_range", "count", "node", "nodes", "point", "vector",
    "choice", "flag", "times", "instant", "time_step", "path_like", "real_array", "int_array", "forces",
]

DT_MIN, DT_MAX = 1e-9, 1e3  # time steps outside this range are typos (ns .. ks)


def one_line(text: str, limit: int | None = None) -> str:
    """``text`` for a terminal: whitespace runs collapsed to one space, control characters as '?',
    cut to ``limit`` characters."""
    text = "".join(c if c.isprintable() else "?" for c in " ".join(text.split()))
    return text if limit is None or len(text) <= limit else text[: limit - 3] + "..."


def show(value: Any, limit: int = 60) -> str:
    """A one-line, length-limited repr of a user value for an error message."""
    if isinstance(value, np.ndarray):
        text = f"array of shape {value.shape} and dtype {value.dtype}" if value.size > 6 else \
            "array(" + np.array2string(value, separator=", ").replace("\n", "") + ")"
    else:
        try:
            text = repr(value)
        except Exception:  # pragma: no cover - a repr that raises
            text = f"<{type(value).__name__}>"
    return one_line(text, limit)


def _float_array(value: Any) -> np.ndarray | None:
    """``value`` as a float array when it is real numeric data (not None, text, bools, objects
    or complex numbers); None otherwise. The one conversion behind every array check here."""
    if type(value) is np.ndarray and value.dtype == np.float64:  # the common case, at run time
        return value
    if value is None or isinstance(value, (str, bytes)):
        return None
    try:
        a = np.asarray(value)
    except (TypeError, ValueError):
        return None
    if a.dtype == object or a.dtype == bool or not np.issubdtype(a.dtype, np.number) or np.iscomplexobj(a):
        return None
    return a.astype(float, copy=False)


def _label(name: str, value: Any) -> str:
    return f"{name}={show(value)}"


def _is_real(value: Any) -> bool:
    if isinstance(value, (bool, np.bool_)):
        return False
    if isinstance(value, np.ndarray):
        return value.ndim == 0 and np.issubdtype(value.dtype, np.number) and not np.iscomplexobj(value)
    return isinstance(value, numbers.Real)


def number(value: Any, name: str, what: str = "a number", *, error: type = ModelError) -> float:
    """A finite real number (not a bool, not a string)."""
    if not _is_real(value):
        raise error(f"{_label(name, value)} is not a number; give {what}")
    v = float(value)
    if not math.isfinite(v):
        raise error(f"{_label(name, value)} is not finite; give {what}")
    return v


def positive(value: Any, name: str, what: str = "a number > 0", *, error: type = ModelError) -> float:
    v = number(value, name, what, error=error)
    if v <= 0.0:
        raise error(f"{_label(name, value)} must be > 0 ({what})")
    return v


def nonnegative(value: Any, name: str, what: str = "a number >= 0", *, error: type = ModelError) -> float:
    v = number(value, name, what, error=error)
    if v < 0.0:
        raise error(f"{_label(name, value)} must be >= 0 ({what})")
    return v


def in_range(value: Any, name: str, lo: float, hi: float, *, lo_open: bool = False, hi_open: bool = False,
             what: str = "", error: type = ModelError) -> float:
    """A finite number in [lo, hi] (open ends as asked)."""
    interval = f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    v = number(value, name, f"a number in {interval}" + (f" ({what})" if what else ""), error=error)
    if v < lo or v > hi or (lo_open and v == lo) or (hi_open and v == hi):
        raise error(f"{_label(name, value)} is outside {interval}" + (f": {what}" if what else ""))
    return v


def count(value: Any, name: str, minimum: int = 1, maximum: int | None = None, *, what: str = "",
          error: type = ModelError) -> int:
    """An integer (Python or numpy, not a bool) in [minimum, maximum]."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (numbers.Integral, np.integer)):
        raise error(f"{_label(name, value)} must be a whole number >= {minimum}" + (f" ({what})" if what else ""))
    v = int(value)
    if v < minimum or (maximum is not None and v > maximum):
        bound = f">= {minimum}" if maximum is None else f"between {minimum} and {maximum}"
        raise error(f"{_label(name, value)} must be {bound}" + (f" ({what})" if what else ""))
    return v


def node(value: Any, n: int, name: str = "node", *, error: type = ModelError) -> int:
    """A node index: a Python or numpy integer (not a bool, a float or a string) in 0..n-1."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (numbers.Integral, np.integer)):
        raise error(f"{_label(name, value)}: a node index must be an integer 0..{n - 1} "
                    f"(got {type(value).__name__})")
    v = int(value)
    if not 0 <= v < n:
        raise error(f"{_label(name, value)}: node index {v} is out of range: not on the mesh (0..{n - 1})")
    return v


def nodes(value: Any, n: int, name: str = "nodes", *, allow_empty: bool = False, error: type = ModelError) -> np.ndarray:
    """An integer array of node indices in 0..n-1 (a single index is accepted too); always a new array."""
    if type(value) is np.ndarray and value.dtype == np.int64 and value.ndim == 1 and value.size:
        if 0 <= value.min() and value.max() < n:  # the run-time fast path: a grasp's or a patch's nodes, each step
            return value.copy()
    if isinstance(value, (str, bytes, bool, np.bool_)) or value is None:
        raise error(f"{_label(name, value)}: give node indices (integers 0..{n - 1})")
    try:
        arr = np.asarray(value)
    except Exception:
        raise error(f"{_label(name, value)}: give node indices (integers 0..{n - 1})") from None
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.integer) or (arr.size == 0 and arr.dtype == float)):
        raise error(f"{_label(name, value)}: node indices must be integers 0..{n - 1}, got dtype {arr.dtype}")
    arr = np.atleast_1d(arr).astype(np.int64).ravel()
    if arr.size == 0 and not allow_empty:
        raise error(f"{name} is empty: give at least one node index")
    bad = arr[(arr < 0) | (arr >= n)]
    if bad.size:
        raise error(f"{name}: node index {bad[0]} out of range 0..{n - 1}")
    return arr


def vector(value: Any, name: str, size: int | Sequence[int] = 3, *, error: type = ModelError) -> np.ndarray:
    """A 1-D array of finite numbers with one of the allowed sizes."""
    sizes = (size,) if isinstance(size, int) else tuple(size)
    arr = _float_array(value)
    if arr is not None and arr.ndim == 1 and arr.size in sizes and np.isfinite(arr).all():
        return arr
    want = str(sizes[0]) + "".join(f" (or {s})" for s in sizes[1:])
    if arr is None:
        raise error(f"{_label(name, value)}: give {want} numbers")
    if arr.ndim != 1 or arr.size not in sizes:
        raise error(f"{_label(name, value)}: need {want} components, got {arr.size} (shape {arr.shape})")
    if not np.all(np.isfinite(arr)):
        raise error(f"{_label(name, value)}: non-finite (NaN or infinite) value")
    return arr


POINT_LIMIT = 1e6  # m: a coordinate beyond it is a unit mistake (squares overflow near 1e154)


def point(value: Any, name: str = "point", *, error: type = ModelError) -> np.ndarray:
    """A point (or a vector) in 3-D: three finite numbers within 1e6 m of the origin (a float
    (3,) array is returned as is)."""
    if type(value) is np.ndarray and value.shape == (3,) and value.dtype == np.float64 \
            and abs(value[0]) <= POINT_LIMIT and abs(value[1]) <= POINT_LIMIT and abs(value[2]) <= POINT_LIMIT:
        return value  # the haptic loop's fast path: no conversion, no copy (NaN fails the comparisons)
    v = vector(value, name, 3, error=error)
    if np.abs(v).max() > POINT_LIMIT:
        raise error(f"{_label(name, value)} lies more than {POINT_LIMIT:g} m from the origin: positions are in "
                    "metres (scale millimetres by 1e-3)")
    return v


def choice(value: Any, name: str, options: Iterable[str], *, error: type = ModelError) -> str:
    options = tuple(options)
    if not isinstance(value, str) or value not in options:
        raise error(f"{_label(name, value)}; choose one of {', '.join(repr(o) for o in options)}")
    return value


def flag(value: Any, name: str, *, error: type = ModelError) -> bool:
    """A boolean (True/False, numpy bools, or the integers 0 and 1)."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (numbers.Integral, np.integer)) and int(value) in (0, 1):
        return bool(value)
    raise error(f"{_label(name, value)} must be True or False")


def times(value: Any, name: str = "times", *, bound: str = "positive", increasing: bool = True,
          error: type = ModelError) -> np.ndarray:
    """A non-empty 1-D array of finite times in seconds (or frequencies).

    ``bound``: "positive" (> 0), "nonnegative" (>= 0) or "any"; ``increasing``: strictly.
    """
    arr = _float_array(value)
    if arr is None:
        raise error(f"{_label(name, value)}: give a list of numbers")
    arr = np.atleast_1d(arr)
    if arr.ndim != 1 or arr.size == 0:
        raise error(f"{_label(name, value)}: give a non-empty flat list of numbers")
    if not np.all(np.isfinite(arr)):
        raise error(f"{_label(name, value)}: the values must be finite")
    if bound == "positive" and np.any(arr <= 0):
        raise error(f"{_label(name, value)}: the values must be > 0")
    if bound == "nonnegative" and np.any(arr < 0):
        raise error(f"{_label(name, value)}: the values must be >= 0")
    if increasing and np.any(np.diff(arr) <= 0):
        raise error(f"{_label(name, value)}: the values must be strictly increasing")
    return arr


def instant(value: Any, name: str = "t", *, error: type = ModelError) -> float:
    """A time in seconds: a real number, not NaN (+-inf allowed: 'long after', 'long before')."""
    if not _is_real(value) or math.isnan(float(value)):
        raise error(f"{_label(name, value)} is not a time; give a number of seconds")
    return float(value)


def time_step(value: Any, name: str = "dt", *, error: type = ModelError) -> float:
    """A time step in seconds, between 1 ns and 1000 s."""
    v = positive(value, name, "a time step in seconds", error=error)
    if not DT_MIN <= v <= DT_MAX:
        raise error(f"{_label(name, value)} is outside [{DT_MIN:g}, {DT_MAX:g}] s: not a usable time step")
    return v


def path_like(value: Any, name: str = "path", *, error: type = ModelError):
    """A non-empty str or os.PathLike."""
    import os

    if isinstance(value, (str, os.PathLike)) and str(value).strip():
        return value
    raise error(f"{_label(name, value)}: give a file path")


def real_array(value: Any, name: str, ndim: int | None = None, *, finite: bool = True,
               error: type = ModelError) -> np.ndarray:
    """A float array (from any real numeric input) with ``ndim`` dimensions, finite unless told."""
    a = _float_array(value)
    if a is None:
        raise error(f"{_label(name, value)} must be a numeric array")
    if ndim is not None and a.ndim != ndim:
        raise error(f"{name} must have {ndim} dimensions, got shape {a.shape}")
    if finite and not _all_finite(a):
        raise error(f"{name} holds NaN or infinite values")
    return a


def int_array(value: Any, name: str, *, error: type = ModelError) -> np.ndarray:
    """A 1-D int64 array from integer input (no floats, no bools)."""
    try:
        a = np.asarray(value)
    except Exception:
        raise error(f"{_label(name, value)} must be an integer array") from None
    if a.ndim != 1 or not np.issubdtype(a.dtype, np.integer):
        raise error(f"{name} must be a 1-D integer array, got shape {a.shape} and dtype {a.dtype}")
    return a.astype(np.int64, copy=False)


def _all_finite(a: np.ndarray, chunk: int = 1 << 22) -> bool:
    """np.isfinite(a).all() in chunks (no temporary as large as a big array)."""
    flat = a.reshape(-1)
    return all(bool(np.isfinite(flat[i:i + chunk]).all()) for i in range(0, flat.size, chunk))


def entries(value: Any, name: str, item: str, length: int, form: str, *, error: type = ModelError) -> list:
    """The items of a list of fixed-length records (tuples or lists of ``length`` values), such as
    (time, file) frames or (t, node, force) load rows; ``form`` writes one out for the messages
    and ``item`` names one. May be empty (the caller says whether that is allowed)."""
    if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__"):
        raise error(f"{_label(name, value)} must be a list of {form}")
    out = list(value)
    for x in out:
        if not isinstance(x, (tuple, list)) or len(x) != length:
            raise error(f"{item} {show(x)} must be {form}")
    return out


def progress(value: Any, name: str = "progress", *, error: type = ModelError):
    """A progress callback ``progress(done, total, message)`` or None (the one signature of
    modal_analysis, SLDM and ImpedanceMap.build)."""
    if value is not None and not callable(value):
        raise error(f"{_label(name, value)} must be a callable progress(done, total, message) or None")
    return value


def forces(value: Any, n: int, widths: Sequence[int] = (3,), *, error: type = ModelError) -> np.ndarray:
    """Nodal forces as an (n, w) float array, from an (n, w) array or a {node: components} mapping.

    The one rule for loads everywhere: mapping keys are node indices (:func:`node`), values
    have one of the allowed numbers of components, everything is finite. ``widths``: the
    allowed numbers of components per node (3 for forces, 6 with moments); the result has
    the largest width. Nothing is returned (and nothing changed by the caller) unless all of
    it is valid.
    """
    from collections.abc import Mapping

    w = max(widths)
    F = np.zeros((n, w))
    if isinstance(value, Mapping):
        for key, f in value.items():
            i = node(key, n, "force key", error=error)
            v = vector(f, f"force on node {i}", widths, error=error)
            F[i, : v.size] += v
        return F
    A = _float_array(value)
    shapes = "" if A is not None and A.ndim == 2 and A.shape[0] == n and A.shape[1] in widths else \
        " or ".join(f"({n}, {k})" for k in widths)
    if A is None:
        raise error(f"forces={show(value)} must be a {{node: (fx, fy, fz)}} mapping or an {shapes} array")
    if shapes:
        raise error(f"forces must be a {{node: (fx, fy, fz)}} mapping or an {shapes} array, got shape {A.shape}")
    if not np.isfinite(A).all():
        bad = np.flatnonzero(~np.isfinite(A).all(axis=1))
        raise error(f"non-finite (NaN or infinite) force at node {bad[0]} ({bad.size} nodes in all)")
    F[:, : A.shape[1]] = A
    return F
