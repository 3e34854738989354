"""Files and clusters that must not run code or write where they should not (issue 53, section 3).

A scene file or a batch plan is someone else's file: it cannot choose a remote Dask cluster (only
``--scheduler`` does; ``tls://`` with certificates is supported), a ``local:N`` cluster listens on
loopback only, a name in it cannot lead a file out of ``--out`` (nor can a link in that folder), a
FIFO, a link to /dev/zero, an oversized or too deeply nested file is one line at once, too many
bodies or a tool path 1e300 m away are refused before any work, and every key of a plan is checked
before any organ runs, all problems said together. Each case runs through the real command line
(``python -m rtfem.cli.main`` in a subprocess, with a time and a memory limit) where the issue saw
a command-line symptom."""

from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import rtfem as rt
from rtfem.cli.main import main
from rtfem.errors import ModelError
from rtfem.interaction.scene_file import load_scene

ROOT = Path(rt.__file__).resolve().parents[2]  # the checkout whose rtfem is under test (its src/, its docs/)
MEMORY = 4 * 2**30  # bytes of address space a command may take (a read of /dev/zero stops there)

SCENE = """[[body]]
name = {name}
mesh = "box.vtu"
element = "tet4"
material = {{ E = 3e4, nu = 0.3, density = 1000 }}
modes = 6
"""

PLAN = """[defaults]
mesh = "box.vtu"
fix = "z<0.001"
element = "tet4"
modes = 4
[[organ]]
name = "a"
"""


def _limits() -> None:  # in the child, before exec
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (MEMORY, MEMORY))


def _cli(*args, cwd, timeout: float = 60, env: dict | None = None) -> subprocess.CompletedProcess:
    """``rtfem ARGS`` in a subprocess (this interpreter, this source tree), within ``timeout`` s and
    :data:`MEMORY` bytes: a command that hangs or reads without end fails the test, not the machine."""
    environ = dict(os.environ, PYTHONPATH=str(ROOT / "src"), **(env or {}))
    return subprocess.run([sys.executable, "-m", "rtfem.cli.main", *map(str, args)], cwd=cwd, env=environ,
                          capture_output=True, text=True, timeout=timeout, preexec_fn=_limits)


def _refused(run: subprocess.CompletedProcess, *said: str) -> str:
    """The run exited 2 with one line on stderr, no traceback, saying each of ``said``."""
    err = run.stderr.strip()
    assert run.returncode == 2, (run.returncode, run.stdout[-2000:], err[-2000:])
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    for text in said:
        assert text in err, err
    return err


@pytest.fixture()
def folder(tmp_path):
    """A folder with a small tet mesh (18 nodes), a scene of one body on it and a plan of one organ."""
    work = tmp_path / "work"
    work.mkdir()
    rt.save_mesh(rt.meshes.box(0.1, 0.1, 0.05, nx=2, ny=2, nz=1), work / "box.vtu")
    (work / "scene.toml").write_text(SCENE.format(name='"box"'))
    (work / "plan.toml").write_text(PLAN)
    return work


# ---------------------------------------------------------------- the cluster
def test_a_plan_cannot_make_rtfem_connect_to_a_remote_scheduler(folder):
    """A plan's scheduler = "tcp://..." made `rtfem batch` connect there (and Dask unpickles what comes
    back): now it is refused before any work, the message says to pass --scheduler, and nothing
    connects to the address."""
    with socket.create_server(("127.0.0.1", 0)) as listener:
        listener.settimeout(0.0)
        port = listener.getsockname()[1]
        (folder / "plan.toml").write_text(f'scheduler = "tcp://127.0.0.1:{port}"\n' + PLAN)
        run = _cli("batch", "plan.toml", cwd=folder, timeout=60)
        with pytest.raises(BlockingIOError):
            listener.accept()  # nobody knocked
    _refused(run, "--scheduler", "never by a file")
    assert not (folder / "plan").exists()  # nothing was built


