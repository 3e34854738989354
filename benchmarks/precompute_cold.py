"""Cold, fresh-process whole runs against CalculiX (issue 54): what a user waits for when a script or
`rtfem modes` is launched on an organ file, every case in a new process.

- rtfem: `python -m rtfem.cli.main modes FILE --scale S [--thickness T | --element tet4 --mass M]
  -n r -o out.npz` in a new interpreter with an empty precompute cache (RTFEM_CACHE, a fresh folder
  per run), timed whole from the parent: interpreter start, imports, reading the file, assembly,
  factorization, the modes, writing the .npz. Before the timed runs one untimed run of the same
  command leaves what an installed rtfem keeps on disk after its first use (Python's .pyc files,
  numba's compiled kernels), and brings the files into the page cache.
- ccx: `ccx -i job` timed whole on the deck of benchmarks/precompute.py (the same nodes, elements,
  material, density and held nodes: those `rtfem modes` holds, its default --fix), on
  --ccx-threads threads (default: the machine's cores); one untimed run first too.
- The runs alternate (rtfem, ccx, rtfem, ...), each number the median of --repeat; the ratio
  ccx / rtfem comes from the same run. The CPU seconds (user + system, medians) of each say what the
  runs cost apart from the machine's load (this 2-core machine is shared); f1 of both checks that one
  problem was solved (ccx's S3 is its own shell: its frequencies differ from rtfem's a little on shells).

Cases: the organs of ../shared/data/organs and the embedded liver as in benchmarks/precompute.py
(shells 10 modes; tet4 solids written to a VTU first, 20 modes, lumped mass as there), the issue's
22k-tet liver with a consistent mass (20 modes), and the organs fetched for this benchmark,
benchmarks/organs/ (README.md there: HRA reference organs, CC BY 4.0): a kidney, a heart's left
ventricle, a uterus wall and a thymus lobe as shells of 1 mm (10 modes; ccx's S3 expands a shell into
wedges, which fold at 2-4 mm on these), and the thymus lobe filled with tet4 by fTetWild at 4 mm
(consistent mass, 20 modes; the kidney's fill at 4-5 mm has a non-manifold boundary).

    python benchmarks/precompute_cold.py [--repeat 5] [--busy] [--ccx-threads N] [--only TEXT]
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import busy_core, print_table  # noqa: E402
from precompute import CCX, ORGANS, time_ccx  # noqa: E402

import rtfem as rt  # noqa: E402
from rtfem.cli.common import fixed_nodes  # noqa: E402

FETCHED = Path(__file__).resolve().parent / "organs"
DEFAULT_THICKNESS = rt.Material().thickness


@dataclass
class Case:
    name: str
    file: Path | None  # None: the embedded liver (`rtfem modes` without a file)
    r: int
    scale: float = 1.0
    thickness: float = DEFAULT_THICKNESS  # shells
    mass: str | None = None  # solids: "lumped" or "consistent"
    make: object = None  # solids: a function making the TetMesh, written to `file` as VTU first
    extra: list = field(default_factory=list)

    @property
    def solid(self) -> bool:
        return self.mass is not None

    def args(self, out: Path) -> list[str]:
        a = [] if self.file is None else [str(self.file)]
        if self.scale != 1.0:
            a += ["--scale", repr(self.scale)]
        a += ["--element", "tet4", "--mass", self.mass] if self.solid else ["--thickness", repr(self.thickness)]
        return a + ["-n", str(self.r), "-o", str(out)] + self.extra


def cases(tmp: Path) -> list[Case]:
    """Every case whose files are here (the shared organs are skipped where ../shared is absent)."""
    liver2 = ORGANS / "sofa_liver2.obj"
    out = [Case("liver shell (embedded)", None, 10)]
    for name, f, s, t in [("SOFA liver2 shell", "sofa_liver2.obj", 0.1, DEFAULT_THICKNESS),
                          ("OpenHELP gallbladder shell (t 1 mm)", "sofa_env_gallbladder_visual.stl", 1e-3, 1e-3),
                          ("GCA small intestine shell (t 1 mm)", "GCA-Models_small_intestine_20k.vtk", 1e-3, 1e-3)]:
        if (ORGANS / f).is_file():
            out.append(Case(name, ORGANS / f, 10, s, t))
    liver_tets = lambda: rt.meshes.liver(solid=True, spacing=0.007)  # noqa: E731
    out.append(Case("liver tet4 (MOR size)", tmp / "liver_tet4.vtu", 20, mass="lumped", make=liver_tets))
    if liver2.is_file():
        out.append(Case("SOFA liver2 tet4 (8 mm)", tmp / "liver2_tet4.vtu", 20, mass="lumped",
                        make=lambda: rt.tetrahedralize(rt.load_mesh(liver2, scale=0.1), 0.008)))
    out.append(Case("liver tet4 consistent (issue's 22k tets)", tmp / "liver_tet4.vtu", 20, mass="consistent",
                    make=liver_tets))
    for name, f in [("HRA kidney shell (t 1 mm)", "hra_kidney_right_male.ply"),
                    ("HRA heart left ventricle shell (t 1 mm)", "hra_heart_left_ventricle_male.ply"),
                    ("HRA uterus wall shell (t 1 mm)", "hra_uterus_posterior_wall_female.ply"),
                    ("HRA thymus lobe shell (t 1 mm)", "hra_thymus_left_lobe_female.ply")]:
        out.append(Case(name, FETCHED / f, 10, thickness=1e-3))
    out.append(Case("HRA thymus lobe tet4 consistent (4 mm)", tmp / "thymus_tet4.vtu", 20, mass="consistent",
                    make=lambda: rt.tetrahedralize(rt.load_mesh(FETCHED / "hra_thymus_left_lobe_female.ply"), 0.004)))
    return out


def _children_cpu() -> float:
    """User + system CPU seconds of this process's finished children."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run_rtfem(case: Case, work: Path) -> tuple[float, float, float]:
    """One cold run: a new interpreter, an empty cache folder; (seconds, CPU seconds, f1 in Hz)."""
    with tempfile.TemporaryDirectory(dir=work) as cache:
        out = Path(cache) / "out.npz"
        cmd = [sys.executable, "-m", "rtfem.cli.main", "modes", *case.args(out)]
        env = dict(os.environ, RTFEM_CACHE=str(Path(cache) / "cache"))
        env.pop("PYTHONDONTWRITEBYTECODE", None)  # an installed package has its .pyc files (pip writes them)
        t0, c0 = time.perf_counter(), _children_cpu()
        run = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1800)
        seconds, cpu = time.perf_counter() - t0, _children_cpu() - c0
        if run.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)}: {run.stderr.strip()[-500:]}")
        f1 = float(rt.ModalBasis.load(out).frequencies[0])
    return seconds, cpu, f1


