"""The manual builds (``make docs``): Sphinx over docs/ with warnings as errors, the API reference
from the docstrings, the gallery running examples/. The docs extra brings Sphinx (make installs it)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_the_api_reference_lists_every_public_name_and_module():
    import pkgutil

    import rtfem

    api = (ROOT / "docs" / "api.rst").read_text()
    listed = {ln.strip() for ln in api.splitlines() if ln.startswith("   ") and not ln.strip().startswith(":")}
    names = {n for n in rtfem.__all__ if type(getattr(rtfem, n)).__name__ != "module"}
    modules = {m.name[len("rtfem."):] for m in pkgutil.walk_packages(rtfem.__path__, "rtfem.")}
    assert names | modules == listed, (sorted((names | modules) - listed), sorted(listed - (names | modules)))


def test_the_manual_builds_without_a_warning(tmp_path):
    pytest.importorskip("sphinx", reason="the docs extra (Sphinx) is not installed: pip install 'rtfem[docs]'")
    pytest.importorskip("sphinx_gallery", reason="the docs extra (sphinx-gallery) is not installed")
    out = tmp_path / "html"
    run = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html",
                          "-d", str(tmp_path / "doctrees"), "docs", str(out)], cwd=ROOT, capture_output=True,
                         text=True, timeout=900)
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-4000:]
    # every public name has its page, every guide page and example is there, the gallery has its figure
    import rtfem

    for name in rtfem.__all__:
        obj = getattr(rtfem, name)
        page = obj.__name__ if type(obj).__name__ == "module" else f"rtfem.{name}"  # modules: their own path
        assert (out / "generated" / f"{page}.html").is_file(), name
    for page in (ROOT / "docs" / "guide").glob("*.md"):
        assert (out / "guide" / f"{page.stem}.html").is_file(), page.name
    for example in (ROOT / "examples").glob("[0-9][0-9]_*.py"):
        assert (out / "auto_examples" / f"{example.stem}.html").is_file(), example.name
    assert list((out / "_images").glob("sphx_glr_02_modal_dynamics_*.png"))  # the example's figure
    # the guide's images resolve (a missing one is a warning, which failed the build above)
    assert re.search(r'<img[^>]+viewer\.png', (out / "index.html").read_text())
    assert re.search(r'<img[^>]+modes\.png', (out / "guide" / "getting-started.html").read_text())


def test_public_classes_and_functions_carry_parameters_returns_and_raises_sections():
    """Issue 38 item 4: every public class documents its Parameters and what it Raises (or Warns);
    every public function its Parameters (when it takes any), Returns and Raises. The exceptions
    and the two protocols (Driver, Model: no constructor of their own) are exempt."""
    import inspect

    import rtfem as rt

    def sections(doc: str) -> set[str]:
        lines = doc.splitlines()
        return {a.strip() for a, b in zip(lines, lines[1:]) if b.strip() and set(b.strip()) == {"-"}
                and len(b.strip()) >= len(a.strip()) > 0}

    missing = []
    for name in rt.__all__:
        obj = getattr(rt, name)
        if inspect.ismodule(obj) or name in ("Driver", "Model"):
            continue
        if inspect.isclass(obj) and issubclass(obj, (Exception, Warning)):
            continue
        have = sections(inspect.getdoc(obj) or "")
        if inspect.isclass(obj):
            want = {"Parameters"}
        elif inspect.isfunction(obj):
            takes = [p for p in inspect.signature(obj).parameters.values() if p.kind is not p.VAR_KEYWORD]
            want = {"Returns"} | ({"Parameters"} if takes else set())
        else:
            continue
        if not (have & {"Raises", "Warns"}):
            want.add("Raises")
        if want - have:
            missing.append(f"{name}: {sorted(want - have)}")
    assert not missing, missing
