"""Every rtfem command on the default liver and on a mesh file given by path; broken input -> exit 2."""

from __future__ import annotations

import csv
import glob
import os
import subprocess
import sys
import time
import urllib.request

import numpy as np
import pytest

import rtfem as rt
from rtfem.cli.main import main
from conftest import interrupt, organ, wait_for_viewer_address

GB = ["--scale", "1e-3", "--fix", "bottom:0.2"]  # the gallbladder file is in mm, free-floating


def gallbladder() -> str:
    return str(organ("sofa_env_gallbladder_collision.stl"))


def run(capsys, *argv) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_modes_on_liver_and_file_round_trip(tmp_path, capsys):
    rc, out, _ = run(capsys, "modes", "-n", 12, "-o", tmp_path / "liver.modes.npz")
    assert rc == 0 and "136 nodes fixed (group 'attachment')" in out
    model = rt.ShellModel(rt.meshes.liver(), rt.Material())
    model.fix("attachment")
    basis = rt.ModalBasis.load(tmp_path / "liver.modes.npz", model=model)
    direct = rt.modal_analysis(model, 12)
    np.testing.assert_allclose(basis.omega, direct.omega, rtol=1e-9)
    rc, out, _ = run(capsys, "modes", gallbladder(), *GB, "-n", 8, "-o", tmp_path / "gb.npz")
    assert rc == 0 and (tmp_path / "gb.npz").exists() and "bottom" not in out.split("fixed")[0]


def test_simulate_probe_csv_matches_static_force(tmp_path, capsys):
    """A held probe settles: the CSV's final force during the hold equals the series-spring static force."""
    rc, out, _ = run(capsys, "simulate", "--duration", 3.0, "--alpha", 20, "--out", tmp_path, "--fps", 2)
    assert rc == 0
    rows = list(csv.DictReader(open(tmp_path / "response.csv")))
    assert len(rows) == 3000 and (tmp_path / "response.pvd").exists()
    hold = rows[int(0.6 * 3000) - 2]  # end of the hold (60 % of the run)
    node = int(hold["contact_node"])
    model = rt.ShellModel(rt.meshes.liver(), rt.Material())
    model.fix("attachment")
    n = model.mesh.vertex_normals()[node]
    g = 0.005 + 0.0  # probe 5 mm inside the undeformed surface
    G = model.solve_static({node: tuple(-n)})[node] @ -n  # normal compliance (m/N)
    f_static = g / (G + 1 / 200.0)  # organ and coupling spring in series
    assert float(hold["force"]) == pytest.approx(f_static, rel=0.02)
    assert float(rows[-1]["force"]) == 0.0


def test_simulate_load_file_modal_direct_sldm_agree(tmp_path, capsys):
    node = 885
    # a 20 ms ramp to 0.1 N in 1 ms stairs, held: the truncated modes then respond nearly
    # statically, which is what the static correction assumes
    ramp = "".join(f"{k * 1e-3:g},{node},0,0,{-0.1 * (k + 1) / 20:.6g}\n" for k in range(20))
    (tmp_path / "loads.csv").write_text("t,node,fx,fy,fz\n" + ramp)
    u = {}
    for method in ("direct", "sldm", "modal"):
        extra = ["--modes", 200] if method == "modal" else []
        rc, out, err = run(capsys, "simulate", "--load", tmp_path / "loads.csv", "--duration", 0.1, "--dt", 2.5e-4,
                           "--method", method, "--out", tmp_path / method, *extra)
        assert rc == 0, err
        rows = list(csv.DictReader(open(tmp_path / method / "response.csv")))
        u[method] = np.array([float(r[f"u_z@{node}"]) for r in rows])
    scale = np.abs(u["sldm"]).max()
    # direct Newmark vs the Krylov solution exact in time: O(dt) at the load's jumps
    assert np.abs(u["direct"] - u["sldm"]).max() < 0.02 * scale
    # 200 modes + static correction vs SLDM: the truncation error only
    err = u["modal"] - u["sldm"]
    print("modal vs SLDM: max", np.abs(err).max() / scale, "direct vs SLDM", np.abs(u["direct"] - u["sldm"]).max() / scale)
    assert np.abs(err).max() < 0.02 * scale


def test_simulate_probe_on_file_direct(tmp_path, capsys):
    rc, out, _ = run(capsys, "simulate", gallbladder(), *GB, "--method", "direct", "--duration", 0.05,
                     "--out", tmp_path)
    assert rc == 0 and "peak" in out
    rows = list(csv.DictReader(open(tmp_path / "response.csv")))
    assert max(float(r["force"]) for r in rows) > 0


