"""A tet mesh of regions from a label volume (issue 58): `rtfem mesh LABELS --labels ... -o FILE` and
rt.mesh.segmentation.label_mesh, on label maps made here (a block with a ball inside, a NIfTI file
with a mirrored, anisotropic affine and an NRRD file), and on the shared liver and gallbladder
surfaces voxelized: each region's volume against its surface's, its place within a voxel."""

from __future__ import annotations

import numpy as np
import pytest

import rtfem as rt
from conftest import organ
from rtfem.mesh.segmentation import LabelVolume, label_mesh, read_labels
from test_cli_commands import run

nibabel = pytest.importorskip("nibabel", reason="the segmentation extra (nibabel, pynrrd, scikit-image) is not installed")
pytest.importorskip("skimage", reason="the segmentation extra (scikit-image) is not installed")
pytest.importorskip("trimesh", reason="trimesh (the viewer and segmentation extras) is not installed")


def _needs_mesher():
    from rtfem.mesh._tetwild import find_wrapper

    if find_wrapper() is None:
        pytest.skip("the fTetWild mesher (pytetwild, the mesh extra) is not installed")


def _block_with_ball(spacing=(1.0, 1.25, 0.8)):
    """A 40 x 30 x 24 mm block (label 1) with a ball of radius 7 mm (label 2) centred at (22, 14, 12) mm,
    sampled at voxel centres; the affine mirrors the first axis (x = 60 - 1.0 i) and offsets the origin."""
    sx, sy, sz = spacing
    shape = (int(60 / sx), int(40 / sy), int(34 / sz))
    affine = np.diag([-sx, sy, sz, 1.0])
    affine[:3, 3] = [60.0, -5.0, -5.0]
    i, j, k = np.meshgrid(*[np.arange(n) for n in shape], indexing="ij")
    x, y, z = (affine @ np.stack([i, j, k, np.ones_like(i)]).reshape(4, -1))[:3].reshape(3, *shape)
    data = np.zeros(shape, np.int16)
    data[(x > 0) & (x < 40) & (y > 0) & (y < 30) & (z > 0) & (z < 24)] = 1
    data[(x - 22) ** 2 + (y - 14) ** 2 + (z - 12) ** 2 < 49] = 2
    return LabelVolume(data, affine)


def test_a_block_with_a_ball_through_the_command_line_and_back(tmp_path, capsys):
    """rtfem mesh on a NIfTI label map: the written mesh has the two named regions, the block's place and
    size within a voxel of the map's (the affine's mirror and offset applied), the ball's centre within
    a voxel, and each region's volume within 1 % (the block) and 3 % (the ball) of its voxels' (voxels
    of 1 x 1.25 x 0.8 mm, tets of 2 mm)."""
    _needs_mesher()
    vol = _block_with_ball()
    nibabel.save(nibabel.Nifti1Image(vol.data, vol.affine), tmp_path / "labels.nii.gz")
    rc, out, err = run(capsys, "mesh", tmp_path / "labels.nii.gz", "--labels", "tissue=1,ball=2", "--edge-length",
                       0.002, "-o", tmp_path / "organ.vtu")
    assert rc == 0, err
    assert "region      ball = 2" in out and "wrote" in out
    mesh = rt.load_mesh(tmp_path / "organ.vtu")
    assert set(mesh.regions.tolist()) == {1, 2}
    X = np.asarray(mesh.vertices)
    np.testing.assert_allclose(X.min(axis=0), [0, 0, 0], atol=1.25e-3)
    np.testing.assert_allclose(X.max(axis=0), [0.04, 0.03, 0.024], atol=1.25e-3)
    vols = mesh.volumes()
    ball = np.asarray(mesh.labels) == 2
    c = np.asarray(mesh.vertices)[np.asarray(mesh.corner_tets)].mean(axis=1)
    centre = (c[ball] * vols[ball, None]).sum(axis=0) / vols[ball].sum()
    np.testing.assert_allclose(centre, [0.022, 0.014, 0.012], atol=1e-3)
    voxel = np.prod(vol.spacing) * 1e-9
    # against the map's own voxels (the block's lose half a voxel a face to the sampling): the ball's
    # interface runs along 2 mm tets, a seventh of its radius (measured +0.6 .. +1.5 %; with 3 mm tets
    # -1 .. -3.5 %: the interface's error goes as the tets' size over the region's)
    assert vols[~ball].sum() == pytest.approx(np.sum(vol.data == 1) * voxel, rel=0.01)
    assert vols[ball].sum() == pytest.approx(np.sum(vol.data == 2) * voxel, rel=0.03)
    # a command that gives the mesh one material says so
    rc, out, err = run(capsys, "modes", tmp_path / "organ.vtu", "--fix", "z<0.001", "-n", 4, "--element", "tet4",
                       "-o", tmp_path / "m.npz")
    assert rc == 0 and "the mesh has 2 regions (tissue, ball); this command gives them all one material" in err, err


def test_an_nrrd_map_reads_with_its_space_directions(tmp_path):
    """The same map as NRRD (space directions and origin): read_labels gives the same voxels and
    affine as the NIfTI route."""
    nrrd = pytest.importorskip("nrrd")
    vol = _block_with_ball()
    nrrd.write(str(tmp_path / "labels.nrrd"), vol.data, {"space": "right-anterior-superior",
                                                         "space directions": vol.affine[:3, :3].T,
                                                         "space origin": vol.affine[:3, 3]})
    back = read_labels(tmp_path / "labels.nrrd")
    assert np.array_equal(back.data, vol.data) and np.allclose(back.affine, vol.affine)


