"""Scenes a user can write (issue 54, section 3): ``-o`` for every output folder, VTU frames that ParaView
warps once, ``translate``/``rotate``/``scale`` placing a ``[[body]]``, and any law of ``--material`` as a
``material`` table; the done-when run: a placed neo-Hookean box dropped on a plane by
``rtfem simulate scene.toml --duration T -o DIR`` rests on it with the plane carrying its weight."""

from __future__ import annotations

import csv
import subprocess
import sys

import meshio
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import rtfem as rt
from rtfem.cli.main import build_parser
from rtfem.interaction.scene_file import load_scene


@pytest.mark.parametrize("argv", [["simulate"], ["simulate", "scene.toml"], ["pictures"], ["demo"], ["batch", "plan.toml"]])
def test_minus_o_is_the_short_form_of_out_wherever_an_output_folder_is_taken(argv):
    assert build_parser().parse_args([*argv, "-o", "DIR"]).out == "DIR"
    assert build_parser().parse_args([*argv, "--out", "DIR"]).out == "DIR"


def test_the_demo_script_takes_minus_o_too(monkeypatch, tmp_path):
    from rtfem.cli import demo

    seen = []
    monkeypatch.setattr(demo, "static_poke", seen.append)
    monkeypatch.setattr(demo, "probe_dynamics", lambda out: None)
    monkeypatch.setattr(demo, "haptic_session", lambda: None)
    assert demo.main(["-o", str(tmp_path / "d")]) == 0 and seen == [tmp_path / "d"]


# ---------------------------------------------------------------- the done-when run
DROP = """gravity = [0, 0, -9.81]

[[body]]
name = "box"
mesh = "box.vtu"                   # 0.1 x 0.1 x 0.05 m, corner at the origin
rotate = [90, 0, 30]               # stood on its 0.1 x 0.05 side, turned 30 degrees about the vertical
translate = [0.2, -0.1, 0.005]     # its lowest face 5 mm above the table
element = "tet4"
material = { law = "neo-hookean", mu = 3000, kappa = 30000, density = 1000 }
modes = 20
alpha = 20.0

[[obstacle]]
name = "table"
plane = { point = [0, 0, 0], normal = [0, 0, 1] }
friction = 0.3
"""
ROTATE, TRANSLATE = [90, 0, 30], [0.2, -0.1, 0.005]


@pytest.fixture()
def folder(tmp_path):
    rt.save_mesh(rt.meshes.box(0.1, 0.1, 0.05, nx=4, ny=4, nz=2), tmp_path / "box.vtu")
    (tmp_path / "scene.toml").write_text(DROP)
    return tmp_path


def _placed(points, rotate, translate):
    """The scene's rest positions by hand: scipy's extrinsic x-then-y-then-z rotation, then the offset."""
    return Rotation.from_euler("xyz", rotate, degrees=True).apply(points) + np.asarray(translate)


