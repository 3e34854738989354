"""The stepping threads' scheduling priority (rtfem.threads.raise_priority): raised on the calling
thread only where the system permits it, a reason in words where it does not, never an error."""

import os
import threading

import numpy as np
import pytest

import rtfem as rt
from rtfem import threads


def _in_thread(fn):
    out = {}

    def work():
        out["got"] = fn()
        out["nice"] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    t = threading.Thread(target=work)
    t.start()
    t.join()
    return out


def _permitted() -> bool:
    got = _in_thread(threads.raise_priority)["got"]
    return got.startswith("nice")


@pytest.mark.skipif(not hasattr(os, "setpriority"), reason="per-thread nice values are Linux's")
def test_the_calling_thread_alone_gets_the_raised_priority(monkeypatch):
    monkeypatch.delenv("RTFEM_PHYSICS_NICE", raising=False)
    if not _permitted():
        pytest.skip("raising a thread's priority is not permitted here (no CAP_SYS_NICE or RLIMIT_NICE)")
    before = os.getpriority(os.PRIO_PROCESS, 0)
    out = _in_thread(threads.raise_priority)
    assert out["got"] == f"nice {threads.PHYSICS_NICE}" and out["nice"] == threads.PHYSICS_NICE
    assert os.getpriority(os.PRIO_PROCESS, 0) == before  # this thread (the process's main one) unchanged
    monkeypatch.setenv("RTFEM_PHYSICS_NICE", "-3")
    assert _in_thread(threads.raise_priority) == {"got": "nice -3", "nice": -3}


@pytest.mark.skipif(not hasattr(os, "setpriority"), reason="per-thread nice values are Linux's")
def test_a_priority_not_permitted_or_not_asked_for_is_said_in_words(monkeypatch):
    def refuse(*args):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(os, "setpriority", refuse)
    got = _in_thread(threads.raise_priority)["got"]
    assert got.startswith("normal: not permitted (Permission denied)") and "nice -10" in got
    monkeypatch.setenv("RTFEM_PHYSICS_NICE", "0")
    assert threads.raise_priority() == "normal: RTFEM_PHYSICS_NICE asks for none"
    monkeypatch.setenv("RTFEM_PHYSICS_NICE", "high")
    assert threads.raise_priority() == "normal: RTFEM_PHYSICS_NICE='high' is not a whole number"


def test_a_haptic_loop_reports_its_threads_priority(monkeypatch, liver3_modes):
    """The loop's thread asks for the raised priority and records what it got in its stats."""
    monkeypatch.delenv("RTFEM_PHYSICS_NICE", raising=False)
    model, modes = liver3_modes
    mesh = model.mesh
    sim = rt.ModalSimulator(modes, dt=1e-3)
    far = np.asarray(mesh.vertices).max(axis=0) + 1.0  # a hand far from the organ: free steps
    stats = rt.HapticLoop(rt.Probe(mesh, sim), rt.ScriptedDevice(lambda t: far), rate=1000).run(0.05)
    expected = _in_thread(threads.raise_priority)["got"]
    assert stats.steps >= 10 and stats.priority == expected


@pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="real-time scheduling is Linux's")
def test_real_time_scheduling_is_asked_for_by_the_calling_thread_only_and_said(monkeypatch):
    """raise_to_realtime puts the calling thread (not the process) under SCHED_FIFO where permitted, else
    falls back to raise_priority's nice value and says why; RTFEM_HAPTIC_RT=0 asks for none."""
    def got_in_thread():
        out = {}

        def work():
            out["got"] = threads.raise_to_realtime()
            out["policy"] = os.sched_getscheduler(threading.get_native_id())

        t = threading.Thread(target=work)
        t.start()
        t.join()
        return out

    monkeypatch.delenv("RTFEM_HAPTIC_RT", raising=False)
    monkeypatch.delenv("RTFEM_PHYSICS_NICE", raising=False)
    out = got_in_thread()
    if out["got"].startswith("SCHED_FIFO"):
        assert out["got"] == f"SCHED_FIFO {threads.HAPTIC_RT_PRIORITY}" and out["policy"] == os.SCHED_FIFO
    else:
        assert "real-time scheduling not permitted" in out["got"] and out["policy"] != os.SCHED_FIFO
    assert os.sched_getscheduler(0) != os.SCHED_FIFO  # this (the main) thread unchanged

    def refuse(*args):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    out = got_in_thread()
    assert "real-time scheduling not permitted: Operation not permitted" in out["got"] and "rtprio 10" in out["got"]
    monkeypatch.setenv("RTFEM_HAPTIC_RT", "0")
    assert got_in_thread()["got"] == _in_thread(threads.raise_priority)["got"]


