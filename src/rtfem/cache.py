"""The precompute cache: one folder ($RTFEM_CACHE, else $XDG_CACHE_HOME/rtfem, else ~/.cache/rtfem)
holding what a launch would otherwise compute again: tet meshes (``tets-*``), modal bases
(``modes-*``) and reduced nonlinear models with their cubature (``reduced-*``), each a versioned,
checksummed ``.npz`` named by a digest of everything it was computed from (:func:`digest`), and
checked again when it is loaded (the mesh fingerprint and model key a saved basis carries). A file
that does not load (damaged, altered, written by another rtfem format) is computed again and
replaced; a changed setting is another name. ``rtfem cache`` lists and clears it."""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["cache_dir", "digest", "entry", "entries", "clear", "Entry", "KINDS"]

#: the kinds of file the cache holds (the prefix of their names) and what each is
KINDS = {"tets": "tet mesh (fTetWild)", "modes": "modal basis", "reduced": "reduced nonlinear model + cubature"}


def cache_dir() -> Path:
    """Where precomputed artefacts are kept: $RTFEM_CACHE, else $XDG_CACHE_HOME/rtfem, else ~/.cache/rtfem."""
    if os.environ.get("RTFEM_CACHE"):
        return Path(os.environ["RTFEM_CACHE"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "rtfem"


def digest(*parts) -> str:
    """A hex digest (BLAKE2b, 160 bits) of ``parts``: numpy arrays (dtype, shape and bytes), scipy
    sparse matrices (their CSR arrays), and anything JSON can write (numbers, strings, lists, dicts,
    with sorted keys); the part boundaries are part of the hash."""
    import scipy.sparse as sp

    h = hashlib.blake2b(digest_size=20)
    for part in parts:
        if sp.issparse(part):
            m = part.tocsr()
            if not m.has_sorted_indices:
                m = m.sorted_indices()
            h.update(f"csr{m.shape}".encode())
            for a in (m.indptr, m.indices, m.data):
                _array(h, a)
        elif isinstance(part, np.ndarray):
            _array(h, part)
        else:
            h.update(json.dumps(part, sort_keys=True, default=repr).encode())
        h.update(b"\x00|")
    return h.hexdigest()


def _array(h, a: np.ndarray) -> None:
    a = np.ascontiguousarray(a)
    h.update(f"{a.dtype.str}{a.shape}".encode())
    h.update(memoryview(a).cast("B"))


def entry(kind: str, key: str) -> Path:
    """The cache file of ``kind`` (see :data:`KINDS`) for a :func:`digest` ``key``."""
    return cache_dir() / f"{kind}-{key[:20]}.npz"


@dataclass
class Entry:
    path: Path
    kind: str
    size: int
    age: float  # seconds since it was written


def entries() -> list[Entry]:
    """The cache's files, newest first (a missing folder: none)."""
    folder = cache_dir()
    out = []
    if folder.is_dir():
        now = time.time()
        for p in folder.glob("*-*.npz"):
            kind = p.name.split("-", 1)[0]
            if kind in KINDS and p.is_file():
                st = p.stat()
                out.append(Entry(p, kind, st.st_size, now - st.st_mtime))
    return sorted(out, key=lambda e: e.age)


def clear(kind: str | None = None) -> tuple[int, int]:
    """Remove the cache's files (of one ``kind``, or all); returns (files, bytes) removed."""
    n = size = 0
    for e in entries():
        if kind is None or e.kind == kind:
            try:
                e.path.unlink()
            except OSError:
                continue
            n, size = n + 1, size + e.size
    return n, size