def _ccx_mesh(case: Case):
    """The mesh as `rtfem modes` reads it (the embedded liver as it builds it), its thickness for the
    deck, and the nodes it holds by default."""
    mesh = rt.meshes.liver() if case.file is None else rt.load_mesh(case.file, scale=case.scale)
    mesh.benchmark_thickness = case.thickness
    return mesh, fixed_nodes(mesh, None)[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--busy", action="store_true", help="with another process keeping one core busy")
    ap.add_argument("--ccx-threads", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--only", default=None, help="only the cases whose name contains this text")
    ap.add_argument("--no-ccx", action="store_true", help="rtfem's rows only (e.g. to compare two versions of rtfem)")
    args = ap.parse_args()
    if CCX is None and not args.no_ccx:
        raise SystemExit("ccx (CalculiX) is not installed: nothing to compare with (--no-ccx: rtfem's rows only)")
    load = os.getloadavg()[0]
    print(f"# rtfem {rt.__version__}, python {platform.python_version()}, {os.cpu_count()} cores, load average "
          f"{load:.2f} at the start{', one core busy' if args.busy else ''}; ccx: "
          f"{'not run' if args.no_ccx else f'{CCX} ({args.ccx_threads} threads)'}; "
          f"cold fresh-process runs, medians of {args.repeat}", flush=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        for case in cases(tmp):
            if args.only and args.only.lower() not in case.name.lower():
                continue
            if case.make is not None and not case.file.is_file():
                rt.save_mesh(case.make(), case.file)
            mesh, held = _ccx_mesh(case)
            run_rtfem(case, tmp)  # untimed: .pyc files, numba's kernels on disk, the page cache
            ccx = (lambda: (0.0, float("nan"))) if args.no_ccx else \
                (lambda: time_ccx(mesh, case.solid, case.r, args.ccx_threads, held))  # noqa: B023
            try:
                ccx()
            except RuntimeError as exc:  # ccx refused the deck: say so, keep the others
                print(f"# {case.name}: ccx failed: {exc}", flush=True)
                continue
            t_rt, t_cx, c_rt, c_cx = [], [], [], []
            with busy_core(args.busy):
                for _ in range(args.repeat):
                    t, c, f_rt = run_rtfem(case, tmp)
                    t_rt.append(t)
                    c_rt.append(c)
                    c = _children_cpu()
                    t, f_cx = ccx()
                    t_cx.append(t)
                    c_cx.append(_children_cpu() - c)
            rt_med, cx_med = statistics.median(t_rt), statistics.median(t_cx)
            cx = (lambda text: "-") if args.no_ccx else (lambda text: text)  # noqa: E731
            rows.append([case.name, f"{mesh.n_vertices:,}", case.r, f"{rt_med:.2f}", cx(f"{cx_med:.2f}"),
                         cx(f"{cx_med / rt_med:.2f}"),
                         f"{statistics.median(c_rt):.2f} / {cx(f'{statistics.median(c_cx):.2f}')}",
                         f"{f_rt:.4g} / {cx(f'{f_cx:.4g}')}"])
            print(rows[-1], f"rtfem {np.round(t_rt, 2).tolist()} ccx {np.round(t_cx, 2).tolist()}", flush=True)
    print_table(["organ", "nodes", "r", "rtfem cold (s)", "ccx cold (s)", "ccx / rtfem", "CPU rtfem / ccx (s)",
                 "f1 rtfem / ccx (Hz)"], rows)
    print(f"# load average {os.getloadavg()[0]:.2f} at the end")


if __name__ == "__main__":
    main()
