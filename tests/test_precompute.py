"""The precompute cache (rtfem.cache, rtfem.reduction.precompute; issue 54): a second launch loads
what the first computed, bit for bit; a changed setting, a damaged or altered file, or a file of
another model is computed again, never used; `rtfem cache` lists and clears it."""

import subprocess
import sys

import numpy as np
import pytest

import rtfem as rt
from rtfem import cache
from rtfem.reduction.precompute import cached_modes, precompute


@pytest.fixture
def fresh_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("RTFEM_CACHE", str(tmp_path / "cache"))
    return tmp_path / "cache"


def _block(E=4e4, fix="x0"):
    model = rt.SolidModel(rt.meshes.box(0.1, 0.04, 0.04, nx=6, ny=2, nz=2), rt.Material(E=E, nu=0.45, density=1000.0),
                          element="tet10")
    return model.fix(fix)


def _steps(reduced, n=30):
    """A reduced nonlinear run under a tip load: the displacements of its last step."""
    sim = rt.ReducedNonlinearSimulator(reduced, 1e-3, rt.Damping(alpha=8.0))
    F = np.zeros((reduced.model.n_nodes, 3))
    F[reduced.model.select_nodes("x1"), 2] = 0.05
    for _ in range(n):
        sim.step(F)
    return sim.displacements()


def test_a_second_precompute_loads_the_first_bit_for_bit(fresh_cache):
    first = precompute(_block(), n_modes=8, derivatives=4)
    assert first.from_cache == {"modes": False, "reduced": False}
    second = precompute(_block(), n_modes=8, derivatives=4)  # another model object, the same settings
    assert second.from_cache == {"modes": True, "reduced": True}
    assert np.array_equal(first.modes.omega, second.modes.omega) and np.array_equal(first.modes.shapes,
                                                                                  second.modes.shapes)
    assert np.array_equal(first.reduced.basis, second.reduced.basis)
    assert np.array_equal(first.reduced._cubature_elements, second.reduced._cubature_elements)
    assert np.array_equal(first.reduced._cubature[1], second.reduced._cubature[1])
    assert np.array_equal(_steps(first.reduced), _steps(second.reduced))  # the same physics, bit for bit
    # and what was cached is what a computation without the cache gives (the same modes to round-off)
    plain = rt.modal_analysis(_block(), 8)
    np.testing.assert_allclose(plain.omega, first.modes.omega, rtol=1e-12)
    kinds = sorted(e.kind for e in cache.entries())
    assert kinds == ["modes", "reduced"]


@pytest.mark.parametrize("change", ["E", "fix", "n_modes"])
def test_a_changed_setting_is_computed_again(fresh_cache, change):
    cached_modes(_block(), 6)
    model = _block(E=5e4) if change == "E" else _block(fix="x1") if change == "fix" else _block()
    basis = cached_modes(model, 7 if change == "n_modes" else 6)
    assert basis.info["cache_hit"] is False and len(cache.entries()) == 2
    assert basis.n_modes == (7 if change == "n_modes" else 6)
    if change == "E":  # the frequencies scale with sqrt(E): the other model's were not used
        first = cached_modes(_block(), 6)
        np.testing.assert_allclose(basis.omega, first.omega * np.sqrt(5 / 4), rtol=1e-9)


def test_a_damaged_or_foreign_file_is_computed_again_and_replaced(fresh_cache):
    good = cached_modes(_block(), 6)
    path = cache.entries()[0].path
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte inside an array: its checksum fails
    path.write_bytes(bytes(data))
    again = cached_modes(_block(), 6)
    assert again.info["cache_hit"] is False
    np.testing.assert_allclose(again.omega, good.omega, rtol=1e-12)
    assert cached_modes(_block(), 6).info["cache_hit"] is True  # the file was replaced by a good one
    # another model's file under this model's name (copied over it): its digest or mesh does not match
    other = cached_modes(_block(E=9e4), 6)
    mine = [e.path for e in cache.entries() if e.kind == "modes" and e.path != path][0]
    path.write_bytes(mine.read_bytes())
    taken = cached_modes(_block(), 6)
    assert taken.info["cache_hit"] is False and not np.allclose(taken.omega, other.omega)