def test_a_placed_neo_hookean_box_dropped_on_a_plane_rests_on_it_carrying_its_weight(folder):
    """Issue 54's done-when: ``rtfem simulate scene.toml --duration T -o DIR`` (the command as a user
    types it) on a box placed by rotate and translate 5 mm above a plane, neo-Hookean, under gravity:
    once settled the plane's force in contacts.csv is the weight rho V g (V from the file's tets) to
    1 %, and the last written frame (reference points + displacement, read back with meshio) lies on
    the plane: nothing below it, a face of points on it, the rest at the placed box's height."""
    run = subprocess.run([sys.executable, "-m", "rtfem.cli.main", "simulate", "scene.toml", "--duration", "1.0",
                          "-o", "out"], cwd=folder, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "NeoHookean(mu=3000, kappa=30000, density=1000)" in run.stdout
    box = meshio.read(folder / "box.vtu")
    corners = box.points[box.cells_dict["tetra"]]
    volume = np.abs(np.linalg.det(corners[:, 1:] - corners[:, :1])).sum() / 6
    weight = volume * 1000 * 9.81
    with open(folder / "out" / "contacts.csv") as fh:
        rows = [r for r in csv.DictReader(fh) if (r["a"], r["b"]) == ("box", "table")]
    assert len(rows) == 1000 and float(rows[0]["fz"]) == 0.0  # falling at first: no contact
    settled = np.array([[float(r[k]) for k in ("fx", "fy", "fz")] for r in rows if float(r["t"]) > 0.95])
    force = settled.mean(axis=0)
    assert abs(force[2] - weight) < 0.01 * weight, (force, weight)
    assert np.abs(force[:2]).max() < 0.01 * weight
    frames = sorted((folder / "out" / "box").glob("frame_*.vtu"))
    assert len(frames) == 59  # 60 per simulated second
    last = meshio.read(frames[-1])
    rest = _placed(box.points, ROTATE, TRANSLATE)
    np.testing.assert_allclose(last.points, rest, atol=1e-15)  # the placed body at rest, with the field
    x = last.points + last.point_data["displacement"]
    tol = 1e-5  # m: 0.01 mm on a 10 cm box
    assert x[:, 2].min() > -tol  # not sunk
    on = np.flatnonzero(x[:, 2] < tol)
    assert on.size >= 3 and np.allclose(rest[on, 2], TRANSLATE[2])  # resting on its lowest face, not floating
    assert abs(x[:, 2].max() - 0.1) < 0.01  # standing on its 0.1 x 0.05 side, a little compressed


def test_a_placed_body_rests_at_the_files_mesh_rotated_then_translated(folder):
    """rotate = [rx, ry, rz] turns the mesh about the scene's fixed x axis, then y, then z (extrinsic,
    scipy's from_euler("xyz")), about the file's origin after scale; translate moves it after: the
    body's model holds the file's points so placed, and the law of its material table."""
    box = meshio.read(folder / "box.vtu")
    angles = [20.0, -35.0, 110.0]  # a generic turn: extrinsic and intrinsic orders differ here
    (folder / "scene.toml").write_text(DROP.replace(f"rotate = {ROTATE}", f"rotate = {angles}")
                                       .replace("modes = 20", "modes = 6"))
    scene = load_scene(folder / "scene.toml")
    model = scene.bodies[0].model
    n = box.points.shape[0]
    X = np.asarray(model.tetmesh.vertices)[:n]
    np.testing.assert_allclose(X, _placed(box.points, angles, TRANSLATE), rtol=0, atol=1e-15)
    intrinsic = Rotation.from_euler("XYZ", angles, degrees=True).apply(box.points) + TRANSLATE
    assert np.abs(X - intrinsic).max() > 1e-3  # not the intrinsic order
    assert isinstance(model.law, rt.NeoHookean) and (model.law.mu, model.law.kappa) == (3000.0, 30000.0)
    np.testing.assert_allclose(model.material.E, 9 * 30000 * 3000 / (3 * 30000 + 3000), rtol=1e-12)
    # an embedded mesh: scale, then the turn, then the offset (a shell)
    (folder / "gb.toml").write_text('[[body]]\nname = "gb"\nmesh = "rtfem:gallbladder"\nscale = 2.0\n'
                                    'rotate = [0, 90, 0]\ntranslate = [1, 2, 3]\nmodes = 8\n')
    gb = load_scene(folder / "gb.toml").bodies[0]
    np.testing.assert_allclose(gb.X, _placed(2.0 * np.asarray(rt.meshes.gallbladder().vertices), [0, 90, 0],
                                             [1, 2, 3]), atol=1e-15)


# ---------------------------------------------------------------- material tables
def _params(law) -> dict:
    """A law's class and moduli, to compare two routes to it."""
    out = {"type": type(law).__name__, "density": law.density}
    if isinstance(law, rt.Prony):
        return {**out, "g": law.g.tolist(), "tau": law.tau.tolist(), "of": _params(law.instantaneous)}
    if isinstance(law, rt.Material):
        return {**out, "E": law.E, "nu": law.nu}
    names = ("mu", "kappa", "c10", "c01") if not isinstance(law, rt.Ogden) else ("kappa",)
    out.update({k: pytest.approx(getattr(law, k), rel=1e-13) for k in names})
    if isinstance(law, rt.Ogden):
        out.update(mus=law.mus.tolist(), alphas=law.alphas.tolist())
    return out


@pytest.mark.parametrize("table, text", [
    ({"E": 2e4, "nu": 0.4, "density": 1050}, "linear"),
    ({"law": "neo-hookean", "E": 2e4, "nu": 0.4, "density": 1050}, "neo-hookean"),
    ({"law": "mooney-rivlin", "c10": 500, "c01": 200, "nu": 0.4, "density": 1050}, "mooney-rivlin:500,200"),
    ({"law": "ogden", "mu": [3000, -500], "alpha": [8, -2], "nu": 0.4, "density": 1050}, "ogden:3000,8,-500,-2"),
    ({"law": "neo-hookean", "E": 2e4, "nu": 0.4, "density": 1050, "prony": {"g": [0.5, 0.2], "tau": [0.1, 1.0]}},
     "neo-hookean+prony:0.5,0.1,0.2,1.0"),
])
def test_a_material_table_is_the_law_the_command_line_names(table, text):
    """One builder for --material and the scene's table: the same law from both (E and nu standing
    in for what the table leaves out, as --E and --nu do)."""
    from rtfem.fe.viscoelastic import material_from_table, material_from_text

    cli = material_from_text(text, rt.Material(E=2e4, nu=0.4, density=1050.0))
    assert _params(material_from_table(table)) == _params(cli)


def test_a_material_tables_own_moduli_are_the_laws():
    """mu and kappa as given; E and nu give a neo-Hookean mu = E / 2 (1 + nu), kappa = E / 3 (1 - 2 nu);
    a law's kappa left out keeps nu's ratio (the same Poisson's ratio at rest)."""
    from rtfem.fe.viscoelastic import material_from_table

    law = material_from_table({"law": "neo-hookean", "mu": 3000, "kappa": 30000, "density": 1000})
    assert (type(law), law.mu, law.kappa, law.density) == (rt.NeoHookean, 3000.0, 30000.0, 1000.0)
    law = material_from_table({"law": "neo-hookean", "E": 2.9e4, "nu": 0.45})
    assert law.mu == pytest.approx(2.9e4 / 2.9, rel=1e-14) and law.kappa == pytest.approx(2.9e4 / 0.3, rel=1e-14)
    assert law.density == rt.Material().density
    law = material_from_table({"law": "mooney-rivlin", "c10": 500, "c01": 200, "kappa": 1e5})
    assert (law.c10, law.c01, law.kappa) == (500.0, 200.0, 1e5)
    for table in ({"law": "mooney-rivlin", "c10": 500, "c01": 200, "nu": 0.47},
                  {"law": "ogden", "mu": [2000.0], "alpha": [8.0], "nu": 0.47},
                  {"law": "neo-hookean", "mu": 2000.0, "nu": 0.47}):
        assert material_from_table(table).linearized().nu == pytest.approx(0.47, rel=1e-12)


BAD = [
    ("mu = 3000", "mu = -5", r"key 'material': mu=-5 must be > 0 \(the shear modulus in Pa"),
    ("kappa = 30000", "kappa = 0", r"key 'material': kappa=0.0 must be > 0 \(the bulk modulus"),
    ("kappa = 30000", "kappa = nan", r"key 'material': kappa=nan is not finite"),
    ("mu = 3000", 'mu = "3000"', r"key 'material': mu='3000' is not a number"),
    ("density = 1000", "density = -1", r"key 'material': .*density"),
    ('law = "neo-hookean"', 'law = "liver"', r"key 'material': law='liver'; choose one of 'linear', 'neo-hookean'"),
    ("kappa = 30000", "kappa = 30000, E = 3e4", r"key 'material': mu and E: give one"),
    ("kappa = 30000", "kappa = 30000, nu = 0.4", r"key 'material': kappa and nu: give one"),
    ("kappa = 30000", "kappa = 30000, c10 = 3", r"key 'material': c10: not a key of law 'neo-hookean'"),
    ('law = "neo-hookean", mu = 3000', 'law = "mooney-rivlin", c10 = 3000', r"key 'material': mooney-rivlin needs both"),
    ('law = "neo-hookean", mu = 3000', 'law = "ogden", mu = [3000, 1], alpha = [8]', r"key 'material': Ogden .*two lists"),
    ('law = "neo-hookean"', 'law = "linear"', r"key 'material': mu: not a key of law 'linear'"),
    ("density = 1000", "density = 1000, prony = { g = [1.5], tau = [0.1] }", r"key 'material': g = \[1.5\]"),
    ("density = 1000", "density = 1000, prony = { g = [0.5] }", r"key 'material': prony must be \{ g = "),
    ('element = "tet4"', 'kind = "shell"', r"key 'material': law 'neo-hookean' is for solids"),
    ("rotate = [90, 0, 30]", "rotate = [90, 0]", r"key 'rotate': rotate must be 3 numbers|key 'rotate'.*3"),
    ("rotate = [90, 0, 30]", "rotate = [nan, 0, 30]", r"key 'rotate': .*finite"),
    ("rotate = [90, 0, 30]", 'rotate = ["90", 0, 30]', r"key 'rotate'"),
    ("rotate = [90, 0, 30]", "rotate = [1000, 0, 30]", r"key 'rotate': .*degrees, -360 .. 360"),
    ("translate = [0.2, -0.1, 0.005]", "translate = [0.2, 0.005]", r"key 'translate'"),
    ("translate = [0.2, -0.1, 0.005]", "translate = [2e3, 0, 0]", r"key 'translate': .*more than 1000 m"),
    ("translate = [0.2, -0.1, 0.005]", "translate = [inf, 0, 0]", r"key 'translate'"),
    ("translate = [0.2, -0.1, 0.005]", "translate = 0.2", r"key 'translate'"),
]


@pytest.mark.parametrize("old, new, match", BAD)
def test_bad_material_and_placement_keys_name_the_key_and_what_to_give(folder, old, new, match):
    assert old in DROP
    (folder / "scene.toml").write_text(DROP.replace(old, new, 1))
    with pytest.raises(rt.ModelError, match=r"scene.toml: \[\[body\]\] 1 'box': " + match):
        load_scene(folder / "scene.toml")


def test_the_cli_refuses_a_bad_material_table_in_one_line(folder, capsys):
    from rtfem.cli.main import main

    (folder / "scene.toml").write_text(DROP.replace("mu = 3000", "mu = -5"))
    assert main(["simulate", str(folder / "scene.toml"), "--duration", "0.1", "-o", str(folder / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "key 'material': mu=-5 must be > 0" in err and "Traceback" not in err
    assert not (folder / "out").exists()


def _two_region_box(path, names: dict) -> np.ndarray:
    """A 100 x 100 x 50 mm tet box written to ``path`` (Gmsh), label 1 at x < 50 mm, 2 beyond, with
    ``names``; returns the labels."""
    box = rt.meshes.box(0.1, 0.1, 0.05, nx=4, ny=4, nz=2)
    c = np.asarray(box.vertices)[np.asarray(box.corner_tets)].mean(axis=1)
    labels = np.where(c[:, 0] > 0.05, 2, 1)
    rt.save_mesh(rt.TetMesh(box.vertices, box.tets, labels=labels, region_names=names), path)
    return labels


def test_a_body_of_regions_takes_a_material_per_region_by_label_or_name(tmp_path):
    """A labelled tet mesh (Gmsh physical groups, named) placed by rotate: the body's model keeps the
    labels through the placement and takes each region's table, keyed by name or by label; a key that
    names no region is refused naming it; a shell takes one material."""
    labels = _two_region_box(tmp_path / "box.msh", {"soft": 1, "stiff": 2})
    body = ('[[body]]\nname = "box"\nmesh = "box.msh"\nrotate = [0, 0, 30]\nelement = "tet4"\nfix = "bottom:0.1"\n'
            'modes = 6\nmaterial = { soft = { E = 3e4 }, 2 = { law = "neo-hookean", mu = 1e5, kappa = 1e6 } }\n')
    (tmp_path / "scene.toml").write_text(body)
    model = load_scene(tmp_path / "scene.toml").bodies[0].model
    assert np.array_equal(model.tetmesh.labels, labels)
    assert model.materials[1] == rt.Material(E=3e4) and model.materials[2].mu == 1e5
    (tmp_path / "bad.toml").write_text(body.replace("soft = {", "liver = {"))
    with pytest.raises(rt.ModelError, match="key 'material': material key 'liver' names no region"):
        load_scene(tmp_path / "bad.toml")
    (tmp_path / "shell.toml").write_text(body.replace('element = "tet4"\n', 'kind = "shell"\n'))
    with pytest.raises(rt.ModelError, match="a material per region is for solids"):
        load_scene(tmp_path / "shell.toml")


def test_a_scene_names_a_sourced_tissue_set_as_the_command_line_does(tmp_path):
    """``material = { tissue = "liver#2" }`` is the set ``--material liver#2`` names (rt.tissue's, with
    the density given); per region too; keys a set gives itself, or a name of no set, are refused
    naming the key."""
    from rtfem.fe.viscoelastic import material_from_table, material_from_text

    for text in ("liver", "liver#2", "skin"):
        base = rt.Material(density=1000.0)
        assert _params(material_from_table({"tissue": text, "density": 1000.0})) == _params(material_from_text(text, base))
    assert material_from_table({"tissue": "liver#2"}).E == rt.tissue("liver", which=1).material.E
    _two_region_box(tmp_path / "box.msh", {"liver": 1, "capsule": 2})
    body = ('[[body]]\nname = "box"\nmesh = "box.msh"\nelement = "tet4"\nfix = "bottom:0.1"\nmodes = 6\n'
            'material = { liver = { tissue = "liver" }, capsule = { E = 3e5 } }\n')
    (tmp_path / "scene.toml").write_text(body)
    model = load_scene(tmp_path / "scene.toml").bodies[0].model
    assert model.materials[1] == rt.tissue("liver").material and model.materials[2].E == 3e5
    (tmp_path / "mixed.toml").write_text(body.replace("capsule = { E = 3e5 } }", "capsule = { E = 3e5 }, density = 1000 }"))
    with pytest.raises(rt.ModelError, match="key 'material': a material is either one law's keys .* put density inside"):
        load_scene(tmp_path / "mixed.toml")
    for bad, match in (('{ tissue = "rubber" }', "key 'material.liver': tissue = 'rubber' names no set of the table"),
                       ('{ tissue = "liver", E = 3e4 }', "E: a sourced tissue set gives its own law and moduli"),
                       ('{ tissue = "liver#9" }', "give #1 .. #")):
        (tmp_path / "bad.toml").write_text(body.replace('{ tissue = "liver" }', bad))
        with pytest.raises(rt.ModelError, match=match):
            load_scene(tmp_path / "bad.toml")
