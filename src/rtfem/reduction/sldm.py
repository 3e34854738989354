"""Spectral Lanczos decomposition (SLDM): explicit time- and frequency-domain responses.

Paper section 4 (after Druskin & Knizhnerman 1994, Zunoubi et al. 1998). With the massless
rotations condensed out (Eq. 5, sparse route), y = M^1/2 u, K' = M^-1/2 K_c M^-1/2 and
F' = M^-1/2 F, the damped system y'' + B'(K') y' + K' y = F' H(t) is solved by a function
of K' applied to F':

    y(t) = f(K', t) F',      f(lam, t) = x(t) of x'' + a(lam) x' + lam x = H(t) from rest,

with a(lam) = alpha + beta lam + 2 zeta sqrt(lam) (mass-, stiffness- or modally damped). The
Lanczos process (Eq. 19) with q1 = F'/|F'| gives K' Q_m ~ Q_m T_m, T_m = V Lambda V^T (Eq. 20),
and the response for *every* time from one basis (Eq. 21, corrected):

    y_m(t) = beta0 Q_m V f(Lambda, t) V^T e1,     beta0 = |F'|.

The printed Eq. 18 and 21 drop the t in exp(-alpha t/2), flip the sign of the sine term,
scale by F_o instead of beta0 and take Q square; the closed form used here is derived in
:mod:`rtfem.reduction.oscillator` and checked against an ODE solver in the tests. Frequency responses
come from the same basis with f(lam, w) = 1 / (lam - w^2 + i w a(lam)).

The Krylov dimension m is chosen adaptively. m0 = t_max sqrt(theta_max) / 2 (theta_max the
largest Ritz value) is the dimension at which a polynomial in K' can follow cos(t sqrt(lam))
over the whole spectrum; a load that barely excites the top of the spectrum converges
earlier (measured on the liver: 0.6-0.7 m0), so at least m0/2 steps are run and then more
until the difference estimate |z_m - [z_{m-p}; 0]| (p = max(5, m/8)) is below ``tol``
relative to the response at every requested time or frequency.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import scipy.linalg as sla

from .. import validate
from ..errors import ModelError, RtfemWarning
from .lanczos import REORTHOGONALIZATIONS, Lanczos
from ..fe.material import Damping
from ..fe.protocol import check_model, require_lumped_mass
from .oscillator import step_response as _step_fn
from ..io.scenario import LoadSchedule

__all__ = ["SLDM", "SLDMInfo"]

_ROUNDOFF = 1e-11  # floor of the error estimate: the accuracy of forming y_m in double precision


@dataclass
class SLDMInfo:
    """What the last SLDM evaluation did."""

    m: int  # Krylov dimension used
    m0: int  # the a-priori estimate t_max sqrt(theta_max)/2 (0 for frequency responses); the error estimate
    #          often stops the basis earlier (the damped response forgets the stiffest modes)
    estimate: float  # relative error estimate (difference of z_m and z_{m-p})
    residual: float  # relative Lanczos residual beta0 beta_m |e_m^T z_m| at its worst time
    theta_max: float  # largest Ritz value of K' (rad^2/s^2)
    breakdown: bool  # an invariant subspace was found: the answer is exact
    lanczos_seconds: float
    evaluate_seconds: float
    reorth: str
    orthogonality: float  # max |Q^T Q - I| (computed when check_orthogonality=True)

    def __str__(self) -> str:
        return (
            f"SLDM: m = {self.m} (a-priori estimate m0 = {self.m0}), error estimate {self.estimate:.1e}, "
            f"{'breakdown (exact), ' if self.breakdown else ''}Lanczos {self.lanczos_seconds * 1e3:.1f} ms, "
            f"evaluation {self.evaluate_seconds * 1e3:.1f} ms"
        )


class SLDM:
    """Spectral Lanczos decomposition of a restrained (or free) shell model.

    Parameters
    ----------
    model : a :class:`~rtfem.ShellModel` with fixes by elimination (a penalty multiplies the
        stiffest eigenvalue by the penalty factor and with it the Krylov dimension).
    damping : :class:`~rtfem.Damping` (alpha, beta and/or a scalar zeta).
    tol : default relative accuracy of the responses.
    m : fix the Krylov dimension instead of choosing it adaptively.
    m_max : cap of the adaptive Krylov dimension (default 3000).
    reorth : "cgs2" (classical Gram-Schmidt twice, default) or "householder" (the paper's).
    progress : ``progress(done, total, message)`` as the Krylov basis grows: its dimension m and
        the dimension expected (which grows when the estimate is short).

    Raises
    ------
    ModelError
        A model that is not one (or needs a lumped mass: SLDM takes M^-1/2), damping that is not
        an :class:`~rtfem.Damping`, tol, m or m_max out of range, an unknown reorth.

    Warns
    -----
    RtfemWarning
        When evaluated: the Krylov dimension reaches m_max before the error estimate meets tol
        (the message gives the estimate and what to change).
    """

    def __init__(
        self,
        model,
        damping: Damping | None = None,
        *,
        tol: float = 1e-6,
        m: int | None = None,
        m_max: int = 3000,
        reorth: str = "cgs2",
        progress: Callable[[int, int, str], None] | None = None,
    ) -> None:
        check_model(model)
        if damping is not None and not isinstance(damping, Damping):
            raise ModelError(f"damping={validate.show(damping)} must be an rt.Damping (or None)")
        validate.choice(reorth, "reorth", REORTHOGONALIZATIONS)
        tol = self._check_tol(tol)
        m = None if m is None else validate.count(m, "m", 1, 100_000, what="the Krylov dimension")
        m_max = validate.count(m_max, "m_max", 1, 100_000, what="the largest Krylov dimension")
        model.check_not_all_fixed()
        if model.constraints != "elimination":
            raise ModelError(
                "SLDM needs fixes by elimination: a penalty adds eigenvalues ~penalty times the "
                "stiffness, and the Krylov dimension grows with their square root. Build the model "
                "with constraints='elimination'"
            )
        self.model = model
        self.damping = damping if damping is not None else Damping()
        if isinstance(self.damping.zeta, tuple):
            raise ModelError("SLDM takes a single modal damping ratio zeta (it has no modes to give ratios to)")
        if reorth not in REORTHOGONALIZATIONS:
            raise ModelError(f"reorth={reorth!r}; choose one of {REORTHOGONALIZATIONS}")
        self.tol = self._check_tol(tol)
        self.m = None if m is None else int(m)
        if self.m is not None and self.m < 1:
            raise ModelError(f"m={m} must be >= 1")
        self.m_max = int(m_max)
        self.reorth = reorth
        self.progress = validate.progress(progress)
        self.restrained = bool(model.fixed.any())
        t0 = time.perf_counter()
        require_lumped_mass(model, "SLDM")  # M^-1/2 of the lumped mass (Eq. 12); a Cholesky of M is not built
        self._c = model.condensation()
        self._t = self._c.t
        mt = model.mass_diagonal[self._t]
        if np.any(mt <= 0):
            raise ModelError("every free translation needs mass for SLDM (a vertex without triangles?)")
        self._s = 1.0 / np.sqrt(mt)  # M^-1/2
        self.setup_seconds = time.perf_counter() - t0
        self.last_info: SLDMInfo | None = None
        self.matvecs = 0

    @staticmethod
    def _check_tol(tol) -> float:
        return validate.in_range(tol, "tol", 0.0, 1.0, lo_open=True, hi_open=True, what="a relative accuracy")

    # ---------------------------------------------------------------- operators
    def apply(self, y: np.ndarray) -> np.ndarray:
        """K' y = M^-1/2 K_c M^-1/2 y with K_c = K_tt - K_tr K_rr^-1 K_rt (Eq. 5, never formed)."""
        self.matvecs += 1
        return self._s * self._c.apply(self._s * y)

    def _load(self, forces) -> np.ndarray:
        """F' = M^-1/2 (F_t - K_tr K_rr^-1 F_r): the condensed, mass-scaled load."""
        return self._s * self._c.load(self.model.force_vector(forces))

    def _alpha_of(self, lam: np.ndarray) -> np.ndarray:
        return self.damping.alpha_of_eigenvalue(lam)

    def _displacements(self, L: Lanczos, z: np.ndarray) -> np.ndarray:
        """u = M^-1/2 beta0 Q_m z for every column of z: (k, n, 3) nodal translations.

        Filled in chunks of samples so that no (k, 6n) temporary is formed.
        """
        k = z.shape[1]
        out = np.zeros((k, 3 * self.model.n_nodes), dtype=z.dtype)
        dpn = self.model.dofs_per_node
        idx = (self._t // dpn) * 3 + self._t % dpn
        Q = L.Q
        chunk = max(1, int(2**24 // max(Q.shape[0], 1)))
        for c in range(0, k, chunk):
            Y = Q @ (L.beta0 * z[:, c : c + chunk])  # (n_t, chunk)
            out[c : c + chunk, idx] = (Y * self._s[:, None]).T
        return out.reshape(k, -1, 3)

    # ---------------------------------------------------------------- the Krylov machinery
    def _krylov(self, b: np.ndarray, coefficients: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray],
                n_samples: int, t_max: float, tol: float, m_fixed: int | None) -> tuple[Lanczos, np.ndarray, SLDMInfo]:
        """Grow a Lanczos basis until the reduced response z_m (m x k) has converged.

        ``coefficients(lam, v0, sel)`` gives f(lam, sample) * v0 for the samples ``sel``. The
        convergence checks use at most 128 samples spread evenly (the last one included);
        the returned z_m covers all of them.
        """
        every = np.arange(n_samples)
        check = np.unique(np.linspace(0, n_samples - 1, min(n_samples, 128)).round().astype(int))
        t0 = time.perf_counter()
        L = Lanczos(self.apply, b, self.reorth, capacity=64)
        target = m_fixed if m_fixed is not None else None
        first = min(10, target or 10)
        L.extend(first)
        estimate = float("nan")
        m0 = 0
        z = None
        while True:
            a, bt = L.tridiagonal()
            lam, V = _eig_tridiagonal(a, bt)
            theta_max = float(lam.max())
            m0 = int(math.ceil(t_max * math.sqrt(max(theta_max, 0.0)) / 2)) if t_max > 0 else 0
            m = L.m
            z = V @ coefficients(lam, V[0], check)  # (m, k_check)
            if L.breakdown:
                estimate = 0.0
                break
            estimate = _difference_estimate(a, bt, z, coefficients, check, estimate)
            if self.progress is not None:
                self.progress(m, max(m, m0 // 2, target or 0, 10), f"Lanczos m = {m}, error estimate {estimate:.1e}")
            if target is not None:
                if m >= target:
                    break
                L.extend(target - m)
                continue
            # m0 over-estimates what a load that barely excites the top of the spectrum needs
            # (measured: 0.6-0.7 m0 on the liver), so only half of it is a hard floor and the
            # difference estimate decides the rest
            if m >= max(m0 // 2, 10) and estimate < tol:
                break
            if m >= self.m_max or m >= b.size:
                warnings.warn(
                    f"SLDM stopped at m = {m} (m_max) with an error estimate of {estimate:.1e} > tol = {tol:.1e}; "
                    "raise m_max, loosen tol, or shorten the time horizon",
                    RtfemWarning,
                    stacklevel=4,
                )
                break
            grow = max(5, m // 16)
            if m < m0 // 2:
                grow = max(grow, min(m0 // 2 - m, 200))
            L.extend(min(grow, self.m_max - m))
        z = V @ coefficients(lam, V[0], every)  # lam, V: T_m of the last pass of the loop
        # below ~1e-11 the difference estimate measures round-off, not truncation
        estimate = max(estimate, _ROUNDOFF) if np.isfinite(estimate) else estimate
        # rigorous-style residual beta0 beta_m |e_m^T z_m(t)|, relative to |z_m|
        scale = np.linalg.norm(z, axis=0).max()
        residual = float(L.last_beta * np.abs(z[-1]).max() / scale) if scale > 0 else 0.0
        info = SLDMInfo(m=L.m, m0=m0, estimate=estimate, residual=residual, theta_max=theta_max,
                        breakdown=L.breakdown, lanczos_seconds=time.perf_counter() - t0, evaluate_seconds=0.0,
                        reorth=self.reorth, orthogonality=float("nan"))
        return L, z, info

    # ---------------------------------------------------------------- public responses
    def step_response(self, forces, times: Sequence[float], *, tol: float | None = None, m: int | None = None,
                      check_orthogonality: bool = False) -> np.ndarray:
        """Displacements (len(times), n, 3) for ``forces`` switched on at t = 0 and held.

        Eq. 17-21 (corrected), every time from one Krylov basis. ``tol`` and ``m`` override the
        defaults; :attr:`last_info` reports the Krylov dimension and the error estimate.
        """
        times = self._times(times)
        tol = self.tol if tol is None else self._check_tol(tol)
        m = None if m is None else validate.count(m, "m", 1, 100_000, what="the Krylov dimension")
        b = self._load(forces)
        if not np.any(b):
            return np.zeros((times.size, self.model.n_nodes, 3))

        def coefficients(lam, v0, sel):
            a = self._alpha_of(lam)
            return _step_fn(lam[:, None], a[:, None], times[sel][None, :]) * v0[:, None]

        L, z, info = self._krylov(b, coefficients, times.size, float(times.max()), tol, m if m is not None else self.m)
        t0 = time.perf_counter()
        U = self._displacements(L, z)
        info.evaluate_seconds = time.perf_counter() - t0
        if check_orthogonality:
            info.orthogonality = L.orthogonality_loss()
        self.last_info = info
        return U

    def frequency_response(self, forces, frequencies: Sequence[float], *, tol: float | None = None,
                           m: int | None = None) -> np.ndarray:
        """Steady-state complex amplitudes (len(frequencies), n, 3) of u under F e^{i w t}.

        Solves (K - w^2 M + i w B) u = F for every frequency (in Hz) from one Krylov basis:
        u = M^-1/2 beta0 Q V diag(1 / (lam - w^2 + i w a(lam))) V^T e1.
        """
        f = validate.times(frequencies, "frequencies", bound="nonnegative", increasing=False)
        m = None if m is None else validate.count(m, "m", 1, 100_000, what="the Krylov dimension")
        if not self.restrained and np.any(f == 0):
            raise ModelError("an unconstrained model has no static (0 Hz) response: fix some nodes")
        w = 2 * np.pi * f
        tol = self.tol if tol is None else self._check_tol(tol)
        b = self._load(forces)

        def coefficients(lam, v0, sel):
            a = self._alpha_of(lam)
            ws = w[sel]
            return v0[:, None] / (lam[:, None] - ws[None, :] ** 2 + 1j * ws[None, :] * a[:, None])

        L, z, info = self._krylov(b, coefficients, w.size, 0.0, tol, m if m is not None else self.m)
        t0 = time.perf_counter()
        U = self._displacements(L, z)
        info.evaluate_seconds = time.perf_counter() - t0
        self.last_info = info
        return U

    def response(self, forces_of_time, times: Sequence[float], *, tol: float | None = None) -> np.ndarray:
        """Displacements (len(times), n, 3) under a piecewise-constant force history (Duhamel).

        ``forces_of_time``: a :class:`~rtfem.io.scenario.LoadSchedule`, or a sequence of
        ``(t_k, forces_k)`` with increasing t_k; the load is ``forces_k`` from t_k until t_{k+1}
        and zero before t_0. The history is the sum of the
        step responses of its jumps F_k - F_{k-1}, each delayed to t_k; jumps along the same
        spatial pattern share one Krylov basis (a scalar force profile needs only one).
        """
        times = self._times(times, allow_negative=True)
        tol = self.tol if tol is None else self._check_tol(tol)
        if isinstance(forces_of_time, LoadSchedule):
            forces_of_time = forces_of_time.piecewise()
        events = validate.entries(forces_of_time, "forces_of_time", "entry of forces_of_time", 2,
                                  "a (t_k, forces_k) pair (or give a LoadSchedule)")
        if not events:
            raise ModelError("forces_of_time is empty: give a sequence of (t_k, forces_k)")
        t_k = np.array([validate.number(e[0], "switch time t_k", "a time in seconds") for e in events])
        if not np.all(np.isfinite(t_k)) or np.any(np.diff(t_k) <= 0):
            raise ModelError("the switch times t_k of forces_of_time must be finite and strictly increasing")
        loads = [self._load(e[1]) for e in events]
        jumps = [loads[0]] + [loads[k] - loads[k - 1] for k in range(1, len(loads))]
        # group parallel jumps: one Krylov basis per spatial pattern
        patterns: list[tuple[np.ndarray, list[tuple[float, float]]]] = []
        for tk, j in zip(t_k, jumps):
            nj = np.linalg.norm(j)
            if nj == 0:
                continue
            for pat, uses in patterns:
                c = float(pat @ j)
                if abs(abs(c) - nj) <= 1e-12 * nj:
                    uses.append((tk, c))
                    break
            else:
                patterns.append((j / nj, [(tk, nj)]))
        U = np.zeros((times.size, self.model.n_nodes, 3))
        infos = []
        for pat, uses in patterns:
            delays = np.array([u[0] for u in uses])
            scales = np.array([u[1] for u in uses])
            horizon = float(times.max() - delays.min())
            if horizon <= 0:
                continue
            tau = np.clip(times[None, :] - delays[:, None], 0.0, None)  # (jumps, k)
            active = (times[None, :] > delays[:, None]).astype(float)

            def coefficients(lam, v0, sel, tau=tau, active=active, scales=scales):
                a = self._alpha_of(lam)
                g = _step_fn(lam[:, None, None], a[:, None, None], tau[None, :, sel])  # (m, jumps, k)
                return np.einsum("mjk,j,jk->mk", g, scales, active[:, sel]) * v0[:, None]

            L, z, info = self._krylov(pat, coefficients, times.size, horizon, tol, self.m)
            U += self._displacements(L, z)
            infos.append(info)
        if infos:
            worst = max(infos, key=lambda i: i.estimate if np.isfinite(i.estimate) else -1)
            worst.m = max(i.m for i in infos)
            self.last_info = worst
        return U

    @staticmethod
    def _times(times, allow_negative: bool = False) -> np.ndarray:
        return validate.times(times, "times", bound="any" if allow_negative else "nonnegative")


def _difference_estimate(a, bt, z, coefficients, check, previous: float) -> float:
    """The error estimate of z_m: its change against the reduced response of T_{m-p} (p = m/8,
    at least 5); ``previous`` when m is too small to compare."""
    m = a.size
    p = max(5, m // 8)
    if m <= p:
        return previous
    lam2, V2 = _eig_tridiagonal(a[: m - p], bt[: m - p - 1])
    z2 = V2 @ coefficients(lam2, V2[0], check)
    diff = np.abs(z.copy())
    diff[: m - p] = np.abs(z[: m - p] - z2)
    scale = np.linalg.norm(z, axis=0).max()
    return float(np.linalg.norm(diff, axis=0).max() / scale) if scale > 0 else 0.0


def _eig_tridiagonal(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if a.size == 1:
        return a.copy(), np.ones((1, 1))
    return sla.eigh_tridiagonal(a, b)