def _certificates(folder: Path) -> dict:
    """A CA, and certificates it signed for the cluster ("node") and the client; another CA's client."""
    openssl = shutil.which("openssl")
    if openssl is None:
        pytest.skip("openssl is not installed: it makes the test's certificates")

    def run(*args):
        subprocess.run([openssl, *args], cwd=folder, check=True, capture_output=True, timeout=60)

    (folder / "ext.cnf").write_text("subjectAltName=IP:127.0.0.1,DNS:localhost\n")
    run("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem", "-days", "2",
        "-subj", "/CN=test-ca")
    for who in ("node", "client"):
        run("req", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{who}.key", "-out", f"{who}.csr", "-subj", f"/CN={who}")
        run("x509", "-req", "-in", f"{who}.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial", "-out",
            f"{who}.pem", "-days", "2", "-extfile", "ext.cnf")
    run("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "other.key", "-out", "other.pem", "-days", "2",
        "-subj", "/CN=someone-else")
    return {k: folder / k for k in ("ca.pem", "node.pem", "node.key", "client.pem", "client.key", "other.pem",
                                    "other.key")}


def test_a_tls_scheduler_with_certificates_runs_the_plan_and_refuses_other_clients(folder):
    """--scheduler tls://HOST:PORT with --tls-ca-file/--tls-cert/--tls-key (Dask's Security): the organ is
    built on the TLS cluster; without the certificates, or with another CA's, one line and no work."""
    distributed = pytest.importorskip("distributed", reason="the cluster extra (Dask) is not installed")
    from distributed.security import Security

    c = _certificates(folder)
    security = Security(tls_ca_file=str(c["ca.pem"]), tls_scheduler_cert=str(c["node.pem"]),
                        tls_scheduler_key=str(c["node.key"]), tls_worker_cert=str(c["node.pem"]),
                        tls_worker_key=str(c["node.key"]), tls_client_cert=str(c["node.pem"]),
                        tls_client_key=str(c["node.key"]), require_encryption=True)  # the cluster's own clients
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tls://",
                                  host="127.0.0.1", security=security, dashboard_address="127.0.0.1:0") as cluster:
        address = cluster.scheduler_address
        assert address.startswith("tls://127.0.0.1:")
        tls = ["--tls-ca-file", c["ca.pem"], "--tls-cert", c["client.pem"], "--tls-key", c["client.key"]]
        run = _cli("batch", "plan.toml", "--out", folder / "out", "--scheduler", address, *tls, cwd=folder)
        assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
        assert f"on {address}" in run.stdout and (folder / "out" / "a.modes.npz").is_file()
        _refused(_cli("batch", "plan.toml", "--out", folder / "none", "--scheduler", address, cwd=folder),
                 "needs --tls-ca-file and --tls-cert")
        other = ["--tls-ca-file", c["ca.pem"], "--tls-cert", c["other.pem"], "--tls-key", c["other.key"]]
        _refused(_cli("batch", "plan.toml", "--out", folder / "none", "--scheduler", address, *other, cwd=folder),
                 f"could not reach the Dask scheduler at {address}")
        _refused(_cli("batch", "plan.toml", "--out", folder / "none", "--scheduler", "local:1", *tls, cwd=folder),
                 "the certificates are for --scheduler tls://")
    assert not (folder / "none").exists()


@pytest.mark.parametrize("address", ["tcp://", "tcp://host:notaport", "foo://bar:1", "inproc://x", "ucx://1.2.3.4:5",
                                     "tcp://127.0.0.1:99999", "local:x"])
def test_a_garbage_scheduler_is_one_line_before_any_work(folder, address):
    err = _refused(_cli("batch", "plan.toml", "--scheduler", address, cwd=folder, timeout=60), "scheduler")
    assert "tcp://HOST:PORT" in err or "local:N takes" in err
    assert not (folder / "plan").exists()


