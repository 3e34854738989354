"""The elements whose Prony history the reduced nonlinear step carries (:class:`rtfem.ReducedNonlinearSimulator`
with a relaxing law, issue 41; or a solid whose regions have laws of their own, some relaxing, issue 58).

With one :class:`~rtfem.Prony` law every force element (the cubature's, or all of them) carries its
history. With regions, only the elements of a relaxing region do, each region with its own law and its
own segment of the one history array; the elements of the other regions give their elastic forces as
in a step without history. The step is linearized about the instantaneous laws of the relaxing regions
and the rest tangents of the others (at least as stiff as the step's algorithmic tangent, so the
linearly implicit step stays stable).
"""

from __future__ import annotations

import numpy as np

__all__ = ["ViscousTerms", "viscous_terms"]


def viscous_terms(red, cubature: bool):
    """The :class:`ViscousTerms` of reduced model ``red`` (its cubature's elements, or all of them), or None
    when no law of it relaxes."""
    from ..fe.viscoelastic import Prony

    laws = [red.law] if red.law is not None else [law for _, law in getattr(red.system.kernel, "laws", None) or ()]
    return ViscousTerms(red, cubature) if any(isinstance(law, Prony) for law in laws) else None


class ViscousTerms:
    """The force elements of a reduced model with a relaxing law (see the module).

    ``parts``: [(element data (five arrays), weights, the region's Prony law)] that carry a history,
    ``elastic``: (element data, weights) of the other regions' elements, or None; ``bounds``: each
    part's segment of the history (``size`` floats in all); ``Kc`` (r, r): the step's linearization."""

    def __init__(self, red, cubature: bool) -> None:
        from ..fe.viscoelastic import Prony, history_size

        data, w = red._cubature if cubature else (red._element_data(), np.ones(red.system.cells.shape[0]))
        if isinstance(red.law, Prony):
            self.parts, self.elastic = [(tuple(data[:5]), w, red.law)], None
        else:
            groups, rest, self.parts = data[5], np.ones(w.size, dtype=bool), []
            for g, (_, law) in enumerate(red.system.kernel.laws):
                sel = np.flatnonzero(groups == g)
                if isinstance(law, Prony) and sel.size:
                    rest[sel] = False
                    self.parts.append((tuple(np.ascontiguousarray(a[sel]) for a in data[:5]), w[sel], law))
            sel = np.flatnonzero(rest)
            self.elastic = (tuple(np.ascontiguousarray(a[sel]) for a in data), w[sel]) if sel.size else None
        sizes = [history_size(law, d[2].shape[1], ww.size) for d, ww, law in self.parts]
        self.bounds = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
        self.size = int(self.bounds[-1])
        # each part's rest tangents (the relaxing regions' with their instantaneous laws), and their sum projected
        self.rest = [red._element_tangents(np.zeros(d[0].shape[:2]), d, law=law.instantaneous) for d, _, law in self.parts]
        if self.elastic is not None:
            self.rest.append(red._element_tangents(np.zeros(self.elastic[0][0].shape[:2]), self.elastic[0]))
        Kc = sum(_projected(d, ww, Ke) for (d, ww), Ke in zip(self._all(), self.rest))
        self.Kc = 0.5 * (Kc + Kc.T)
        self.whole = cubature and isinstance(red.law, Prony)  # one law over the whole cubature

    def _all(self):
        """(element data, weights) of each part, the elastic one last."""
        return [(d, ww) for d, ww, _ in self.parts] + ([self.elastic] if self.elastic is not None else [])

    def tangent(self, red, q: np.ndarray, single: bool) -> np.ndarray:
        """The step's tangent at coordinates q (r, r): ``Kc`` plus each part's change from rest (one law's
        over the whole cubature with its rows, in ``single`` precision where the simulator runs so)."""
        laws = [law.instantaneous for _, _, law in self.parts] + [None] * (self.elastic is not None)
        rows = red.cubature_rows(single) if self.whole else None
        return self.Kc + sum(red.tangent_change(q, d, ww, Ke, rows, law=law)
                             for (d, ww), Ke, law in zip(self._all(), self.rest, laws))

    def forces(self, red, q: np.ndarray, history: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """(the reduced forces (r,) of a step dt from ``history`` to coordinates q, the history that step
        leaves): each relaxing region's algorithmic forces, and the other regions' elastic ones."""
        g, new = np.zeros(red.size), np.empty_like(history)
        for (d, w, law), lo, hi in zip(self.parts, self.bounds[:-1], self.bounds[1:]):
            f, new[lo:hi] = red.viscous_forces(q, d, w, history[lo:hi], dt, law=law)
            g += f
        if self.elastic is not None:
            g += red._element_forces(q, *self.elastic, False)[0]
        return g, new


def _projected(d, w: np.ndarray, Ke: np.ndarray) -> np.ndarray:
    """sum_e w_e U_e^T K_e U_e (r, r)."""
    return np.einsum("eir,eij,ejs->rs", d[0] * w[:, None, None], Ke, d[0], optimize=True)
