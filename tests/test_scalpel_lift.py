"""rt.Scalpel.lift() with the physics on its own thread (the haptic setting) waits for nothing. It used to
take the physics' lock, which the thread stepping flat out took again first, step after step (7-283 ms on the
9k-tet liver of benchmarks/scalpel.py, the ticks meanwhile giving the cutting force), and sweep the blade's
last strip itself; the physics thread now sweeps it at its next step, or finish().
Checked: lift() returns while a physics step holds the lock; the force is zero at once; the last strip
(shorter than ``advance``) joins the cut surface all the same, from where the physics last swept to where
the blade was lifted; the next stroke starts where the blade is placed again, with no strip across the
gap; unthreaded, lift() sweeps at once as before and ends as the threaded one does."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

import rtfem as rt

L, W = 0.1, 0.02
MAT = rt.Material(E=3e4, nu=0.45, density=1060.0)
BLADE = (0.0, 0.0, W / 2 + 0.01)


def _scalpel(thread: bool) -> rt.Scalpel:
    mesh = rt.meshes.box(L, W, W, nx=20, ny=4, nz=4)
    model = rt.SolidModel(mesh, MAT).fix(mesh.groups["x0"])
    return rt.Scalpel(rt.DirectSimulator(model, 2e-3, large_deformation=True), blade=BLADE, gravity=(0, 0, 0),
                      toughness=0.0, thread=thread, worker=False)


def _at(y: float) -> np.ndarray:
    return np.array([L / 2, y, 0.005])


def _ticks(sc: rt.Scalpel, y: float, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        sc.update(_at(y))
        time.sleep(1e-3)


def _y_of_cells(sc: rt.Scalpel) -> np.ndarray:
    """Each cell's (two triangles') y extent, (c, 2)."""
    y = sc.vertices[sc.triangles[0::2]][:, :, 1] if sc.triangles.size else np.zeros((0, 3))
    return np.stack([y.min(axis=1), y.max(axis=1)], axis=1) if y.size else np.zeros((0, 2))


def test_a_lift_while_a_physics_step_holds_the_lock_returns_at_once_and_its_strip_is_swept_after():
    sc = _scalpel(thread=True)
    try:
        _ticks(sc, 0.004, 0.3)  # the physics thread running, its last sweep at y = 4 mm
        assert sc._thread is not None and sc.physics_steps > 0
        y1 = 0.004 + 0.6 * sc.advance  # past the last sweep by less than an advance: no strip yet
        with sc._lock:  # a physics step in progress
            before = sc.triangles.shape[0]
            sc.update(_at(y1))
            done = threading.Event()
            lifter = threading.Thread(target=lambda: (sc.lift(), done.set()))
            lifter.start()
            assert done.wait(5.0), "lift() waited for the physics step"
            assert np.all(sc.force == 0.0) and sc.lifted
            assert sc.triangles.shape[0] == before  # not swept by the tick
        lifter.join()
        sc.finish()
        assert not sc._lifts
        cells = _y_of_cells(sc)
        assert cells.shape[0] > 0 and cells[:, 1].max() == pytest.approx(y1, abs=1e-9)  # to where it was lifted
        # the next stroke, placed 8 mm on: its strips begin there, none across the gap
        _ticks(sc, 0.012, 0.3)
        for y in np.linspace(0.012, 0.018, 7):
            _ticks(sc, y, 0.05)
        sc.lift()
        sc.finish()
        cells = _y_of_cells(sc)
        assert not np.any((cells[:, 0] < y1 + 1e-6) & (cells[:, 1] > 0.012 - 1e-6))
        assert cells[:, 1].max() == pytest.approx(0.018, abs=1e-9)
    finally:
        sc.close()


def test_unthreaded_a_lift_sweeps_at_once_the_strip_the_threaded_one_sweeps_later():
    """The same blade positions and physics steps, unthreaded (lift sweeps at once) and as the threaded scalpel
    has it (a physics thread marked running: the next step sweeps): the same cut surface, the block at rest."""
    surfaces = []
    for deferred in (False, True):
        sc = _scalpel(thread=False)
        sc.update(_at(0.004))
        sc.physics_step()
        sc.update(_at(0.004 + 0.6 * sc.advance))
        if deferred:
            sc._thread = threading.current_thread()  # (as a running physics thread is, for lift())
        sc.lift()
        assert np.all(sc.force == 0.0) and len(sc._lifts) == (1 if deferred else 0)
        sc.physics_step()
        sc._thread = None
        assert not sc._lifts
        sc.update(_at(0.012))
        sc.physics_step()
        surfaces.append((sc.vertices.copy(), sc.triangles.copy()))
        sc.close()
    assert surfaces[0][1].shape[0] > 0
    assert np.array_equal(surfaces[0][1], surfaces[1][1])
    assert np.abs(surfaces[0][0] - surfaces[1][0]).max() < 1e-12  # (m: the block at rest moves by round-off in a step)
