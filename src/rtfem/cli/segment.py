"""``rtfem mesh``: a tet mesh of regions from a segmentation (a label volume: NIfTI or NRRD), written
as a mesh file with a region per label (:mod:`rtfem.mesh.segmentation`)."""

from __future__ import annotations

import argparse

import numpy as np

from .common import positive


def cmd_mesh(args: argparse.Namespace) -> int:
    from ..mesh.files import save_mesh
    from ..mesh.segmentation import label_mesh, parse_labels, read_labels

    labels = parse_labels(args.labels)  # a bad --labels before any reading
    volume = read_labels(args.volume)
    size = " x ".join(str(n) for n in volume.data.shape)
    spacing = " x ".join(f"{s:.4g}" for s in volume.spacing)
    print(f"labels      {args.volume}: {size} voxels of {spacing} mm (the file's units read as mm, times --scale "
          f"{args.scale:g} to metres)")
    mesh = label_mesh(volume, labels, edge_length=args.edge_length, scale=args.scale, smoothing=args.smoothing)
    voxel = float(np.prod(volume.spacing)) * args.scale**3
    vols = mesh.volumes()
    for name, value in mesh.region_names.items():
        inside = np.asarray(mesh.labels) == value
        print(f"region      {name} = {value}: {int(inside.sum()):,} tets, {vols[inside].sum():.4g} m^3 (its voxels "
              f"{int(np.sum(volume.data == value)) * voxel:.4g} m^3)")
    save_mesh(mesh, args.output)
    print(f"wrote       {args.output}: {mesh.n_vertices:,} nodes, {mesh.n_tets:,} tets, regions "
          f"{', '.join(f'{k}={v}' for k, v in mesh.region_names.items())}")
    return 0


def add_mesh_command(sub) -> None:
    p = sub.add_parser("mesh", help="a tet mesh with a region per label from a segmentation (NIfTI or NRRD label map)",
                       description="Marching cubes on the labels asked for (scikit-image), Taubin smoothing (trimesh), "
                                   "fTetWild's tets, each tet labelled by the map at its centre; the file keeps the "
                                   "regions (a VTU 'region' field, Gmsh physical groups, ...).")
    p.add_argument("volume", help="the label map (.nii, .nii.gz, .nrrd, .nhdr)")
    p.add_argument("--labels", required=True, metavar="NAME=N,...", help="the regions: names and label values, e.g. "
                   "liver=1,tumor=2")
    p.add_argument("-o", "--output", required=True, help="the tet mesh file (.vtu, .msh, .mesh, .inp, .vtk)")
    p.add_argument("--edge-length", type=positive, default=None, metavar="M", help="target tet edge in m (default: 5 %% "
                   "of the diagonal)")
    p.add_argument("--scale", type=positive, default=1e-3, help="the file's units to metres (default 1e-3: mm)")
    p.add_argument("--smoothing", type=int, default=10, metavar="N", help="Taubin iterations on the surface (default 10)")
    p.set_defaults(func=cmd_mesh)
