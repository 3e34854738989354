"""Modal analysis: the lowest eigenpairs of K phi = w^2 M phi (paper section 3, Eq. 8).

The generalized eigenproblem is solved on the sparse constrained matrices by shift-invert
Lanczos with the model's sparse factorization as the operator: a block Lanczos of our own
(lanczos.block_eigs: 8 right-hand sides per solve, which a supernodal solver does for about
the cost of 3) where K - sigma M is positive definite, ARPACK (``scipy.sparse.linalg.eigsh``)
otherwise. The rotations are massless, so M is only semi-definite: the eigenvalues
found are exactly those of the condensed stiffness of Eq. 5 (K_c phi_t = w^2 M_t phi_t),
without forming K_c. Unconstrained models are shifted below zero so that their six
rigid-body modes come first.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import time
from pathlib import Path
from typing import Callable

import numpy as np

from .. import validate
from ..errors import ModelError, SolverError
from ..storage import load_versioned, save_versioned
from .lanczos import BlockLanczosFailed, block_eigs
from ..fe.linalg import factorize
from ..threads import blas_limits
from ..fe.protocol import check_model, is_diagonal
from ..mesh.surface import TriMesh

__all__ = ["ModalBasis", "modal_analysis", "mesh_fingerprint"]

FORMAT_VERSION = 1
SOLVERS = ("auto", "block", "arpack")
_BLOCK = 8  # right-hand sides per block solve (benchmarks/eigen.py: 4, 8, 12, 16 measured)
_BLOCK_TOL = 1e-10  # the block method's relative Ritz residual
_DENSE_ALL = 3000  # "all" modes through a dense eigensolver up to this many massed dofs


def model_key(model) -> str:
    """A hash of what a basis depends on besides the mesh: the supports (which dofs are fixed), the
    material and the model's kind (:attr:`metadata`). A saved basis records it, so that it does not
    load onto the same mesh held or made otherwise."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(np.asarray(model.fixed, dtype=bool)).tobytes())
    material = None if getattr(model, "materials", None) else getattr(model, "material", None)  # regions: metadata
    h.update(repr(tuple(float(getattr(material, k, 0.0)) for k in ("E", "nu", "thickness", "density"))).encode())
    h.update(json.dumps(getattr(model, "metadata", {}), sort_keys=True, default=str).encode())
    return h.hexdigest()[:32]


def check_model_key(info: dict, model, what: str) -> None:
    """Refuse ``model`` when ``info`` (a basis's) records another :func:`model_key`."""
    key = info.get("model_key")
    if key is not None and key != model_key(model):
        raise ModelError(f"{what} was computed for this mesh with other supports, material or model settings than "
                         "the model given: recompute it with rt.modal_analysis(model, ...) (or fix the model as it was)")


