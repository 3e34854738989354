"""Tool-tissue contact at haptic rate: step-time percentiles of a 1 kHz loop with about 1, 10 and
50 contact points, and the worst step of a probe sliding over the organ.

Each row runs rt.ToolContact in an rt.HapticLoop (Python ticks) for ``--seconds`` with a modal
driver (r modes, static correction) and gives the mean number of active contact points:
- spheres of 0, 6 and 15 mm pressed 4 mm into the default liver shell's probe point through the
  200 N/m coupling spring (the soft, convex lobe swings away: about one contact point each);
- a 3 cm flat jaw held at the device (constraint coupling) pressed 6 mm into the 10,242-vertex
  liver (``rt.meshes.liver(5)``) 2 cm from its attachment, where the lobe cannot swing away
  (about ten points: the shell wraps the jaw's rim);
- a 3 cm flat punch (constraint) pressed 1 mm into the top of a 10 x 10 x 5 cm block of tissue
  (linear tets, 5 mm spacing, bottom held): the solid stays on the whole footprint, fifty points.
  (A thin plate under a flat punch bends away from its middle and touches it at the corners.)
The step times are those of the ticks in contact.
Then a 1 cm sphere comes down from 3 cm above onto the liver's top and slides 4 mm deep over the whole organ, end
to end (a path on the surface, about 20 cm) at 2 cm/s in the 1 kHz loop with nothing prepared before:
with ``lookahead=0`` the ticks that meet new vertices
compute their static-correction columns (sparse solves) themselves; with the default lookahead
a background thread has prepared them before the tool arrives. The table gives both loops' step
times and how many ticks prepared vertices. The
baseline, measured in the same run, is the single-vertex rt.Probe (compiled ticks where numba is
present).

    python benchmarks/contact.py [--modes 40] [--seconds 3]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import rtfem as rt  # noqa: E402
from _common import print_table  # noqa: E402


def stats_row(label, stats, contacts=None) -> list:
    """A table row: with ``contacts`` (the active points of each tick), the step times of the ticks
    in contact only (the press's approach and release ticks touch nothing)."""
    c = np.asarray(stats.compute) * 1e6
    if contacts is not None:
        touching = np.asarray(contacts[:c.size]) > 0
        c = c[:touching.size][touching]
    mean = f"{np.mean(np.asarray(contacts)[np.asarray(contacts) > 0]):.1f}" if contacts is not None else "1"
    return [label, mean, f"{stats.steps}", f"{c.size}", f"{stats.missed}", f"{np.median(c):.0f}",
            f"{np.percentile(c, 99):.0f}", f"{c.max():.0f}", "compiled" if stats.compiled else "Python"]


def loop_row(label, tc, touching, normal, depth, seconds, radius) -> list:
    """The haptic loop of ``tc`` pressing from 1 mm above ``touching`` to ``depth`` along -``normal``
    (the scripted press: ramp, hold, back out), its contact points counted on every tick."""
    tc.prepare(around=touching, radius=radius)
    counts = []
    update = tc.update

    def counted(p):
        f = update(p)
        counts.append(tc.contacts)
        return f

    tc.update = counted
    stats = rt.HapticLoop(tc, rt.ScriptedDevice.press(touching, normal, depth, seconds, approach=0.001)).run(seconds)
    return stats_row(f"rt.ToolContact, {label}", stats, counts)


def near_support(model, distance: float) -> int:
    """The upward-facing surface vertex about ``distance`` from the nearest held node."""
    from scipy.spatial import cKDTree

    X, up = np.asarray(model.mesh.vertices), model.mesh.vertex_normals()[:, 2]
    used = model.mesh.used_vertices()
    gap, _ = cKDTree(X[np.flatnonzero(model.held_nodes)]).query(X[used])
    near = used[np.abs(gap - distance) < 0.003]
    return int(near[np.argmax(up[near])])


def run(n_modes: int, seconds: float) -> None:
    mesh = rt.meshes.liver(4)
    model = rt.ShellModel(mesh, rt.Material()).fix("attachment")
    modes = rt.modal_analysis(model, n_modes)
    node = int(model.select_nodes("probe")[0])
    X, n = np.asarray(mesh.vertices)[node], mesh.vertex_normals()[node]
    print(f"liver shell: {model.n_nodes:,} nodes, r = {n_modes}", flush=True)
    rows = []

    def sim():
        return rt.ModalSimulator(modes, 1e-3, rt.Damping(alpha=5.0), static_correction=True)

    probe = rt.Probe(mesh, sim(), stiffness=200.0)
    probe.prepare(around=X, radius=0.02)
    device = rt.ScriptedDevice.press(X, n, 0.004, seconds, approach=0.001)
    rows.append(stats_row("rt.Probe (one vertex): baseline", rt.HapticLoop(probe, device).run(seconds)))
    for R in (0.0, 0.006, 0.015):
        tc = rt.ToolContact(mesh, sim(), rt.Tool.sphere(R), stiffness=200.0)
        rows.append(loop_row(f"sphere R = {R * 1e3:g} mm, liver 2,562 vertices", tc, X + R * n, n, 0.004,
                             seconds, R + 0.02))

    # a flat jaw near the attachment of the finer liver: about ten points
    fine = rt.meshes.liver(5)
    fmodel = rt.ShellModel(fine, rt.Material()).fix("attachment")
    fmodes = rt.modal_analysis(fmodel, n_modes)
    node = near_support(fmodel, 0.02)
    Xf, nf = np.asarray(fine.vertices)[node], fine.vertex_normals()[node]
    jaw = rt.Tool.jaw(0.03, 0.03, 0.002, normal=nf)
    tc = rt.ToolContact(fine, rt.ModalSimulator(fmodes, 1e-3, rt.Damping(alpha=5.0), static_correction=True), jaw,
                        coupling="constraint")
    rows.append(loop_row(f"jaw 3 x 3 cm, liver {fine.n_vertices:,} vertices", tc, Xf + jaw.radius * nf, nf, 0.006,
                         seconds, jaw.reach + 0.01))

    # a flat punch on a solid block: about fifty points
    box = rt.meshes.box(0.1, 0.1, 0.05, 20, 20, 10)
    bmodel = rt.SolidModel(box, rt.Material())
    Y = np.asarray(box.vertices)
    bmodel.fix(Y[:, 2] == Y[:, 2].min(), dofs="xyz")
    bmodes = rt.modal_analysis(bmodel, n_modes)
    punch = rt.Tool.jaw(0.031, 0.031, 0.002, normal=(0.0, 0.0, 1.0))
    tc = rt.ToolContact(bmodel.mesh, rt.ModalSimulator(bmodes, 1e-3, rt.Damping(alpha=5.0), static_correction=True),
                        punch, coupling="constraint")
    top = np.array([0.05, 0.05, Y[:, 2].max() + punch.radius])
    rows.append(loop_row(f"punch 3 x 3 cm, tet block {box.n_vertices:,} nodes", tc, top, np.array([0.0, 0.0, 1.0]), 0.001,
                         seconds, punch.reach + 0.01))
    print_table(["tool", "contact points (mean)", "ticks", "ticks in contact", "skipped", "step p50 (us)",
                 "p99 (us)", "max (us)", "ticks in"], rows)

    # sliding over the whole organ, nothing prepared: a step that meets vertices nobody prepared
    # computes their columns (sparse solves, ms) itself; with the lookahead a background thread has
    # done it
    R, depth, speed = 0.01, 0.004, 0.02
    path = surface_path(mesh, R - depth)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    up = np.array([0.0, 0.0, 1.0])
    lower, travel = 1.5, arc[-1] / speed

    def slide(time_s):  # from 3 cm above the first point down onto it in 1.5 s, then along the path
        if time_s < lower:
            return path[0] + 0.03 * (1.0 - time_s / lower) * up
        s = min((time_s - lower) * speed, arc[-1])
        return np.array([np.interp(s, arc, path[:, i]) for i in range(3)])

    seconds = lower + travel + 0.2
    rows = []
    for lookahead, label in ((0.0, "lookahead 0 (prepared in the loop)"), (None, "default lookahead (background)")):
        tc = rt.ToolContact(mesh, sim(), rt.Tool.sphere(R), stiffness=200.0, lookahead=lookahead)
        here, counts, update = [], [], tc.update

        def counted(p, tc=tc, update=update, here=here, counts=counts):
            f = update(p)
            here.append(tc._block.prepared_here)
            counts.append(tc.contacts)
            return f

        tc.update = counted
        stats = rt.HapticLoop(tc, rt.ScriptedDevice(slide)).run(seconds)
        c = np.asarray(stats.compute) * 1e6
        k = min(c.size, len(here))
        met = np.asarray(here[:k]) > 0
        touching = np.asarray(counts[:k]) > 0
        rows.append([label, f"{stats.steps}", f"{int(touching.sum())}", f"{int(met.sum())}",
                     f"{tc._block.preparer.background}", f"{stats.missed}", f"{np.median(c):.0f}",
                     f"{np.percentile(c, 99):.0f}", f"{c.max():.0f}", f"{np.median(c[:k][met]):.0f}" if met.any() else "-"])
    print()
    print_table([f"slide: 1 cm sphere 4 mm deep along the liver's top, {arc[-1] * 100:.0f} cm at 2 cm/s, nothing "
                 "prepared", "ticks", "ticks in contact", "ticks that prepared vertices", "prepared in the background",
                 "skipped", "step p50 (us)", "p99 (us)", "max (us)", "median of the preparing ticks (us)"], rows)


def surface_path(mesh, offset: float, step: float = 0.001) -> np.ndarray:
    """Points ``offset`` above the organ's top (along the interpolated vertex normals), on the line
    over it from one end to the other along x through its middle: rays cast down (-z) onto the
    triangles every ``step`` m, the highest hit kept, where the surface faces up (n_z >= 0.3); (k, 3)."""
    X, T = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    N = mesh.vertex_normals()
    A, B, C = X[T[:, 0]], X[T[:, 1]], X[T[:, 2]]
    e1, e2 = B - A, C - A
    down = np.array([0.0, 0.0, -1.0])
    p = np.cross(down, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-14
    y = 0.5 * (X[:, 1].min() + X[:, 1].max())
    top = X[:, 2].max() + 0.1
    out = []
    for x in np.arange(X[:, 0].min() + step, X[:, 0].max(), step):
        o = np.array([x, y, top])
        s = o - A
        u = np.einsum("ij,ij->i", s, p) / np.where(ok, det, 1.0)
        q = np.cross(s, e1)
        v = (q @ down) / np.where(ok, det, 1.0)
        t = np.einsum("ij,ij->i", e2, q) / np.where(ok, det, 1.0)
        hit = np.flatnonzero(ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0))
        if hit.size == 0:
            continue
        j = hit[np.argmin(t[hit])]  # the first surface from above: the top
        w = np.array([1.0 - u[j] - v[j], u[j], v[j]])
        n = w @ N[T[j]]
        n /= np.linalg.norm(n)
        if n[2] < 0.3:  # the organ's steep ends (grazing rays): off the top
            if len(out):
                break
            continue
        out.append(o + t[j] * down + offset * n)
    return np.array(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--modes", type=int, default=40)
    ap.add_argument("--seconds", type=float, default=3.0)
    args = ap.parse_args()
    run(args.modes, args.seconds)


if __name__ == "__main__":
    main()
