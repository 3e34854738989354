"""``rtfem batch PLAN.toml`` (issue 42 item 3): two organs (a dome at two Young's moduli) precomputed
into one folder, here and on a LocalCluster of two processes; the files equal what the library builds
directly with the same settings, the stiffer dome's frequencies are sqrt(3) times the softer's (a linear
shell: f ~ sqrt(E)); a second run keeps every valid file, a changed organ or a damaged file is rebuilt;
a bad plan is one line."""

from __future__ import annotations

import numpy as np
import pytest

import rtfem as rt
from rtfem.cli.main import main
from rtfem.reduction.reduced import ReducedNonlinearModel

PLAN = """out = "out"
[defaults]
build = ["modes", "map", "reduced"]
modes = 10
radius = 0.02
times = [0.01, 0.05]
derivatives = 4
fix = "z<0.0001"
mesh = "dome.obj"
[[organ]]
name = "soft"
E = 20000.0
[[organ]]
name = "stiff"
E = {stiff}
"""


def _model(E):
    model = rt.ShellModel(rt.meshes.hemisphere(), rt.Material(E=E))
    X = np.asarray(model.mesh.vertices)
    return model.fix(np.flatnonzero(X[:, 2] < 0.0001))


@pytest.fixture()
def plan(tmp_path):
    rt.save_mesh(rt.meshes.hemisphere(), tmp_path / "dome.obj")
    (tmp_path / "plan.toml").write_text(PLAN.format(stiff=60000.0))
    return tmp_path


def _stamps(out):
    return {p.name: p.stat().st_mtime_ns for p in out.glob("*.npz")}


def test_a_batch_writes_what_the_library_builds_and_resumes(plan, capsys):
    out = plan / "out"
    assert main(["batch", str(plan / "plan.toml")]) == 0
    assert len(list(out.glob("*.npz"))) == 6 and (out / "summary.csv").is_file()
    soft, stiff = _model(20000.0), _model(60000.0)
    modes = rt.ModalBasis.load(out / "soft.modes.npz", model=soft)
    direct = rt.modal_analysis(soft, 10)
    np.testing.assert_allclose(modes.omega, direct.omega, rtol=1e-10)
    ratio = rt.ModalBasis.load(out / "stiff.modes.npz", model=stiff).omega / modes.omega
    np.testing.assert_allclose(ratio, np.sqrt(3.0), rtol=1e-9)
    imap = rt.ImpedanceMap.load(out / "soft.map.npz", model=soft)
    ref = rt.ImpedanceMap.build(soft, modes=direct, n_modes=10, radius=0.02, times=(0.01, 0.05))
    np.testing.assert_array_equal(imap.neighbours, ref.neighbours)
    assert np.abs(imap.responses - ref.responses).max() <= 1e-8 * np.abs(ref.responses).max()
    red = ReducedNonlinearModel.load(out / "soft.reduced.npz", soft)
    assert red.n_modes == 10 and red.n_derivatives == 10 and red._cubature is not None
    with pytest.raises(rt.ModelError, match="other supports, material"):
        rt.ImpedanceMap.load(out / "soft.map.npz", model=stiff)  # the same mesh, another material
    capsys.readouterr()

    before = _stamps(out)
    assert main(["batch", str(plan / "plan.toml"), "--scheduler", "local:2"]) == 0
    text = capsys.readouterr().out
    assert "| soft | 469 | 2,814 | - | modes map reduced |" in text and _stamps(out) == before

    (plan / "plan.toml").write_text(PLAN.format(stiff=90000.0))  # the stiff organ changes
    (out / "soft.map.npz").write_bytes(b"not a map")  # and a file is damaged
    assert main(["batch", str(plan / "plan.toml")]) == 0
    after = _stamps(out)
    assert after["soft.modes.npz"] == before["soft.modes.npz"] and after["soft.reduced.npz"] == before["soft.reduced.npz"]
    assert all(after[f"stiff.{k}.npz"] != before[f"stiff.{k}.npz"] for k in ("modes", "map", "reduced"))
    imap = rt.ImpedanceMap.load(out / "soft.map.npz", model=soft)
    assert np.abs(imap.responses - ref.responses).max() <= 1e-8 * np.abs(ref.responses).max()


@pytest.mark.parametrize("text, said", [
    ("[[organ]]\nname = 'a'\ncolour = 'red'\n", "unknown key(s) ['colour']"),
    ("[[organ]]\nname = 'a'\nmesh = 'nowhere.obj'\n", "does not exist"),
    ("[[organ]]\nname = 'a'\n[[organ]]\nname = 'a'\n", "its own name"),
    ("[[organ]]\nname = 'a'\nbuild = ['maps']\n", "give a list of modes, map, reduced"),
    ("out = 'x'\n", "at least one [[organ]]"),
    ("[[organ]\n", "not a TOML plan"),
])
def test_a_bad_plan_is_one_line(tmp_path, capsys, text, said):
    (tmp_path / "plan.toml").write_text(text)
    assert main(["batch", str(tmp_path / "plan.toml")]) == 2
    err = capsys.readouterr().err
    assert said in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err


