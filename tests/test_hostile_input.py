"""Hostile input, as a new user meets it on the newer parts (issue 36, item 8): each case gets a
specific RtfemError that says what to do, and nothing already computed is changed."""

import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

import rtfem as rt
from rtfem.reduction.reduced import ReducedNonlinearModel
from rtfem.drivers.reduced_nonlinear import ReducedNonlinearSimulator


@pytest.fixture(scope="module")
def beam():
    model = rt.SolidModel(rt.meshes.box(1.0, 0.1, 0.1, nx=6, ny=2, nz=2), rt.Material(E=1e5, nu=0.3, density=10.0))
    model.fix("x0")
    modes = rt.modal_analysis(model, 6)
    red = ReducedNonlinearModel(model, modes, 2)
    red.train_cubature(4, tol=0.1)
    return model, modes, red


def test_unvalidated_arguments_are_refused_by_name(beam):
    model, modes, red = beam
    tip = int(model.select_nodes("x1")[0])
    load = {tip: (0.0, 0.0, 0.01)}
    cases = [
        ("cubature", lambda: red.solve_static(load, cubature="no")),
        ("max_cuts", lambda: red.solve_static(load, max_cuts=-5)),
        ("tol", lambda: red.solve_static(load, tol=float("nan"))),
        ("max_iterations", lambda: red.solve_static(load, max_iterations=0)),
        ("seed", lambda: red.train_cubature(4, seed="abc")),
        ("progress", lambda: ReducedNonlinearModel(model, modes, 2, progress=5)),
        ("cubature", lambda: ReducedNonlinearSimulator(red, 1e-3, cubature="no")),
        ("not a model", lambda: ReducedNonlinearModel("model", modes, 2)),
        ("out", lambda: rt.ModalSimulator(modes, 1e-3).displacements(out=np.zeros((3, 3)))),
        ("half_extents", lambda: rt.Tool(0.01, (0.01, 0.02, 0.03))),
        ("metres", lambda: rt.ToolContact(model.mesh, rt.ModalSimulator(modes, 1e-3)).update([1e300, 0.0, 0.0])),
        ("metres", lambda: rt.Probe(model.mesh, rt.ModalSimulator(modes, 1e-3)).update([1e300, 0.0, 0.0])),
        ("0.5", lambda: rt.Material(E=1e4, nu=0.5 - 1e-12)),
        ("pascals", lambda: rt.Material(E=1e-300, nu=0.3)),
    ]
    for match, call in cases:
        with pytest.raises(rt.RtfemError, match=match):
            call()
    assert red.info["cubature"]["elements"] > 0  # the cubature trained before is kept


def test_a_mechanism_has_no_silent_zero_frequency_modes():
    """Two tets joined at a vertex, one of them held: the static solve refuses it, and so does
    the modal analysis now (it returned three zero frequencies)."""
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0], [0, 0, -1.0]])
    model = rt.SolidModel(rt.TetMesh(V, np.array([[0, 1, 2, 3], [0, 4, 6, 5]])), rt.Material(E=1e3, nu=0.3, density=1.0))
    model.fix([1, 2, 3])
    with pytest.raises(rt.ModelError, match="mechanism"):
        rt.modal_analysis(model, 3)
    with pytest.raises(rt.ModelError, match="mechanism"):
        model.solve_static({4: (0.0, 0.0, 1.0)})


def test_a_driver_built_on_old_supports_refuses_to_step(beam):
    model0 = beam[0]
    model = rt.SolidModel(model0.tetmesh, model0.material).fix("x0")
    sim = rt.DirectSimulator(model, 1e-3)
    tip = int(model.select_nodes("x1")[0])
    sim.step({tip: (0.0, 0.0, 1.0)})
    state = sim.get_state()
    model.fix("x1")
    with pytest.raises(rt.ModelError, match="supports changed"):
        sim.step({tip: (0.0, 0.0, 1.0)})
    assert all(np.array_equal(v, state[k]) for k, v in sim.get_state().items())


def test_a_grasp_of_an_interior_node_is_refused(beam):
    model, modes, _ = beam
    interior = np.setdiff1d(np.arange(model.n_nodes), model.mesh.used_vertices())
    assert interior.size
    g = rt.Grasp(model.mesh, rt.ModalSimulator(modes, 1e-3))
    with pytest.raises(rt.ModelError, match="not on the surface"):
        g.grab(int(interior[0]))
    assert g.node is None


