"""Pictures and plots, headless (matplotlib's Agg backend; no display needed).

:func:`pictures` writes the set that ``rtfem pictures`` makes and the README shows:
mode shapes, a deformed state, a GIF of a push-release response, the modal frequency
spectrum, the step response of a node by modal (r modes, with and without the static
correction), SLDM and direct Newmark integration, the error against the number of modes,
and time-per-step scaling curves. Needs the ``plots`` extra (matplotlib; imageio-ffmpeg for
MP4).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import RtfemError
from ..fe.material import Damping


def _plt():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise RtfemError("pictures and plots need matplotlib: pip install 'rtfem[plots]' (make test installs it)") from None
    return plt


def _shaded_colors(mesh, u: np.ndarray, values: np.ndarray, vmax: float, light=(0.3, -0.5, 0.8)):
    import matplotlib

    X = np.asarray(mesh.vertices) + u
    T = mesh.triangles
    P = X[T]
    n = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    lv = np.asarray(light) / np.linalg.norm(light)
    shade = 0.45 + 0.55 * np.abs(n @ lv)
    face_val = values[T].mean(axis=1)
    rgba = matplotlib.colormaps["viridis"](np.clip(face_val / vmax, 0, 1) if vmax > 0 else np.zeros_like(face_val))
    rgba[:, :3] *= shade[:, None]
    return P, rgba


def draw_surface(ax, mesh, u: np.ndarray | None = None, values: np.ndarray | None = None, vmax: float | None = None,
                 title: str | None = None, view=(28, -62)) -> None:
    """The surface displaced by ``u`` on a 3D axes, coloured by ``values`` (default |u|)."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    u = np.zeros((mesh.n_vertices, 3)) if u is None else u
    values = np.linalg.norm(u, axis=1) if values is None else values
    vmax = float(values.max()) if vmax is None else vmax
    P, rgba = _shaded_colors(mesh, u, values, vmax)
    ax.add_collection3d(Poly3DCollection(P, facecolors=rgba, edgecolors="none"))
    lo, hi = mesh.bounds()
    c, half = (lo + hi) / 2, (hi - lo).max() / 2 * 1.05
    ax.set_xlim(c[0] - half, c[0] + half)
    ax.set_ylim(c[1] - half, c[1] + half)
    ax.set_zlim(c[2] - half, c[2] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(*view)
    ax.set_axis_off()
    if title:
        ax.set_title(title, fontsize=9)


def _save(fig, ax, path, *, legend: dict | None = None, grid: str = "major") -> Path:
    plt = _plt()
    if legend is not None:
        ax.legend(**legend)
    ax.grid(alpha=0.3, which=grid)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)


