"""The compiled assembly (numba, rtfem.fe.assembly_kernels) against the batched numpy path it replaced
(``RTFEM_ASSEMBLY=numpy``), in the same run: the time to assemble K and the lumped M of a fresh model,
median of --repeat, and the largest difference of the two stiffnesses relative to the largest entry.

Meshes: the liver shell at levels 4 and 5 (and the OpenHELP liver when ../shared/data is there) and
the liver solid as tet4 at 7 and 5 mm and as tet10 at 10 mm.

    python benchmarks/assembly_compiled.py [--repeat 5]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import print_table  # noqa: E402

import rtfem as rt  # noqa: E402
from rtfem.fe import assembly  # noqa: E402

ORGANS = Path(__file__).resolve().parents[2] / "shared" / "data" / "organs"


def cases() -> list:
    out = [("liver shell level 4", lambda: rt.meshes.liver(4), "shell"),
           ("liver shell level 5", lambda: rt.meshes.liver(5), "shell")]
    if (ORGANS / "sofa_env_Liver.stl").is_file():
        out.append(("OpenHELP liver shell", lambda: rt.load_mesh(ORGANS / "sofa_env_Liver.stl", scale=1e-3), "shell"))
    out += [("liver tet4 7 mm", lambda: rt.meshes.liver(solid=True, spacing=0.007), "tet4"),
            ("liver tet4 5 mm", lambda: rt.meshes.liver(solid=True, spacing=0.005), "tet4"),
            ("liver tet10 10 mm", lambda: rt.meshes.liver(solid=True, spacing=0.010), "tet10")]
    return out


def _assemble(mesh, kind: str, how: str):
    os.environ["RTFEM_ASSEMBLY"] = how
    model = rt.ShellModel(mesh, rt.Material()) if kind == "shell" else rt.SolidModel(mesh, rt.Material(), element=kind)
    t0 = time.perf_counter()
    model.K  # noqa: B018 - assembles K and M
    return time.perf_counter() - t0, model


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    print(f"# rtfem {rt.__version__}, python {platform.python_version()}, {os.cpu_count()} cores; compiled assembly "
          f"available: {assembly.compiled_assembly()}; medians of {args.repeat}")
    rows = []
    for name, make, kind in cases():
        mesh = make()
        times = {}
        for how in ("numpy", ""):
            _assemble(mesh, kind, how)  # warm: compiled kernels, caches
            runs = [_assemble(mesh, kind, how) for _ in range(args.repeat)]
            times[how] = (float(np.median([t for t, _ in runs])), runs[-1][1])
        (t_np, a), (t_c, b) = times["numpy"], times[""]
        diff = abs(a.K - b.K).max() / abs(a.K).max()
        n_el = mesh.n_triangles if kind == "shell" else mesh.n_tets
        rows.append([name, f"{mesh.n_vertices:,}", f"{n_el:,}", f"{t_np * 1e3:.1f}", f"{t_c * 1e3:.1f}",
                     f"{t_np / t_c:.1f}x", f"{diff:.1e}"])
        print(rows[-1], flush=True)
    os.environ.pop("RTFEM_ASSEMBLY", None)
    print_table(["mesh", "nodes", "elements", "numpy (ms)", "compiled (ms)", "speed-up", "max |dK| / max |K|"], rows)


if __name__ == "__main__":
    main()