def mesh_fingerprint(mesh: TriMesh) -> str:
    """A hash of the mesh arrays: a saved basis refuses to load onto another mesh."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.triangles, dtype=np.int64).tobytes())
    return h.hexdigest()[:32]


class ModalBasis:
    """The r lowest modes of a model: w_i and mass-normalized translational shapes.

    Attributes
    ----------
    omega : (r,) circular frequencies in rad/s, ascending (Eq. 8).
    shapes : (n, 3, r) translational parts of the mass-normalized mode shapes
        (Phi^T M Phi = I; the rotations carry no mass).
    fingerprint : hash of the mesh the basis belongs to.
    model : the ShellModel it was computed from, when known (needed for the static
        correction); ``None`` after :meth:`load` without a model.

    Parameters
    ----------
    omega, shapes, fingerprint, model : as the attributes (:func:`~rtfem.modal_analysis` makes
        bases; :meth:`load` reads them).
    info : what the analysis recorded (solver, residuals, model key).

    Raises
    ------
    ModelError
        Shapes and frequencies that do not fit (count, finiteness, ascending order).
    """

    def __init__(self, omega: np.ndarray, shapes: np.ndarray, fingerprint: str, model=None, info: dict | None = None):
        omega = validate.real_array(omega, "omega", 1)
        if omega.size == 0:
            raise ModelError("omega is empty: a modal basis needs at least one mode")
        if np.any(omega < 0):
            raise ModelError(f"omega holds a negative frequency ({omega.min():.4g} rad/s); frequencies are >= 0")
        if np.any(np.diff(omega) < 0):
            i = int(np.flatnonzero(np.diff(omega) < 0)[0])
            raise ModelError(f"omega is not ascending (mode {i + 1}: {omega[i + 1]:.6g} after {omega[i]:.6g} rad/s)")
        shapes = validate.real_array(shapes, "shapes", 3)
        if shapes.shape[1] != 3 or shapes.shape[2] != omega.size or shapes.shape[0] == 0:
            raise ModelError(f"shapes must be (n, 3, {omega.size}) for {omega.size} frequencies in omega, got {shapes.shape}")
        if not isinstance(fingerprint, str):
            raise ModelError(f"fingerprint={validate.show(fingerprint)} must be a string (the mesh hash)")
        if model is not None:
            check_model(model)
            if model.n_nodes != shapes.shape[0]:
                raise ModelError(f"model={validate.show(model)} must be the model of this basis "
                                 f"({shapes.shape[0]} nodes)")
        if info is not None and not isinstance(info, dict):
            raise ModelError(f"info={validate.show(info)} must be a dict")
        self.omega = omega
        self.shapes = shapes
        self.fingerprint = fingerprint
        self.model = model
        self.info = dict(info or {})

    @property
    def n_modes(self) -> int:
        return self.omega.size

    @property
    def n_nodes(self) -> int:
        return self.shapes.shape[0]

    @property
    def frequencies(self) -> np.ndarray:
        """Natural frequencies in Hz."""
        return self.omega / (2 * np.pi)

    @property
    def eigenvalues(self) -> np.ndarray:
        """w^2 (rad^2/s^2)."""
        return self.omega**2

    @property
    def matrix(self) -> np.ndarray:
        """The shapes as a (3n, r) matrix (rows x0, y0, z0, x1, ...)."""
        return self.shapes.reshape(-1, self.n_modes)

    def truncated(self, n_modes: int) -> "ModalBasis":
        """The first ``n_modes`` modes."""
        n_modes = validate.count(n_modes, "n_modes", 1, self.n_modes, what=f"this basis has {self.n_modes} modes")
        return ModalBasis(self.omega[:n_modes].copy(), np.ascontiguousarray(self.shapes[:, :, :n_modes]), self.fingerprint,
                          self.model, self.info)

    def __repr__(self) -> str:
        f = self.frequencies
        return f"ModalBasis({self.n_modes} modes, {f[0]:.3g} .. {f[-1]:.3g} Hz, {self.n_nodes} nodes)"

    # ------------------------------------------------------------ files
    def save(self, path: str | os.PathLike) -> Path:
        """Save as a versioned ``.npz`` (no pickle)."""
        return save_versioned(path, "rtfem.ModalBasis", FORMAT_VERSION,
                              {"omega": self.omega, "shapes": self.shapes, "fingerprint": np.array(self.fingerprint)}, self.info)

    @classmethod
    def load(cls, path: str | os.PathLike, model=None, mesh: TriMesh | None = None) -> "ModalBasis":
        """Load a saved basis; with ``model`` (or ``mesh``) it must belong to that mesh."""
        z, info = load_versioned(path, "rtfem.ModalBasis", FORMAT_VERSION, ["omega", "shapes", "fingerprint"], "modal basis")
        omega, shapes, fp = z["omega"], z["shapes"], z["fingerprint"]
        if fp.dtype.kind != "U" or fp.ndim != 0:
            raise ModelError(f"{str(path)!r}: field 'fingerprint' is not a string: the file is damaged or altered")
        fp = str(fp)
        try:
            basis = cls(omega, shapes, fp, None, info)
        except ModelError as exc:
            raise ModelError(f"{str(path)!r}: {exc}; the file is damaged or altered") from None
        if model is not None:
            check_model(model)
        if mesh is not None and not isinstance(mesh, TriMesh):
            raise ModelError(f"mesh={validate.show(mesh)} must be a TriMesh (or None)")
        target = model.mesh if model is not None else mesh
        if target is not None:
            if shapes.shape[0] != target.n_vertices or fp != mesh_fingerprint(target):
                raise ModelError(
                    f"{str(path)!r} was computed for a different mesh ({shapes.shape[0]} nodes, "
                    f"fingerprint {fp[:8]}) than the one given ({target.n_vertices} nodes, "
                    f"fingerprint {mesh_fingerprint(target)[:8]}); recompute it with rt.modal_analysis"
                )
        if model is not None:
            check_model_key(info, model, repr(str(path)))
        basis.model = model
        return basis


def modal_analysis(
    model,
    n_modes: int | str = 20,
    *,
    sigma: float | None = None,
    tol: float = 0.0,
    solver: str = "auto",
    progress: Callable[[int, int, str], None] | None = None,
) -> ModalBasis:
    """The lowest ``n_modes`` eigenpairs of K phi = w^2 M phi (Eq. 8).

    Parameters
    ----------
    model : a :class:`~rtfem.ShellModel` (fixes applied by elimination or penalty).
    n_modes : number of modes, or "all" (dense solver; small models only).
    sigma : shift of the shift-invert iteration. Default: 0 for a restrained model (reusing
        the static factorization) and a small negative value for an unconstrained one, so
        that its six rigid-body modes come first.
    tol : relative residual |K x - w^2 M x| asked of the eigensolver, in its own norm (0: the
        default, machine precision for ARPACK and 1e-10 for the block method).
    solver : "auto" (the block method where it applies, else ARPACK), "block" (block
        shift-invert Lanczos: several right-hand sides per solve, needs sigma <= 0) or
        "arpack" (scipy's eigsh, one right-hand side per solve).
    progress : ``progress(done, total, message)``: solves done, an estimate of the solves
        needed (it may grow) and a one-line message; called at each step of the solve.

    Returns
    -------
    ModalBasis with ascending w, mass-normalized shapes (Phi^T M Phi = I).

    Raises
    ------
    ModelError
        A model that is not one, n_modes out of range (at least 1, fewer than the free dofs), an
        unknown solver, "block" with sigma > 0, a mechanism's zero-frequency modes on a model
        that is supposed to be held.
    SolverError
        The eigensolver does not converge, or the shifted matrix cannot be factorized.
    """
    check_model(model)
    if not (isinstance(n_modes, str) and n_modes == "all"):
        n_modes = validate.count(n_modes, "n_modes", 1, what="a number of modes, or 'all'")
    if sigma is not None:
        sigma = validate.number(sigma, "sigma", "a shift in rad^2/s^2")
    tol = validate.in_range(tol, "tol", 0.0, 1.0, hi_open=True, what="the eigensolver's relative accuracy, 0 for the default")
    solver = validate.choice(solver, "solver", SOLVERS)
    progress = validate.progress(progress)
    model.check_not_all_fixed()
    report = _Reporter(progress)
    t_start = time.perf_counter()
    K, dofs = model.constrained_stiffness()
    M, _ = model.constrained_mass()
    n_modes, massed = _mode_count(model, M, n_modes)
    timing: dict = {}
    if n_modes > 0.1 * massed and massed <= _DENSE_ALL:
        omega, phi = _dense_modes(model, K, M, dofs, n_modes)
        method = "dense"
    else:
        sigma = _default_shift(model, K, M) if sigma is None else sigma
        omega, phi, method = _shift_invert_modes(model, K, M, dofs, n_modes, sigma, tol, solver, report, timing)
    if model.fixed.any():  # a held model has no zero-frequency mode: one is a part moving freely
        free = _mechanism_modes(model, K, M, dofs, omega, phi)
        if free:
            raise ModelError(f"{free} of the modes have zero frequency although the model is held: the fixes cannot "
                             "hold it, a part can move freely (a mechanism, e.g. pieces joined at a single vertex or "
                             "edge). Fix more nodes, or join the pieces")
    shapes = _nodal_shapes(model, phi, dofs)
    elapsed = time.perf_counter() - t_start
    report.done(f"{omega.size} modes in {elapsed:.2f} s: {omega[0] / 2 / np.pi:.4g} .. {omega[-1] / 2 / np.pi:.4g} Hz")
    info = {"method": method, "seconds": elapsed, "sigma": float(sigma) if sigma is not None else 0.0,
            "model_key": model_key(model),
            **timing, **model.metadata}
    return ModalBasis(omega, np.ascontiguousarray(shapes), mesh_fingerprint(model.mesh), model, info)


def _mechanism_modes(model, K, M, dofs, omega: np.ndarray, phi: np.ndarray) -> int:
    """How many modes of a held model are a part moving freely: a mode whose stiffness per unit
    displacement, w^2 phi^T M phi / |phi|^2 = w^2 / |phi|^2 (mass-normalized), is round-off
    (below 1e-12, 4500 eps) of the largest stiffness on a free massed dof. Stiffness against
    stiffness: the mass does not enter the scale, so a graded mesh's tiny elements (a node of tiny
    mass has a huge K_ii / m_i) are not taken for a mechanism. Measured: two tets joined at a
    vertex 1e-17; the held shells of ../shared/data/organs 5e-10 and up (a 9 cm gallbladder at
    1.8 Hz, a 0.3 m small intestine at 0.025 Hz), which the former test (w^2 against 1e-10 of the
    largest K_ii / m_i) refused."""
    use = (M.diagonal() > 0) & ~np.asarray(model.fixed).reshape(-1)[dofs]  # (penalty constraints: not the held dofs)
    if not use.any():
        return 0
    stiffest = float(np.max(K.diagonal()[use]))
    return int(np.count_nonzero(omega**2 <= 1e-12 * stiffest * np.einsum("ij,ij->j", phi[use], phi[use])))


class _Reporter:
    """progress(done, total, message) with a total that grows when the estimate was short."""

    def __init__(self, progress) -> None:
        self.progress, self.done_count, self.total = progress, 0, 1

    def __call__(self, message: str, done: int | None = None, total: int | None = None) -> None:
        if self.progress is None:
            return
        if done is not None:
            self.done_count = done
        if total is not None:
            self.total = total
        self.total = max(self.total, self.done_count)
        self.progress(self.done_count, self.total, message)

    def done(self, message: str) -> None:
        self(message, self.total, self.total)


def _mode_count(model, M, n_modes) -> tuple[int, int]:
    """The number of modes asked for ("all" resolved) and the number of massed dofs."""
    massed = int(np.count_nonzero(M.diagonal()))
    if isinstance(n_modes, str):
        n_modes = massed - (int(model.fixed[:, :3].sum()) if model.constraints == "penalty" else 0)
        if massed > _DENSE_ALL:
            raise ModelError(f"n_modes='all' needs a dense eigensolver of size {massed}; ask for fewer modes")
    n_modes = int(n_modes)
    if n_modes > massed or (n_modes == massed and massed > _DENSE_ALL):
        raise ModelError(f"n_modes={n_modes} must be below the number of massed dofs ({massed})")
    return n_modes, massed


def _default_shift(model, K, M) -> float:
    """0 for a restrained model (reusing the static factorization); below the rigid-body modes
    for a free one, so that K - sigma M is positive definite."""
    if model.fixed.any():
        return 0.0
    d, m = K.diagonal(), M.diagonal()
    return -1e-6 * float(np.median(d[m > 0] / m[m > 0]))


def _shifted_factorization(model, K, M, dofs, sigma: float, report, timing: dict):
    """The model's factorization (sigma = 0, restrained) or one of K - sigma M; records its
    time and backend in ``timing``."""
    restrained = bool(model.fixed.any())
    report(f"factorizing the shifted stiffness ({K.shape[0]} dof, shift {sigma:.3g})")
    t_fac = time.perf_counter()
    if sigma == 0.0 and restrained:
        fac = model.factorization()
    else:
        try:
            fac = factorize((K - sigma * M).tocsc(), spd=sigma < 0 or restrained, what="K - sigma M",
                            order=lambda: model.dof_order(dofs))
        except SolverError as exc:
            raise ModelError(f"{exc}; try another sigma") from None
    timing["factorize_seconds"] = time.perf_counter() - t_fac
    timing["backend"] = fac.backend
    return fac


def _block_modes(model, K, M, dofs, fac, n_modes: int, sigma: float, tol: float, report, timing: dict):
    """Block shift-invert Lanczos (lanczos.block_eigs) on C = M^1/2 (K - sigma M)^-1 M^1/2 over
    the massed dofs: C y = theta y gives K x = (sigma + 1/theta) M x with x = (K - sigma M)^-1
    M^1/2 y / theta. Its massed rows are M^-1/2 C y / theta, which the Lanczos relation gives
    without another solve. Of its massless rows only translations are wanted (the shell's
    rotations are not part of a mode shape); where a model has massless translations, their
    rows of each block solve are kept and combined with the Ritz coefficients. Raises
    BlockLanczosFailed when the caller should use ARPACK instead."""
    m = M.diagonal()
    massed = np.flatnonzero(m > 0)
    massless = np.flatnonzero(m <= 0)
    wanted = massless[np.asarray(dofs)[massless] % model.dofs_per_node < 3]  # massless translations
    root = np.sqrt(m[massed])[:, None]
    n = K.shape[0]
    kept: list[np.ndarray] = []

    def apply(Y: np.ndarray) -> np.ndarray:
        B = np.zeros((n, Y.shape[1]), order="F")
        B[massed] = root * Y
        X = fac.solve(B)
        if wanted.size:
            kept.append(X[wanted])
        return root * X[massed]

    t0 = time.perf_counter()

    def progress(dim: int, estimate: int) -> None:
        report(f"block Lanczos: {dim} vectors, {time.perf_counter() - t0:.1f} s", dim, estimate)

    report(f"block shift-invert Lanczos for {n_modes} modes (block {_BLOCK})", 0, int(3.4 * n_modes))
    theta, _, stats = block_eigs(apply, massed.size, n_modes, block=_BLOCK, tol=tol or _BLOCK_TOL, report=progress,
                                 vectors=False)
    image = stats["image"]
    image /= root
    image /= theta
    if massed.size == n:  # a solid: every dof massed, the image is the whole vector
        vec = image
    else:
        vec = np.zeros((n, n_modes))
        vec[massed] = image
    if wanted.size:
        vec[wanted] = np.hstack(kept) @ (stats["coefficients"] / theta)
    timing["solve_seconds"] = stats["solve_seconds"]
    timing["lanczos_other_seconds"] = time.perf_counter() - t0 - timing["solve_seconds"]
    timing["solves"] = stats["block_solves"] * _BLOCK
    timing.update(block_solves=stats["block_solves"], block=_BLOCK, krylov_dim=stats["krylov_dim"],
                  reorthogonalized_blocks=stats["reorthogonalized"])
    lam = sigma + 1.0 / theta
    order = np.argsort(lam)
    return lam[order], vec[:, order], f"block shift-invert Lanczos ({stats['block_solves']} blocks of {_BLOCK})"


def _arpack_modes(K, M, fac, n_modes: int, sigma: float, tol: float, report, timing: dict):
    """ARPACK's shift-invert Lanczos (scipy eigsh) through the factorization."""
    import scipy.sparse.linalg as spla  # here: the block method's runs need not import it (issue 54)

    solve = fac.solve
    solve_time = [0.0]
    massed = int(np.count_nonzero(M.diagonal()))
    ncv = min(massed, max(2 * n_modes + 1, 20))
    count = [0]
    t0 = time.perf_counter()
    expected = 2 * ncv  # ARPACK typically needs 1.5-2 ncv solves

    def op(b: np.ndarray) -> np.ndarray:
        count[0] += 1
        report(f"Lanczos: {count[0]} solves, {time.perf_counter() - t0:.1f} s", count[0], max(expected, count[0] + 1))
        ts = time.perf_counter()
        x = solve(b)
        solve_time[0] += time.perf_counter() - ts
        return x

    report(f"shift-invert Lanczos for {n_modes} modes (ncv = {ncv})", 0, expected)
    try:
        lam, vec = spla.eigsh(K, k=n_modes, M=M, sigma=sigma, which="LM",
                              OPinv=spla.LinearOperator(K.shape, matvec=op, dtype=float), ncv=ncv, tol=tol)
    except spla.ArpackNoConvergence as exc:
        raise SolverError(
            f"ARPACK did not converge for {n_modes} modes ({len(exc.eigenvalues)} converged); "
            "ask for fewer modes or a looser tol"
        ) from None
    timing["solve_seconds"] = solve_time[0]
    timing["lanczos_other_seconds"] = time.perf_counter() - t0 - solve_time[0]
    timing["solves"] = count[0]
    order = np.argsort(lam)
    return lam[order], vec[:, order], f"shift-invert Lanczos ({count[0]} solves)"