def mode_shapes_png(mesh, modes, path, n: int = 6) -> Path:
    plt = _plt()
    n = min(n, modes.n_modes)
    cols = 3
    rows = (n + cols - 1) // cols
    fig = plt.figure(figsize=(3.2 * cols, 2.9 * rows), dpi=110)
    size = float(np.linalg.norm(mesh.bounds()[1] - mesh.bounds()[0]))
    for i in range(n):
        phi = modes.shapes[:, :, i]
        u = 0.08 * size * phi / np.abs(phi).max()
        ax = fig.add_subplot(rows, cols, i + 1, projection="3d")
        draw_surface(ax, mesh, u, title=f"mode {i + 1}: {modes.frequencies[i]:.2f} Hz")
    fig.suptitle("Lowest mode shapes (coloured by |phi|, exaggerated)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)


def deformed_png(mesh, u, path, title: str) -> Path:
    plt = _plt()
    fig = plt.figure(figsize=(6.4, 4.8), dpi=120)
    ax = fig.add_subplot(111, projection="3d")
    mag = np.linalg.norm(u, axis=1)
    draw_surface(ax, mesh, u, mag, title=title)
    import matplotlib as mpl

    sm = mpl.cm.ScalarMappable(norm=mpl.colors.Normalize(0, mag.max() * 1e3), cmap="viridis")
    fig.colorbar(sm, ax=ax, shrink=0.6, label="|u| (mm)")
    fig.savefig(path)
    plt.close(fig)
    return Path(path)


def animation(mesh, fields: list[np.ndarray], times: list[float], path, *, fps: int = 15, forces=None) -> Path:
    """A GIF (Pillow) or MP4 (imageio-ffmpeg) of displacement fields, colour scale fixed."""
    plt = _plt()
    from matplotlib import animation as anim

    path = Path(path)
    vmax = max(float(np.linalg.norm(u, axis=1).max()) for u in fields) or 1.0
    fig = plt.figure(figsize=(5.2, 4.2), dpi=90)
    ax = fig.add_subplot(111, projection="3d")

    def frame(k: int):
        ax.clear()
        label = f"t = {times[k] * 1e3:5.0f} ms"
        if forces is not None:
            label += f", force {forces[k]:.2f} N"
        draw_surface(ax, mesh, fields[k], vmax=vmax, title=label)
        return []

    ani = anim.FuncAnimation(fig, frame, frames=len(fields), blit=False)
    if path.suffix == ".mp4":
        try:
            import imageio_ffmpeg
        except ImportError:
            plt.close(fig)
            raise RtfemError("MP4 needs imageio-ffmpeg: pip install imageio-ffmpeg (or write a .gif)") from None
        plt.rcParams["animation.ffmpeg_path"] = imageio_ffmpeg.get_ffmpeg_exe()
        ani.save(path, writer=anim.FFMpegWriter(fps=fps, bitrate=1800))
    else:
        ani.save(path, writer=anim.PillowWriter(fps=fps))
    plt.close(fig)
    return path


def spectrum_png(modes, path) -> Path:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.4, 3.4), dpi=110)
    f = modes.frequencies
    ax.stem(np.arange(1, f.size + 1), f, basefmt=" ")
    ax.set_xlabel("mode number")
    ax.set_ylabel("frequency (Hz)")
    ax.set_title(f"Modal frequency spectrum ({f.size} lowest modes)")
    return _save(fig, ax, path)


def _modal_step(basis, node: int, force: np.ndarray, damping: Damping, times: np.ndarray, static: float):
    """Closed-form modal step response at ``node`` along ``force``: r -> (r modes, r modes + static correction)."""
    from ..reduction.oscillator import step_response

    e = force / np.linalg.norm(force)
    phi_p = basis.shapes[node]  # (3, r)
    lam = basis.omega**2
    g = step_response(lam[:, None], damping.modal_alpha(basis.omega)[:, None], times[None, :])  # (r, nt)
    gain = (e @ phi_p) * (force @ phi_p)  # (r,)

    def at(r: int) -> tuple[np.ndarray, np.ndarray]:
        plain = gain[:r] @ g[:r]
        return plain, plain + static - (gain[:r] / lam[:r]).sum()

    return at