def test_bad_labels_and_files_are_one_line(tmp_path, capsys):
    vol = _block_with_ball((2.0, 2.0, 2.0))
    nibabel.save(nibabel.Nifti1Image(vol.data, vol.affine), tmp_path / "labels.nii")
    for argv, message in ((["--labels", "tissue=7"], "no voxel has it; the map's labels are [1, 2]"),
                          (["--labels", "tissue"], "NAME=LABEL pairs"),
                          (["--labels", "tissue=0"], "nonzero integer label")):
        rc, out, err = run(capsys, "mesh", tmp_path / "labels.nii", *argv, "-o", tmp_path / "x.vtu")
        assert rc == 2 and message in err and "Traceback" not in err, err
    (tmp_path / "junk.nii").write_bytes(b"not a nifti file at all")
    rc, out, err = run(capsys, "mesh", tmp_path / "junk.nii", "--labels", "a=1", "-o", tmp_path / "x.vtu")
    assert rc == 2 and "could not read" in err and "Traceback" not in err
    (tmp_path / "labels.vtu").write_text("a mesh, not a label map")
    with pytest.raises(rt.MeshError, match=r"NIfTI \(.nii, .nii.gz\) or NRRD"):
        read_labels(tmp_path / "labels.vtu")


def _voxelize(surface, origin, shape, h) -> np.ndarray:
    """Voxels (centres) inside a closed surface: the parity of z-rays through each column's centre."""
    P = np.asarray(surface.vertices)[np.asarray(surface.triangles)]
    nx, ny, nz = shape
    cols, zs = [], []
    for a, b, c in P:
        lo, hi = np.minimum(np.minimum(a, b), c), np.maximum(np.maximum(a, b), c)
        i0, i1 = int(np.ceil((lo[0] - origin[0]) / h - 0.5)), int(np.floor((hi[0] - origin[0]) / h - 0.5))
        j0, j1 = int(np.ceil((lo[1] - origin[1]) / h - 0.5)), int(np.floor((hi[1] - origin[1]) / h - 0.5))
        d = (b[1] - c[1]) * (a[0] - c[0]) + (c[0] - b[0]) * (a[1] - c[1])
        if i1 < i0 or j1 < j0 or d == 0:
            continue
        I, J = np.meshgrid(np.arange(max(i0, 0), min(i1, nx - 1) + 1), np.arange(max(j0, 0), min(j1, ny - 1) + 1),
                           indexing="ij")
        px, py = origin[0] + h * (I.ravel() + 0.5), origin[1] + h * (J.ravel() + 0.5)
        l1 = ((b[1] - c[1]) * (px - c[0]) + (c[0] - b[0]) * (py - c[1])) / d
        l2 = ((c[1] - a[1]) * (px - c[0]) + (a[0] - c[0]) * (py - c[1])) / d
        ok = (l1 >= 0) & (l2 >= 0) & (1 - l1 - l2 >= 0)
        cols.append((I.ravel() * ny + J.ravel())[ok])
        zs.append((l1 * a[2] + l2 * b[2] + (1 - l1 - l2) * c[2])[ok])
    key, z = np.concatenate(cols), np.concatenate(zs)
    order = np.lexsort((z, key))
    key, z = key[order], z[order]
    zc = origin[2] + h * (np.arange(nz) + 0.5)
    mask = np.zeros(shape, bool)
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    for s, e in zip(starts, np.r_[starts[1:], key.size]):
        hits = z[s:e][: (e - s) // 2 * 2]
        crossings = np.searchsorted(hits, zc)
        mask[key[s] // ny, key[s] % ny] = crossings % 2 == 1
    return mask


def _surface_volume(surface) -> float:
    P = np.asarray(surface.vertices)[np.asarray(surface.triangles)]
    return float(np.einsum("ij,ij->i", P[:, 0], np.cross(P[:, 1], P[:, 2])).sum() / 6)


def test_the_shared_liver_and_gallbladder_as_a_label_map_give_one_mesh_of_two_regions():
    """Issue 58's done-when: SOFA's liver and gallbladder surfaces (the shared organs, mm), the
    gallbladder moved against the liver's underside, voxelized at 2 mm into one label map (liver 1,
    gallbladder 2): label_mesh gives one tet mesh of two regions whose volumes are the surfaces'
    within 2 % (measured -0.2 % and -0.9 .. -1.1 % at 10-15 mm tets)."""
    _needs_mesher()
    liver, bladder = (rt.load_mesh(organ(f)) for f in ("sofa_env_Liver.stl", "sofa_env_gallbladder_visual.stl"))
    L = np.asarray(liver.vertices)
    G = np.asarray(bladder.vertices)
    G = G + (L[np.argmin(L[:, 2])] + [0.0, 0.0, -15.0] - G.mean(axis=0))  # touching the liver's lowest point
    bladder = rt.TriMesh(G, bladder.triangles)
    h = 2.0
    lo = np.minimum(L.min(axis=0), G.min(axis=0)) - 3 * h
    shape = tuple(np.ceil((np.maximum(L.max(axis=0), G.max(axis=0)) + 3 * h - lo) / h).astype(int))
    data = np.zeros(shape, np.uint8)
    data[_voxelize(liver, lo, shape, h)] = 1
    data[_voxelize(bladder, lo, shape, h)] = 2
    affine = np.diag([h, h, h, 1.0])
    affine[:3, 3] = lo + h / 2  # voxel (i, j, k)'s centre
    mesh = label_mesh(LabelVolume(data, affine), {"liver": 1, "gallbladder": 2}, edge_length=0.015)
    assert mesh.region_names == {"liver": 1, "gallbladder": 2} and mesh.components()[0] == 1
    vols = mesh.volumes()
    for value, surface in ((1, liver), (2, bladder)):
        assert vols[np.asarray(mesh.labels) == value].sum() == pytest.approx(_surface_volume(surface) * 1e-9, rel=0.02)
