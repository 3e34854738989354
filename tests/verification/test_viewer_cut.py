"""The viewer's scalpel mode (issue 57: "in the viewer, drag with a modifier key cuts"), through the
session the front end drives (rtfem.viewer.cutting): a tet4 block 0.1 x 0.02 x 0.02 m clamped at both
ends, its blade drawn across its width at mid-length from above its top to 0.4 of its height.

- Entering scalpel mode hangs the organ at its static equilibrium under gravity (rt.solve_static's,
  set at rest): the steps after move it by nothing measurable.
- The stroke cuts the slit the blade swept and the session takes the cut organ as its own: the
  chosen method rebuilt on it (Reset) has the frequencies of the block built slit by index
  arithmetic (test_cut's mesh, the slit from the top to half the height at mid-length) within 0.1 %
  (the split nudges nodes by under a fifth of an edge; measured 0.016 %), lower than the uncut block's.
- A tet10 solid (the default organ's element) enters scalpel mode as tet4 on its corner nodes, and the
  panel says so (a cut tet10 organ turned its split elements inside out in the steps after): the same
  surface drawn, the same fixes, then the same cut as the tet4 block's, and Reset rebuilds tet4.
- A lifted blade cuts nothing more; a grasp, a device or a driver of one's own in scalpel mode, a
  shell and a blade of no length are refused, each with what to do; Reset through configure() starts
  from the method and switches the user had before scalpel mode.
"""

from __future__ import annotations

import numpy as np
import pytest

import rtfem as rt
from rtfem.viewer.session import Session, Settings

from test_cut import _slit_box

L, W = 0.1, 0.02
MAT = rt.Material(E=3e5, nu=0.45, density=1060.0)


def _ends(mesh):
    return np.concatenate([mesh.groups["x0"], mesh.groups["x1"]])


def _hz(model, r: int = 6) -> np.ndarray:
    return np.asarray(rt.modal_analysis(model, r).omega) / (2 * np.pi)


@pytest.fixture(scope="module", params=["tet4", "tet10"])
def stroke(request):
    mesh = rt.meshes.box(L, W, W, nx=20, ny=4, nz=4)
    s = Session(mesh, MAT, fixed=_ends(mesh), settings=Settings(method="direct", large=True, dt=2e-3),
                model_options={"element": request.param})
    drawn = np.asarray(s.mesh.vertices)[np.asarray(s.mesh.triangles)]
    s.cut((L / 2, -0.02, 0.1), (L / 2, -0.02, 0.12))  # enters scalpel mode (the blade far above), hangs
    s.lift()
    entered = {"element": request.param, "status": s.cut_status, "drawn": drawn,
               "now drawn": np.asarray(s.mesh.vertices)[np.asarray(s.mesh.triangles)], "model": s.model}
    uncut = _hz(s.model)  # (a tet10 organ's: the tet4 model on its corners)
    n0, drawn0 = s.model.n_nodes, s.drawn.size
    hung = s.displacements()
    for _ in range(5):
        s.step()
    drift = float(np.abs(s.displacements() - hung).max())
    x = s.X + s.displacements()
    mid = np.abs(s.X[:, 0] - L / 2) < 1e-9
    xc, top, bot = x[mid, 0].mean(), x[mid, 2].max(), x[mid, 2].min()
    for k in range(80):
        y = -0.005 + (W + 0.01) * k / 79
        s.cut((xc, y, bot + 0.4 * (top - bot)), (xc, y, top + 0.01))
        s.step()
    s.lift()
    swept = s.scalpel.triangles.shape[0]
    s.scalpel.finish()
    for _ in range(20):
        s.step()
    yield {"session": s, "uncut": uncut, "n0": n0, "drawn0": drawn0, "hung": hung, "drift": drift, "swept": swept,
           "entered": entered}
    s.stop()


def test_scalpel_mode_hangs_the_organ_at_rest_under_gravity(stroke):
    hung = stroke["hung"]
    assert hung[:, 2].min() < -1e-4  # it sags (0.27 mm at mid-span)
    assert stroke["drift"] <= 1e-6 * np.abs(hung).max()  # and stays there: an equilibrium, at rest


def test_a_tet10_organ_enters_scalpel_mode_as_tet4_on_its_corners_and_says_so(stroke):
    e = stroke["entered"]
    assert e["model"].element == "tet4" and np.flatnonzero(e["model"].fixed.any(axis=1)).size == 50  # both ends' nodes
    np.testing.assert_array_equal(e["now drawn"], e["drawn"])  # the same surface drawn
    if e["element"] == "tet10":
        assert "tet10 organ (3321 nodes) is cut as tet4 on its 525 corner nodes" in e["status"]
        assert e["model"].n_nodes == rt.SolidModel(rt.meshes.box(L, W, W, nx=20, ny=4, nz=4), MAT).n_nodes
    else:
        assert "corner" not in e["status"]


