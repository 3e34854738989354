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