def _shift_invert_modes(model, K, M, dofs, n_modes: int, sigma: float, tol: float, solver: str, report, timing: dict):
    """Shift-invert modes through the model's factorization (or one of K - sigma M): the block
    method where K - sigma M is positive definite and the problem is large enough for it, else
    (or when it stops short) ARPACK. ``timing`` receives the split: factorize, solves, and the
    rest of the iteration (orthogonalization, Ritz values, restarts), in seconds, and the backend."""
    fac = _shifted_factorization(model, K, M, dofs, sigma, report, timing)
    quiet = blas_limits(1, "openblas") if fac.backend == "pardiso" else contextlib.nullcontext()
    with quiet:  # MKL's threads do the solves; OpenBLAS's spinning workers would take their cores
        lam, vec, method = _iterate(model, K, M, dofs, fac, n_modes, sigma, tol, solver, report, timing)
    vec /= np.sqrt(np.einsum("ij,ij->j", vec, M @ vec))  # mass-normalize: Phi^T M Phi = I
    return np.sqrt(np.clip(lam, 0.0, None)), vec, method


def _iterate(model, K, M, dofs, fac, n_modes, sigma, tol, solver, report, timing):
    """The block method where it applies (falling back to ARPACK when it stops short), else ARPACK."""
    lam = vec = None
    if not is_diagonal(M):
        # the block method works on M^1/2 of a diagonal (lumped) mass; ARPACK's generalized
        # shift-invert mode takes a consistent M as it is
        if solver == "block":
            raise ModelError("solver='block' needs a diagonal (lumped) mass; this model's is consistent: use "
                             "solver='arpack' or 'auto'")
        timing["fallback"] = "consistent mass: ARPACK's generalized shift-invert mode"
    elif solver != "arpack" and (sigma < 0 or (sigma == 0.0 and model.fixed.any())):
        try:
            lam, vec, method = _block_modes(model, K, M, dofs, fac, n_modes, sigma, tol, report, timing)
        except BlockLanczosFailed as exc:
            if solver == "block":
                raise SolverError(f"block Lanczos: {exc}; use solver='arpack'") from None
            timing["fallback"] = str(exc)
    elif solver == "block":
        raise ModelError(f"solver='block' needs K - sigma M positive definite (sigma <= 0); got sigma = {sigma:g}")
    if lam is None:
        lam, vec, method = _arpack_modes(K, M, fac, n_modes, sigma, tol, report, timing)
    return lam, vec, method


