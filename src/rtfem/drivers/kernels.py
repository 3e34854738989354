"""Compiled run-time kernels (numba), with the pure-Python definitions they are compiled from.

The haptic step of :class:`~rtfem.ModalSimulator` under one point load, and the read-back of one
node, are a few hundred flops; from numpy they cost microseconds of call overhead. Here they
are single compiled loops that release the GIL (``nogil``), evaluated in the same order as the
numpy path (C1 x + C2 v, then + G1 f, then + G0 f_old; no fused multiply-add), so both paths
give the same state to round-off. Without numba (``pip install numba``, part of
``rtfem[fast]``) ``HAVE_NUMBA`` is False and the simulators use numpy.

Signatures are given explicitly, so compilation happens once at import (cached on disk by
numba when the package folder is writable), never inside a force loop.
"""

from __future__ import annotations

import os

import numpy as np

__all__ = ["HAVE_NUMBA", "point_step", "point_displacement"]


def _point_step(coef, S, f_old, phi, node, fx, fy, fz, newmark):
    """One modal step under a force (fx, fy, fz) on ``node`` (node < 0: no load).

    coef (8, r): C1 (x, v), C2 (x, v), G1 (x, v), G0 (x, v) rows; S (2, r) state [x; v],
    updated in place; f_old (r,) the previous modal force (Newmark only); phi (n, 3, r).
    """
    r = S.shape[1]
    for j in range(r):
        f = 0.0
        if node >= 0:
            f = phi[node, 0, j] * fx + phi[node, 1, j] * fy + phi[node, 2, j] * fz
        x = S[0, j]
        v = S[1, j]
        xn = coef[0, j] * x + coef[2, j] * v
        vn = coef[1, j] * v + coef[3, j] * x
        xn = xn + coef[4, j] * f
        vn = vn + coef[5, j] * f
        if newmark:
            xn = xn + coef[6, j] * f_old[j]
            vn = vn + coef[7, j] * f_old[j]
            f_old[j] = f
        S[0, j] = xn
        S[1, j] = vn


def _point_displacement(phi, S, node, out):
    """out (3,) = phi[node] @ S[0]."""
    r = S.shape[1]
    a = 0.0
    b = 0.0
    c = 0.0
    for j in range(r):
        q = S[0, j]
        a += phi[node, 0, j] * q
        b += phi[node, 1, j] * q
        c += phi[node, 2, j] * q
    out[0] = a
    out[1] = b
    out[2] = c


HAVE_NUMBA = False
point_step = None
point_displacement = None
if os.environ.get("RTFEM_NUMBA", "1") != "0":
    try:
        import numba

        _opts = dict(cache=True, nogil=True, fastmath=False, error_model="numpy")
        point_step = numba.njit("void(f8[:, ::1], f8[:, ::1], f8[::1], f8[:, :, ::1], i8, f8, f8, f8, b1)",
                                **_opts)(_point_step)
        point_displacement = numba.njit("void(f8[:, :, ::1], f8[:, ::1], i8, f8[::1])", **_opts)(_point_displacement)
        HAVE_NUMBA = True
    except Exception:  # numba absent or unable to compile here: the numpy path is used
        HAVE_NUMBA = False
        point_step = point_displacement = None


def reference_step(coef: np.ndarray, S: np.ndarray, f_old: np.ndarray, phi: np.ndarray, node: int, force, newmark: bool):
    """The kernel's arithmetic in plain Python (for tests; slow)."""
    _point_step(coef, S, f_old, phi, int(node), float(force[0]), float(force[1]), float(force[2]), bool(newmark))


# ---------------------------------------------------------------------------------------------
# The haptic loop: whole probe ticks in compiled code, timed by the loop thread's own clock.

def _monotonic_clock():
    """libc's clock_gettime (the clock of time.perf_counter on Linux), callable from nopython
    code, or None where there is none (Windows)."""
    import ctypes
    import time

    if not hasattr(time, "CLOCK_MONOTONIC"):
        return None, None, None
    try:
        libc = ctypes.CDLL(None)
        gettime, usleep = libc.clock_gettime, libc.usleep
    except (OSError, AttributeError):
        return None, None, None
    gettime.argtypes, gettime.restype = [ctypes.c_int, ctypes.c_void_p], ctypes.c_int
    usleep.argtypes, usleep.restype = [ctypes.c_uint], ctypes.c_int
    return gettime, usleep, int(time.CLOCK_MONOTONIC)


