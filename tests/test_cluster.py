"""Precompute on a Dask cluster (issue 42): an impedance map built on a LocalCluster of two worker
processes, and on a real ``dask scheduler`` with two ``dask worker`` processes on loopback started
here (one killed mid-run), equals the map built here; the command line does the same; a scheduler
that cannot be reached is one line; a task that fails for good keeps what came back."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import rtfem as rt
from rtfem.errors import ModelError, SolverError

distributed = pytest.importorskip("distributed", reason="the cluster extra (dask.distributed) is not installed")

KW = dict(method="modal", n_modes=20, radius=0.02, times=(0.01, 0.05))


def _model():
    model = rt.ShellModel(rt.meshes.hemisphere(), rt.Material())
    X = np.asarray(model.mesh.vertices)
    return model.fix(np.flatnonzero(X[:, 2] <= X[:, 2].min() + 1e-9))


@pytest.fixture(scope="module")
def serial():
    return rt.ImpedanceMap.build(_model(), **KW)


def _same(a, b) -> None:
    assert b.info["complete"] and not b.info["error"]
    np.testing.assert_array_equal(a.loaded, b.loaded)
    np.testing.assert_array_equal(a.offsets, b.offsets)
    np.testing.assert_array_equal(a.neighbours, b.neighbours)
    for key in ("responses", "point"):
        x, y = getattr(a, key), getattr(b, key)
        assert np.abs(x - y).max() <= 1e-12 * np.abs(x).max(), key


def _kept_are_serial(serial, part) -> None:
    """Each node an incomplete map kept has the serial map's responses (to 1e-12)."""
    for k, j in enumerate(part.loaded):
        s = int(np.searchsorted(serial.loaded, j))
        a = serial.responses[serial.offsets[s]:serial.offsets[s + 1]]
        b = part.responses[part.offsets[k]:part.offsets[k + 1]]
        assert a.shape == b.shape and np.abs(a - b).max() <= 1e-12 * np.abs(serial.responses).max()


def _once(at: int, act):
    """A progress callback that calls ``act()`` once, when ``at`` results have come back, and the list
    it then holds that count in."""
    fired: list = []

    def progress(done, total, message=""):
        if done >= at and not fired:
            act()
            fired.append(done)
    return progress, fired


def _bar_once(monkeypatch, at: int, act) -> list:
    """The command line's progress bar replaced by :func:`_once`'s callback; its list."""
    import contextlib

    import rtfem.cli.main as cli

    tick, fired = _once(at, act)

    @contextlib.contextmanager
    def bar(*args, **kwargs):
        yield tick

    monkeypatch.setattr(cli, "progress_bar", bar)
    return fired


def _dome_args(tmp_path) -> list:
    """``rtfem impedance``'s arguments for the dome (written into ``tmp_path``) with the map settings of KW."""
    mesh = tmp_path / "dome.obj"
    rt.save_mesh(rt.meshes.hemisphere(), mesh)
    return [str(mesh), "--fix", "z<0.0001", "-n", "20", "--radius", "0.02", "--times", "0.01,0.05"]


def test_a_local_cluster_of_two_processes_builds_the_same_map(serial):
    _same(serial, rt.ImpedanceMap.build(_model(), scheduler="local:2", **KW))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture()
def real_cluster():
    """A ``dask scheduler`` and two ``dask worker`` processes (no nanny: a killed worker stays dead)."""
    dask = shutil.which("dask", path=str(Path(sys.executable).parent)) or shutil.which("dask")
    if dask is None:
        pytest.skip("the dask command is not installed (the cluster extra)")
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    quiet = dict(stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
                              **quiet)]
    try:
        for name in ("a", "b"):
            procs.append(subprocess.Popen([dask, "worker", address, "--nthreads", "1", "--no-nanny", "--no-dashboard",
                                           "--name", name], **quiet))
        client = None
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                client = client or distributed.Client(address, timeout=5)
                if len(client.scheduler_info()["workers"]) == 2:
                    break
            except OSError:
                pass
            time.sleep(0.3)
        else:
            pytest.fail("the scheduler and two workers did not come up within 60 s")
        yield address, client, procs
        client.close()
    finally:
        for p in procs:
            p.kill()
            p.wait()