def test_impedance_on_liver_and_file(tmp_path, capsys):
    rc, out, _ = run(capsys, "impedance", "--nodes", "nodes:885", "--radius", 0.05, "-o", tmp_path / "m.npz")
    assert rc == 0
    model = rt.ShellModel(rt.meshes.liver(), rt.Material())
    model.fix("attachment")
    imap = rt.ImpedanceMap.load(tmp_path / "m.npz", model=model)
    # the map's exact point compliance is the static solve's
    G = np.stack([model.solve_static({885: e})[885] for e in np.eye(3)], axis=1)
    np.testing.assert_allclose(imap.point_compliance(885), G, rtol=1e-8, atol=1e-12 * np.abs(G).max())
    rc, out, _ = run(capsys, "impedance", gallbladder(), *GB, "--nodes", "nodes:100,200", "-o", tmp_path / "gb.npz",
                     "--modes", 10)
    assert rc == 0 and (tmp_path / "gb.npz").exists()


def test_bench_on_liver_and_file(tmp_path, capsys):
    rc, out, _ = run(capsys, "bench", "--modes-list", 10, "--direct-steps", 5)
    assert rc == 0 and "direct / haptic" in out and "2,562 |" in out
    rc, out, _ = run(capsys, "bench", gallbladder(), *GB, "--modes-list", 5, 10, "--direct-steps", 5,
                     "--plot", tmp_path / "b.png")
    assert rc == 0 and (tmp_path / "b.png").stat().st_size > 1000


def test_pictures_on_file(tmp_path, capsys):
    pytest.importorskip("matplotlib")
    rc, out, _ = run(capsys, "pictures", gallbladder(), *GB, "--modes", 10, "--no-scaling", "--out", tmp_path)
    assert rc == 0
    for name in ("modes.png", "spectrum.png", "deformed.png", "step_response.png", "error_vs_modes.png", "response.gif"):
        assert (tmp_path / name).stat().st_size > 1000, name