def _knn(c, X, grid_lo, grid_h, dims, cell_start, cell_order, k, out, d2):
    """The k vertices of X nearest to c (ascending distance in d2, indices in out) by rings of
    a uniform grid, exact: a ring stops the search once the k-th distance is within the radius
    the rings so far cover. Returns how many were found (k unless X has fewer vertices)."""
    found = 0
    ci = np.empty(3, np.int64)
    for a in range(3):
        v = int(np.floor((c[a] - grid_lo[a]) / grid_h))
        ci[a] = min(max(v, 0), dims[a] - 1)
    top = max(dims[0], max(dims[1], dims[2]))
    for ring in range(top + 1):
        for i in range(ci[0] - ring, ci[0] + ring + 1):
            if i < 0 or i >= dims[0]:
                continue
            for j in range(ci[1] - ring, ci[1] + ring + 1):
                if j < 0 or j >= dims[1]:
                    continue
                for l in range(ci[2] - ring, ci[2] + ring + 1):
                    if l < 0 or l >= dims[2]:
                        continue
                    if max(abs(i - ci[0]), max(abs(j - ci[1]), abs(l - ci[2]))) != ring:
                        continue
                    cell = (i * dims[1] + j) * dims[2] + l
                    for s in range(cell_start[cell], cell_start[cell + 1]):
                        v = cell_order[s]
                        dx = X[v, 0] - c[0]
                        dy = X[v, 1] - c[1]
                        dz = X[v, 2] - c[2]
                        d = dx * dx + dy * dy + dz * dz
                        if found < k:
                            pos = found
                            found += 1
                        elif d < d2[k - 1]:
                            pos = k - 1
                        else:
                            continue
                        while pos > 0 and (d2[pos - 1] > d or (d2[pos - 1] == d and out[pos - 1] > v)):
                            d2[pos] = d2[pos - 1]
                            out[pos] = out[pos - 1]
                            pos -= 1
                        d2[pos] = d
                        out[pos] = v
        reach = ring * grid_h
        if found == k and d2[k - 1] <= reach * reach:
            break
    return found


def _predict(coef, S, f_old, phi, newmark, p, out, at):
    """out[at:at + 3] = predict(p) = phi_p (C1 x + C2 v (+ G0 f_old)): node p after one more step
    with no new load."""
    r = S.shape[1]
    ux = 0.0
    uy = 0.0
    uz = 0.0
    for j in range(r):
        x = coef[0, j] * S[0, j] + coef[2, j] * S[1, j]
        if newmark:
            x = x + coef[6, j] * f_old[j]
        ux += phi[p, 0, j] * x
        uy += phi[p, 1, j] * x
        uz += phi[p, 2, j] * x
    out[at] = ux
    out[at + 1] = uy
    out[at + 2] = uz


def _probe_tick(c, coef, S, f_old, phi, newmark, X, normals, grid_lo, grid_h, dims, cell_start, cell_order,
                fpar, ist, cand, fst, wslot, wtab, d2, u):
    """One Probe.update (haptics.Probe, same formulas and order) at probe position c.

    fpar: radius, 1/stiffness (0 for the constraint coupling), requery distance; ist: contact
    node (-1 none), candidates held, node to prepare (set on return -1); fst: candidate query
    point (3), force on the probe (3), penetration; d2 (k,) and u (3,) scratch. Returns 0 after a
    step, or -1 without touching anything when the contact node's compliance is not in wtab yet
    (ist[2] names it).
    """
    k = cand.shape[0]
    p = ist[0]
    if p < 0:
        dx = c[0] - fst[0]
        dy = c[1] - fst[1]
        dz = c[2] - fst[2]
        if ist[1] == 0 or np.sqrt(dx * dx + dy * dy + dz * dz) > fpar[2]:
            ist[1] = _knn(c, X, grid_lo, grid_h, dims, cell_start, cell_order, k, cand, d2)
            fst[0] = c[0]
            fst[1] = c[1]
            fst[2] = c[2]
        best = np.inf
        for s in range(ist[1]):
            v = cand[s]
            _point_displacement(phi, S, v, u)
            ex = X[v, 0] + u[0] - c[0]
            ey = X[v, 1] + u[1] - c[1]
            ez = X[v, 2] + u[2] - c[2]
            d = ex * ex + ey * ey + ez * ez
            if d < best:
                best = d
                p = v
    nx = normals[p, 0]
    ny = normals[p, 1]
    nz = normals[p, 2]
    g = nx * (c[0] - X[p, 0]) + ny * (c[1] - X[p, 1]) + nz * (c[2] - X[p, 2]) - fpar[0]
    _predict(coef, S, f_old, phi, newmark, p, u, 0)  # u_free = predict(p)
    un = nx * u[0] + ny * u[1] + nz * u[2]
    lam = 0.0
    if un > g:
        slot = wslot[p]
        if slot < 0:
            ist[2] = p
            return -1
        W = wtab[slot]
        wn = (nx * (W[0, 0] * nx + W[0, 1] * ny + W[0, 2] * nz) + ny * (W[1, 0] * nx + W[1, 1] * ny + W[1, 2] * nz)
              + nz * (W[2, 0] * nx + W[2, 1] * ny + W[2, 2] * nz))
        lam = (un - g) / (wn + fpar[1])
    if lam > 0:
        _point_step(coef, S, f_old, phi, p, -lam * nx, -lam * ny, -lam * nz, newmark)
        ist[0] = p
        fst[6] = max(0.0, un - g)
    else:
        _point_step(coef, S, f_old, phi, -1, 0.0, 0.0, 0.0, newmark)
        ist[0] = -1
        fst[6] = 0.0
        lam = 0.0
    fst[3] = lam * nx
    fst[4] = lam * ny
    fst[5] = lam * nz
    return 0


