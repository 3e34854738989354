"""The scalpel's cut worker process (rtfem.interaction.cut_worker) warmed up for the model it will cut: a
fresh worker's first job used to load rtfem's cutting and its compiled kernels (0.9-1.7 s on the 9k-tet
liver, against 0.13-0.16 s a job after; benchmarks/scalpel.py prints both), so the worker now first cuts
a small block of the model's kind, element and law. What is checked here: the jobs after a warm-up are
answered in order and the model a warmed worker returns is the one this process makes (the same nodes and
tets, K and M to round-off), for tet4 and tet10, one law, a hyperelastic law and two regions; a warm-up that
fails is said in ``warm_note`` and the jobs go on; a worker that cannot be warmed for the model (a shell)
is refused before a process is started."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import scipy.sparse as sp

import rtfem as rt
from rtfem.errors import ModelError
from rtfem.interaction.cut_worker import CutWorker, cut_and_assemble

L, W = 0.1, 0.02
QUAD = np.array([[0, 1, 2], [0, 2, 3]])
#: a slit from the top halfway down at mid-length, through the middle of elements (10 cells along x: 10 mm
#: each, so x = 53 mm is 0.3 of a cell in), across the whole width
SLIT = np.array([[0.053, -0.001, W + 0.001], [0.053, W + 0.001, W + 0.001], [0.053, W + 0.001, W / 2],
                 [0.053, -0.001, W / 2]])


def _model(element: str, law: str) -> rt.SolidModel:
    mesh = rt.meshes.box(L, W, W, nx=10, ny=2, nz=4)
    if law == "regions":  # the far half ten times stiffer
        X = np.asarray(mesh.vertices)
        far = X[np.asarray(mesh.tets)].mean(axis=1)[:, 0] > L / 2
        mesh = rt.TetMesh(mesh.vertices, mesh.tets, labels=far.astype(int), groups=mesh.groups)
        material = {0: rt.Material(E=3e4, nu=0.45), 1: rt.Material(E=3e5, nu=0.45)}
    elif law == "neo-Hookean":
        material = rt.NeoHookean(mu=1.03e4, kappa=1e5)
    else:
        material = rt.Material(E=3e4, nu=0.45)
    return rt.SolidModel(mesh, material, element=element).fix(mesh.groups["x0"])


def _same(a, b) -> None:
    assert np.array_equal(np.asarray(a.tetmesh.tets), np.asarray(b.tetmesh.tets))
    assert np.array_equal(np.asarray(a.tetmesh.vertices), np.asarray(b.tetmesh.vertices))
    for A, B in ((a.K, b.K), (a.M, b.M)):
        assert abs(A - B).max() <= 1e-12 * abs(B).max()


@pytest.mark.parametrize("element,law", [("tet4", "linear"), ("tet10", "linear"), ("tet4", "neo-Hookean"),
                                         ("tet4", "regions")])
def test_a_warmed_worker_answers_its_jobs_in_order_with_the_model_this_process_makes(element, law):
    model = _model(element, law)
    worker = CutWorker(warm=model)
    try:
        first = worker.cut(model, SLIT, QUAD, "split")  # sent at once: the warm-up's answer is read first
        assert worker.warm_note == ""
        assert first.cut_info.nodes_added > 0
        _same(first, cut_and_assemble(model, SLIT, QUAD, "split"))
        lower = SLIT - [0.0, 0.0, W / 4]  # the next job, on the cut model: the slit deepened by a layer of cells
        _same(worker.cut(first, np.concatenate([SLIT, lower]), np.concatenate([QUAD, QUAD + 4]), "split"),
              cut_and_assemble(first, np.concatenate([SLIT, lower]), np.concatenate([QUAD, QUAD + 4]), "split"))
        assert worker.alive
    finally:
        worker.close()


def test_a_warm_up_that_fails_is_said_and_the_jobs_go_on():
    """A warm-up job the worker cannot do (a material that is none) is answered with why, read with the
    first job's answer; that job and the next are answered as a fresh worker's are."""
    model = _model("tet4", "linear")
    worker = CutWorker()
    try:
        pickle.dump(("warm", rt.SolidModel, "not a material", {}), worker._proc.stdin)
        worker._proc.stdin.flush()
        worker._owed = 1
        cut = worker.cut(model, SLIT, QUAD, "split")
        assert worker.warm_note and "material" in worker.warm_note.lower()
        _same(cut, cut_and_assemble(model, SLIT, QUAD, "split"))
        assert worker.cut(model, SLIT, QUAD, "split").n_nodes == cut.n_nodes
    finally:
        worker.close()


def test_a_worker_warmed_for_a_model_it_cannot_cut_is_refused_before_a_process_starts(monkeypatch):
    import subprocess

    started = []
    monkeypatch.setattr(subprocess, "Popen", lambda *a, **k: started.append(a))
    shell = rt.ShellModel(rt.meshes.liver(1), rt.Material(E=3e4, nu=0.45, thickness=0.005))
    with pytest.raises(ModelError):
        CutWorker(warm=shell)
    with pytest.raises(ModelError):
        CutWorker(warm="a model")
    assert started == []
    assert sp.issparse(_model("tet4", "linear").K)


def test_a_worker_warms_up_for_a_model_of_more_regions_than_its_block_had_tets():
    """A probe's case: 30 regions (the warm-up block had 24 tets, one region each at most): the warm-up goes well."""
    mesh = rt.meshes.box(L, W, W, nx=10, ny=2, nz=4)
    labels = np.arange(mesh.n_tets) % 30
    model = rt.SolidModel(rt.TetMesh(mesh.vertices, mesh.tets, labels=labels, groups=mesh.groups),
                          {k: rt.Material(E=3e4 * (1 + k / 10), nu=0.45) for k in range(30)}).fix(mesh.groups["x0"])
    worker = CutWorker(warm=model)
    try:
        worker.cut(model, SLIT, QUAD, "split")
        assert worker.warm_note == ""
    finally:
        worker.close()


def test_a_worker_that_answers_nothing_in_time_is_killed_and_said_gone():
    """A probe's case: a worker stopped (SIGSTOP) during its warm-up left the cut job waiting for good; past the
    timeout it is killed and cut() raises WorkerGone (the scalpel then cuts in its own process)."""
    import os
    import signal

    from rtfem.interaction.cut_worker import WorkerGone

    model = _model("tet4", "linear")
    for after_a_job in (False, True):  # stopped during its warm-up, and after it answered a job
        worker = CutWorker(warm=model, timeout=2.0)
        try:
            if after_a_job:
                assert worker.cut(model, SLIT, QUAD, "split").cut_info.nodes_added > 0
            os.kill(worker._proc.pid, signal.SIGSTOP)
            with pytest.raises(WorkerGone, match="answered nothing in 2 s and was killed"):
                worker.cut(model, SLIT, QUAD, "split")
            assert not worker.alive
        finally:
            worker.close()
    with pytest.raises(ModelError, match="timeout"):
        CutWorker(timeout=0.0)