def test_an_organ_that_fails_is_a_row_and_the_others_finish(plan, capsys):
    text = PLAN.format(stiff=60000.0) + "[[organ]]\nname = 'loose'\nfix = 'z<-1'\n"  # fixes no node
    (plan / "plan.toml").write_text(text.replace('build = ["modes", "map", "reduced"]', 'build = ["modes"]'))
    assert main(["batch", str(plan / "plan.toml")]) == 1
    out = capsys.readouterr().out
    assert "| loose | 0 | 0 | - | - |" in out and "selects no vertex" in out.split("| loose |")[1], out
    assert sorted(p.name for p in (plan / "out").glob("*.npz")) == ["soft.modes.npz", "stiff.modes.npz"]


def test_a_saved_reduced_model_loads_only_onto_its_own_model_and_whole(tmp_path):
    soft = _model(20000.0)
    red = ReducedNonlinearModel(soft, rt.modal_analysis(soft, 8), 3)
    red.train_cubature(6)
    path = red.save(tmp_path / "r.npz")
    same = ReducedNonlinearModel.load(path, soft)
    np.testing.assert_array_equal(same.basis, red.basis)
    np.testing.assert_array_equal(same._cubature_elements, red._cubature_elements)
    with pytest.raises(rt.ModelError, match="other supports, material"):
        ReducedNonlinearModel.load(path, _model(60000.0))  # the same mesh, another material
    other = rt.ShellModel(rt.meshes.hemisphere(radius=0.04), rt.Material())
    other.fix(np.flatnonzero(np.asarray(other.mesh.vertices)[:, 2] < 1e-4))
    with pytest.raises(rt.ModelError, match="another mesh"):
        ReducedNonlinearModel.load(path, other)
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one byte of the basis flipped
    (tmp_path / "bad.npz").write_bytes(bytes(data))
    with pytest.raises(rt.ModelError):
        ReducedNonlinearModel.load(tmp_path / "bad.npz", soft)
    local = red.localize([int(np.flatnonzero(~soft.held_nodes)[0])], 0.01)
    with pytest.raises(rt.ModelError, match="localized"):
        local.save(tmp_path / "local.npz")
    assert not (tmp_path / "local.npz").exists() and path.read_bytes() == red.save(path).read_bytes()


def test_a_plan_gives_a_mesh_of_regions_a_material_per_region(tmp_path, capsys):
    """``material = ["stiff=linear:3e5"]`` in a plan is --material repeated: the organ's modes are those
    of rt.SolidModel(mesh, {label: material}); a material that is not a law or a list of them is one
    line naming the key."""
    box = rt.meshes.box(0.06, 0.02, 0.02, nx=6, ny=2, nz=2)
    c = np.asarray(box.vertices)[np.asarray(box.corner_tets)].mean(axis=1)
    mesh = rt.TetMesh(box.vertices, box.tets, labels=(c[:, 0] > 0.03).astype(int), region_names={"soft": 0, "stiff": 1})
    rt.save_mesh(mesh, tmp_path / "bar.vtu")
    (tmp_path / "plan.toml").write_text('out = "out"\n[[organ]]\nname = "bar"\nmesh = "bar.vtu"\nbuild = ["modes"]\n'
                                        'modes = 6\nelement = "tet4"\nfix = "x<0.001"\n'
                                        'material = ["linear", "stiff=linear:3e5"]\n')
    assert main(["batch", str(tmp_path / "plan.toml")]) == 0
    model = rt.SolidModel(mesh, {0: rt.Material(), 1: rt.Material(E=3e5)}, element="tet4")
    model.fix(np.flatnonzero(np.asarray(mesh.vertices)[:, 0] < 0.001))
    got = rt.ModalBasis.load(tmp_path / "out" / "bar.modes.npz", model=model).omega
    np.testing.assert_allclose(got, rt.modal_analysis(model, 6).omega, rtol=1e-9)
    (tmp_path / "plan.toml").write_text((tmp_path / "plan.toml").read_text().replace('"stiff=linear:3e5"]', "3]"))
    capsys.readouterr()
    assert main(["batch", str(tmp_path / "plan.toml")]) == 2
    err = capsys.readouterr().err
    assert "material = ['linear', 3]: give a law" in err and err.count("\n") == 1, err


def test_a_shell_given_materials_per_region_is_refused_before_any_work(tmp_path, capsys):
    """A surface organ is a shell of one material: REGION=LAW is refused when the plan is read (it
    failed only when the organ ran), naming the organ; the same organ as a solid is taken."""
    rt.save_mesh(rt.meshes.liver(1), tmp_path / "liver.obj")
    plan = ('out = "out"\n[[organ]]\nname = "liver"\nmesh = "liver.obj"\nbuild = ["modes"]\nmodes = 4\n'
            'fix = "attachment"\nmaterial = ["liver", "0=linear:3e5"]\n')
    (tmp_path / "plan.toml").write_text(plan)
    assert main(["batch", str(tmp_path / "plan.toml")]) == 2
    err = capsys.readouterr().err
    assert "organ 1 ('liver'): material REGION=LAW needs a solid of regions" in err and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()
    from rtfem.cli.batch import load_plan

    (tmp_path / "plan.toml").write_text(plan + "solid = true\n")
    assert load_plan(tmp_path / "plan.toml")[2][0]["solid"] is True