def step_responses(model, node: int, force: np.ndarray, times: np.ndarray, damping: Damping, modes_list,
                   basis, dt_direct: float = 2.5e-4, sldm_tol: float = 1e-8) -> dict:
    """u(t) at ``node`` (component along ``force``) for a step load there: modal (closed form per
    mode, truncated to each r, plain and with the static correction), SLDM and direct Newmark."""
    from ..drivers.fullorder import DirectSimulator
    from ..reduction.sldm import SLDM

    e = force / np.linalg.norm(force)
    out = {"t": times}
    F = {node: tuple(force)}
    static = model.solve_static(F)[node] @ e
    out["modal"] = modal = _modal_step(basis, node, force, damping, times, static)
    for r in modes_list:
        out[f"modal r={r}"], out[f"modal r={r} + static correction"] = modal(r)
    t0 = time.perf_counter()
    sl = SLDM(model, damping, tol=sldm_tol)
    out["sldm"] = sl.step_response(F, times)[:, node] @ e
    out["sldm_info"] = sl.last_info
    out["sldm_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    d = DirectSimulator(model, dt_direct, damping)
    n_steps = int(round(times[-1] / dt_direct))
    u, tt = [0.0], [0.0]
    for k in range(n_steps):
        d.step(F)
        u.append(d.displacement(node) @ e)
        tt.append((k + 1) * dt_direct)
    out["direct"] = np.interp(times, tt, u)
    out["direct_s"] = time.perf_counter() - t0
    out["static"] = static
    return out


def step_response_png(res: dict, path, dt_direct: float, modes_list) -> Path:
    plt = _plt()
    t = res["t"] * 1e3
    fig, ax = plt.subplots(figsize=(7.0, 4.0), dpi=110)
    ax.plot(t, res["direct"] * 1e3, color="k", lw=2.5, label=f"direct Newmark, dt = {dt_direct * 1e3:g} ms")
    ax.plot(t, res["sldm"] * 1e3, color="#ff7f0e", lw=1.5, ls="--", label=f"SLDM (m = {res['sldm_info'].m})")
    for r, c in zip(modes_list, ("#1f77b4", "#2ca02c", "#9467bd")):
        ax.plot(t, res[f"modal r={r}"] * 1e3, color=c, lw=1, ls=":", label=f"modal r = {r}")
        ax.plot(t, res[f"modal r={r} + static correction"] * 1e3, color=c, lw=1.2, label=f"modal r = {r} + static correction")
    ax.axhline(res["static"] * 1e3, color="grey", lw=0.8, ls="-.", label="static solution")
    ax.set_xlabel("time (ms)")
    ax.set_ylabel("displacement along the load (mm)")
    ax.set_title("Step response of the loaded node")
    return _save(fig, ax, path, legend=dict(fontsize=7, loc="lower right"))


def error_vs_modes(res: dict, rs) -> dict:
    """Error of the modal step response of :func:`step_responses` against its SLDM one, per r:
    largest over time and RMS, relative to the SLDM response, without and with the correction."""
    ref = res["sldm"]
    scale, rms = np.abs(ref).max(), np.sqrt(np.mean(ref**2))
    out = {"r": np.asarray(rs), "plain": [], "corrected": [], "plain_rms": [], "corrected_rms": []}
    for r in rs:
        u, uc = res["modal"](r)
        out["plain"].append(np.abs(u - ref).max() / scale)
        out["corrected"].append(np.abs(uc - ref).max() / scale)
        out["plain_rms"].append(np.sqrt(np.mean((u - ref) ** 2)) / rms)
        out["corrected_rms"].append(np.sqrt(np.mean((uc - ref) ** 2)) / rms)
    return {k: np.asarray(v) for k, v in out.items()}


def error_png(err: dict, path) -> Path:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.4, 3.8), dpi=110)
    ax.loglog(err["r"], err["plain_rms"], "o-", color="#1f77b4", label="modal, r modes: RMS over time")
    ax.loglog(err["r"], err["corrected_rms"], "s-", color="#ff7f0e", label="modal + static correction: RMS")
    ax.loglog(err["r"], err["plain"], "o:", color="#1f77b4", label="modal: largest (early times)")
    ax.loglog(err["r"], err["corrected"], "s:", color="#ff7f0e", label="modal + static correction: largest")
    ax.set_xlabel("number of modes r")
    ax.set_ylabel("error relative to SLDM (0 .. 300 ms)")
    ax.set_title("Loaded-node step response: error against the number of modes")
    return _save(fig, ax, path, legend={}, grid="both")


