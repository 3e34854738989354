import subprocess
import sys

from rtfem.cli import main
from conftest import organ


def test_info_default_liver(capsys):
    assert main(["info"]) == 0
    out = capsys.readouterr().out
    assert "2562 vertices" in out and "attachment" in out and "repairs: none" in out


def test_info_reference_file(capsys):
    assert main(["info", str(organ("sofa_env_gallbladder_collision.stl")), "--scale", "1e-3"]) == 0
    assert "252 vertices" in capsys.readouterr().out


def test_broken_file_exit_code_2_no_traceback(tmp_path):
    bad = tmp_path / "broken.obj"
    bad.write_text("v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n")
    r = subprocess.run([sys.executable, "-m", "rtfem.cli", "info", str(bad)], capture_output=True, text=True)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr and r.stderr.startswith("rtfem: error:") and "vertex 1" in r.stderr
    r = subprocess.run([sys.executable, "-m", "rtfem.cli", "info", str(tmp_path / "missing.stl")], capture_output=True, text=True)
    assert r.returncode == 2 and "does not exist" in r.stderr