def test_the_stroke_cuts_the_slit_the_session_then_draws_and_rebuilds(stroke):
    s = stroke["session"]
    assert s.scalpel.triangles.shape[0] == stroke["swept"]  # nothing swept after the lift
    assert s.model.n_nodes == stroke["n0"] + 10  # the slit's two node rows above its front, copied
    assert s.generation >= 1 and s.drawn.size > stroke["drawn0"] and s.model.cut_info.pieces == 1
    assert s.displacements().shape == (s.model.n_nodes, 3)
    assert s.surface_displacements().shape == (s.drawn.size, 3)
    assert "cut" in s.cut_status
    with pytest.raises(rt.ModelError, match="scalpel mode.*Reset"):
        s.grab((L, W / 2, W / 2))
    cut_nodes = s.model.n_nodes
    s.configure(method="modal", n_modes=6)  # Reset: leaves scalpel mode, the cut kept
    assert s.scalpel is None and s.model.n_nodes == cut_nodes and s.modes.model is s.model and s.model.element == "tet4"
    mesh = _slit_box()
    slit = rt.SolidModel(mesh, MAT, element="tet4").fix(np.flatnonzero(np.isclose(np.asarray(mesh.vertices)[:, 0], 0.0)
                                                                        | np.isclose(np.asarray(mesh.vertices)[:, 0], L)))
    f_cut, f_slit = np.asarray(s.modes.frequencies[:6]), _hz(slit)
    np.testing.assert_allclose(f_cut, f_slit, rtol=1e-3)
    assert f_cut[0] < stroke["uncut"][0] * 0.99  # the slit softens the first bending mode


def test_what_scalpel_mode_refuses_is_said():
    shell = Session(rt.meshes.liver(), fixed="attachment", settings=Settings(method="modal", n_modes=6))
    with pytest.raises(rt.ModelError, match="shell cannot be cut.*--solid"):
        shell.cut((0, 0, 0), (0, 0, 0.03))
    mesh = rt.meshes.box(L, W, W, nx=10, ny=2, nz=2)
    s = Session(mesh, MAT, fixed=_ends(mesh), settings=Settings(method="modal", n_modes=6, dt=2e-3))
    with pytest.raises(rt.ModelError, match="tip and heel coincide"):
        s.cut((0.05, 0.01, 0.01), (0.05, 0.01, 0.01))
    assert s.scalpel is None
    s.cut((0.05, -0.01, 0.1), (0.05, -0.01, 0.12))  # scalpel mode, the blade away from the block
    assert s.scalpel is not None and s.settings.method == "direct"
    with pytest.raises(rt.ModelError, match="scalpel mode.*Reset"):
        s.attach_device(rt.ScriptedDevice(lambda t: (0.0, 0.0, 0.0)))
    with pytest.raises(rt.ModelError, match="scalpel mode.*Reset"):
        s.use_driver(s.driver)
    s.configure(n_modes=6)  # Reset through the API: the method and switches from before scalpel mode
    assert s.scalpel is None and (s.settings.method, s.settings.large) == ("modal", False)
    s.stop()


def test_a_cut_job_that_fails_after_the_stroke_is_said_and_the_next_stroke_cuts_again(monkeypatch):
    """A cut job failing (not a refusal: an error of the code's own) after the blade was lifted is said in the
    panel (it was said only by the blade's next tick, so never after a lift) and the organ steps on; the next
    stroke's job takes the strips that failed with its own: the block is cut through as rt.cut cuts it along
    the plane the strokes swept (mid-length, on element faces: its nodes there copied)."""
    mesh = rt.meshes.box(L, W, W, nx=10, ny=2, nz=2)
    s = Session(mesh, MAT, fixed=_ends(mesh), settings=Settings(method="direct", large=True, dt=2e-3))
    uncut = s.model
    s.cut((L / 2, -0.02, 0.1), (L / 2, -0.02, 0.12))  # scalpel mode, the blade away from the block
    sc = s.scalpel

    def fails(*args, **kwargs):
        raise ValueError("a fault of the cut's own")

    def stroke(y0, y1):
        for y in np.linspace(y0, y1, 30):
            s.cut((L / 2, y, -0.005), (L / 2, y, W + 0.01))
            s.step()
        s.lift()
        sc.join()
        s.step()

    with monkeypatch.context() as m:
        m.setattr(sc, "_cut", fails)
        stroke(-0.005, W / 2)
    assert sc.cuts == 0 and "a cut failed (ValueError: a fault of the cut's own)" in s.error
    failed = sc.triangles.shape[0]
    stroke(-0.005, W + 0.005)  # (over the first's strips too: a blade drawn along its slit adds none there)
    sc.finish()
    s.step()
    plane = np.array([[L / 2, -0.001, -0.005], [L / 2, W + 0.001, -0.005], [L / 2, W + 0.001, W + 0.01],
                      [L / 2, -0.001, W + 0.01]])
    # every strip in a job after the failed one, and the block cut through (a job that finds nothing new to cut leaves
    # _applied behind: in 3 of 10 runs the jobs went 42, 56, 70 and 84 triangles, the last cutting nothing the one of
    # 70 had not, and _applied stayed at 70 with the block cut through; the others went 42, 84)
    assert failed > 0 and sc._tried == sc.triangles.shape[0]
    assert sc.cuts >= 1 and s.model.n_nodes == rt.cut(uncut, plane, [[0, 1, 2], [0, 2, 3]]).n_nodes == uncut.n_nodes + 9
    s.stop()
