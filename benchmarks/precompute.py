"""Precompute ahead of CalculiX (issue 43): whole runs of assembly, factorization and r modes on the
same meshes, rtfem against ccx's *FREQUENCY (where ccx is installed) and scipy's eigsh, quiet and
with a competing busy process; each number the median of --repeat runs, in one process per case.

- rtfem: a fresh model of the mesh (assembly), its fixes, rt.modal_analysis(model, r) (the
  factorization and the block Lanczos): the wall time of the whole.
- ccx: the same nodes, elements (S3 shells of the shell's thickness, C3D4 tets), material, density
  and fixed nodes (translations; a shell's rotations too) written as a deck with *FREQUENCY r, then
  `ccx -i job` timed whole (reading, assembly, its factorization and eigen-solve, writing), on
  --ccx-threads threads (OMP_NUM_THREADS; default: the machine's cores).
- eigsh: scipy.sparse.linalg.eigsh(K, r, M, sigma=0) on rtfem's assembled free-dof K and M (the
  assembly not included).
- The lowest frequency of each, for a check that the same problem was solved (ccx's S3 is its own
  shell: its frequencies differ from rtfem's a little).

Cases: the embedded liver shell (2,562 vertices, 10 modes); the shells of ../shared/data/organs, 10 modes each:
SOFA's liver2 (1,170 vertices, scaled to 0.21 m), the OpenHELP gallbladder (7,352) and the GCA small
intestine (10,002) (SOFA's liver-smooth is left out: its 0.6-degree slivers give the held shell a
zero-frequency mode, which modal_analysis refuses); the liver solid of the size of SOFA's
ModelOrderReduction scene as tet4 (spacing 7 mm: 4,664 nodes) and SOFA's liver2 filled by fTetWild at 8 mm
(4,300-4,450 nodes, 20,800-21,300 tets: fTetWild differs run to run; the same mesh for all three solvers),
20 modes each; with --large, the OpenHELP liver shell (15,365 vertices, 100
modes) and the 40,962-vertex liver (100 modes).

    python benchmarks/precompute.py [--repeat 3] [--busy] [--large] [--ccx-threads N]
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.sparse.linalg as spla

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import busy_core, print_table  # noqa: E402

import rtfem as rt  # noqa: E402

ORGANS = Path(__file__).resolve().parents[2] / "shared" / "data" / "organs"
CCX = shutil.which("ccx")


def cases(large: bool) -> list:
    """(name, a function making the mesh, solid, r): every organ of ../shared/data/organs that is there."""
    shared = [("SOFA liver2 shell", "sofa_liver2.obj", 0.1, rt.Material().thickness),
              ("OpenHELP gallbladder shell (t 1 mm)", "sofa_env_gallbladder_visual.stl", 1e-3, 1e-3),
              ("GCA small intestine shell (t 1 mm)", "GCA-Models_small_intestine_20k.vtk", 1e-3, 1e-3)]
    out = [("liver shell (embedded)", lambda: rt.meshes.liver(), False, 10)]
    out += [(name, lambda f=f, s=s, t=t: _thick(rt.load_mesh(ORGANS / f, scale=s), t), False, 10)
            for name, f, s, t in shared if (ORGANS / f).is_file()]
    out.append(("liver tet4 (MOR size)", lambda: rt.meshes.liver(solid=True, spacing=0.007), True, 20))
    if (ORGANS / "sofa_liver2.obj").is_file():  # SOFA's liver filled by fTetWild at 8 mm: the MOR liver's size
        out.append(("SOFA liver2 tet4 (8 mm)", lambda: rt.tetrahedralize(rt.load_mesh(ORGANS / "sofa_liver2.obj", scale=0.1),
                                                                         0.008), True, 20))
    if large:
        if (ORGANS / "sofa_env_Liver.stl").is_file():
            out.append(("OpenHELP liver shell", lambda: rt.load_mesh(ORGANS / "sofa_env_Liver.stl", scale=1e-3),
                        False, 100))
        out.append(("liver shell level 6", lambda: rt.meshes.liver(6), False, 100))
    return out


def _fixed(mesh) -> np.ndarray:
    """The attachment group where the mesh has one, else the lowest 10 % of its height."""
    groups = getattr(mesh, "groups", None) or {}
    if "attachment" in groups:
        return np.asarray(groups["attachment"], int)
    z = np.asarray(mesh.vertices)[:, 2]
    return np.flatnonzero(z <= z.min() + 0.1 * (z.max() - z.min()))


def _thick(mesh, thickness: float):
    """The mesh, marked with the shell thickness both solvers use on it (ccx's S3 expands a shell into
    wedges, which fold where the thickness exceeds the small organs' curvature radii: 1 mm there)."""
    mesh.benchmark_thickness = thickness
    return mesh


def _material(mesh) -> rt.Material:
    return rt.Material(thickness=getattr(mesh, "benchmark_thickness", rt.Material().thickness))


def _model(mesh, solid: bool):
    m = _material(mesh)
    model = rt.SolidModel(mesh, m, element="tet4") if solid else rt.ShellModel(mesh, m)
    return model.fix(_fixed(mesh))


def time_rtfem(mesh, solid: bool, r: int) -> tuple[float, float]:
    t0 = time.perf_counter()
    basis = rt.modal_analysis(_model(mesh, solid), r)
    return time.perf_counter() - t0, float(basis.frequencies[0])


def time_eigsh(mesh, solid: bool, r: int) -> tuple[float, float]:
    model = _model(mesh, solid)
    K, _ = model.constrained_stiffness()
    M, _ = model.constrained_mass()
    t0 = time.perf_counter()
    lam = spla.eigsh(K, r, M, sigma=0, which="LM", return_eigenvectors=False)
    return time.perf_counter() - t0, float(np.sqrt(np.sort(lam)[0]) / (2 * np.pi))


def _deck(mesh, solid: bool, r: int, fixed: np.ndarray | None = None) -> str:
    """The ccx input deck of the case; ``fixed``: the held nodes (default :func:`_fixed`)."""
    m, X = _material(mesh), np.asarray(mesh.vertices)
    cells = np.array(mesh.tets if solid else mesh.triangles)
    if solid:  # ccx wants (x2 - x1) x (x3 - x1) . (x4 - x1) > 0: two nodes swapped where rtfem's order is the other
        P = X[cells]
        neg = np.einsum("ij,ij->i", np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), P[:, 3] - P[:, 0]) < 0
        cells[neg] = cells[neg][:, [0, 2, 1, 3]]
    kind = "C3D4" if solid else "S3"
    lines = ["*HEADING", "rtfem precompute benchmark", "*NODE"]
    lines += [f"{i + 1},{x:.12e},{y:.12e},{z:.12e}" for i, (x, y, z) in enumerate(X.tolist())]  # ccx: 20 chars a field
    lines += [f"*ELEMENT,TYPE={kind},ELSET=EALL"] + [f"{e + 1}," + ",".join(str(v + 1) for v in c)
                                                    for e, c in enumerate(cells.tolist())]
    held = _fixed(mesh) if fixed is None else np.asarray(fixed, int)
    lines += ["*NSET,NSET=FIX"] + [f"{i + 1}," for i in held.tolist()]
    lines += ["*BOUNDARY", "FIX,1,3" if solid else "FIX,1,6", "*MATERIAL,NAME=M", "*ELASTIC",
              f"{m.E!r},{m.nu!r}", "*DENSITY", f"{m.density!r}"]
    lines += ["*SOLID SECTION,ELSET=EALL,MATERIAL=M"] if solid else \
        ["*SHELL SECTION,ELSET=EALL,MATERIAL=M", f"{m.thickness!r}"]
    return "\n".join(lines + ["*STEP", "*FREQUENCY", f"{r}", "*END STEP"]) + "\n"


