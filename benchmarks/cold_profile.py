"""Where a cold `rtfem modes` spends its time (issue 54): one fresh interpreter per run, an empty
precompute cache, the phases stamped inside it (wall and CPU seconds of the process, all threads),
medians of --repeat. After the run the same stiffness is factorized twice more in that process, to
compare the first factorization of a process with later ones.

    python benchmarks/cold_profile.py [--repeat 5] [-- MODES ARGS]   (default: the HRA kidney shell, 1 mm, 10 modes)
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import print_table  # noqa: E402

KIDNEY = Path(__file__).resolve().parent / "organs" / "hra_kidney_right_male.ply"

CHILD = r"""
import time, sys, json
T0, C0 = time.perf_counter(), time.process_time()
marks = []
def mark(what):
    marks.append((what, time.perf_counter() - T0, time.process_time() - C0))
mark("interpreter")
import numpy; mark("import numpy")
import scipy.sparse; mark("import scipy.sparse")
import rtfem.cli.main as cli; mark("import rtfem.cli.main")
from rtfem.cli import common
from rtfem.fe import build
from rtfem.reduction import modal, precompute
def stamp(mod, name, label):
    f = getattr(mod, name)
    def g(*a, **k):
        out = f(*a, **k); mark(label); return out
    setattr(mod, name, g)
stamp(common, "mesh_of_args", "other imports, parse, read the mesh")
stamp(precompute, "model_digest", "model, assembly, cache key")
stamp(modal, "_shifted_factorization", "factorization")
stamp(modal, "_iterate", "Lanczos (block or ARPACK)")
import contextlib, io
with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
    rc = cli.main(sys.argv[1:])
mark("mass-normalize, shapes, write")
from rtfem.fe.linalg import factorize
K = precompute._last_K
for i in (2, 3):
    t, c = time.perf_counter(), time.process_time()
    factorize(K, what="K")
    marks.append((f"factorization {i} (same K)", time.perf_counter() - t, time.process_time() - c))
print(json.dumps([rc, marks]))
"""

# the child keeps the constrained K that the cache key was taken from, to factorize it again
PATCH = r"""
from rtfem.reduction import precompute as _p
_orig = _p.model_digest
def _keep(model):
    _p._last_K = model.constrained_stiffness()[0]
    return _orig(model)
_p.model_digest = _keep
"""


def one_run(args: list[str]) -> tuple[float, list]:
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, RTFEM_CACHE=str(Path(tmp) / "cache"))
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        code = CHILD.replace("from rtfem.cli import common", PATCH + "\nfrom rtfem.cli import common")
        t0 = time.perf_counter()
        run = subprocess.run([sys.executable, "-c", code, "modes", *args, "-o", str(Path(tmp) / "out.npz")],
                             capture_output=True, text=True, env=env, timeout=1800)
        whole = time.perf_counter() - t0
    if run.returncode != 0:
        raise SystemExit(run.stderr[-2000:])
    rc, marks = json.loads(run.stdout.strip().splitlines()[-1])
    if rc != 0:
        raise SystemExit(f"rtfem modes {' '.join(args)} exited {rc}")
    return whole, marks


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("modes_args", nargs="*", help="rtfem modes arguments (after --)")
    a = ap.parse_args()
    args = a.modes_args or [str(KIDNEY), "--thickness", "1e-3", "-n", "10"]
    one_run(args)  # untimed: .pyc files and the page cache
    runs = [one_run(args) for _ in range(a.repeat)]
    print(f"# rtfem modes {' '.join(args)}: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}; "
          f"medians of {a.repeat} fresh processes")
    names = [m[0] for m in runs[0][1]]
    med = [(statistics.median(r[1][i][1] for r in runs), statistics.median(r[1][i][2] for r in runs)) for i in range(len(names))]
    phases = [i for i, n in enumerate(names) if "(same K)" not in n]
    rows, prev = [], (0.0, 0.0)
    for i in phases[1:]:
        rows.append([names[i], f"{med[i][0] - prev[0]:.3f}", f"{med[i][1] - prev[1]:.3f}"])
        prev = med[i]
    extra = [i for i in range(len(names)) if i not in phases]
    whole = statistics.median(r[0] - sum(r[1][i][1] for i in extra) for r in runs)
    rows.append(["interpreter start and exit (the rest of the whole)", f"{whole - prev[0]:.3f}", "-"])
    rows.append(["whole run, timed from the parent", f"{whole:.3f}", "-"])
    rows += [[names[i] + ", afterwards", f"{med[i][0]:.3f}", f"{med[i][1]:.3f}"] for i in extra]
    print_table(["phase", "wall (s)", "CPU (s)"], rows)


if __name__ == "__main__":
    main()