def _probe_tick_packed(c, a, fout):
    """_probe_tick on the packed arguments of :func:`_make_chunk`; the force into fout (3,)."""
    status = _probe_tick(c, a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7], a[8], a[9], a[10], a[11], a[12], a[13],
                         a[14], a[15], a[16], a[17], a[18], a[19])
    fst = a[15]
    fout[0] = fst[3]
    fout[1] = fst[4]
    fout[2] = fst[5]
    return status


def _grasp_tick(c, a, fout):
    """One Grasp.update (haptics.Grasp, same formulas) of a jaw held on m vertices, at hand
    position c, with a ModalSimulator whose step compliances do not change (linear modes).

    a: coef, S, f_old, phi, newmark (the simulator, as in _point_step); nodes (m,) held;
    A the precomputed inverse: (3, 3) of I + k W for one vertex, else (3m + 3, 3m + 3) of the
    jaw system [[W + I/grip, -E], [E^T, k I]]; base: X[node] (3,) for one vertex, else the held
    displacements at the grab and the jaw's grab position (3m + 3); gpar: k, max_force (inf:
    none); F (m, 3) the forces on the held vertices (out); w (3m + 3,) and fm (r,) scratch.
    Writes the total force on the organ to fout; returns 0."""
    coef, S, f_old, phi, newmark, nodes, A, base, gpar, F, w, fm = a
    r = S.shape[1]
    m = nodes.shape[0]
    k = gpar[0]
    for i in range(m):  # predict(nodes)
        _predict(coef, S, f_old, phi, newmark, nodes[i], w, 3 * i)
    if m == 1:  # (I + k W) f = k (c - X - u_free)
        for d in range(3):
            w[d] = k * (c[d] - base[d] - w[d])
        n_rhs = 3
    else:  # [h; k (c - x_jaw)] with h = u_S(grab) - u_free
        for d in range(3 * m):
            w[d] = base[d] - w[d]
        for d in range(3):
            w[3 * m + d] = k * (c[d] - base[3 * m + d])
        n_rhs = 3 * m + 3
    tx = 0.0
    ty = 0.0
    tz = 0.0
    for i in range(m):
        for d in range(3):
            acc = 0.0
            row = 3 * i + d
            for e in range(n_rhs):
                acc += A[row, e] * w[e]
            F[i, d] = acc
        tx += F[i, 0]
        ty += F[i, 1]
        tz += F[i, 2]
    mag = np.sqrt(tx * tx + ty * ty + tz * tz)
    if mag > gpar[1]:
        scale = gpar[1] / mag
        for i in range(m):
            for d in range(3):
                F[i, d] *= scale
        tx = 0.0
        ty = 0.0
        tz = 0.0
        for i in range(m):
            tx += F[i, 0]
            ty += F[i, 1]
            tz += F[i, 2]
    for j in range(r):
        f = 0.0
        for i in range(m):
            p = nodes[i]
            f += phi[p, 0, j] * F[i, 0] + phi[p, 1, j] * F[i, 1] + phi[p, 2, j] * F[i, 2]
        fm[j] = f
    for j in range(r):  # the step, as _point_step
        x = S[0, j]
        v = S[1, j]
        xn = coef[0, j] * x + coef[2, j] * v
        vn = coef[1, j] * v + coef[3, j] * x
        xn = xn + coef[4, j] * fm[j]
        vn = vn + coef[5, j] * fm[j]
        if newmark:
            xn = xn + coef[6, j] * f_old[j]
            vn = vn + coef[7, j] * f_old[j]
            f_old[j] = fm[j]
        S[0, j] = xn
        S[1, j] = vn
    fout[0] = tx
    fout[1] = ty
    fout[2] = tz
    return 0