def time_ccx(mesh, solid: bool, r: int, threads: int, fixed: np.ndarray | None = None) -> tuple[float, float]:
    with tempfile.TemporaryDirectory() as tmp:
        Path(tmp, "job.inp").write_text(_deck(mesh, solid, r, fixed))
        t0 = time.perf_counter()
        run = subprocess.run([CCX, "-i", "job"], cwd=tmp, capture_output=True, text=True, timeout=1800,
                             env=dict(os.environ, OMP_NUM_THREADS=str(threads)))
        seconds = time.perf_counter() - t0
        if run.returncode != 0:
            errors = sorted({line.strip() for line in run.stdout.splitlines() if "*ERROR" in line})
            raise RuntimeError("; ".join(errors) or (run.stdout[-500:] + run.stderr[-500:]))
        text = Path(tmp, "job.dat").read_text()
    rows = text.split("E I G E N V A L U E   O U T P U T")[-1].strip().splitlines()
    first = next(line.split() for line in rows if line.split() and line.split()[0] == "1")
    return seconds, float(first[3])  # MODE NO, EIGENVALUE, OMEGA (RAD/TIME), OMEGA (CYCLES/TIME)


def _median(fn, repeat: int) -> tuple[float, float]:
    runs = [fn() for _ in range(repeat)]
    return float(np.median([t for t, _ in runs])), runs[0][1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--busy", action="store_true", help="with another process keeping one core busy")
    ap.add_argument("--large", action="store_true", help="also the OpenHELP liver and the 40,962-vertex liver")
    ap.add_argument("--ccx-threads", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--no-eigsh", action="store_true")
    args = ap.parse_args()
    print(f"# rtfem {rt.__version__}, python {platform.python_version()}, {os.cpu_count()} cores"
          f"{', one core busy' if args.busy else ', quiet'}; ccx: {CCX or 'not installed'} "
          f"({args.ccx_threads} threads); medians of {args.repeat}")
    rows = []
    for name, make, solid, r in cases(args.large):
        mesh = make()
        time_rtfem(mesh, solid, r)  # warm: imports, compiled kernels
        with busy_core(args.busy):
            t_rt, f_rt = _median(lambda: time_rtfem(mesh, solid, r), args.repeat)
            t_eig, f_eig = (None, None) if args.no_eigsh else _median(lambda: time_eigsh(mesh, solid, r), args.repeat)
            missing = "-"
            try:
                t_cx, f_cx = (None, None) if CCX is None else _median(lambda: time_ccx(mesh, solid, r, args.ccx_threads),
                                                                      args.repeat)
            except RuntimeError as exc:  # ccx refused the deck: say so in the row, keep the others
                print(f"# {name}: ccx failed: {exc}", flush=True)
                t_cx, f_cx, missing = None, None, "failed"
        n = mesh.n_vertices
        rows.append([name, f"{n:,}", r, f"{t_rt:.2f}", missing if t_cx is None else f"{t_cx:.2f}",
                     missing if t_cx is None else f"{t_cx / t_rt:.2f}", "-" if t_eig is None else f"{t_eig:.2f}",
                     "-" if t_eig is None else f"{t_eig / t_rt:.2f}",
                     f"{f_rt:.4g} / {missing if f_cx is None else f'{f_cx:.4g}'} / {'-' if f_eig is None else f'{f_eig:.4g}'}"])
        print(rows[-1], flush=True)
    print_table(["mesh", "nodes", "r", "rtfem whole (s)", "ccx whole (s)", "ccx / rtfem", "eigsh (s)",
                 "eigsh / rtfem", "f1 rtfem / ccx / eigsh (Hz)"], rows)


if __name__ == "__main__":
    main()
