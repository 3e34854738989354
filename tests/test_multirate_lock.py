"""The physics' lock of the multi-rate tools (rt.MultiRateGrasp, rt.MultiRateProbe, rt.Scalpel) shared with
the threads that grab, release, prepare or lift: the physics thread, stepping flat out, took it again first,
step after step, so such a call waited many steps (a grasp's release() on the 9k-tet liver of
benchmarks/fullorder.py returned after 19-267 ms by the median, the jaw pulling the hand meanwhile;
benchmarks/grab_wait.py).
Checked on a physics step made slow on purpose (40 ms busy in Python, the lock held): a grab gets the lock within the step
in progress and the next (the physics thread pauses for it); a release waits for nothing, zeroes the hand's
force at once and is taken by the physics at its next step; a grab after a release not yet taken grips
anew."""

from __future__ import annotations

import contextlib
import threading
import time

import numpy as np

import rtfem as rt

STEP = 0.04  # s: the slow physics step


def _grasp():
    mesh = rt.meshes.box(0.1, 0.04, 0.04, nx=10, ny=4, nz=4)
    model = rt.SolidModel(mesh, rt.Material(E=3e4, nu=0.45, density=1000.0), element="tet4").fix("x0")
    X = np.asarray(model.mesh.vertices)
    top = np.flatnonzero(np.isclose(X[:, 2], X[:, 2].max()))
    p = int(top[np.argmin(np.linalg.norm(X[top, :2] - [0.07, 0.02], axis=1))])
    sim = rt.DirectSimulator(model, 2e-3, rt.Damping(alpha=30.0), large_deformation=True)
    grasp = rt.MultiRateGrasp(model.mesh, sim, stiffness=300.0, radius=0.012, pace=False)
    advance = grasp._advance

    def slow():  # (under the lock, as every physics step; busy in Python, as the step's own code is between kernels)
        advance()
        end = time.perf_counter() + STEP
        while time.perf_counter() < end:
            pass

    grasp._advance = slow
    return grasp, X, p


@contextlib.contextmanager
def _held(lock):
    """``lock`` held by another thread (as a physics step holds it) for the block."""
    taken, free = threading.Event(), threading.Event()

    def hold():
        with lock:
            taken.set()
            free.wait(30.0)

    holder = threading.Thread(target=hold)
    holder.start()
    assert taken.wait(30.0)
    try:
        yield
    finally:
        free.set()
        holder.join()