def _slot(k, start, target, t0, period, deadline, n_script, counters):
    """The slot a tick starting at ``start`` takes: k on time; past whole periods late, the
    current one (the ones skipped counted); -1 when the loop is over (after the deadline or
    the script: the slots skipped counted, counters[0] the next)."""
    if start >= deadline:  # woke after the end: the slots still due are skipped, and counted
        while period > 0.0 and t0 + k * period < deadline:
            k += 1
            counters[2] += 1
        counters[0] = k
        return -1
    if period > 0.0 and start - target > period:  # behind by whole ticks: skip them
        skip = int((start - target) / period)
        if n_script > 0 and k + skip >= n_script:
            counters[2] += n_script - k  # the rest of the script: skipped
            counters[0] = n_script
            return -1
        k += skip
        counters[2] += skip
        counters[0] = k
    return k


def _record(start, target, end, k, fout, lateness, compute, forces, slots, counters):
    """The tick's lateness, compute time, force and slot, while the record has room; returns
    whether it is now full."""
    i = counters[4]
    if i < lateness.shape[0]:
        lateness[i] = start - target
        compute[i] = end - start
        forces[i, 0] = fout[0]
        forces[i, 1] = fout[1]
        forces[i, 2] = fout[2]
        slots[i] = k
        counters[4] = i + 1
    return i + 1 >= lateness.shape[0]


def _make_chunk(gettime, usleep, clock_id, tick, jit):
    """The compiled loop of ``tick`` on the monotonic clock (``gettime(clock_id, timespec)``,
    ``usleep``), its named steps compiled with ``jit`` (numba.njit)."""

    @jit
    def now_s(clock):
        gettime(clock_id, clock.ctypes)
        return clock[0] + 1e-9 * clock[1]

    @jit
    def wait_until(target, spin, clock):
        """Sleep until ``spin`` before target, then spin; returns the clock then."""
        now = now_s(clock)
        while now < target:
            if target - now > spin:
                usleep(int((target - now - spin) * 1e6))
            now = now_s(clock)
        return now

    slot, record = jit(_slot), jit(_record)

    def chunk(targs, fout, sched, positions, mailbox, ctl, lateness, compute, forces, slots, counters, clock):
        """Ticks of a loop until the deadline, max steps, a stop request or a node to prepare;
        each tick is ``tick(c, targs, fout)`` (a probe's or a grasp's, on its packed arguments;
        the force it hands back in fout (3,)). sched: t0, period, deadline (clock seconds),
        spin; positions (N, 3) by slot (scripted) or mailbox (3,) read each tick (len(positions)
        == 0); ctl[0] == 1 stops, 2 pauses; counters: next slot k, steps, missed, max steps (-1
        none), records written. Returns 0 (deadline/steps), 1 (a node to prepare: the probe's
        ist[2]), 2 (stopped) or 3 (paused: a grab or a release is waiting)."""
        c = np.empty(3)
        t0, period, deadline, spin = sched[0], sched[1], sched[2], sched[3]
        n_script = positions.shape[0]
        while True:
            if ctl[0] != 0:
                return 2 if ctl[0] == 1 else 3
            if counters[3] >= 0 and counters[1] >= counters[3]:
                return 0
            k = counters[0]
            target = t0 + k * period
            if target >= deadline:
                return 0
            if period <= 0.0:  # back to back (an offline replay): no schedule to keep
                start = target = now_s(clock)
            else:
                start = wait_until(target, spin, clock)
            k = slot(k, start, target, t0, period, deadline, n_script, counters)
            if k < 0:
                return 0
            target = t0 + k * period if period > 0.0 else target
            if n_script > 0:
                if k >= n_script:
                    return 0
                c[0], c[1], c[2] = positions[k, 0], positions[k, 1], positions[k, 2]
            else:
                c[0], c[1], c[2] = mailbox[0], mailbox[1], mailbox[2]
            if tick(c, targs, fout) < 0:
                return 1
            if n_script == 0:
                mailbox[3], mailbox[4], mailbox[5] = fout[0], fout[1], fout[2]
                if mailbox.shape[0] > 6:  # a SharedDevice's count of the forces written (its watchdog reads it)
                    mailbox[6] += 1.0
            full = record(start, target, now_s(clock), k, fout, lateness, compute, forces, slots, counters)
            counters[0] = k + 1
            counters[1] += 1
            if full:
                return 0  # the record is full: the caller makes room
    return chunk