def test_real_workers_build_the_same_map_also_when_one_is_killed(serial, real_cluster):
    address, client, procs = real_cluster
    progress, killed = _once(3, lambda: procs[1].send_signal(signal.SIGKILL))  # mid-run: "a" dies with its tasks

    imap = rt.ImpedanceMap.build(_model(), scheduler=client, progress=progress, **KW)
    assert killed and killed[0] < serial.loaded.size and procs[1].wait(10) != 0
    _same(serial, imap)
    assert len(client.scheduler_info()["workers"]) == 1


def test_the_command_line_against_real_workers_writes_the_serial_map(real_cluster, tmp_path, capsys, monkeypatch):
    """rtfem impedance --scheduler tcp://... against a scheduler and two workers (issue 42's done-when),
    worker "a" killed after the third node came back (through the command's progress bar)."""
    import rtfem.cli.main as cli

    address, _, procs = real_cluster
    common = _dome_args(tmp_path)
    assert cli.main(["impedance", *common, "-o", str(tmp_path / "serial.npz")]) == 0
    killed = _bar_once(monkeypatch, 3, lambda: procs[1].send_signal(signal.SIGKILL))
    assert cli.main(["impedance", *common, "--scheduler", address, "-o", str(tmp_path / "cluster.npz")]) == 0
    assert killed and procs[1].wait(10) != 0
    a, b = rt.ImpedanceMap.load(tmp_path / "serial.npz"), rt.ImpedanceMap.load(tmp_path / "cluster.npz")
    assert a.loaded.size > 100
    _same(a, b)
    capsys.readouterr()
    assert cli.main(["impedance", *common, "--scheduler", f"tcp://127.0.0.1:{_free_port()}", "-o",
                     str(tmp_path / "none.npz")]) == 2
    err = capsys.readouterr().err
    said = [line for line in err.splitlines() if "error" in line]
    assert len(said) == 1 and "could not reach the Dask scheduler at tcp://127.0.0.1:" in said[0], err
    assert "Traceback" not in err
    assert not (tmp_path / "none.npz").exists()


def test_modal_derivatives_on_real_workers_equal_the_serial_ones_also_when_one_is_killed(real_cluster):
    """ReducedNonlinearModel(scheduler=...): the tangent differences (one derivative mode a task) on
    the workers, the solves here: the basis equals the serial one (to 1e-12; the same sums in the same
    order: bit for bit here), also with worker "a" killed after the first column came back."""
    from rtfem.reduction.reduced import ReducedNonlinearModel

    address, client, procs = real_cluster
    model = _model()
    modes = rt.modal_analysis(model, 10)
    serial = ReducedNonlinearModel(model, modes, derivatives=6)
    progress, killed = _once(1, lambda: procs[1].send_signal(signal.SIGKILL))

    cluster = ReducedNonlinearModel(_model(), modes, derivatives=6, progress=progress, scheduler=address)
    assert killed and killed[0] < 6
    assert np.abs(cluster.basis - serial.basis).max() <= 1e-12 * np.abs(serial.basis).max()
    assert serial.n_derivatives == cluster.n_derivatives == 21


@pytest.fixture(scope="module")
def local2():
    from rtfem.cluster import connect

    with connect("local:2") as client:
        yield client


def test_cubature_poses_on_a_local_cluster_choose_the_same_elements_and_weights(local2):
    from rtfem.reduction.reduced import ReducedNonlinearModel

    model = _model()
    red = ReducedNonlinearModel(model, rt.modal_analysis(model, 10), derivatives=4)
    for remainder in (False, True):
        here = red.train_cubature(8, remainder=remainder)
        there = red.train_cubature(8, remainder=remainder, scheduler=local2)
        np.testing.assert_array_equal(here["elements"], there["elements"])
        assert np.abs(here["weights"] - there["weights"]).max() <= 1e-12 * here["weights"].max()