def test_a_cache_that_cannot_be_written_still_computes(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("RTFEM_CACHE", str(blocker / "cache"))
    basis = cached_modes(_block(), 5)
    assert basis.n_modes == 5 and basis.info["cache_hit"] is False


def test_precompute_refuses_bad_arguments(fresh_cache):
    for bad in (dict(n_modes=0), dict(derivatives=-1), dict(cubature="yes"), dict(progress=5)):
        with pytest.raises(rt.ModelError):
            precompute(_block(), **bad)
    with pytest.raises(rt.ModelError, match="is not a model"):
        precompute("liver")
    assert not cache.entries()  # nothing computed, nothing kept


def test_rtfem_cache_lists_and_clears(fresh_cache):
    cached_modes(_block(), 5)
    run = lambda *a: subprocess.run([sys.executable, "-m", "rtfem.cli.main", "cache", *a], capture_output=True,  # noqa
                                    text=True, timeout=120)
    r = run()
    assert r.returncode == 0 and str(fresh_cache) in r.stdout and "modes" in r.stdout and "1 file" in r.stdout
    r = run("--clear", "--kind", "reduced")
    assert r.returncode == 0 and "removed 0" in r.stdout and len(cache.entries()) == 1
    r = run("--clear")
    assert r.returncode == 0 and "removed 1 file (" in r.stdout and not cache.entries()
    assert run("--kind", "nothing").returncode == 2


def test_simulate_twice_loads_the_precompute_and_writes_the_same_run(fresh_cache, tmp_path):
    """`rtfem simulate --method nonlinear` on a shell, cold then warm: the second says it loaded the modes and
    the reduced model, and writes the same CSV byte for byte."""
    outs = []
    for i in range(2):
        out = tmp_path / f"run{i}"
        r = subprocess.run([sys.executable, "-m", "rtfem.cli.main", "simulate", "--method", "nonlinear", "-n", "10",
                            "--duration", "0.05", "--out", str(out)], capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr
        outs.append((r.stdout, (out / "response.csv").read_bytes()))
    assert "kept in" in outs[0][0] and "loaded modes and reduced model from" in outs[1][0]
    assert outs[0][1] == outs[1][1]


def test_the_cache_is_found_whichever_assembly_made_the_model(fresh_cache, monkeypatch):
    """The numpy and the compiled assembly give K to the last bits differently (a process that has loaded
    numba assembles the other way): the cache's key is the model's inputs, so either finds the other's."""
    monkeypatch.setenv("RTFEM_ASSEMBLY", "compiled")
    first = cached_modes(_block(), 6)
    monkeypatch.setenv("RTFEM_ASSEMBLY", "numpy")
    model = _block()
    assert abs(model.K - _block().K).max() < 1e-9 * abs(model.K).max()  # the same matrix, near enough
    again = cached_modes(model, 6)
    assert again.info["cache_hit"] is True and np.array_equal(again.omega, first.omega)


def test_a_law_parameter_changed_in_its_last_digits_is_another_model(fresh_cache):
    """The law's parameters enter the key at full precision (its repr rounds to 6 digits)."""
    law = rt.NeoHookean(mu=1.0e4, kappa=5.0e4, density=1000.0)
    nearby = rt.NeoHookean(mu=1.0e4 * (1 + 1e-9), kappa=5.0e4, density=1000.0)
    assert repr(law) == repr(nearby)
    models = [rt.SolidModel(rt.meshes.box(0.1, 0.04, 0.04, nx=4, ny=2, nz=2), m, element="tet4").fix("x0")
              for m in (law, nearby)]
    cached_modes(models[0], 4)
    assert cached_modes(models[1], 4).info["cache_hit"] is False
