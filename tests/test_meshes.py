import numpy as np
import pytest

import rtfem as rt


def test_default_liver():
    m = rt.meshes.liver()
    assert 2000 <= m.n_vertices <= 5000
    assert m.is_closed() and m.report.n_components == 1
    assert m.n_vertices - m.edges().shape[0] + m.n_triangles == 2  # genus 0
    ext = m.bounds()[1] - m.bounds()[0]
    assert np.allclose(ext, [0.2, 0.15, 0.08], rtol=0.1)
    assert m.report.min_angle_deg > 20.0  # well-shaped triangles
    assert m.volume() > 0
    att = m.groups["attachment"]
    assert 0.02 * m.n_vertices < att.size < 0.1 * m.n_vertices
    # the attachment is one connected patch on the posterior (-y), upper (+z) side
    V = np.asarray(m.vertices)
    c = V.mean(axis=0)
    assert V[att, 1].mean() < c[1] and V[att, 2].mean() > c[2]
    sub = m.adjacency()[att][:, att]
    from scipy.sparse.csgraph import connected_components

    assert connected_components(sub, directed=False)[0] == 1


@pytest.mark.parametrize("level,nv", [(3, 642), (5, 10242)])
def test_liver_refinements_share_the_surface(level, nv):
    m = rt.meshes.liver(level)
    assert m.n_vertices == nv and m.is_closed()
    assert m.report.min_angle_deg > 20.0
    assert m.volume() == pytest.approx(rt.meshes.liver(4).volume(), rel=0.03)


def test_generators_areas():
    assert rt.meshes.plate(2.0, 0.5, 8, 3).areas().sum() == pytest.approx(1.0)
    cyl = rt.meshes.cylinder(0.05, 0.2, 64, 40)
    assert cyl.areas().sum() == pytest.approx(2 * np.pi * 0.05 * 0.2, rel=0.005)
    hem = rt.meshes.hemisphere(0.05, 16)
    assert hem.areas().sum() == pytest.approx(2 * np.pi * 0.05**2, rel=0.01)
    sph = rt.meshes.icosphere(0.05, 4)
    assert sph.areas().sum() == pytest.approx(4 * np.pi * 0.05**2, rel=0.005)
    for mesh in (cyl, hem, sph):
        assert mesh.report.min_angle_deg > 25


@pytest.mark.parametrize(
    "call", [lambda: rt.meshes.plate(-1.0), lambda: rt.meshes.plate(1.0, nx=0), lambda: rt.meshes.liver(0),
             lambda: rt.meshes.cylinder(n_around=2), lambda: rt.meshes.plate(pattern="zigzag")]
)
def test_generator_argument_errors(call):
    with pytest.raises(rt.MeshError):
        call()
