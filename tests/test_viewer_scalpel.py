"""The viewer's scalpel front end (rtfem.viewer.cut_view) without a browser: ctrl+drag events as viser sends
them (start, updates, end; the pointer on the camera-facing plane through the point picked, the camera
above) on a tet4 block clamped at both ends. The first event enters scalpel mode on a thread of its own;
the blade is along the line of sight, from CUT_ABOVE in front of the pointer to CUT_DEPTH behind it; each
cut the session takes is drawn: the frames' encoder and the grabbable copy are rebuilt on the new surface
(its vertex count, the session's drawn vertices), and the frames go on without an error. The blade of a
ray is checked against its definition. (tests/test_viewer_browser.py drags in a real browser.)"""

from __future__ import annotations

import time
from types import SimpleNamespace as NS

import numpy as np
import pytest

import rtfem as rt
from conftest import cut_state, cuts_settled, free_port, wait_until

pytest.importorskip("viser", reason="the viewer extra (viser) is not installed")

from rtfem.viewer.cut_view import CUT_ABOVE, CUT_DEPTH, blade  # noqa: E402

L, W = 0.1, 0.02


def test_the_blade_runs_along_the_line_of_sight():
    tip, heel = blade((1.0, 2.0, 3.0), (1.0, 2.0, 13.0))
    np.testing.assert_allclose(tip, (1.0, 2.0, 3.0 - CUT_DEPTH))
    np.testing.assert_allclose(heel, (1.0, 2.0, 3.0 + CUT_ABOVE))


def _event(phase, y):
    """A ctrl+drag event as viser sends it: the pointer on the plane facing the camera, through the block's top."""
    p = (L / 2, y, 0.019)
    return NS(phase=phase, end_position=p, start_position=p, client=NS(camera=NS(position=(L / 2, y, 0.5))))


def test_a_ctrl_drag_across_the_block_cuts_it_and_the_viewer_draws_the_cut():
    from rtfem.viewer.app import Viewer
    from rtfem.viewer.session import Session, Settings

    mesh = rt.meshes.box(L, W, W, nx=20, ny=4, nz=4)
    ends = np.concatenate([mesh.groups["x0"], mesh.groups["x1"]])
    s = Session(mesh, rt.Material(E=3e5, nu=0.45, density=1060.0), fixed=ends,
                settings=Settings(method="direct", large=True, dt=2e-3))
    n0 = s.model.n_nodes
    v = Viewer(s, port=free_port()).start()
    try:
        v._on_cut(_event("start", -0.005))
        wait_until(lambda: s.scalpel is not None, 180, "scalpel mode")
        assert "hung at its equilibrium under gravity" in s.cut_status
        for k in range(60):
            v._on_cut(_event("update", -0.005 + 0.03 * k / 59))
            time.sleep(0.05)
        v._on_cut(_event("end", 0.025))
        # (generous: in a fresh clone beside the suite, the worker process's first cut compiles its kernels)
        wait_until(lambda: v.cuts_drawn >= 1, 240, lambda: f"a cut drawn ({cut_state(s, v)})")
        wait_until(lambda: cuts_settled(s, v), 240, "the cuts to settle")
        frames = v.frames
        wait_until(lambda: v.frames > frames + 3, 10, "frames after the cut")
        assert s.model.n_nodes > n0 and s.generation >= 1
        assert v._drawn_sent is s.drawn and np.asarray(v.pick.vertices).shape == (s.drawn.size, 3)
        assert v.state()["error"] is None
        with pytest.raises(rt.ModelError, match="scalpel mode"):
            s.grab((L, W / 2, W / 2))
    finally:
        v.stop()


class _Recorder:
    """A session's cut and lift, recorded (scalpel mode entered by the first cut, after ``delay`` s)."""

    def __init__(self, delay: float = 0.0) -> None:
        self.calls, self.scalpel, self.generation, self.cut_status, self.error, self.delay = [], None, 0, "", None, delay

    def cut(self, tip, heel) -> None:
        if self.scalpel is None:
            time.sleep(self.delay)
            self.scalpel = object()
        self.calls.append(("cut", float(tip[1])))

    def lift(self) -> None:
        self.calls.append(("lift",))


def _front_end(session):
    from rtfem.viewer.cut_view import CutView

    class Front(CutView):
        def __init__(self) -> None:
            self.session, self.mode_index, self._mode_dropdown = session, None, NS(value="")
            self._init_cut()

    return Front()


def test_strokes_that_come_between_two_frames_reach_the_session_in_order_each_ending_in_a_lift():
    """Two strokes within one frame (and one while scalpel mode is being entered): each stroke's blade
    moves, its end lifts the blade, and the second does not continue the first (the mouse's last blade
    of a stroke is the one placed: the places between are the frames', not the session's)."""
    s = _Recorder(delay=0.3)
    front = _front_end(s)
    front._on_cut(_event("start", 0.001))
    front._apply_cut()  # enters scalpel mode with the first blade, on a thread
    for phase, y in [("update", 0.002), ("update", 0.003), ("end", 0.003), ("start", 0.010), ("update", 0.011),
                     ("end", 0.011)]:
        front._on_cut(_event(phase, y))
        front._apply_cut()  # (held: still entering)
    front._entering.join()
    front._on_cut(_event("start", 0.020))
    front._on_cut(_event("end", 0.020))
    front._apply_cut()
    assert s.calls == [("cut", 0.001), ("cut", 0.003), ("lift",), ("cut", 0.011), ("lift",), ("cut", 0.020), ("lift",)]
    assert front.cut_drags == 3
