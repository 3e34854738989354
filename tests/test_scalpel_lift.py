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


def _scalpel(thread: bool, toughness: float = 0.0) -> rt.Scalpel:
    mesh = rt.meshes.box(L, W, W, nx=20, ny=4, nz=4)
    model = rt.SolidModel(mesh, MAT).fix(mesh.groups["x0"])
    return rt.Scalpel(rt.DirectSimulator(model, 2e-3, large_deformation=True), blade=BLADE, gravity=(0, 0, 0),
                      toughness=toughness, thread=thread, worker=False)


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


def _played(seq, deferred: bool):
    """The scalpel after ``seq``: blade positions (y, m), "lift" and "step" (a physics step); ``deferred``: each lift
    as the threaded scalpel takes it (a physics thread marked running: the next step or finish() takes it)."""
    sc = _scalpel(thread=False)
    for op in seq:
        if op == "step":
            sc.physics_step()
        elif op == "lift":
            sc._thread = threading.current_thread() if deferred else None  # (as a running physics thread is)
            sc.lift()
            sc._thread = None
        else:
            sc.update(_at(op))
    sc.finish()
    return sc


@pytest.mark.parametrize("name", ["re-placed and moved an advance a step", "lifted twice, then re-placed",
                                  "placed and lifted twice before a step", "lifted before any blade"])
def test_unthreaded_a_lift_sweeps_at_once_the_surface_the_threaded_one_sweeps_later(name):
    """The same blade positions and physics steps, unthreaded (lift sweeps at once) and as the threaded scalpel
    has it (the next step sweeps): the same cut surface, the block at rest (a hostile probe's sequences: the
    threaded scalpel lost the strips of a stroke placed after a lift until the step after next)."""
    a = _scalpel(thread=False).advance
    seq = {"re-placed and moved an advance a step": [0.0, "step", 0.004, "step", 0.004 + 0.6 * a, "lift", 0.012, "step",
                                                     0.012 + a, "step", 0.012 + 2 * a, "step", 0.012 + 3 * a, "step",
                                                     "lift", "step"],
           "lifted twice, then re-placed": [0.0, "step", 0.004, "step", 0.0045, "lift", "lift", 0.010, "step",
                                            0.010 + 1.2 * a, "step", 0.010 + 2.4 * a, "step", "lift", "step"],
           "placed and lifted twice before a step": [0.0, "step", 0.004, "step", 0.0045, "lift", 0.008, "lift", 0.012,
                                                     "step", 0.012 + 1.5 * a, "step", "lift", "step"],
           "lifted before any blade": ["lift", 0.0, "step", 0.004, "step", 0.006, "lift", "step"]}[name]
    now, later = _played(seq, False), _played(seq, True)
    assert now.triangles.shape[0] > 0 and not later._lifts
    assert np.array_equal(now.triangles, later.triangles)
    assert np.abs(now.vertices - later.vertices).max() < 1e-12  # (m: the block at rest moves by round-off in a step)
    now.close()
    later.close()


def test_a_tick_while_the_physics_takes_a_lift_feels_nothing_and_nor_do_ticks_in_the_air_after():
    """A cut with liver's toughness, lifted as the threaded scalpel lifts; a tick comes while the physics step
    sweeps the lift's strip (it read the last stroke's resistance there: 0.6 N in a probe's run), then ticks with
    the blade in the air above the block: zero force, each."""
    sc = _scalpel(thread=False, toughness=164.0)
    for y in np.linspace(0.0, 0.012, 25):
        sc.update(_at(y), t=y / 0.02)
        sc.physics_step()
    assert sc.resistance > 0.1
    sc._thread = threading.current_thread()
    sc.lift()
    sc._thread = None
    air = [(_at(0.012 + 0.0005 * k) + [0, 0, 0.04], 1.0 + 1e-3 * k) for k in range(30)]  # the blade moving in the air
    felt = [sc.update(x, t=t).copy() for x, t in air[:5]]  # (before the physics step: the hand's motion is known)
    sweep = sc._sweep

    def sweep_and_tick(U, final=False, blade=None):
        sweep(U, final, blade)
        if final:
            felt.append(sc.update(air[5][0], t=air[5][1]).copy())

    sc._sweep = sweep_and_tick
    sc.physics_step()
    sc._sweep = sweep
    for x, t in air[6:]:
        felt.append(sc.update(x, t=t).copy())
        sc.physics_step()
    assert len(felt) == 30 and np.all(np.asarray(felt) == 0.0)
    sc.close()


def test_a_lift_after_the_ticks_stopped_joins_the_surface_at_close():
    sc = _scalpel(thread=True)
    try:
        _ticks(sc, 0.004, 0.3)
        y1 = 0.004 + 0.6 * sc.advance
        _ticks(sc, y1, 0.02)
        time.sleep(0.5)  # the ticks stopped: the physics thread waits for them
        sc.lift()
    finally:
        sc.close()
    assert not sc._lifts and _y_of_cells(sc)[:, 1].max() == pytest.approx(y1, abs=1e-9)


def test_a_close_whose_last_lift_cannot_be_swept_ends_all_the_same_and_says_so():
    """close() on a failing tick's way to zero force: a pending lift whose sweep raises is dropped with a word in
    ``refused``; the close ends (its worker process too)."""
    sc = _scalpel(thread=False)
    sc.update(_at(0.004))
    sc.physics_step()
    sc._thread = threading.current_thread()  # (a physics thread marked running: the lift waits for it)
    sc.update(_at(0.006))
    sc.lift()
    sc._thread = None

    def broken(*args, **kwargs):
        raise ValueError("a broken state")

    sc._sweep = broken
    sc.close()
    assert not sc._lifts and "not added to the cut (ValueError: a broken state)" in sc.refused