def test_a_local_cluster_listens_on_loopback_only():
    """local:N's scheduler, workers and dashboard (it was dashboard_address=":0": every interface)."""
    psutil = pytest.importorskip("psutil")
    pytest.importorskip("distributed", reason="the cluster extra (Dask) is not installed")
    from rtfem.cluster import connect

    me = psutil.Process()
    with connect("local:1") as client:
        assert "127.0.0.1" in client.dashboard_link
        listening = [c.laddr.ip for p in (me, *me.children(recursive=True))
                     for c in p.net_connections(kind="inet") if c.status == psutil.CONN_LISTEN]
    assert listening and set(listening) <= {"127.0.0.1", "::1"}, listening


def test_the_cluster_guide_binds_loopback_or_tls_and_says_a_scheduler_runs_code():
    guide = (ROOT / "docs" / "guide" / "cluster.md").read_text()
    commands = [ln for ln in guide.splitlines() if ln.strip().startswith("dask scheduler")]
    assert commands
    for line in commands:
        assert "--host 127.0.0.1" in line or "--protocol tls" in line, line
        assert "--dashboard-address 127.0.0.1" in line or "--dashboard-address" in guide.split(line)[1][:200], line
    box = re.search(r"```\{warning\}(.*?)```", guide, re.S)
    assert box and "runs code from any client that reaches it" in box.group(1) and "TLS" in box.group(1)
    assert "--tls-ca-file" in guide and "tls://" in guide


# ---------------------------------------------------------------- where files go
def test_a_body_name_cannot_lead_the_output_out_of_the_folder(folder):
    """A body named "../../escaped\\u202e" wrote files two folders above --out; now one line, nothing written."""
    (folder / "scene.toml").write_text(SCENE.format(name='"../../escaped\\u202e"'))
    out = folder / "runs" / "one"
    err = _refused(_cli("simulate", "scene.toml", "--out", out, "--duration", "0.01", cwd=folder),
                   "path separator", "U+202E")
    assert "\u202e" not in err  # shown escaped, not reversing the terminal's text
    assert not [p for p in folder.parent.rglob("*") if "escaped" in p.name]
    assert not out.exists()


@pytest.mark.parametrize("name", ["", ".", "..", "a/b", "a\\\\b", "bell\\u0007", "rtl\\u202ename", "zero\\u200bwidth",
                                  "line\\u2028break", " padded", 5])
def test_a_name_that_cannot_name_a_file_is_refused_before_any_work(folder, name):
    text = f'"{name}"' if isinstance(name, str) else str(name)
    (folder / "scene.toml").write_text(SCENE.format(name=text))
    with pytest.raises(ModelError, match=r"\[\[body\]\] 1.*key 'name'"):
        load_scene(folder / "scene.toml", progress=lambda m: pytest.fail(f"work began: {m}"))


def test_a_link_in_the_output_folder_cannot_lead_a_write_out_of_it(folder, tmp_path):
    """Every output path is checked inside --out after links are followed: a body's folder linked
    elsewhere (simulate), a summary.csv linked to another file (batch)."""
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    out = folder / "out"
    out.mkdir()
    (out / "box").symlink_to(elsewhere, target_is_directory=True)
    _refused(_cli("simulate", "scene.toml", "--out", out, "--duration", "0.01", cwd=folder), "outside the output folder")
    assert not list(elsewhere.iterdir())
    victim = tmp_path / "precious.txt"
    victim.write_text("keep me")
    (folder / "plan").mkdir()
    (folder / "plan" / "summary.csv").symlink_to(victim)
    _refused(_cli("batch", "plan.toml", cwd=folder), "outside the output folder")
    assert victim.read_text() == "keep me" and not (folder / "plan" / "a.modes.npz").exists()


# ---------------------------------------------------------------- what is read
def _command(kind: str, name: str) -> list:
    return ["simulate", name, "--out", "out", "--duration", "0.01"] if kind == "scene" else ["batch", name]


@pytest.mark.parametrize("kind", ["scene", "plan"])
def test_a_fifo_is_refused_at_once(folder, kind):
    os.mkfifo(folder / "pipe.toml")
    _refused(_cli(*_command(kind, "pipe.toml"), cwd=folder, timeout=30), "not a regular file")


