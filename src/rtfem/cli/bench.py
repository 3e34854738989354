"""``rtfem bench``: time per step of the modal simulator against direct integration, measured now.

A compact version of ``benchmarks/dynamics.py`` for any mesh: for each r, the modal
precompute, the haptic step (one loaded node, its displacement read back), the full-field
step, and the direct Newmark step of the same model measured in the same run. Times are
medians over batches; the ratios are direct / modal.
"""

from __future__ import annotations

import statistics
import time


from ..mesh.selection import probe_vertex
from ..threads import runtime

from ..fe.material import Damping
from ..reduction.modal import modal_analysis
from ..drivers.fullorder import DirectSimulator
from ..drivers.modal import ModalSimulator


def per_step(fn, batch: int, batches: int = 5) -> float:
    """Median over ``batches`` of the mean time of ``batch`` calls of fn (s)."""
    times = []
    for _ in range(batches):
        t0 = time.perf_counter()
        for _ in range(batch):
            fn()
        times.append((time.perf_counter() - t0) / batch)
    return statistics.median(times)


def dynamics_table(model, modes_list, *, dt: float = 1e-3, damping: Damping | None = None,
                   direct_steps: int = 30, large: bool = False) -> list[dict]:
    """Per-step times of the modal simulator (haptic: one node; field: every node) against the
    direct Newmark step, measured now; ``large``: the warped modal simulator against the
    corotational full order."""
    damping = damping if damping is not None else Damping(alpha=8.0)
    node = probe_vertex(model)
    f = (0.0, 0.0, -0.1)
    t0 = time.perf_counter()
    direct = DirectSimulator(model, dt, damping, large_deformation=large)
    direct_setup = time.perf_counter() - t0
    with runtime():  # the run-time steps as a loop runs them: one BLAS thread (rtfem.threads)
        t_direct = per_step(lambda: direct.step({node: f}), max(1, direct_steps // 5))
    rows = []
    for r in modes_list:
        t0 = time.perf_counter()
        basis = modal_analysis(model, int(r))
        t_modes = time.perf_counter() - t0
        sim = ModalSimulator(basis, dt, damping, warping=large)

        def haptic():
            sim.step({node: f})
            sim.displacement(node)

        def full():
            sim.step({node: f})
            sim.displacements()

        with runtime():
            t_h = per_step(haptic, 2000)
            t_f = per_step(full, 50)
        rows.append({
            "vertices": model.n_nodes, "dof": model.n_dofs, "r": basis.n_modes, "modes_s": t_modes,
            "haptic_step_s": t_h, "field_step_s": t_f, "direct_step_s": t_direct, "direct_setup_s": direct_setup,
            "ratio_haptic": t_direct / t_h, "ratio_field": t_direct / t_f,
        })
    return rows


def _fmt(t: float) -> str:
    if t < 1e-3:
        return f"{t * 1e6:.1f} us"
    if t < 1.0:
        return f"{t * 1e3:.2f} ms"
    return f"{t:.2f} s"


def format_table(headers: list[str], rows: list[list[object]]) -> str:
    """A Markdown table, columns right-aligned."""
    cells = [[str(h) for h in headers]] + [[str(c) for c in r] for r in rows]
    widths = [max(len(c[i]) for c in cells) for i in range(len(headers))]
    line = lambda c: "| " + " | ".join(x.rjust(w) for x, w in zip(c, widths)) + " |"  # noqa: E731
    return "\n".join([line(cells[0]), "|" + "|".join("-" * (w + 2) for w in widths) + "|"] + [line(c) for c in cells[1:]])


def print_table(rows: list[dict]) -> None:
    headers = ["vertices", "dof", "r", "modes (precompute)", "modal haptic step", "modal field step",
               "direct Newmark step", "direct / haptic", "direct / field"]
    print(format_table(headers, [[f"{r['vertices']:,}", f"{r['dof']:,}", r["r"], _fmt(r["modes_s"]),
                                  _fmt(r["haptic_step_s"]), _fmt(r["field_step_s"]), _fmt(r["direct_step_s"]),
                                  f"{r['ratio_haptic']:,.0f}x", f"{r['ratio_field']:,.0f}x"] for r in rows]))