def loop_kernels():
    """The compiled loops ``(probe_chunk, probe_tick, grasp_chunk)``, compiled on first use (cached
    on disk), or None without numba or a monotonic clock numba can call."""
    global _LOOP
    if _LOOP is None:
        _LOOP = False
        gettime, usleep, clock_id = _monotonic_clock()
        if HAVE_NUMBA and gettime is not None:
            try:
                import numba

                opts = dict(nogil=True, fastmath=False, error_model="numpy")
                knn = numba.njit(**opts, cache=True)(_knn)
                # the tick calls the compiled point step and read-back the simulator uses
                predict = numba.njit(**opts, cache=True)(_predict)
                g = dict(_probe_tick.__globals__, _point_step=point_step, _point_displacement=point_displacement,
                         _knn=knn, _predict=predict)
                jit = numba.njit(**opts)
                tick = jit(type(_probe_tick)(_probe_tick.__code__, g, "_probe_tick"))
                packed = jit(type(_probe_tick_packed)(_probe_tick_packed.__code__, dict(g, _probe_tick=tick),
                                                      "_probe_tick_packed"))
                chunk = jit(_make_chunk(gettime, usleep, clock_id, packed, jit))
                grasp = jit(_make_chunk(gettime, usleep, clock_id, jit(
                    type(_grasp_tick)(_grasp_tick.__code__, dict(g), "_grasp_tick")), jit))
                _warm(chunk, grasp)
                # a call with other types fails loudly instead of compiling in a tick
                chunk.disable_compile()
                grasp.disable_compile()
                _LOOP = (chunk, tick, grasp)
            except Exception:  # pragma: no cover - a numba that cannot compile this
                _LOOP = False
    return _LOOP or None


_LOOP = None


def _warm(chunk, grasp) -> None:
    """Compile the loops for the argument types HapticLoop passes, on a schedule already over
    (nothing runs): compilation happens here, not inside the first tick."""
    r, n = 2, 1
    f, i = np.float64, np.int64
    sim = (np.zeros((8, r)), np.zeros((2, r)), np.zeros(r), np.zeros((n, 3, r)), False)
    rest = (np.array([0.0, 1.0, -np.inf, 0.0]), np.zeros((0, 3)), np.zeros(6), np.zeros(1, i), np.zeros(1, f),
            np.zeros(1, f), np.zeros((1, 3)), np.zeros(1, i), np.zeros(5, i), np.zeros(2, i))
    chunk(probe_arguments(*sim, np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(3), 1.0, np.ones(3, i), np.zeros(2, i),
                          np.zeros(n, i), np.zeros(3), np.zeros(3, i), np.zeros(1, i), np.zeros(7), np.zeros(n, i),
                          np.zeros((1, 3, 3))), np.zeros(3), *rest)
    grasp(grasp_arguments(*sim, np.zeros(1, i), np.eye(3), np.zeros(3), np.zeros(2), np.zeros((1, 3)), np.zeros(6),
                          np.zeros(r)), np.zeros(3), *rest)


def probe_arguments(coef, S, f_old, phi, newmark, X, normals, grid_lo, grid_h, dims, cell_start, cell_order, fpar,
                    ist, cand, fst, wslot, wtab) -> tuple:
    """The probe tick's packed arguments (the types the compiled loop was compiled for), with
    its scratch arrays."""
    return (coef, S, f_old, phi, bool(newmark), X, normals, grid_lo, float(grid_h), dims, cell_start, cell_order, fpar,
            ist, cand, fst, wslot, wtab, np.empty(cand.shape[0]), np.empty(3))


def grasp_arguments(coef, S, f_old, phi, newmark, nodes, A, base, gpar, F, w, fm) -> tuple:
    """The grasp tick's packed arguments (see _grasp_tick)."""
    return (coef, S, f_old, phi, bool(newmark), nodes, A, base, gpar, F, w, fm)
