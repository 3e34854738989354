import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import rtfem as rt

from rtfem.cli.main import main
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
    r = subprocess.run([sys.executable, "-m", "rtfem.cli.main", "info", str(bad)], capture_output=True, text=True)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr and r.stderr.startswith("rtfem: error:") and "vertex 1" in r.stderr
    r = subprocess.run([sys.executable, "-m", "rtfem.cli.main", "info", str(tmp_path / "missing.stl")], capture_output=True,
                       text=True)
    assert r.returncode == 2 and "does not exist" in r.stderr


def test_no_help_text_prints_a_doubled_percent_sign(capsys):
    """argparse %-formats help= strings but prints descriptions as written: `rtfem simulate
    --help` printed "20 %%"."""
    import argparse

    from rtfem.cli.main import build_parser, main

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    for name in sub.choices:
        assert main([name, "--help"]) == 0
        assert "%%" not in capsys.readouterr().out, name


def test_info_gives_the_extent_in_metres_and_says_when_it_looks_like_millimetres(tmp_path, capsys):
    from rtfem.cli.main import main

    assert main(["info"]) == 0
    out = capsys.readouterr().out
    assert " m (x, y, z" in out and "m^2" in out and "--scale 1e-3" not in out
    path = tmp_path / "mm.stl"
    rt.save_mesh(rt.TriMesh(np.asarray(rt.meshes.liver(2).vertices) * 1e3, rt.meshes.liver(2).triangles), path)
    assert main(["info", str(path)]) == 0
    assert "--scale 1e-3" in capsys.readouterr().out


@pytest.mark.parametrize("args", [["info", "--solid", "--scale", "1e-6"], ["modes", "--scale", "1e-6", "-n", "4"],
                                  ["info", "examples/organ.stl", "--solid", "--scale", "1e-6"]])
def test_a_micron_organ_is_refused_before_any_work(args, capsys, monkeypatch):
    """A scale that makes an organ under 1 mm across (issue 53: `rtfem info --solid --scale 1e-6` took
    it, and meshed it) is a units mistake: exit 2 with the size and the fix, before any meshing."""
    from rtfem.mesh import meshing

    monkeypatch.chdir(Path(__file__).resolve().parents[1])
    monkeypatch.setattr(meshing, "cached_tetrahedralize", lambda *a, **k: pytest.fail("meshed a micron organ"))
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "m across after --scale 1e-06" in err and "at least 1 mm" in err