def _nodal_shapes(model, phi: np.ndarray, dofs: np.ndarray) -> np.ndarray:
    """Mode shapes (n, 3, r) on the nodes, signed so that each mode's largest translation is
    positive, and exactly zero at dofs a penalty holds."""
    shapes = model.nodal_translations(phi, dofs)
    flat = shapes.reshape(-1, shapes.shape[2])
    sign = np.sign(flat[np.argmax(np.abs(flat), axis=0), np.arange(flat.shape[1])])
    shapes = shapes * sign
    if model.constraints == "penalty":
        # the penalty leaves ~1/penalty motion at fixed dofs: remove it so shapes vanish there
        shapes[model.fixed[:, :3]] = 0.0
    return shapes


def _dense_modes(model, K, M, dofs, n_modes):
    """All or many modes of a small model through the dense condensed problem (Eq. 5)."""
    import scipy.linalg as sla

    m = M.diagonal()
    massed = m > 0
    Kd = K.toarray()
    # condense the massless dofs (the rotations) exactly: K_c = K_mm - K_mz K_zz^-1 K_zm
    a, z = np.flatnonzero(massed), np.flatnonzero(~massed)
    Kc = Kd[np.ix_(a, a)]
    if z.size:
        Kc = Kc - Kd[np.ix_(a, z)] @ np.linalg.solve(Kd[np.ix_(z, z)], Kd[np.ix_(z, a)])
    Kc = 0.5 * (Kc + Kc.T)
    lam, v = sla.eigh(Kc, M[a][:, a].toarray(), subset_by_index=[0, n_modes - 1])  # lumped or consistent
    vec = np.zeros((K.shape[0], n_modes))
    vec[a] = v
    if z.size:
        vec[z] = -np.linalg.solve(Kd[np.ix_(z, z)], Kd[np.ix_(z, a)] @ v)
    return np.sqrt(np.clip(lam, 0.0, None)), vec