def test_a_load_file_that_is_a_fifo_is_refused_at_once(folder):
    os.mkfifo(folder / "loads.csv")
    _refused(_cli("simulate", "box.vtu", "--fix", "z<0.001", "-n", "3", "--load", "loads.csv", "--out", "out",
                  "--duration", "0.01", cwd=folder, timeout=30), "not a regular file")


@pytest.mark.parametrize("url", ["ws://203.0.113.5:10001", "wss://example.org/haply", "ws://localhost.evil.org:1"])
def test_a_scene_file_cannot_choose_a_remote_device_service(folder, url):
    tool = f'[[tool]]\nname = "hand"\ndevice = "haply"\nurl = "{url}"\n'
    (folder / "scene.toml").write_text(SCENE.format(name='"box"') + tool)
    with pytest.raises(ModelError, match="a device on this machine only"):
        load_scene(folder / "scene.toml", progress=lambda m: pytest.fail(f"work began: {m}"))


@pytest.mark.parametrize("kind", ["scene", "plan"])
def test_a_link_to_dev_zero_is_refused_at_once(folder, kind):
    if not Path("/dev/zero").exists():
        pytest.skip("no /dev/zero here")
    (folder / "zero.toml").symlink_to("/dev/zero")
    _refused(_cli(*_command(kind, "zero.toml"), cwd=folder, timeout=30), "not a regular file")


@pytest.mark.parametrize("kind", ["scene", "plan"])
def test_a_file_over_the_size_cap_is_refused_and_the_message_says_how_to_raise_it(folder, kind):
    source = (folder / ("scene.toml" if kind == "scene" else "plan.toml")).read_text()
    (folder / "big.toml").write_text(source + ("# padding\n" * 900_000))  # 9 MB of comments
    _refused(_cli(*_command(kind, "big.toml"), cwd=folder), "more than the 8.39 MB", "RTFEM_MAX_TEXT_MB")
    (folder / "small.toml").write_text(source + ("# padding\n" * 3_000))  # 30 kB
    _refused(_cli(*_command(kind, "small.toml"), cwd=folder, env={"RTFEM_MAX_TEXT_MB": "0.01"}),
             "more than the 10.5 kB")


@pytest.mark.parametrize("kind", ["scene", "plan"])
@pytest.mark.parametrize("nesting", ["a = " + "[" * 5000 + "]" * 5000, "a = " + "{b = " * 5000 + "1" + "}" * 5000,
                                     "a = " + "[" * 20 + "]" * 20])
def test_toml_nested_deep_is_one_line(folder, kind, nesting):
    (folder / "deep.toml").write_text(nesting + "\n")
    _refused(_cli(*_command(kind, "deep.toml"), cwd=folder), "nested")


def test_ten_thousand_bodies_are_refused_before_any_work(folder):
    body = SCENE.format(name='"b{}"')
    (folder / "many.toml").write_text("".join(body.replace("{}", str(i)) for i in range(10_000)))
    err = _refused(_cli("simulate", "many.toml", "--out", "out", "--duration", "0.01", cwd=folder, timeout=60),
                   "10,000 [[body]] tables, more than the 32")
    assert "meshed and its modes computed" in err


def test_a_tool_path_far_away_is_refused_before_any_work(folder):
    tool = '[[tool]]\nname = "p"\npath = [[0.0, 1e300, 0.0, 0.0], [0.1, 0.05, 0.05, 0.06]]\n'
    (folder / "far.toml").write_text(SCENE.format(name='"box"') + tool)
    run = _cli("simulate", "far.toml", "--out", "out", "--duration", "0.01", cwd=folder)
    _refused(run, "more than 1000 m from the origin")
    assert "modes" not in run.stdout  # no body was reduced first
    with pytest.raises(ModelError, match="more than 1000 m"):
        rt.Keyframes(np.array([[0.0, 0.0, 0.0, 0.0], [1.0, 0.0, -2e3, 0.0]]))


