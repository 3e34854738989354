"""``rtfem view --benchmark``: the viewer's session run headless under a scripted grab.

The session steps on its own thread exactly as behind the browser (its clock, the BLAS limit of
run time, the background tangent of the reduced nonlinear model), and a frame thread does the
viewer's per-frame work at up to 30 frames per second (the field, its colours and the binary
glTF of the surface; only the websocket is missing). The script: at 10 % of the time the
default vertex (the mesh's ``probe`` group, else the free surface vertex farthest from the
supports) is grabbed with the panel's jaw, pulled 3 cm along its outward normal by 30 %, held
until 60 % and released; the organ then settles. One JSON line reports what a user would see.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from .. import validate
from ..errors import ModelError
from .app import surface_encoder, surface_glb
from .session import Session

PULL = 0.03  # m


# A page script (playwright's add_init_script) counting the animation frames in which the page issued
# WebGL draw calls (the frames a browser drew, not the frames the server sent) and the shaders it
# compiled, in window.__rtfem: benchmarks/viewer_browser.py and the browser test read it.
BROWSER_COUNTER = """
window.__rtfem = {drawn: 0, compiled: 0, frame: 0, last: -1};
(function tick() { window.__rtfem.frame++; requestAnimationFrame(tick); })();
for (const C of [WebGLRenderingContext, WebGL2RenderingContext]) {
  for (const name of ["drawElements", "drawArrays", "compileShader"]) {
    const f = C.prototype[name];
    C.prototype[name] = function (...a) {
      const c = window.__rtfem;
      if (name === "compileShader") c.compiled++;
      else if (c.last !== c.frame) { c.last = c.frame; c.drawn++; }
      return f.apply(this, a);
    };
  }
}
"""

def default_vertex(session: Session) -> int:
    """The vertex the benchmark grabs: the mesh's ``probe`` group, else the free surface vertex
    farthest from the supports."""
    probe = session.mesh.groups.get("probe") if session.mesh.groups else None
    if probe is not None and len(probe):
        return int(np.asarray(probe)[0])
    from ..mesh.selection import probe_vertex

    return probe_vertex(session.model)


class _Drawer:
    """The viewer's per-frame work on a thread, at up to ``fps``: the drawn surface's field, its
    colours and the binary glTF (:mod:`rtfem.viewer.gltf`), the force record."""

    def __init__(self, session: Session, fps: float) -> None:
        self._glb = surface_encoder(session)
        self.session, self.period = session, 1.0 / fps
        self.peak = 0.0  # the largest displacement drawn (m)
        self.frames = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="rtfem-benchmark-frames", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def _loop(self) -> None:
        s = self.session
        while not self._stop.is_set():
            t0 = time.perf_counter()
            u = s.surface_displacements()
            top = float(np.linalg.norm(u, axis=1).max())
            self.peak = max(self.peak, top)
            surface_glb(s, self._glb, u, max(top, 1e-4))
            s.record_force()
            self.frames += 1
            time.sleep(max(0.0, self.period - (time.perf_counter() - t0)))


def _script(session: Session, X: np.ndarray, normal: np.ndarray, seconds: float, pull: float) -> tuple[float, int]:
    """The scripted hand until ``seconds`` have passed: grab at 10 % of the time, pull ``pull`` along
    ``normal`` by 30 %, hold to 60 %, release. Returns the largest force (N) and the polls at which
    the grasp clipped it."""
    wall0 = time.perf_counter()
    grabbed = released = False
    force, clipped = 0.0, 0
    while not session.error:
        f = (time.perf_counter() - wall0) / seconds
        if f >= 1.0:
            break
        if not grabbed and f >= 0.1:
            session.grab(X)
            grabbed = True
        if grabbed and not released:
            if f >= 0.6:
                session.release()
                released = True
            else:
                session.drag(X + pull * min(1.0, (f - 0.1) / 0.2) * normal)
                force = max(force, float(np.linalg.norm(session.force)))
                clipped += bool(getattr(session.grasp, "clipped", False))
        time.sleep(0.005)
    return force, clipped


def _report(session: Session, node: int, wall: float, steps: int, drawer: _Drawer, force: float, clipped: int) -> dict:
    computes = np.array(session.stats.computes, dtype=float) * 1e6
    s = session.settings
    model = session.model
    return {
        "model": "solid" if session.volume is not None else "shell",
        "element": getattr(model, "element", "shell"),
        "method": s.method,
        "nodes": int(model.n_nodes),
        "coordinates": int(getattr(getattr(session.driver, "reduced", None), "size", session.reduced.n_modes)),
        "seconds": round(wall, 3),
        "steps_per_s": round(steps / wall, 1),
        "realtime": round(steps * session.driver.dt / wall, 4),
        "step_p50_us": round(float(np.median(computes)), 1) if computes.size else None,
        "step_p99_us": round(float(np.percentile(computes, 99)), 1) if computes.size else None,
        "frames_per_s": round(drawer.frames / wall, 1),
        "max_force_N": round(force, 4),
        "force_limit_N": s.max_force,
        "clipped": clipped > 0,
        "peak_mm": round(drawer.peak * 1e3, 3),
        "vertex": node,
        "local": session.local_status or None,
        # tangents the step computed itself because the background worker was starved (a busy machine)
        "sync_refreshes": getattr(session.driver, "sync_refreshes", None),
        "priority": session.stats.priority,  # the stepping thread's (rtfem.threads.raise_priority)
        "error": session.error,
    }


def run(session: Session, seconds: float, *, pull: float = PULL, fps: float = 30.0) -> dict:
    """Run the scripted grab for ``seconds`` of wall-clock time and return the report."""
    if not isinstance(session, Session):
        raise ModelError(f"session={validate.show(session)} must be a viewer Session")
    seconds = validate.in_range(seconds, "seconds", 0.0, 3600.0, lo_open=True, what="the benchmark's duration in s")
    pull = validate.in_range(pull, "pull", 0.0, 1.0, lo_open=True, what="the pull in m")
    fps = validate.in_range(fps, "fps", 0.0, 1000.0, lo_open=True, what="frames per second")
    node = default_vertex(session)
    drawer = _Drawer(session, fps)
    steps0 = session.stats.steps
    session.stats.computes.clear()
    session.start()
    wall0 = time.perf_counter()
    drawer.start()
    try:
        force, clipped = _script(session, session.X[node], session.mesh.vertex_normals()[node], seconds, pull)
    finally:
        wall = time.perf_counter() - wall0
        drawer.stop()
        session.stop()
    return _report(session, node, wall, session.stats.steps - steps0, drawer, force, clipped)
