"""How the files of this folder were made from the HRA 3D Reference Object Library (README.md):
one named closed surface from each glTF file, its vertices merged where exactly equal (the glTF
stores a vertex per corner), turned from the glTF's y-up frame to z-up ((x, y, z) -> (x, -z, y),
so that "bottom" is inferior), and written as binary little-endian PLY in float32, as the glTF
holds them (metres; nothing scaled, decimated or smoothed). trimesh reads the glTF and writes the PLY.

    python benchmarks/organs/convert.py PATH/TO/ccf-3d-reference-object-library
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import trimesh

FILES = {  # output: (library file, mesh name inside it)
    "hra_kidney_right_male.ply": ("VH_Male/v1.2/VH_M_Kidney_R.glb", "VH_M_kidney_capsule_R"),
    "hra_heart_left_ventricle_male.ply": ("VH_Male/v1.2/VH_M_Heart.glb", "VH_M_heart_left_ventricle"),
    "hra_uterus_posterior_wall_female.ply": ("VH_Female/v1.2/VH_F_Uterus.glb", "VH_F_posterior_wall_of_uterus"),
    "hra_thymus_left_lobe_female.ply": ("VH_Female/v1.2/VH_F_Thymus.glb", "VH_F_thymus_lobe_L"),
}


def main(library: str) -> None:
    out = Path(__file__).resolve().parent
    for name, (path, mesh_name) in FILES.items():
        scene = trimesh.load(Path(library) / path)
        node = next(n for n in scene.graph.nodes_geometry if scene.graph[n][1] == mesh_name)
        transform, _ = scene.graph[node]
        mesh = scene.geometry[mesh_name].copy()
        mesh.apply_transform(transform)  # the identity in these files
        mesh.merge_vertices()
        v = np.asarray(mesh.vertices)
        mesh = trimesh.Trimesh(np.column_stack([v[:, 0], -v[:, 2], v[:, 1]]).astype(np.float32), mesh.faces,
                               process=False)
        assert mesh.is_watertight, name
        (out / name).write_bytes(mesh.export(file_type="ply", encoding="binary"))
        print(f"{name}: {len(mesh.vertices)} vertices, {len(mesh.faces)} triangles, extent {np.round(mesh.extents, 4)} m")


if __name__ == "__main__":
    main(sys.argv[1])
