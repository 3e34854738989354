"""Load schedules and the writer of headless runs (used by ``rtfem simulate``, the demo and SLDM).

:class:`LoadSchedule` is a piecewise-constant load history: from each row's time on, its node
carries its force until that node's next row. The stepping simulators read it per step
(:meth:`LoadSchedule.forces_at`), SLDM takes its switches whole (:meth:`SLDM.response`).
:class:`RunWriter` writes what a run produces: a CSV of per-step values and VTU frames at a
frame rate, listed in a ParaView collection.
"""

from __future__ import annotations

import bisect
import csv
import os
from pathlib import Path

import numpy as np

from .. import validate
from ..errors import ModelError
from .vtk import write_pvd, write_vtu

__all__ = ["LoadSchedule", "RunWriter"]


class LoadSchedule:
    """A piecewise-constant load history on nodes.

    ``rows``: ``(t, node, (fx, fy, fz))``; from time t (s) on, ``node`` carries that force (N)
    until its next row (a zero force ends it). Rows may come in any order; at equal times the
    later row wins.
    """

    def __init__(self, rows, n_nodes: int) -> None:
        self.n_nodes = validate.count(n_nodes, "n_nodes", 1)
        parsed = []
        for r in validate.entries(rows, "rows", "load row", 3, "(t, node, (fx, fy, fz))"):
            t = validate.nonnegative(r[0], "load time", "a time in s")
            parsed.append((t, validate.node(r[1], self.n_nodes, "load node"), validate.vector(r[2], "load force", 3)))
        if not parsed:
            raise ModelError("a load schedule needs at least one row (t, node, (fx, fy, fz))")
        parsed.sort(key=lambda r: r[0])  # stable: equal times keep their order
        self.rows = parsed
        self.nodes = sorted({n for _, n, _ in parsed})
        # the loads in force after each switch time, built once
        self.switches = sorted({t for t, _, _ in parsed})
        self._states: list[dict[int, np.ndarray]] = []
        cur: dict[int, np.ndarray] = {}
        i = 0
        for ts in self.switches:
            while i < len(parsed) and parsed[i][0] == ts:
                cur[parsed[i][1]] = parsed[i][2]
                i += 1
            self._states.append({n: f for n, f in cur.items() if np.any(f)})

    @classmethod
    def from_csv(cls, path: str | os.PathLike, n_nodes: int) -> "LoadSchedule":
        """Read rows ``t,node,fx,fy,fz`` (a header line and # comments are skipped); errors name
        the file and line."""
        from ..userfiles import regular_file

        rows = []
        regular_file(path, "load file")  # a pipe or /dev/zero would never end
        try:
            with open(path, newline="") as fh:
                for i, row in enumerate(csv.reader(fh), start=1):
                    if not row or row[0].strip().startswith("#") or row[0].strip().lower() == "t":
                        continue
                    if len(row) != 5:
                        raise ModelError(f"{path}, line {i}: expected 5 columns t,node,fx,fy,fz, found {len(row)}")
                    try:
                        t, node = float(row[0]), int(row[1])
                        f = np.array([float(v) for v in row[2:]])
                    except ValueError:
                        raise ModelError(f"{path}, line {i}: not numbers: {validate.one_line(','.join(row))}") from None
                    if not (np.isfinite(t) and t >= 0 and np.all(np.isfinite(f))):
                        raise ModelError(f"{path}, line {i}: time must be >= 0 and forces finite")
                    if not 0 <= node < n_nodes:
                        raise ModelError(f"{path}, line {i}: node {node} is not on the mesh (0..{n_nodes - 1})")
                    rows.append((t, node, f))
        except UnicodeDecodeError:
            raise ModelError(f"{path}: not a text CSV file") from None
        except OSError as exc:
            raise ModelError(f"{path}: cannot be read ({exc.strerror or exc})") from None
        if not rows:
            raise ModelError(f"{path}: no load rows (t,node,fx,fy,fz)")
        return cls(rows, n_nodes)

    def __len__(self) -> int:
        return len(self.rows)

    def forces_at(self, t: float) -> dict[int, np.ndarray]:
        """The loads in force at time ``t`` ({node: force}; empty before the first row)."""
        k = bisect.bisect_right(self.switches, t + 1e-12) - 1
        return self._states[k] if k >= 0 else {}

    def array(self, state: dict[int, np.ndarray]) -> np.ndarray:
        F = np.zeros((self.n_nodes, 3))
        for n, f in state.items():
            F[n] = f
        return F

    def piecewise(self) -> list[tuple[float, np.ndarray]]:
        """``[(t_k, (n, 3) forces_k)]``: what :meth:`SLDM.response` takes."""
        return [(t, self.array(s)) for t, s in zip(self.switches, self._states)]


class RunWriter:
    """Writes a run: CSV rows (one per step) and VTU frames every ``frame_every`` steps.

    ``row(values)`` appends a CSV row (floats written with 9 significant digits);
    ``frame(step, t, U)`` writes ``frame_#####.vtu`` when ``step`` is a multiple of
    ``frame_every``; ``close()`` writes the CSV and the ParaView collection and returns their
    paths. Frames go to ``folder`` as they come, the CSV at the end (atomically).
    """

    def __init__(self, folder: str | os.PathLike, mesh, header: list[str], frame_every: int = 1,
                 name: str = "response", frame_folder: str | os.PathLike | None = None) -> None:
        from ..userfiles import file_stem

        self.folder = Path(folder)
        file_stem(name, "name")  # <name>.csv and <name>.pvd stay in the folder
        if self.folder.exists() and not self.folder.is_dir():
            raise ModelError(f"{str(folder)!r} is a file; give a folder for the frames")
        self.folder.mkdir(parents=True, exist_ok=True)
        self.frames_in = Path(frame_folder) if frame_folder is not None else self.folder
        self.frames_in.mkdir(parents=True, exist_ok=True)
        self.mesh, self.header, self.name = mesh, list(header), name
        self.frame_every = validate.count(frame_every, "frame_every", 1)
        self.rows: list[list] = []
        self.frames: list[tuple[float, Path]] = []

    def row(self, values) -> None:
        self.rows.append(list(values))

    def frame(self, step: int, t: float, displacements) -> None:
        if step % self.frame_every == 0:
            U = displacements() if callable(displacements) else displacements
            path = write_vtu(self.frames_in / f"frame_{len(self.frames):05d}.vtu", self.mesh, U)
            self.frames.append((t, path))

    def close(self) -> tuple[Path | None, Path]:
        """Write ``<name>.csv`` (when there are rows) and ``<name>.pvd``; returns their paths."""
        csv_path = None
        if self.rows:
            from ..storage import atomic_target

            csv_path = self.folder / f"{self.name}.csv"
            with atomic_target(csv_path) as tmp, open(tmp, "w", newline="") as fh:
                w = csv.writer(fh)
                w.writerow(self.header)
                w.writerows([[f"{v:.9g}" if isinstance(v, float) else v for v in r] for r in self.rows])
        return csv_path, write_pvd(self.folder / f"{self.name}.pvd", self.frames)