def test_two_loops_on_one_simulator_are_refused(beam):
    """Two probes (or a probe and a tool) on the same simulator would step it twice per tick."""
    model, modes, _ = beam
    sim = rt.ModalSimulator(modes, 1e-3)
    x = np.asarray(model.mesh.vertices)[int(model.select_nodes("x1")[0])] + [0.0, 0.0, 0.05]
    first = rt.HapticLoop(rt.Probe(model.mesh, sim), rt.ScriptedDevice(lambda t: x), compiled=False).start()
    try:
        for other in (rt.Probe(model.mesh, sim), rt.ToolContact(model.mesh, sim)):
            with pytest.raises(rt.ModelError, match="already driven"):
                rt.HapticLoop(other, rt.ScriptedDevice(lambda t: x), compiled=False).start()
    finally:
        first.stop()
    second = rt.HapticLoop(rt.Probe(model.mesh, sim), rt.ScriptedDevice(lambda t: x), compiled=False)
    second.start()  # once the first has stopped, another may drive it
    second.stop()


def test_the_cli_refuses_a_depth_through_the_organ(tmp_path):
    from rtfem.cli.main import main

    t0 = time.perf_counter()
    assert main(["simulate", "--depth", "1e9", "--duration", "0.01", "--out", str(tmp_path / "o")]) == 2
    assert time.perf_counter() - t0 < 30  # before the modes are computed
    assert not (tmp_path / "o").exists()


