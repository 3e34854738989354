import os
import signal
from pathlib import Path

import numpy as np
import pytest

import rtfem as rt

# A suite started in the background of a non-interactive shell (`make test &`, nohup) inherits
# SIGINT ignored, and so would every `rtfem` subprocess the Ctrl-C tests start: they would run on,
# and fail those tests. A handled SIGINT is reset to the default in a child at exec; an ignored one
# is not. So the suite takes it back.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

# The suite keeps its precompute cache (tet meshes, modes, reduced models: rtfem.cache) in a folder of its
# own, made afresh for each run, so that it neither reads nor fills the user's ~/.cache/rtfem; its
# subprocesses inherit the setting. RTFEM_CACHE set by the caller is kept.
_OWN_CACHE = None
if not os.environ.get("RTFEM_CACHE"):
    import tempfile

    _OWN_CACHE = os.environ["RTFEM_CACHE"] = tempfile.mkdtemp(prefix="rtfem-test-cache-")


def pytest_sessionfinish(session, exitstatus):
    if _OWN_CACHE is not None:
        import shutil

        shutil.rmtree(_OWN_CACHE, ignore_errors=True)

#: reference data shipped beside the project (../shared/data), never inside it
SHARED_DATA = Path(os.environ.get("RTFEM_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
ORGANS = SHARED_DATA / "organs"


def organ(name: str) -> Path:
    path = ORGANS / name
    if not path.exists():
        pytest.skip(f"reference organ mesh {name} not found under {ORGANS} (the shared data folder is absent)")
    return path


@pytest.fixture
def plate_material():
    return rt.Material(E=1.0e7, nu=0.3, thickness=0.01, density=1000.0)


def liver_model(level: int = 4) -> rt.ShellModel:
    """The embedded liver at ``level``, default material, fixed at its attachment."""
    model = rt.ShellModel(rt.meshes.liver(level), rt.Material())
    model.fix("attachment")
    return model


@pytest.fixture(scope="session")
def liver3_modes():
    """The level-3 liver (642 vertices) fixed at its attachment, and its 30 lowest modes."""
    model = liver_model(3)
    return model, rt.modal_analysis(model, 30)


def rigid_body_modes(X: np.ndarray) -> np.ndarray:
    """The six analytic rigid-body motions (6n, 6) of nodes at X: translations, rotations."""
    n = X.shape[0]
    R = np.zeros((n, 6, 6))
    c = X - X.mean(axis=0)
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1.0
        R[:, k, k] = 1.0
        R[:, :3, 3 + k] = np.cross(e, c)
        R[:, 3 + k, 3 + k] = 1.0
    return R.reshape(6 * n, 6)


def wait_for_viewer_address(p, timeout: float = 120.0) -> str:
    """The viewer's "open http://..." line from a `rtfem view` subprocess ('' if it never came)."""
    import time

    t0 = time.time()
    line = ""
    while "open http" not in line and time.time() - t0 < timeout:
        line = p.stdout.readline()
        if not line and p.poll() is not None:
            break
    return line


def serves_and_stops_on_ctrl_c(*view_args) -> None:
    """`rtfem view ARGS --port P` in a subprocess: it says its address, serves the page, and Ctrl-C
    stops it (exit 130, "stopped", no traceback)."""
    import socket
    import subprocess
    import sys
    import urllib.request

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    p = subprocess.Popen([sys.executable, "-m", "rtfem.cli.main", "view", *map(str, view_args), "--port", str(port)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = wait_for_viewer_address(p)
        assert f"http://127.0.0.1:{port}" in line, (line, p.stderr.read() if p.poll() is not None else "")
        assert b"<html" in urllib.request.urlopen(f"http://127.0.0.1:{port}", timeout=30).read().lower()
    finally:
        out, err = interrupt(p, 30)
    assert p.returncode == 130 and "stopped" in out and "Traceback" not in err, (out, err)


def interrupt(p, timeout: float = 30.0) -> tuple[str, str]:
    """Ctrl-C a subprocess and collect its output. One that has not stopped within ``timeout`` s
    is killed (a test that fails must not leave a viewer running, holding a port and a core for
    the tests after it) and the test fails saying so."""
    import signal
    import subprocess

    if p.poll() is None:
        p.send_signal(signal.SIGINT)
    try:
        return p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        p.kill()
        out, err = p.communicate()
        raise AssertionError(f"the process did not stop within {timeout:g} s of Ctrl-C (killed); "
                             f"its output: {out[-2000:]!r} {err[-2000:]!r}") from None


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now (for a viewer a test serves)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def thread_stacks(depth: int = 6) -> str:
    """Where each thread of this process is now (its innermost ``depth`` frames): for a timeout's message."""
    import sys
    import threading
    import traceback

    names = {t.ident: t.name for t in threading.enumerate()}
    out = []
    for ident, frame in sys._current_frames().items():
        lines = [line for line in traceback.format_stack(frame) if "/threading.py" not in line][-depth:]
        out.append(f"--- thread {names.get(ident, ident)}:\n" + "".join(lines))
    return "\n".join(out)


def wait_until(cond, timeout: float, what, poll: float = 0.1) -> None:
    """Poll ``cond()`` until it is true; an AssertionError naming ``what`` (a string, or a callable giving
    one then: the state at the timeout) after ``timeout`` s."""
    import time

    t0 = time.time()
    while not cond():
        if time.time() - t0 > timeout:
            raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what() if callable(what) else what}")
        time.sleep(poll)


def cut_state(s, v) -> str:
    """The session's, its scalpel's and the viewer's state, and every thread's stack: what a timeout says."""
    sc = s.scalpel
    job = sc._job is not None and sc._job.is_alive()
    worker = sc._worker is not None and sc._worker.alive
    return (f"{s.cut_status!r}; error: {s.error}; steps {s.stats.steps}, frames {v.frames}; the scalpel: "
            f"{sc.triangles.shape[0]} triangles swept, {sc._tried} tried, {sc.cuts} cuts, job at work {job}, "
            f"a cut ready {sc._ready is not None}, lifted {sc.lifted}, refused {sc.refused}, worker alive {worker}, "
            f"worker note {sc.worker_note}, its error {sc.error!r}, stopped {sc.stop_reason}\n{thread_stacks()}")


def cuts_settled(s, v) -> bool:
    """Whether viewer ``v``'s session ``s`` in scalpel mode has every strip swept tried, no cut job at work or
    waiting, and every cut it took drawn."""
    sc = s.scalpel
    idle = (sc._job is None or not sc._job.is_alive()) and sc._ready is None and sc._tried == sc.triangles.shape[0]
    return idle and v._generation == s.generation
