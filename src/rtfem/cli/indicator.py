"""``rtfem simulate --method nonlinear``: the reduced model's error indicator recorded beside the run
(issue 56): :func:`rtfem.reduction.indicator.error_estimate` of the state every ``--error-every`` s
of simulated time and at the end, in ``error_estimate.csv`` (t, the largest estimate in m, its node,
the full-order residual in N)."""

from __future__ import annotations

from pathlib import Path

__all__ = ["ErrorRecord"]


class ErrorRecord:
    """The estimates of one run (nothing is recorded where ``every`` is 0 or the method is not the
    reduced nonlinear one)."""

    def __init__(self, model, folder, every: float, on: bool, sim) -> None:
        self.model, self.folder, self.every, self.sim = model, Path(folder), float(every), sim
        self.loads = None
        self.on = bool(on) and self.every > 0
        self.rows: list[tuple[float, float, int, float]] = []
        self._next = self.every

    def _estimate(self, t: float, loads) -> None:
        sim = self.sim
        from ..reduction.indicator import driver_inertia, error_estimate

        est = error_estimate(self.model, sim.displacements(), loads or None, inertia=driver_inertia(sim, self.model))
        self.rows.append((t, est.max_error, est.worst_node, est.residual))

    def maybe(self, t: float, loads) -> None:
        """After the step ending at ``t`` under ``loads`` ({node: force} or None)."""
        self.loads = loads
        if self.on and t + 1e-12 >= self._next:
            self._estimate(t, loads)
            while self._next <= t + 1e-12:
                self._next += self.every

    def close(self, t: float) -> str | None:
        """The estimate at the end (unless just taken), the file written; a line for the summary."""
        if not self.on:
            return None
        if not self.rows or self.rows[-1][0] < t - 1e-12:
            self._estimate(t, self.loads)
        path = self.folder / "error_estimate.csv"
        lines = ["t,max_error_m,worst_node,residual_N"] + [f"{a:.9g},{b:.9g},{c},{d:.9g}" for a, b, c, d in self.rows]
        path.write_text("\n".join(lines) + "\n")
        t_end, e, node, _ = self.rows[-1]
        peak = max(r[1] for r in self.rows)
        return (f"error       estimate {e * 1e3:.3g} mm at node {node} at the end, peak {peak * 1e3:.3g} mm "
                f"(the full order's residual of the state, every {self.every:g} s: {path})")