def test_tetrahedralize_checks_its_flag_estimates_its_size_and_keeps_ctrl_c():
    import signal

    from rtfem.mesh.meshing import mesher_available

    surface = rt.meshes.liver(3)
    with pytest.raises(rt.MeshError, match="optimize"):
        rt.tetrahedralize(surface, optimize="no")
    with pytest.raises(rt.MeshError, match="edge_length >="):  # ~6e7 tets: refused before meshing
        rt.tetrahedralize(surface, edge_length=1.01e-3 * surface.diagonal())
    if not mesher_available():
        pytest.skip("the fTetWild mesher (rtfem[mesh]) is not installed")
    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signal handlers live on the main thread")
    handler = signal.getsignal(signal.SIGINT)
    tiny = rt.TriMesh(np.asarray(surface.vertices) * 1e-7, surface.triangles)  # fTetWild crashed at this scale
    tets = rt.tetrahedralize(tiny)
    assert signal.getsignal(signal.SIGINT) is handler  # fTetWild's own handler is not left behind
    assert tets.n_tets > 100 and np.abs(np.asarray(tets.vertices)).max() < 1e-6
    assert abs(tets.volume() / (surface.volume() * 1e-21) - 1) < 0.01  # the same body, at its own scale
    # getsignal reports Python's table, not the C-level handler fTetWild replaces: a real Ctrl-C after
    # meshing must still raise KeyboardInterrupt (it killed `rtfem view organ.stl` with -2 instead)
    code = ("import os, signal, time, rtfem as rt\n"
            "rt.tetrahedralize(rt.meshes.liver(2))\n"
            "try:\n    os.kill(os.getpid(), signal.SIGINT); time.sleep(5)\n"
            "except KeyboardInterrupt:\n    print('interrupted')\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and "interrupted" in r.stdout, (r.returncode, r.stderr[-500:])
    assert tets.surface.n_vertices > 100


def _write_vtu_with(tmp_path, extra_cell):
    """A unit cube of 6 tets (VTU) plus one more cell of another kind."""
    import meshio

    box = rt.meshes.box(1.0, 1.0, 1.0, 1, 1, 1)
    P = np.vstack([np.asarray(box.vertices), np.asarray(box.vertices) + [2.0, 0.0, 0.0]])
    cells = [("tetra", np.asarray(box.tets))] + ([extra_cell(np.arange(8) + 8)] if extra_cell else [])
    path = tmp_path / "mixed.vtu"
    meshio.write_points_cells(str(path), P, cells)
    return path


def test_volume_files_with_other_cells_than_tets_are_refused(tmp_path):
    """A hexahedron beside the tets (VTU; an INP C3D8 or Gmsh type 5 reads the same way) was
    dropped with half the volume, without a word."""
    hexed = _write_vtu_with(tmp_path, lambda idx: ("hexahedron", idx[None, [0, 1, 3, 2, 4, 5, 7, 6]]))
    with pytest.raises(rt.MeshError, match="hexahedron.*tetrahedra"):
        rt.load_mesh(hexed)
    assert isinstance(rt.load_mesh(_write_vtu_with(tmp_path, None)), rt.TetMesh)  # tets alone load


def test_pipes_devices_and_inflating_files_are_refused(tmp_path):
    import os
    import zipfile

    fifo = tmp_path / "pipe.stl"
    os.mkfifo(fifo)
    for call in (lambda: rt.load_mesh(fifo), lambda: rt.load_mesh("/dev/zero"),
                 lambda: rt.ModalBasis.load("/dev/zero")):
        with pytest.raises(rt.RtfemError, match="not a regular file"):
            call()  # (they hung, or read until memory ran out)
    bomb = tmp_path / "bomb.npz"  # 400 MB of zeros in a few hundred kB
    with zipfile.ZipFile(bomb, "w", compression=zipfile.ZIP_DEFLATED) as z:
        with z.open("omega.npy", "w", force_zip64=True) as fh:
            np.lib.format.write_array_header_1_0(fh, {"descr": "<f8", "fortran_order": False, "shape": (50_000_000,)})
            block = bytes(2**20)
            for _ in range(400):
                fh.write(block)
    assert bomb.stat().st_size < 5e6
    with pytest.raises(rt.ModelError, match="inflates"):
        rt.ModalBasis.load(bomb)


def test_tampered_bases_and_bases_of_other_supports_are_refused(tmp_path, beam):
    import json

    model, modes, _ = beam
    path = modes.save(tmp_path / "b.npz")
    z = dict(np.load(path))

    def tampered(**change):
        out = dict(z, **change)
        out = {k: v for k, v in out.items() if v is not None}
        p = tmp_path / f"t{len(list(tmp_path.iterdir()))}.npz"
        np.savez(p, **out)
        return p

    sums = json.loads(str(z["checksums"]))
    cases = {
        "no checksums": tampered(checksums=None),
        "has no checksum": tampered(checksums=np.array(json.dumps({k: v for k, v in sums.items() if k != "omega"}))),
        "format version": tampered(version=np.array(-1)),
        "checksums": tampered(checksums=np.array(json.dumps(list(sums.values())))),
    }
    for match, p in cases.items():
        with pytest.raises(rt.ModelError, match=match):
            rt.ModalBasis.load(p, model)
    other = rt.SolidModel(model.tetmesh, model.material).fix("x0").fix("x1")
    with pytest.raises(rt.ModelError, match="other supports"):
        rt.ModalBasis.load(path, other)
    with pytest.raises(rt.ModelError, match="other supports"):
        ReducedNonlinearModel(other, modes, 2)
    assert rt.ModalBasis.load(path, rt.SolidModel(model.tetmesh, model.material).fix("x0")).n_modes == modes.n_modes


def test_a_killed_save_leaves_nothing_that_later_saves_keep(tmp_path, beam):
    modes = beam[1]
    dead = tmp_path / ".b.npz.999999999.abcd.tmp.npz"  # named after a process that is gone
    dead.write_bytes(b"partial")
    alive = tmp_path / f".b.npz.{__import__('os').getpid()}.efgh.tmp.npz"  # a save running now
    alive.write_bytes(b"partial")
    modes.save(tmp_path / "b.npz")
    assert not dead.exists() and alive.exists()


def test_tangled_duplicated_and_non_conforming_tet_meshes_are_refused():
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0.3, 0.3, 0.3]], float)
    folded = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])  # node 4 inside the first tet: the second folds back over it
    with pytest.raises(rt.MeshError, match="tangled"):  # it re-oriented the folded tet and simulated it
        rt.TetMesh(V, folded, repair=True)
    with pytest.raises(rt.MeshError, match="inverted"):
        rt.TetMesh(V, folded, repair=False)
    V2 = np.vstack([V[:4], V[:1]])  # node 4 on node 0
    with pytest.raises(rt.MeshError, match="coincide"):
        rt.TetMesh(V2, np.array([[0, 1, 2, 3], [4, 2, 1, 3 + 0]])[:1].tolist() + [[4, 1, 3, 2]], repair=False)
    q = rt.meshes.box(1.0, 1.0, 1.0, 1, 1, 1).quadratic()
    T = np.array(q.tets)
    P = np.vstack([np.asarray(q.vertices), np.asarray(q.vertices)[T[1, 4]]])
    T[1, 4] = P.shape[0] - 1  # the second tet's first mid-edge node: a copy not shared with its neighbour
    shared = rt.TetMesh(P, T, repair=True)  # repair merges the copy back: conforming again
    assert shared.n_vertices == q.n_vertices
    with pytest.raises(rt.MeshError, match="not conforming|coincide"):
        rt.TetMesh(P, T, repair=False)