def plot_bench(rows: list[dict], path) -> Path:
    """Time per step against model size: modal (haptic, full field) and direct Newmark."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=110)
    rs = sorted({r["r"] for r in rows})
    sizes = sorted({r["vertices"] for r in rows})
    direct = [next(r["direct_step_s"] for r in rows if r["vertices"] == n) for n in sizes]
    ax.loglog(sizes, np.array(direct) * 1e3, "ko-", lw=2, label="direct Newmark (full model)")
    for r in rs:
        sub = sorted((x for x in rows if x["r"] == r), key=lambda x: x["vertices"])
        ax.loglog([x["vertices"] for x in sub], [x["field_step_s"] * 1e3 for x in sub], "o--", label=f"modal r = {r}, full field")
        ax.loglog([x["vertices"] for x in sub], [x["haptic_step_s"] * 1e3 for x in sub], "s-",
                  label=f"modal r = {r}, haptic (one node)")
    ax.axhline(1.0, color="red", lw=0.8, ls=":", label="1 ms: the 1 kHz haptic budget")
    ax.set_xlabel("vertices")
    ax.set_ylabel("time per step (ms)")
    ax.set_title("Time per step, measured in one run")
    return _save(fig, ax, path, legend=dict(fontsize=7), grid="both")


def pictures(model, out: Path, *, n_modes: int = 40, damping: Damping | None = None, dt: float = 1e-3,
             gif: bool = True, mp4: bool = False, scaling_levels=(2, 3, 4),
             say: Callable[[str], None] = lambda s: None) -> list[Path]:
    """Write every picture for ``model`` to ``out``; returns the paths."""
    from ..mesh.selection import probe_vertex
    from .bench import dynamics_table
    from ..reduction.modal import modal_analysis
    from ..drivers.modal import ModalSimulator

    _plt()
    damping = damping if damping is not None else Damping(alpha=8.0)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    mesh = model.mesh
    paths = []
    r_max = max(n_modes, 100)
    basis = modal_analysis(model, r_max)
    node = probe_vertex(model)
    force = -0.1 * mesh.vertex_normals()[node]
    paths.append(mode_shapes_png(mesh, basis, out / "modes.png"))
    paths.append(spectrum_png(basis, out / "spectrum.png"))
    u = model.solve_static({node: tuple(force * 2)})
    paths.append(deformed_png(mesh, u, out / "deformed.png", f"static: {np.linalg.norm(force) * 2:.1f} N at vertex {node}"))
    say(f"step responses: modal, SLDM, direct at vertex {node} ...")
    times = np.linspace(0.0, 0.3, 301)[1:]
    modes_list = [m for m in (10, n_modes) if m <= r_max]
    res = step_responses(model, node, force, times, damping, modes_list, basis)
    paths.append(step_response_png(res, out / "step_response.png", 2.5e-4, modes_list))
    err = error_vs_modes(res, [r for r in (1, 2, 5, 10, 20, 40, 70, 100) if r <= r_max])
    paths.append(error_png(err, out / "error_vs_modes.png"))
    if scaling_levels:
        say("scaling: time per step on the liver at levels " + ", ".join(map(str, scaling_levels)) + " ...")
        from ..mesh import meshes
        from ..fe.shellmodel import ShellModel

        rows = []
        for lv in scaling_levels:
            m = meshes.liver(level=lv)
            mod = ShellModel(m, model.material)
            mod.fix("attachment")
            rows += dynamics_table(mod, [n_modes], dt=dt, damping=damping, direct_steps=10)
        paths.append(plot_bench(rows, out / "scaling.png"))
    if gif or mp4:
        say("animation: push for 0.15 s, release, 0.45 s ...")
        sim = ModalSimulator(basis.truncated(n_modes), dt, damping, static_correction=True)
        fields, ts, fs = [], [], []
        push, total, every = int(0.15 / dt), int(0.6 / dt), max(1, int(round(1 / 30 / dt)))
        for k in range(total):
            on = k < push
            sim.step({node: tuple(2 * force)} if on else None)
            if (k + 1) % every == 0:
                fields.append(sim.displacements())
                ts.append((k + 1) * dt)
                fs.append(float(np.linalg.norm(2 * force)) if on else 0.0)
        if gif:
            paths.append(animation(mesh, fields, ts, out / "response.gif", forces=fs))
        if mp4:
            paths.append(animation(mesh, fields, ts, out / "response.mp4", forces=fs))
    return paths