@pytest.mark.parametrize("command", ["info", "modes", "simulate", "impedance", "bench", "pictures", "view"])
def test_every_command_rejects_a_broken_file(tmp_path, command):
    bad = tmp_path / "broken.stl"
    bad.write_bytes(b"solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0\nendloop\nendfacet\nendsolid\n")
    r = subprocess.run([sys.executable, "-m", "rtfem.cli.main", command, str(bad)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert r.stderr.startswith("rtfem: error:") and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("argv, words", [
    (["simulate", "--fix", "nowhere"], "--fix 'nowhere'"),
    (["simulate", "--fix", "z<-5"], "selects no vertex"),
    (["simulate", "--method", "sldm"], "add --load"),
    (["simulate", "--E", "-3"], "E"),
    (["simulate", "--at", "1,2"], "three finite numbers"),
    (["modes", "-n", "0"], "at least one mode"),
    (["view", "--dt", "5"], "time step"),
    (["view", "--method", "modal", "--local", "20"], "use it with --method nonlinear"),
    (["view", "--shell", "--solid"], "contradict"),
    (["view", "--max-force", "0"], "max-force"),
    (["view", "--adapt", "-1"], "--adapt"),
    (["view", "--adapt-radius", "0"], "--adapt-radius"),
    (["view", "--adapt", "2000"], "at most 1000 mm"),
    (["view", "--adapt-radius", "60"], "at most 1000 mm and 50 mm"),
    (["view", "--method", "modal", "--adapt", "1"], "use them with --method nonlinear"),
    (["view", "--method", "nonlinear", "--local", "10", "--adapt", "1"], "without --local"),
    (["view", "--benchmark", "0"], "--benchmark"),
])
def test_bad_options_exit_2_with_a_message(capsys, argv, words):
    rc, out, err = run(capsys, *argv)
    assert rc == 2 and err.startswith("rtfem: error:") and words in err


def test_view_serves_a_mesh_file_and_stops_on_ctrl_c():
    pytest.importorskip("viser")
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    p = subprocess.Popen([sys.executable, "-m", "rtfem.cli.main", "view", gallbladder(), *GB, "--shell", "--method", "modal",
                          "--port", str(port)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = wait_for_viewer_address(p)
        assert f"http://127.0.0.1:{port}" in line, (line, p.stderr.read() if p.poll() is not None else "")
        page = urllib.request.urlopen(f"http://127.0.0.1:{port}", timeout=30).read()
        assert b"<html" in page.lower()
    finally:
        out, err = interrupt(p, 30)
    assert p.returncode == 130 and "stopped" in out and "Traceback" not in err


needs_mesher = pytest.mark.skipif(not rt.mesh.meshing.mesher_available(), reason="the mesh extra (pytetwild) is not installed")


@pytest.fixture(scope="module")
def tet_file(tmp_path_factory):
    """A tetrahedral organ file: the solid liver, written as VTU (no groups: --fix is given)."""
    if not rt.mesh.meshing.mesher_available():
        pytest.skip("the mesh extra (pytetwild) is not installed")
    path = tmp_path_factory.mktemp("tets") / "liver.vtu"
    rt.save_mesh(rt.meshes.liver(solid=True), path)
    return str(path)


TET_FIX = ["--fix", "y<-0.045"]


@needs_mesher
def test_info_modes_simulate_impedance_bench_on_a_tet_file(tet_file, tmp_path, capsys):
    rc, out, _ = run(capsys, "info", tet_file)
    assert rc == 0 and "volume mesh" in out and "radius ratio" in out
    rc, out, _ = run(capsys, "modes", tet_file, *TET_FIX, "--element", "tet4", "-n", 10, "-o", tmp_path / "m.npz")
    assert rc == 0 and "tet4 tets" in out
    mesh = rt.load_mesh(tet_file)
    model = rt.SolidModel(mesh, rt.Material()).fix("y<-0.045")
    basis = rt.ModalBasis.load(tmp_path / "m.npz", model=model)
    np.testing.assert_allclose(basis.omega, rt.modal_analysis(model, 10).omega, rtol=1e-8)
    rc, out, _ = run(capsys, "simulate", tet_file, *TET_FIX, "--duration", 0.05, "--out", tmp_path / "run")
    assert rc == 0 and "tet10 tets" in out  # the default element: tet10 does not lock at nu = 0.45
    import meshio

    frame = meshio.read(sorted((tmp_path / "run").glob("frame_*.vtu"))[-1])
    assert frame.cells[0].type == "tetra10"
    rc, out, _ = run(capsys, "impedance", tet_file, *TET_FIX, "--nodes", "nodes:3", "-n", 10, "-o", tmp_path / "i.npz")
    assert rc == 0
    rc, out, _ = run(capsys, "bench", tet_file, *TET_FIX, "--modes-list", 10, "--direct-steps", 5)
    assert rc == 0 and "direct / haptic" in out


@needs_mesher
def test_solid_option_meshes_a_surface_file(tmp_path, capsys):
    rc, out, _ = run(capsys, "simulate", gallbladder(), *GB, "--solid", "--duration", 0.02, "--out", tmp_path)
    assert rc == 0 and "tets" in out and "peak" in out
    rc, out, err = run(capsys, "info", gallbladder(), "--scale", "1e-3", "--solid", "--edge-length", "1e-9")
    assert rc == 2 and "edge_length" in err and "Traceback" not in err


def test_simulate_large_deformation_modal_and_direct(tmp_path, capsys):
    """--large: modal warping for modal, the corotational full order for direct; a 5 mm probe is
    a small deformation, so both agree with the linear runs there (to a few per cent)."""
    forces = {}
    for extra in ([], ["--large"]):
        rc, out, err = run(capsys, "simulate", "--duration", 0.3, "--alpha", 20, "--out", tmp_path / f"m{len(extra)}",
                           "--fps", 2, *extra)
        assert rc == 0, err
        assert ("modal, warped" in out) == bool(extra)
        rows = list(csv.DictReader(open(tmp_path / f"m{len(extra)}" / "response.csv")))
        forces[bool(extra)] = float(rows[-1]["force"])
    assert forces[True] == pytest.approx(forces[False], rel=0.05)
    rc, out, err = run(capsys, "simulate", "--solid", "--element", "tet4", "--method", "direct", "--large", "--duration", 0.005,
                       "--out", tmp_path / "d")
    assert rc == 0 and "direct, corotational" in out, err
    (tmp_path / "loads.csv").write_text("t,node,fx,fy,fz\n0,885,0,0,-0.1\n")
    rc, out, err = run(capsys, "simulate", "--method", "sldm", "--large", "--load", tmp_path / "loads.csv")
    assert rc == 2 and "--large" in err


def test_simulate_reduced_nonlinear_method(tmp_path, capsys):
    """--method nonlinear: the reduced nonlinear model (modes + modal derivatives, cubature, the
    static correction). A 2 mm probe is a small deformation, where both it and the modal run
    (with its static correction) have the organ's linear stiffness: the probe force, averaged
    over the hold (the light damping leaves it ringing), agrees between them (measured 0.00199
    and 0.00188 N; the peaks, at the end of the approach, differ with the two models' inertia).
    The same on the solid liver (the default element, tet10; 10 modes and their derivatives)."""
    forces = {}
    for method in ("modal", "nonlinear"):
        rc, out, err = run(capsys, "simulate", gallbladder(), *GB, "-n", 12, "--method", method, "--duration", 0.3,
                           "--alpha", 20, "--depth", 0.002, "--fps", 2, "--out", tmp_path / method)
        assert rc == 0, err
        rows = list(csv.DictReader(open(tmp_path / method / "response.csv")))
        hold = [float(r["force"]) for r in rows if 0.06 < float(r["t"]) < 0.2]
        forces[method] = sum(hold) / len(hold)
    assert "reduced nonlinear" in out and "derivatives" in out and "static correction" in out
    assert forces["modal"] > 0.001 and abs(forces["nonlinear"] / forces["modal"] - 1) < 0.1
    # the error indicator recorded beside the run (issue 56; checked against the full order in
    # tests/verification/test_error_indicator.py): every 0.1 s of simulated time, and said at the end
    errs = list(csv.DictReader(open(tmp_path / "nonlinear" / "error_estimate.csv")))
    assert [round(float(r["t"]), 6) for r in errs] == [0.1, 0.2, 0.3]
    # with the inertial forces taken off, the press held and settling: tens of microns at 0.2 and 0.3 s (the
    # statics alone read 26 mm at 0.1 s; with the inertia 1.6 mm there, while the organ still rings)
    assert all(0 < float(r["max_error_m"]) < 0.002 for r in errs)
    assert all(float(r["max_error_m"]) < 1e-4 for r in errs[1:])
    assert "error       estimate" in out and "error_estimate.csv" in out
    assert not (tmp_path / "modal" / "error_estimate.csv").exists()
    forces = {}  # the same on the solid liver (corotated tets in the cubature)
    for method in ("modal", "nonlinear"):
        rc, out, err = run(capsys, "simulate", "--solid", "-n", 10, "--method", method, "--duration", 0.3,
                           "--alpha", 20, "--depth", 0.002, "--fps", 2, "--out", tmp_path / f"solid-{method}")
        assert rc == 0, err
        rows = list(csv.DictReader(open(tmp_path / f"solid-{method}" / "response.csv")))
        hold = [float(r["force"]) for r in rows if 0.06 < float(r["t"]) < 0.2]
        forces[method] = sum(hold) / len(hold)
    assert "reduced nonlinear" in out and "10 modes + 55 derivatives" in out
    assert forces["modal"] > 0.01 and abs(forces["nonlinear"] / forces["modal"] - 1) < 0.1
    rc, out, err = run(capsys, "simulate", "--solid", "--element", "tet4", "-n", 10, "--method", "nonlinear", "--local", 15,
                       "--duration",
                       0.05, "--out", tmp_path / "solid-local")
    assert rc == 0 and "of a 15 mm patch" in out, err
    rc, out, err = run(capsys, "simulate", "--local", 15, "--out", tmp_path / "bad")
    assert rc == 2 and "--method nonlinear" in err and "Traceback" not in err


def _children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (from /proc)."""
    out = []
    for stat in glob.glob("/proc/[0-9]*/stat"):
        try:
            fields = open(stat).read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.split("/")[2]))
    return out


def _alive(pid: int) -> bool:
    """Whether ``pid`` is a process that has not ended (a zombie counts as ended)."""
    try:
        state = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")


@needs_mesher
def test_ctrl_c_while_meshing_exits_130_and_leaves_no_scratch(tmp_path):
    """fTetWild's own SIGINT handler ended the process (-2) and left its scratch folder (issue 53): the
    mesher runs in a child now, and Ctrl-C is the CLI's interrupt (exit 130, one line), with no scratch
    folder, no cache entry and no mesher process left."""
    import signal
    import tempfile

    env = dict(os.environ, RTFEM_CACHE=str(tmp_path / "cache"))
    p = subprocess.Popen([sys.executable, "-m", "rtfem.cli.main", "info", "--solid", "--edge-length", "0.0015"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        assert "meshing" in p.stdout.readline()
        time.sleep(1.5)  # fTetWild at work (this edge length takes 5-10 s)
        assert glob.glob(f"{tempfile.gettempdir()}/rtfem-tetwild-{p.pid}-*"), "the mesher was not running"
        children = _children(p.pid)
        assert children, "the mesher runs in no child process"
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130 and "interrupted" in err and "Traceback" not in err, (p.returncode, err)
    deadline = time.monotonic() + 10.0
    while any(_alive(c) for c in children) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(c) for c in children), f"mesher processes {children} outlived the interrupted command"
    assert not glob.glob(f"{tempfile.gettempdir()}/rtfem-tetwild-{p.pid}-*")
    assert not (tmp_path / "cache").exists() or not list((tmp_path / "cache").iterdir())