def test_a_haptic_loop_refuses_a_bad_device_at_start_and_does_not_hang_on_a_blocked_one(beam):
    model, modes, _ = beam
    x = np.asarray(model.mesh.vertices)[int(model.select_nodes("x1")[0])] + [0.0, 0.0, 0.05]
    probe = rt.Probe(model.mesh, rt.ModalSimulator(modes, 1e-3))
    text = rt.CallbackDevice(lambda: "1, 2, 3", lambda f: None)
    with pytest.raises(rt.ModelError, match="device's position"):  # (it failed only at stop())
        rt.HapticLoop(probe, text, compiled=False).start()
    release = threading.Event()
    calls = []

    def read():
        calls.append(1)
        if len(calls) > 3:
            release.wait()  # a device read that blocks
        return x

    loop = rt.HapticLoop(probe, rt.CallbackDevice(read, lambda f: None), compiled=False).start()
    time.sleep(0.05)
    t0 = time.perf_counter()
    with pytest.raises(rt.SolverError, match="did not stop"):
        loop.stop(timeout=0.2)  # (it waited forever)
    assert time.perf_counter() - t0 < 2.0
    release.set()
    loop._thread.join(2.0)
    assert not loop._thread.is_alive()


def test_an_hour_of_a_scripted_device_is_not_sampled_in_advance(beam):
    model, modes, _ = beam
    x = np.asarray(model.mesh.vertices)[int(model.select_nodes("x1")[0])] + [0.0, 0.0, 0.05]
    loop = rt.HapticLoop(rt.Probe(model.mesh, rt.ModalSimulator(modes, 1e-3)), rt.ScriptedDevice(lambda t: x),
                         rate=10_000)
    t0 = time.perf_counter()
    loop.start(seconds=3600.0)
    time.sleep(0.05)
    stats = loop.stop()
    assert time.perf_counter() - t0 < 5.0 and not stats.compiled  # Python ticks, started at once
    with pytest.raises(rt.ModelError, match="in advance"):
        rt.HapticLoop(rt.Probe(model.mesh, rt.ModalSimulator(modes, 1e-3)), rt.ScriptedDevice(lambda t: x),
                      rate=10_000, compiled=True).start(seconds=3600.0)


def test_a_tool_jumped_deep_into_the_organ_is_refused_without_a_step():
    """A sphere placed at the liver's centroid (engulfing much of it) took 2-10 s a tick with
    hundreds of contacts and forces of hundreds of newtons; a sphere jumped 4 cm into a block
    had no meaningful answer either. Both are refused before the solve, the state unchanged."""
    liver = rt.meshes.liver(3)
    model = rt.ShellModel(liver, rt.Material()).fix("attachment")
    sim = rt.ModalSimulator(rt.modal_analysis(model, 6), 1e-3, static_correction=True)
    centre = np.asarray(liver.vertices).mean(axis=0)
    for R in (0.05, 1.0):
        tc = rt.ToolContact(liver, sim, rt.Tool.sphere(R))
        t0 = time.perf_counter()
        with pytest.raises(rt.ModelError, match="inside the organ at once"):
            tc.update(centre)
        assert time.perf_counter() - t0 < 1.0 and sim.steps == 0
    block = rt.SolidModel(rt.meshes.box(0.2, 0.1, 0.1, nx=8, ny=4, nz=4), rt.Material(E=1e4, nu=0.3)).fix("x0")
    d = rt.StaticDriver(block)
    tc = rt.ToolContact(block.mesh, d, rt.Tool.sphere(0.01), coupling="constraint")
    tc.update([0.12, 0.05, 0.12])
    with pytest.raises(rt.ModelError, match="in steps"):
        tc.update([0.12, 0.05, 0.11 - 0.04])
    assert d.steps == 1 and np.abs(d.displacements()).max() == 0.0


