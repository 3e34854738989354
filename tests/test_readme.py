"""The README's and the getting-started page's commands, run as written in a fresh folder (a
newcomer's first minutes).

The `rtfem` command block (docs/guide/getting-started.md) is run line by line in an empty folder
holding a copy of `examples/` (its inputs); every line must exit 0 without a traceback, and what
it says it writes must be there. The `view` line serves until it prints its address, then gets
Ctrl-C (exit 130). The README's example and the guide's first script run whole. `make demo` and
`make test` (the README's first block) are what CI itself runs.
"""

from __future__ import annotations

import json
import re
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import interrupt

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
GUIDE = (ROOT / "docs" / "guide" / "getting-started.md").read_text()


def _blocks(lang: str, text: str = README) -> list[str]:
    """The fenced blocks of a language ("" for plain ones), fences read in order."""
    blocks, current, kind = [], None, None
    for line in text.splitlines():
        fence = line.strip()
        if fence.startswith("```"):
            if current is None:
                current, kind = [], fence[3:].strip()
            else:
                if kind == lang:
                    blocks.append("\n".join(current) + "\n")
                current = None
        elif current is not None:
            current.append(line[len(line) - len(line.lstrip()):] and line.strip() if kind == "" else line)
    return blocks


def _command_block() -> list[str]:
    block = next(b for b in _blocks("", GUIDE) if "rtfem info" in b)
    lines = [ln.split("  #")[0].strip() for ln in block.splitlines()]
    return [ln for ln in lines if ln]


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    where = tmp_path_factory.mktemp("newcomer")
    shutil.copytree(ROOT / "examples", where / "examples")
    return where


def test_the_readme_is_short_and_starts_with_the_two_commands():
    lines = README.splitlines()
    assert len(lines) <= 150, len(lines)
    first = _blocks("")[0]
    assert README.startswith("```") and first.startswith("make demo") and "make test" in first, first
    for link in re.findall(r"\]\(([^)#]+)\)", README):  # every relative link resolves
        assert link.startswith("http") or (ROOT / link).exists(), link


def test_the_readme_names_its_inputs_and_they_ship():
    """Every file a command of the guide reads is in the repository."""
    lines = _command_block()
    assert len(lines) >= 8 and all(ln.startswith("rtfem ") for ln in lines), lines
    for ln in lines:
        for word in shlex.split(ln):
            if word.endswith((".stl", ".csv", ".obj", ".vtu")) and not word.startswith("-"):
                assert (ROOT / word).is_file(), f"{ln!r} reads {word}, which the repository lacks"
    assert "../shared" not in README + GUIDE, "a page links a file outside the repository"


@pytest.mark.parametrize("line", [ln for ln in _command_block() if " view " not in f" {ln} " or "--benchmark" in ln])
def test_every_rtfem_command_in_the_readme_runs_as_written(line, folder):
    argv = [sys.executable, "-m", "rtfem.cli.main", *shlex.split(line)[1:]]
    r = subprocess.run(argv, cwd=folder, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, (line, r.stdout[-2000:], r.stderr[-2000:])
    assert "Traceback" not in r.stderr, r.stderr
    for m in re.finditer(r"^wrote\s+(\S+)", r.stdout, flags=re.M):  # what it says it wrote is there
        assert (folder / m.group(1)).exists() or Path(m.group(1)).exists(), (line, m.group(0))
    if "--benchmark" in line:  # the default scene: a solid of tet10 with the reduced nonlinear model, pulled
        report = json.loads(r.stdout.strip().splitlines()[-1])
        assert report["model"] == "solid" and report["element"] == "tet10" and report["method"] == "nonlinear"
        assert report["error"] is None and report["steps_per_s"] > 0 and report["frames_per_s"] > 0
        # the 200 N/m jaw pulled 3 cm: the tissue follows part of the way, within the 10 N limit
        assert 1.0 < report["peak_mm"] < 30.0 and 0.1 < report["max_force_N"] <= report["force_limit_N"]
        assert {"realtime", "step_p50_us", "step_p99_us"} <= set(report)


def test_the_readme_view_command_serves_and_stops_on_ctrl_c(folder):
    pytest.importorskip("viser")
    line = next(ln for ln in _command_block() if ln.startswith("rtfem view ") and "--benchmark" not in ln)
    argv = [sys.executable, "-m", "rtfem.cli.main", *shlex.split(line)[1:]]
    p = subprocess.Popen(argv, cwd=folder, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    said = []
    try:
        t0 = time.time()
        while not (said and "open http" in said[-1]) and time.time() - t0 < 400:
            said.append(p.stdout.readline())
            if not said[-1] and p.poll() is not None:
                break
        assert "open http://127.0.0.1:" in said[-1], said
    finally:
        out, err = interrupt(p, 60)
    out = "".join(said) + out
    assert p.returncode == 130 and "Traceback" not in err, (out, err)
    # a closed surface file is meshed into tets and modelled as a solid of tet10, with progress shown
    assert "tet10 tets" in out and "precomputed reduced nonlinear" in out, out
    assert "modal derivatives" in err, err


@pytest.mark.parametrize("page", ["README", "guide"])
def test_the_first_scripts_run(page, folder, monkeypatch):
    monkeypatch.chdir(folder)
    code = _blocks("python", README if page == "README" else GUIDE)[0]
    assert "rt.HapticLoop" in code
    scope: dict = {}
    exec(compile(code, f"the {page}'s first script", "exec"), scope)  # noqa: S102 - our own pages' code
    stats = scope["stats"]
    assert stats.steps > 500 and stats.peak_force > 0.0