@pytest.mark.parametrize("method", ["solves", "condensation"])
def test_a_solids_surface_compliance_on_a_local_cluster_equals_the_one_here(local2, method):
    model = rt.SolidModel(rt.meshes.box(0.04, 0.02, 0.02, nx=4, ny=2, nz=2), rt.Material())
    X = np.asarray(model.tetmesh.vertices)
    model.fix(np.flatnonzero(X[:, 0] == 0.0))
    nodes, C = model.surface_compliance(method=method)
    memory = 8 * model.n_dofs * 8  # blocks of 8 columns: several tasks
    nodes2, C2 = model.surface_compliance(method=method, memory=memory, scheduler=local2)
    np.testing.assert_array_equal(nodes, nodes2)
    assert np.abs(C - C2).max() <= 1e-12 * np.abs(C).max()


def _fails_on_seven(chunk):
    if 7 in chunk:
        time.sleep(2.0)  # after the others
        raise RuntimeError("node 7 broke")
    return [int(j) * 2 for j in chunk]


def test_a_task_that_fails_for_good_keeps_what_came_back(local2):
    from rtfem.cluster import run_tasks

    got = []
    why = run_tasks(local2, _fails_on_seven, (), [[j] for j in range(10)], got.extend)
    # what came back is kept (a task queued behind the failing one on its worker may be cancelled)
    assert "node 7 broke" in why and set(got) <= {0, 2, 4, 6, 8, 10, 12, 16, 18} and len(got) >= 5, got
    with pytest.raises(SolverError, match="first tasks failed"):
        run_tasks(local2, _fails_on_seven, (), [[7]], got.extend)


def test_ctrl_c_on_a_cluster_keeps_the_nodes_that_came_back(serial, local2):
    def progress(done, total, message):
        if done == 40:
            raise KeyboardInterrupt

    imap = rt.ImpedanceMap.build(_model(), scheduler=local2, progress=progress, **KW)
    assert not imap.info["complete"] and imap.info["error"] == "interrupted"
    assert 40 <= imap.loaded.size < serial.loaded.size
    _kept_are_serial(serial, imap)  # each node kept is the serial map's


def test_bad_scheduler_texts_are_refused():
    with pytest.raises(ModelError, match="local:N takes"):
        rt.ImpedanceMap.build(_model(), scheduler="local:0", **KW)
    with pytest.raises(ModelError, match="tcp://HOST:PORT"):
        rt.ImpedanceMap.build(_model(), scheduler="somehost:8786", **KW)
    with pytest.raises(ModelError, match="static='solves'"):
        rt.ImpedanceMap.build(_model(), scheduler="local:1", static="condensation", **KW)
    assert os.environ.get("DASK_SCHEDULER_ADDRESS") is None  # nothing here reaches for a default cluster