def test_a_static_correction_refuses_to_solve_on_changed_supports(beam):
    """The correction's columns are solved with the model's current supports; its modes were
    computed on the old ones: a new column (or load pattern) is refused once the supports change."""
    model0, _, _ = beam
    model = rt.SolidModel(model0.tetmesh, model0.material).fix("x0")
    sim = rt.ModalSimulator(rt.modal_analysis(model, 4), 1e-3, static_correction=True)
    tip = model.select_nodes("x1")
    sim.step({int(tip[0]): (0.0, 0.0, 1.0)})
    model.fix("x1")
    for call in (lambda: sim.prepare(tip[2:5]), lambda: sim.prepare(tip[1:2]),
                 lambda: (sim.step({int(tip[1]): (0.0, 0.0, 1.0)}), sim.displacements())):  # (the field needs its column)
        with pytest.raises(rt.ModelError, match="supports changed"):
            call()


def test_a_bad_runtime_thread_count_warns_and_keeps_one_thread():
    """RTFEM_RUNTIME_THREADS is read when rtfem is imported: a bad value is a warning naming it,
    not a traceback, and the run-time limit stays one thread."""
    code = ("import warnings\nwarnings.simplefilter('always')\n"
            "with warnings.catch_warnings(record=True) as w:\n"
            "    import rtfem.threads as t\n"
            "print(t.RUNTIME_THREADS, [str(x.message) for x in w])\n")
    for bad in ("abc", "-2"):
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                           env=dict(os.environ, RTFEM_RUNTIME_THREADS=bad))
        assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
        assert r.stdout.startswith("1 ") and "RTFEM_RUNTIME_THREADS" in r.stdout, r.stdout


def test_background_threads_are_stopped_and_joined_before_the_interpreter_exits():
    """A daemon thread inside C++ code (scipy's sparse kernels) when Python finalizes is unwound
    by force and libstdc++ aborts the process (a fresh clone's passing test run exited so):
    threads.background() threads are stopped and joined at exit, so they end on their own."""
    code = ("import threading, time, numpy as np, scipy.sparse as sp, rtfem.threads as th\n"
            "A = sp.random(2000, 2000, density=0.01, format='csr', random_state=0); x = np.ones(2000)\n"
            "stop = threading.Event()\n"
            "def work():\n"
            "    try:\n"
            "        while not stop.is_set():\n"
            "            A @ x\n"
            "    finally:\n"
            "        print('worker ended', flush=True)\n"
            "th.background(threading.Thread(target=work, daemon=True), stop.set).start()\n"
            "time.sleep(0.2)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "worker ended" in r.stdout, (r.returncode, r.stdout, r.stderr[-500:])


def _refined_at(mesh, a: int, delta: float):
    """The surface with vertex a's one-ring refined by a fan of triangles delta times its size."""
    X = np.asarray(mesh.vertices).tolist()
    new: dict[int, int] = {}

    def node(v: int) -> int:
        if v not in new:
            new[v] = len(X)
            X.append((np.asarray(X[a]) + delta * (np.asarray(X[v]) - np.asarray(X[a]))).tolist())
        return new[v]

    out = []
    for tri in np.asarray(mesh.triangles).tolist():
        if a not in tri:
            out.append(tri)
            continue
        i = tri.index(a)
        v1, v2 = tri[(i + 1) % 3], tri[(i + 2) % 3]
        out += [[a, node(v1), node(v2)], [node(v1), v1, v2], [node(v1), v2, node(v2)]]
    return rt.TriMesh(np.array(X), np.array(out))


def test_a_graded_mesh_is_not_taken_for_a_mechanism():
    """A vertex refined by triangles 1 % of their neighbours' size has 1e-4 of their mass and the
    same membrane stiffness: its K_ii / m_i is 1e4 times theirs. The modes are the unrefined
    mesh's (the old check, against 1e-10 of the largest K_ii / m_i, refused them as a mechanism)."""
    base = rt.meshes.liver(3)
    top = int(np.argmax(np.asarray(base.vertices)[:, 2]))
    fixes = "bottom:0.1"
    reference = rt.modal_analysis(rt.ShellModel(base, rt.Material()).fix(fixes), 4)
    graded = rt.modal_analysis(rt.ShellModel(_refined_at(base, top, 1e-2), rt.Material()).fix(fixes), 4)
    np.testing.assert_allclose(graded.frequencies, reference.frequencies, rtol=1e-5)