def _ticking(grasp, at, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        grasp.update(at)
        time.sleep(1e-3)


def test_a_grab_waits_one_step_not_many_and_a_release_waits_for_nothing():
    grasp, X, p = _grasp()
    try:
        _ticking(grasp, X[p], 0.3)
        assert grasp._thread is not None and grasp.physics_steps >= 3
        seen = []
        grab = grasp.physics.grab
        grasp.physics.grab = lambda *a, **k: (seen.append(grasp.physics_steps), grab(*a, **k))[1]
        for _ in range(3):  # the ticks go on on another thread while this one grabs and releases
            before = grasp.physics_steps
            ticks = threading.Thread(target=_ticking, args=(grasp, X[p] + [0, 0, 0.004], 0.5))
            ticks.start()
            time.sleep(0.1)
            before = grasp.physics_steps
            held = grasp.grab(p)
            assert held.size > 3 and seen[-1] - before <= 2  # the step in progress, and one begun as it was asked
            time.sleep(3 * STEP)
            assert np.linalg.norm(grasp.force) > 0  # the jaw pulls
            with _held(grasp._lock):  # a physics step in progress, on another thread, as long as this takes
                done = threading.Event()
                threading.Thread(target=lambda: (grasp.release(), done.set())).start()
                assert done.wait(5.0), "release() waited for the physics step"
                assert grasp.physics.node is not None  # the physics has not let go yet ...
                assert np.all(grasp.update(X[p] + [0, 0, 0.004]) == 0.0)  # ... but the hand feels nothing
            ticks.join()
            _ticking(grasp, X[p], 3 * STEP)
            assert grasp.physics.node is None and grasp.node is None  # taken at the next step
    finally:
        grasp.close()


def test_a_grab_after_a_release_the_physics_has_not_taken_grips_anew():
    grasp, X, p = _grasp()
    try:
        _ticking(grasp, X[p], 0.2)
        grasp.grab(p)
        with _held(grasp._lock):
            grasp.release()
            assert grasp._let_go
        q = int(np.argmin(np.linalg.norm(X - (X[p] - [0.02, 0, 0]), axis=1)))
        held = grasp.grab(q)
        assert grasp.physics.node == q == grasp.node and not grasp._let_go and held.size > 0
        _ticking(grasp, X[q] + [0, 0, 0.004], 4 * STEP)
        assert grasp.physics.node == q and np.linalg.norm(grasp.force) > 0
    finally:
        grasp.close()


def test_grabs_back_to_back_from_another_thread_do_not_stop_the_physics():
    """The physics thread pauses for the calls waiting when its step ends, not for those that come while it
    pauses: a thread grabbing back to back stopped it (0 steps a second against 500, a hostile probe)."""
    grasp, X, p = _grasp()
    stop = threading.Event()

    def grabs():
        while not stop.is_set():
            grasp.grab(p)

    try:
        _ticking(grasp, X[p], 0.2)
        grabber = threading.Thread(target=grabs)
        grabber.start()
        time.sleep(0.1)
        before = grasp.physics_steps
        _ticking(grasp, X[p], 20 * STEP)
        steps = grasp.physics_steps - before
        stop.set()
        grabber.join()
        assert steps >= 3, steps  # (about one step in two, each grab going in between)
    finally:
        stop.set()
        grasp.close()


def test_a_grab_that_comes_while_a_release_runs_leaves_both_sides_holding_it():
    """A grab from another thread in the middle of a release (here while the hand's side lets go): it waits for the
    release, then both sides hold its grip. It could grab between the release's two halves and have the
    release's second half let go of the hand's side alone: the organ pulled, the hand feeling nothing."""
    grasp, X, p = _grasp()
    try:
        _ticking(grasp, X[p], 0.2)
        grasp.grab(p)
        q = int(np.argmin(np.linalg.norm(X - (X[p] - [0.02, 0, 0]), axis=1)))
        let_go = grasp.haptic.release
        grabber = threading.Thread(target=grasp.grab, args=(q,))

        def release_slowly():
            grabber.start()
            time.sleep(0.2)  # (the grab has the physics' lock by now and waits for the release's)
            let_go()

        grasp.haptic.release = release_slowly
        grasp.release()
        grasp.haptic.release = let_go
        grabber.join(30.0)
        _ticking(grasp, X[q] + [0, 0, 0.004], 4 * STEP)
        assert grasp.physics.node == q == grasp.node and np.linalg.norm(grasp.force) > 0
    finally:
        grasp.close()


def test_a_release_in_the_middle_of_a_tick_leaves_that_tick_at_zero_force_not_an_error():
    """A release from another thread while a tick reads the grip (here inside its read of the jaw's free step): the
    tick read part of each grip and raised 'nodes is empty' (a probe: 4-6 ticks in 30 s of grabs and releases); it
    feels nothing now, and the next tick has the released grip."""
    grasp, X, p = _grasp()
    try:
        _ticking(grasp, X[p], 0.1)
        grasp.grab(p)
        _ticking(grasp, X[p] + [0, 0, 0.004], 3 * STEP)
        assert grasp.nodes.size > 1 and np.linalg.norm(grasp.update(X[p] + [0, 0, 0.004])) > 0
        snapshot = grasp.haptic.driver
        predict_at = snapshot.predict_at

        def released_meanwhile(nodes):
            snapshot.predict_at = predict_at
            out = predict_at(nodes)
            grasp.release()
            return out

        snapshot.predict_at = released_meanwhile
        assert np.all(grasp.update(X[p] + [0, 0, 0.004]) == 0.0)
        assert grasp.node is None and np.all(grasp.update(X[p] + [0, 0, 0.004]) == 0.0)
    finally:
        grasp.close()
