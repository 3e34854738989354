"""fTetWild in a process of its own: :func:`rtfem.mesh.meshing.tetrahedralize` runs this file as a
script (``python _tetwild.py FOLDER ARGS``), not as a module, so the child imports numpy and the
mesher's extension only (not rtfem: it starts in a fraction of a second).

Why a process: fTetWild installs its own SIGINT handler, which ends the whole process on Ctrl-C
(without Python's cleanup: its scratch folder stayed, and a caller could not keep what it had
finished). In a child, Ctrl-C ends the child, and the caller gets a KeyboardInterrupt it can
handle. The child works in FOLDER (fTetWild writes a debug surface into the working directory),
reads V.npy and F.npy there and writes X.npy and T.npy; a failure is one line on stderr and exit 1.
"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path


def find_wrapper():
    """fTetWild's compiled entry point, or None. pytetwild's package __init__ imports pyvista (a
    hard import of an optional dependency in 0.3-0.4); the extension module itself needs only
    numpy, so it is loaded directly when that import fails."""
    try:
        from pytetwild import PyfTetWildWrapper  # noqa: PLC0415

        return PyfTetWildWrapper
    except ImportError:
        pass
    spec = importlib.util.find_spec("pytetwild")
    if spec is None or not spec.submodule_search_locations:
        return None
    for f in Path(list(spec.submodule_search_locations)[0]).glob("PyfTetWildWrapper*"):
        if f.suffix in (".so", ".pyd"):
            s = importlib.util.spec_from_file_location("pytetwild.PyfTetWildWrapper", f)
            module = importlib.util.module_from_spec(s)
            s.loader.exec_module(module)  # type: ignore[union-attr]
            return module
    return None


def main(argv: list[str]) -> int:
    import numpy as np

    folder, args = Path(argv[0]), json.loads(argv[1])
    wrapper = find_wrapper()
    if wrapper is None:
        print("the fTetWild mesher (pytetwild) is not installed", file=sys.stderr)
        return 1
    V, F = np.load(folder / "V.npy"), np.load(folder / "F.npy")
    try:
        X, T = wrapper.tetrahedralize_mesh(V, F, args["optimize"], False, args["fac"], 0.0, args["epsilon"], 10.0,
                                           False, args["threads"], 80, 6, True, False, False, np.zeros((0, 3)),
                                           np.zeros((0, 4), np.int32), np.zeros(0))
    except Exception as exc:  # the mesher's own failures come as RuntimeError or its own types
        print(" ".join(str(exc).split()) or type(exc).__name__, file=sys.stderr)
        return 1
    np.save(folder / "X.npy", np.asarray(X, dtype=float))
    np.save(folder / "T.npy", np.asarray(T if T is not None else np.zeros((0, 4)), dtype=np.int64))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
