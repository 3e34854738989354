"""A cut surface that bends within an element (issue 57): the element faces a split lays on it are chords of
it, their corners on the surface and their midpoints off it by the chord's sagitta. A scalpel's strips taken
back to the reference configuration of a hanging organ bend so (on the hanging tet10 liver, 2-7 % of an edge
off the faces' midpoints): with every point of a face held to the surface's thickness (2 % of an edge), no
face was cut and the scalpel cut nothing in 2.5 s of the example scene; with the midpoints held to
rtfem.mesh.cut.BEND (10 % of an edge) it cut 7 times.

Checked: a parabolic cylinder x = x0 + a (z - H/2)^2 (radius of curvature R = 1 / 2a at its crest) drawn
through the whole of a block 40 x 20 x 20 mm of 5 mm cells, tet4 and tet10, split: the block comes apart in
two (before: one piece, a few faces cut, the rest bridging the slit), every node on its piece's side of the
surface to within the largest move (a split moves a node onto the surface when the crossing is within a fifth
of an edge of it), and the piece at x = 0 the region x < x0 + a (z - H/2)^2, whose volume is
x0 H W + a W H^3 / 12, within the chords' bound (the sagitta of a chord spanning a cell's height dz,
a dz^2 / 4, over the surface's area) and the volume the moved nodes took from the block.
"""

from __future__ import annotations

import numpy as np
import pytest

import rtfem as rt
import rtfem.mesh.cut as C

L, W, H, N = 0.04, 0.02, 0.02, 5e-3  # the block and its cell


def _parabolic_cylinder(x0: float, a: float, n: int = 41):
    """(vertices, triangles): x = x0 + a (z - H/2)^2 over y, z 5 mm beyond the block, 0.75 mm triangles."""
    y, z = np.meshgrid(np.linspace(-N, W + N, n), np.linspace(-N, H + N, n), indexing="ij")
    V = np.column_stack([(x0 + a * (z - H / 2) ** 2).ravel(), y.ravel(), z.ravel()])
    k = np.arange(n * n).reshape(n, n)
    q = np.stack([k[:-1, :-1].ravel(), k[1:, :-1].ravel(), k[1:, 1:].ravel(), k[:-1, 1:].ravel()], axis=1)
    return V, np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])


@pytest.mark.parametrize("element", ["tet4", "tet10"])
@pytest.mark.parametrize("R", [0.015, 0.012, 0.01])
def test_a_cut_bending_within_elements_separates_the_block_along_it(element, R):
    box = rt.meshes.box(L, W, H, nx=int(L / N), ny=int(W / N), nz=int(H / N))
    mesh = box.quadratic() if element == "tet10" else box
    x0, a = 0.0185, 1.0 / (2.0 * R)  # (off the node planes: the surface passes through elements)
    new, info = C.cut_mesh(mesh, *_parabolic_cylinder(x0, a), snap="split")
    assert info.pieces == 2, info.faces
    assert new.volumes().min() > 0 and info.max_move <= C.MIN_SPLIT * np.sqrt(3) * N
    X = np.asarray(new.vertices)
    side = X[:, 0] - (x0 + a * (X[:, 2] - H / 2) ** 2)  # the nodes' distance in x from the surface
    low = int(np.argmin([X[info.piece == p, 0].min() for p in range(2)]))  # the piece at x = 0
    assert side[info.piece == low].max() <= info.max_move + 1e-12
    assert side[info.piece != low].min() >= -info.max_move - 1e-12
    # each piece is its side of the surface: the volume of the region x < surface, within the chords' bound
    # (a node moved onto the surface, at most max_move, dents the block's outside: that volume too)
    vol = new.volumes()
    piece = info.piece[np.asarray(new.tets)[:, 0]]
    exact = x0 * H * W + a * W * H**3 / 12
    z = np.linspace(0, H, 201)
    area = W * np.trapezoid(np.sqrt(1 + (2 * a * (z - H / 2)) ** 2), z)
    bound = a * N**2 / 4 * area + abs(vol.sum() - mesh.volume())
    assert abs(vol[piece == low].sum() - exact) <= bound, (vol[piece == low].sum() / exact - 1, bound / exact)