# ---------------------------------------------------------------- the whole plan before any work
@pytest.mark.parametrize("line, said", [
    ('solid = "yes"', "solid = 'yes': give true or false"),
    ('modes = "ten"', "modes='ten' must be a whole number"),
    ("modes = 0", "modes=0 must be between 1 and 2000"),
    ("modes = true", "modes=True must be a whole number"),
    ("E = -1.0", "E=-1.0 must be > 0"),
    ('E = "soft"', "E='soft' is not a number"),
    ("derivatives = 0", "derivatives=0 must be between 1"),
    ("derivatives = 2.5", "derivatives=2.5 must be a whole number"),
    ("radius = -0.1", "radius=-0.1 must be > 0"),
    ('radius = "x"', "radius='x' is not a number"),
    ("times = [-1.0]", "the values must be > 0"),
    ("times = [0.05, 0.01]", "strictly increasing"),
    ('times = "x"', "give a list of numbers"),
    ('method = "fem"', "method='fem'; choose one of 'modal', 'sldm'"),
    ('element = "tet5"', "element='tet5'; choose one of"),
    ("nu = 0.7", "nu=0.7 is outside (-1, 0.5)"),
    ("nu = 0.49999", "Give nu <= 0.4999"),
    ('material = "rubber"', "material"),
    ('[[organ]]\nname = "../b"', "path separator"),
])
def test_every_key_of_a_plan_is_checked_before_any_organ_runs(folder, capsys, line, said):
    (folder / "plan.toml").write_text(PLAN + line + "\n")
    assert main(["batch", str(folder / "plan.toml")]) == 2
    err = capsys.readouterr().err
    assert said in err and "nothing run" in err and len(err.strip().splitlines()) == 1, err
    assert not (folder / "plan").exists()  # no organ ran, no folder made


@pytest.mark.parametrize("top, said", [
    ('scheduler = "tcp://"', "a plan may only ask for local:N"),
    ("scheduler = 5", "a plan may only ask for local:N"),
    ('scheduler = "local:9999"', "a plan may only ask for local:N"),
    ('out = "../elsewhere"', "outside the plan's folder"),
    ("out = 3", "give a folder relative to the plan"),
])
def test_a_plans_scheduler_and_out_are_checked_before_any_work(folder, capsys, top, said):
    (folder / "plan.toml").write_text(top + "\n" + PLAN)
    assert main(["batch", str(folder / "plan.toml")]) == 2
    err = capsys.readouterr().err
    assert said in err and len(err.strip().splitlines()) == 1, err
    assert not (folder / "plan").exists() and not (folder.parent / "elsewhere").exists()


def test_every_problem_of_a_plan_is_said_at_once_through_the_command_line(folder):
    (folder / "plan.toml").write_text(PLAN + 'solid = "yes"\nradius = -1.0\n[[organ]]\nname = "b"\nmethod = "fem"\n')
    err = _refused(_cli("batch", "plan.toml", cwd=folder), "3 problem(s), nothing run")
    assert "organ 1 ('a'): solid" in err and "organ 1 ('a'): radius" in err and "organ 2 ('b'): method" in err


def test_a_plan_writes_where_out_says_when_the_command_line_names_it(folder, tmp_path):
    (folder / "plan.toml").write_text('out = "../../anywhere"\n' + PLAN)
    run = _cli("batch", "plan.toml", "--out", tmp_path / "chosen", cwd=folder)
    assert run.returncode == 0, run.stderr[-2000:]
    assert (tmp_path / "chosen" / "a.modes.npz").is_file()


# ---------------------------------------------------------------- locking
def test_rtfem_modes_warns_of_tet4_locking(folder):
    run = _cli("modes", "box.vtu", "--element", "tet4", "--nu", "0.4999", "-n", "3", "--fix", "z<0.001", "-o",
               "m.npz", cwd=folder)
    assert run.returncode == 0, run.stderr[-2000:]
    assert re.search(r"rtfem: warning: tet4 at nu = 0.4999 locks.*tet4-anp or tet10", run.stderr), run.stderr
    run = _cli("modes", "box.vtu", "--element", "tet4-anp", "--nu", "0.4999", "-n", "3", "--fix", "z<0.001", "-o",
               "m.npz", cwd=folder)
    assert run.returncode == 0 and "warning" not in run.stderr, run.stderr
