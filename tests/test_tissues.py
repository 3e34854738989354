"""Sourced tissue parameters (issue 58): rt.tissue and --material TISSUE read the package's copy of
the project's sourced table (../shared/data/tissue.toml), keep its values, cite the source and its
confidence, and say what they derived."""

from __future__ import annotations

import tomllib
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

import rtfem as rt
from test_cli_commands import run

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "tissue.toml"


def test_the_package_table_is_the_sourced_one():
    """The shipped table is the project's sourced table, byte for byte (where that is at hand)."""
    shipped = (resources.files("rtfem") / "data" / "tissue.toml").read_bytes()
    rows = tomllib.loads(shipped.decode())["tissue"]
    assert len(rows) == 10 and all(r["source"].startswith("http") and r["quote"] and r["confidence"] for r in rows)
    if not SHARED.exists():
        pytest.skip(f"the project's table is not at {SHARED} (a checkout without ../shared)")
    assert SHARED.read_bytes() == shipped


def test_a_set_in_its_own_law_keeps_the_sources_numbers():
    skin = rt.tissue("skin")  # neo-Hookean C10 4 kPa, K0 666.67 kPa, nu 0.494 (Int Wound J 2018, Table 3)
    assert isinstance(skin.material, rt.NeoHookean)
    assert skin.material.c10 == 4000.0 and skin.material.kappa == 666670.0
    assert skin.confidence == "secondary" and "PMC7949503" in skin.source
    assert np.isclose(skin.material.linearized().nu, 0.494, atol=5e-4)  # the set's nu, from its moduli
    liver = rt.tissue("liver")  # the first liver set: E 2.04 kPa (Mattei et al. 2014)
    assert isinstance(liver.material, rt.Material) and liver.material.E == 2040.0
    assert "Mattei" in liver.citation and liver.confidence == "abstract"
    assert any("nu = 0.45: not in the set, assumed" in d for d in liver.derived)
    text = str(liver)
    assert "doi:10.1016/j.jbiomech.2014.05.017" in text and "confidence: abstract" in text and "assumed" in text


def test_the_issues_spelling_rt_materials_tissue():
    """rt.materials.tissue(name), as the issue writes it, is rt.tissue."""
    assert rt.materials.tissue is rt.tissue
    assert repr(rt.materials.tissue("fat").material) == "NeoHookean(mu=800, kappa=66670, density=1060)"  # C10 400 Pa
    assert rt.materials.Material is rt.Material and rt.materials.fit_material is rt.fit_material


def test_what_is_derived_is_said_and_what_cannot_be_is_refused():
    g = rt.tissue("liver", which=1)  # G = 1.8 kPa: E = 2 G (1 + nu)
    assert g.material.E == pytest.approx(2 * 1800.0 * 1.45) and any("E = 2 G (1 + nu)" in d for d in g.derived)
    nh = rt.tissue("liver", which=1, law="neo-hookean")
    assert nh.material.mu == 1800.0 and any("the source fitted no neo-Hookean" in d for d in nh.derived)
    assert np.isclose(nh.material.linearized().E, g.material.E)  # the same material at rest
    brain = rt.tissue("brain")
    assert any("FEBio" in d for d in brain.derived) and not any("nu" in d for d in brain.derived)  # kappa given
    with pytest.raises(rt.ModelError, match="does not give its law's constants"):
        rt.tissue("brain", which=1)
    assert rt.tissue("brain", which=1, law="neo-hookean").material.mu == 900.0
    with pytest.raises(rt.ModelError, match="the table has: brain, fat"):
        rt.tissue("kidney")
    with pytest.raises(rt.ModelError, match="nu = 0.494"):
        rt.tissue("skin", nu=0.3)
    with pytest.raises(rt.ModelError, match="an Ogden law cannot be made"):
        rt.tissue("liver", law="ogden")


def test_material_tissue_on_the_command_line_says_its_source(tmp_path, capsys):
    bar = tmp_path / "bar.vtu"
    rt.save_mesh(rt.meshes.box(0.06, 0.02, 0.02, nx=6, ny=2, nz=2), bar)
    rc, out, err = run(capsys, "modes", str(bar), "--fix", "x<0.001", "-n", 4, "--material", "liver#2",
                       "--element", "tet4", "--out", tmp_path / "m.npz")
    assert rc == 0, err
    assert "tissue      liver" in out and "PMC6925591" in out and "confidence: secondary" in out
    assert "E = 2 G (1 + nu) = 5220 Pa" in out