def test_every_scheduler_entry_point_refuses_a_bad_address_and_changes_nothing(tmp_path, capsys):
    from rtfem.cli.main import main
    from rtfem.reduction.reduced import ReducedNonlinearModel

    model = _model()
    modes = rt.modal_analysis(model, 8)
    with pytest.raises(ModelError, match="tcp://HOST:PORT"):
        ReducedNonlinearModel(model, modes, derivatives=3, scheduler="nowhere")
    red = ReducedNonlinearModel(model, modes, derivatives=3)
    red.train_cubature(6)
    before = (red._cubature_elements.copy(), red._cubature[1].copy(), red.basis.copy())
    with pytest.raises(ModelError, match="tcp://HOST:PORT"):
        red.train_cubature(6, tol=0.01, scheduler="nowhere")
    np.testing.assert_array_equal(red._cubature_elements, before[0])  # the cubature trained before stays
    np.testing.assert_array_equal(red._cubature[1], before[1])
    np.testing.assert_array_equal(red.basis, before[2])
    with pytest.raises(ModelError, match="tcp://HOST:PORT"):
        model.surface_compliance(scheduler="nowhere")
    with pytest.raises(ModelError, match="local:N takes"):
        model.surface_compliance(method="condensation", scheduler="local:x")
    mesh = tmp_path / "dome.obj"
    rt.save_mesh(rt.meshes.hemisphere(), mesh)
    assert main(["simulate", str(mesh), "--fix", "z<0.0001", "-n", "6", "--method", "nonlinear", "--duration", "0.01",
                 "--scheduler", "nowhere", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "tcp://HOST:PORT" in err and "Traceback" not in err and not (tmp_path / "out" / "response.csv").exists()


def _within(seconds: float, fn):
    """fn() on a thread; its result, or a failure naming the hang when it took longer than ``seconds``."""
    import threading

    out: list = []
    thread = threading.Thread(target=lambda: out.append(fn()), daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), f"the cluster run had not ended after {seconds:g} s"
    assert out, "the cluster run raised (see the thread's traceback above)"
    return out[0]


@pytest.mark.parametrize("moment", ["sending", "last"])
def test_a_worker_killed_while_the_modes_are_sent_or_before_the_last_result_still_gives_the_serial_map(
        serial, real_cluster, moment):
    """Issue 59: worker "a" killed (SIGKILL) while the modes go to the workers (the hang of a broadcast's
    replication waiting on the dead worker), or when all but the last node have come back: the run ends
    within 120 s with the serial map (to 1e-12). Killed while tasks run: the test above."""
    import threading

    address, client, procs = real_cluster
    killed, stages = [], []

    def kill() -> None:
        if not killed:
            procs[1].send_signal(signal.SIGKILL)
            killed.append(time.monotonic())

    def progress(done, total, message):
        stages.append(message)
        if moment == "sending" and message.startswith("copying"):
            threading.Timer(0.05, kill).start()  # while the submit of the modes is under way
        if moment == "last" and done == total - 1:
            kill()

    imap = _within(120, lambda: rt.ImpedanceMap.build(_model(), scheduler=client, progress=progress, **KW))
    assert killed and procs[1].wait(10) != 0
    assert stages[0].startswith("copying") and "MiB to the workers" in stages[0]  # the bar moves from the start
    _same(serial, imap)


def test_every_worker_killed_ends_with_one_line_and_the_partial_file(real_cluster, tmp_path, capsys, monkeypatch):
    """Issue 59: both workers killed (SIGKILL) after the third node came back: ``rtfem impedance
    --stall-timeout 4`` ends within 60 s with exit 1, one line saying no worker is left, and the nodes
    that came back in the .partial.npz (each equal to the serial map's); the output is not written."""
    import rtfem.cli.main as cli

    address, _, procs = real_cluster
    common = _dome_args(tmp_path)
    assert cli.main(["impedance", *common, "-o", str(tmp_path / "serial.npz")]) == 0
    killed = _bar_once(monkeypatch, 3, lambda: [p.send_signal(signal.SIGKILL) for p in procs[1:]])
    capsys.readouterr()
    t0 = time.monotonic()
    rc = cli.main(["impedance", *common, "--scheduler", address, "--stall-timeout", "4",
                   "-o", str(tmp_path / "cluster.npz")])
    took = time.monotonic() - t0
    err = capsys.readouterr().err
    assert rc == 1 and killed and took < 60, (rc, took, err)
    said = [line for line in err.splitlines() if line.startswith("rtfem:")]
    assert len(said) == 1 and "no live Dask worker answering for 4 s" in said[0] and "cluster.partial.npz" in said[0], err
    assert "Traceback" not in err and not (tmp_path / "cluster.npz").exists()
    a, b = rt.ImpedanceMap.load(tmp_path / "serial.npz"), rt.ImpedanceMap.load(tmp_path / "cluster.partial.npz")
    assert 3 <= b.loaded.size < a.loaded.size
    _kept_are_serial(a, b)


def test_stall_timeout_is_refused_when_nonsense_or_without_a_scheduler(tmp_path, capsys):
    import rtfem.cli.main as cli
    from rtfem.cluster import stall_timeout

    for bad in (0, -1, float("nan"), "soon"):
        with pytest.raises(ModelError, match="stall timeout"):
            with stall_timeout(bad):
                pass
    assert cli.main(["impedance", *_dome_args(tmp_path), "--stall-timeout", "5", "-o", str(tmp_path / "m.npz")]) == 2
    assert "--stall-timeout is for a run on a cluster: give --scheduler too" in capsys.readouterr().err
    assert not (tmp_path / "m.npz").exists()
    for bad in ("0", "-3", "nan", "soon"):
        assert cli.main(["impedance", *_dome_args(tmp_path), "--scheduler", "local:1", "--stall-timeout", bad, "-o",
                         str(tmp_path / "m.npz")]) == 2
        assert "argument --stall-timeout" in capsys.readouterr().err
    assert not (tmp_path / "m.npz").exists()


def test_the_scheduler_killed_mid_run_ends_the_run_with_why_and_keeps_what_came_back(serial, real_cluster):
    """Issue 59: the ``dask scheduler`` killed (SIGKILL) after the third node came back: the build
    ends within 90 s, incomplete, saying the scheduler is gone; the nodes kept are the serial map's."""
    from rtfem.cluster import stall_timeout

    address, client, procs = real_cluster
    progress, killed = _once(3, lambda: procs[0].send_signal(signal.SIGKILL))

    def build():
        with stall_timeout(4):
            return rt.ImpedanceMap.build(_model(), scheduler=address, progress=progress, **KW)

    imap = _within(90, build)
    assert killed and not imap.info["complete"], imap.info
    assert "scheduler" in imap.info["error"] and "\n" not in imap.info["error"], imap.info["error"]
    assert 3 <= imap.loaded.size < serial.loaded.size
    _kept_are_serial(serial, imap)


def _sleeps(seconds, chunk):
    time.sleep(seconds)
    return list(chunk)


def test_a_long_task_is_not_a_stall_and_tasks_that_never_run_are(local2):
    """The stall timeout (issue 59) counts time with no result and none of the run's tasks running on
    a live worker: tasks of 4 s under a 1.5 s timeout finish; tasks no worker can take (they ask for a
    resource none has) stop after the 3 s timeout with one line."""
    import dask

    from rtfem.cluster import run_tasks, stall_timeout

    got: list = []
    with stall_timeout(1.5):
        assert run_tasks(local2, _sleeps, (4.0,), [[1], [2]], got.extend) == ""
    assert sorted(got) == [1, 2]
    t0 = time.monotonic()
    with stall_timeout(3), dask.annotate(resources={"rtfem-test-nowhere": 1}):
        with pytest.raises(SolverError, match=r"no result came back and no task ran for 3 s on 2 answering worker"):
            run_tasks(local2, _sleeps, (0.0,), [[3], [4]], got.extend)
    assert 3 <= time.monotonic() - t0 < 12 and sorted(got) == [1, 2]


def test_a_frozen_worker_is_not_progress_and_a_lost_scheduler_is_one_line(real_cluster, tmp_path, capsys, monkeypatch):
    """Found by a hostile probe (issue 59): a worker frozen with SIGSTOP stays listed by the scheduler
    (Dask drops it after 5 min) with the run's tasks on it, which had counted as running, and the run
    hung: it now stops after the stall timeout, saying that a worker stopped answering, with exit 1
    and the nodes that came back. Then the scheduler killed: Dask's reconnect tracebacks stay off stderr."""
    import rtfem.cli.main as cli

    address, _, procs = real_cluster
    common = _dome_args(tmp_path)
    _bar_once(monkeypatch, 3, lambda: procs[1].send_signal(signal.SIGSTOP))  # worker "a" frozen, "b" healthy
    capsys.readouterr()
    t0 = time.monotonic()
    try:
        rc = cli.main(["impedance", *common, "--scheduler", address, "--stall-timeout", "4",
                       "-o", str(tmp_path / "frozen.npz")])
    finally:
        for p in procs[1:]:
            p.send_signal(signal.SIGCONT)
    err = capsys.readouterr().err
    said = [line for line in err.splitlines() if line.startswith("rtfem:")]
    assert rc == 1 and time.monotonic() - t0 < 150, (rc, err)  # a bound on a hang: the healthy worker first finishes its share
    # the frozen worker is named as not answering (a loaded machine's healthy worker may miss its own
    # heartbeats for 4 s too: then no worker answers, and the line says that one is listed but silent)
    assert len(said) == 1 and ("1 worker(s) have not answered for 4 s" in said[0]
                               or "listed but silent" in said[0]), err
    assert rt.ImpedanceMap.load(tmp_path / "frozen.partial.npz").loaded.size >= 3
    _bar_once(monkeypatch, 3, lambda: procs[0].send_signal(signal.SIGKILL))
    rc = cli.main(["impedance", *common, "--scheduler", address, "--stall-timeout", "4", "-o", str(tmp_path / "s.npz")])
    err = capsys.readouterr().err
    assert rc == 1 and "Traceback" not in err and "lost the connection to the Dask scheduler" in err, err
    assert [line for line in err.splitlines() if line.strip()] == [line for line in err.splitlines()
                                                                   if line.startswith("rtfem:")], err


def test_a_batch_on_real_workers_finishes_when_one_is_killed(real_cluster, tmp_path, capsys, monkeypatch):
    """Issue 59, ``rtfem batch``: three organs (a dome at three Young's moduli, their modes) on a real
    scheduler and two workers, worker "a" killed (SIGKILL) as the copy to the workers starts: every
    organ is written, its frequencies those of the library's modal
    analysis here (1e-10)."""
    import rtfem.cluster as cluster
    from rtfem.cli.main import main

    address, _, procs = real_cluster
    rt.save_mesh(rt.meshes.hemisphere(), tmp_path / "dome.obj")
    organs = {"soft": 2e4, "mid": 4e4, "stiff": 6e4}
    plan = 'out = "out"\n[defaults]\nbuild = ["modes"]\nmodes = 10\nfix = "z<0.0001"\nmesh = "dome.obj"\n'
    plan += "".join(f'[[organ]]\nname = "{n}"\nE = {E}\n' for n, E in organs.items())
    (tmp_path / "plan.toml").write_text(plan)
    original, killed = cluster.run_tasks, []

    def run_tasks(*args, stage=None, **kwargs):
        def hook(message):
            if message.startswith("copying") and not killed:  # as the plan's settings go to the workers
                procs[1].send_signal(signal.SIGKILL)
                killed.append(message)
            if stage is not None:
                stage(message)
        return original(*args, stage=hook, **kwargs)

    monkeypatch.setattr(cluster, "run_tasks", run_tasks)
    rc = _within(180, lambda: main(["batch", str(tmp_path / "plan.toml"), "--scheduler", address]))
    out = capsys.readouterr().out
    assert rc == 0 and killed and procs[1].wait(10) != 0, out
    assert "cluster     copying" in out
    for name, E in organs.items():
        model = rt.ShellModel(rt.meshes.hemisphere(), rt.Material(E=E))
        X = np.asarray(model.mesh.vertices)
        model.fix(np.flatnonzero(X[:, 2] < 0.0001))
        got = rt.ModalBasis.load(tmp_path / "out" / f"{name}.modes.npz", model=model).omega
        np.testing.assert_allclose(got, rt.modal_analysis(model, 10).omega, rtol=1e-10)