def test_a_multi_rate_loop_runs_its_ticks_in_real_time_where_permitted(monkeypatch):
    """rt.HapticLoop asks for real-time scheduling for a multi-rate tool's light ticks, the raised nice
    value for a tool whose tick steps the physics."""
    monkeypatch.delenv("RTFEM_HAPTIC_RT", raising=False)
    monkeypatch.delenv("RTFEM_PHYSICS_NICE", raising=False)
    model = rt.SolidModel(rt.meshes.box(0.04, 0.02, 0.02, nx=4, ny=2, nz=2), rt.Material(E=3e4, nu=0.4), element="tet4")
    model.fix("x0")
    sim = rt.DirectSimulator(model, 1e-3, rt.Damping(alpha=10.0), large_deformation=True)
    far = np.asarray(model.mesh.vertices).max(axis=0) + 1.0
    policies = set()  # the physics thread's scheduling, read at each tick

    def position(t):
        physics = probe._thread
        if physics is not None and physics.native_id is not None and probe.physics_steps:
            policies.add((os.sched_getscheduler(physics.native_id), os.sched_getparam(physics.native_id).sched_priority))
        return far

    with rt.MultiRateProbe(model.mesh, sim) as probe:
        stats = rt.HapticLoop(probe, rt.ScriptedDevice(position), rate=1000).run(0.1)
    out = {}  # the words raise_to_realtime gives a thread here
    t = threading.Thread(target=lambda: out.setdefault("got", threads.raise_to_realtime()))
    t.start()
    t.join()
    assert stats.steps >= 10 and stats.priority == out["got"]
    # the physics thread, started by the first tick, runs one real-time priority below the ticks (it had their own,
    # and a tick could not pre-empt it, nor the cut jobs it starts), else at the stepping threads' raised nice value
    if stats.priority.startswith("SCHED_FIFO"):
        below = threads.HAPTIC_RT_PRIORITY - 1
        assert policies == {(os.SCHED_FIFO, below)} and probe.priority == f"SCHED_FIFO {below}"
    else:
        assert policies == {(os.SCHED_OTHER, 0)} and probe.priority == _in_thread(threads.raise_priority)["got"]


@pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="real-time scheduling is Linux's")
def test_a_thread_started_by_a_real_time_one_leaves_its_policy_or_goes_below_it():
    """A thread inherits its creator's scheduling: below_ticks (a multi-rate tool's physics thread) takes one
    FIFO priority below a real-time creator's, leave_realtime (the threads the physics starts: a scalpel's cut
    jobs, a factor refreshed on a thread) the normal policy; neither changes a normal thread's policy."""
    out = {}

    def grandchild():
        out["left"] = threads.leave_realtime(), os.sched_getscheduler(threading.get_native_id())

    def child():
        me = threading.get_native_id()
        out["below"] = threads.below_ticks(), os.sched_getscheduler(me), os.sched_getparam(me).sched_priority
        t = threading.Thread(target=grandchild)
        t.start()
        t.join()

    def parent():
        out["got"] = threads.raise_to_realtime()
        t = threading.Thread(target=child)
        t.start()
        t.join()

    t = threading.Thread(target=parent)
    t.start()
    t.join()
    if not out["got"].startswith("SCHED_FIFO"):
        pytest.skip(f"real-time scheduling not permitted here ({out['got']})")
    assert out["below"] == (f"SCHED_FIFO {threads.HAPTIC_RT_PRIORITY - 1}", os.SCHED_FIFO, threads.HAPTIC_RT_PRIORITY - 1)
    assert out["left"] == (True, os.SCHED_OTHER)
    assert _in_thread(threads.leave_realtime)["got"] is False  # a normal thread: nothing to leave


def test_the_cut_worker_process_takes_the_stepping_threads_nice_value_and_rtfem_physics_nice_0_leaves_it(monkeypatch):
    """The scalpel's cut worker process asks raise_priority for itself (by its pid): nice -10 where permitted,
    and RTFEM_PHYSICS_NICE=0 leaves it at the normal priority (it set PHYSICS_NICE whatever that said)."""
    from rtfem.interaction.cut_worker import CutWorker

    def nice_of_worker():
        worker = CutWorker()
        try:
            return os.getpriority(os.PRIO_PROCESS, worker._proc.pid)
        finally:
            worker.close()

    monkeypatch.delenv("RTFEM_PHYSICS_NICE", raising=False)
    assert nice_of_worker() == (threads.PHYSICS_NICE if _permitted() else os.getpriority(os.PRIO_PROCESS, 0))
    monkeypatch.setenv("RTFEM_PHYSICS_NICE", "0")
    assert nice_of_worker() == os.getpriority(os.PRIO_PROCESS, 0)


@pytest.mark.parametrize("bad", [0, -3, 1.5, "123", True])
def test_raise_priority_refuses_an_id_that_is_not_a_positive_whole_number_and_changes_nothing(bad):
    from rtfem.errors import RtfemError

    before = os.getpriority(os.PRIO_PROCESS, 0)
    with pytest.raises(RtfemError, match="native_id"):
        threads.raise_priority(bad)
    assert os.getpriority(os.PRIO_PROCESS, 0) == before
