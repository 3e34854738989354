"""The viewer's binary glTF frames (rtfem.viewer.gltf), read back by another implementation
(trimesh's glTF loader) and checked against another implementation of the vertex normals
(trimesh's angle-weighted ones) and against the glTF 2.0 container rules. The Khronos glTF
validator (npm gltf-validator 2.0) found no error, warning or info in a liver frame and the speck
when this encoder was written."""

from __future__ import annotations

import io
import json
import struct

import numpy as np
import pytest

import rtfem as rt
from rtfem.viewer.gltf import SurfaceGlb, colormap, srgb_to_linear

trimesh = pytest.importorskip("trimesh", reason="trimesh reads the frames back (the test extra)")


@pytest.fixture(scope="module")
def surface():
    tri = rt.meshes.liver(level=3)
    V = np.asarray(tri.vertices) + 1e-3 * np.random.default_rng(1).normal(size=(tri.n_vertices, 3))
    return V, np.asarray(tri.triangles)


def _chunks(b: bytes):
    magic, version, length = struct.unpack("<III", b[:12])
    jl, jt = struct.unpack("<II", b[12:20])
    bl, bt = struct.unpack("<II", b[20 + jl:28 + jl])
    return (magic, version, length, jt, bt), json.loads(b[20:20 + jl]), b[28 + jl:28 + jl + bl]


def test_a_frame_reads_back_as_the_surface_with_its_colours_and_trimesh_normals(surface):
    V, F = surface
    colors = colormap(np.linalg.norm(V - V.mean(axis=0), axis=1), 0.08)
    glb = SurfaceGlb(F, len(V))
    data = glb(V, colors)
    scene = trimesh.load(io.BytesIO(data), file_type="glb", process=False)
    (mesh,) = scene.geometry.values()
    assert np.array_equal(mesh.faces, F)
    assert np.abs(mesh.vertices - V).max() < 1e-7 * np.abs(V).max()  # float32
    assert np.array_equal(mesh.visual.vertex_attributes["color"], srgb_to_linear(colors))
    want = trimesh.Trimesh(V, F, process=False).vertex_normals  # angle-weighted (Thuerrner & Wuethrich)
    assert np.abs(glb.normals(V) - want).max() < 1e-12
    assert np.abs(mesh.vertex_normals - want).max() < 1e-6  # as read back (float32)
    material = scene.geometry[list(scene.geometry)[0]].visual.material
    assert material.metallicFactor == 0.0 and material.roughnessFactor == pytest.approx(0.65)


def test_the_container_follows_the_gltf_binary_layout(surface):
    V, F = surface
    data = SurfaceGlb(F, len(V))(V, colormap(np.zeros(len(V)), 1.0))
    (magic, version, length, jt, bt), doc, body = _chunks(data)
    assert (magic, version, length, jt, bt) == (0x46546C67, 2, len(data), 0x4E4F534A, 0x004E4942)
    assert (20 + struct.unpack("<I", data[12:16])[0]) % 4 == 0 and len(body) % 4 == 0
    assert doc["buffers"][0]["byteLength"] == len(body)
    views = doc["bufferViews"]
    assert all(v["byteOffset"] % 4 == 0 for v in views)
    assert views[-1]["byteOffset"] + views[-1]["byteLength"] == len(body)
    position = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    # POSITION's bounds are required, and must be those of the float32 values stored
    V32 = V.astype(np.float32)
    assert position["min"] == V32.min(axis=0).tolist() and position["max"] == V32.max(axis=0).tolist()
    stored = np.frombuffer(body, np.float32, 3 * len(V), views[position["bufferView"]]["byteOffset"])
    assert np.array_equal(stored.reshape(-1, 3), V32)


def test_degenerate_triangles_add_no_normal_and_colours_convert_as_srgb():
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [2, 0, 0]])
    F = np.array([[0, 1, 2], [0, 3, 1], [1, 1, 4]])  # the last one has no area
    n = SurfaceGlb(F, 5).normals(V)
    want = trimesh.Trimesh(V, F, process=False).vertex_normals
    assert np.abs(n - want).max() < 1e-12
    assert np.array_equal(n[4], np.zeros(3))  # only on the degenerate face
    c = np.arange(256)
    rgba = np.stack([c, c[::-1], c, np.full(256, 7)], axis=1).astype(np.uint8)
    x = c / 255.0
    lin = np.round(np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4) * 255)
    out = srgb_to_linear(rgba)
    assert np.array_equal(out[:, 0], lin) and np.array_equal(out[:, 1], lin[::-1]) and (out[:, 3] == 7).all()


def test_bad_frames_are_refused():
    glb = SurfaceGlb(np.array([[0, 1, 2]]), 3)
    with pytest.raises(rt.ModelError, match=r"vertices must be \(3, 3\)"):
        glb(np.zeros((4, 3)), colormap(np.zeros(4), 1.0))
    with pytest.raises(rt.ModelError, match="colors"):
        glb(np.eye(3), np.zeros((3, 3), np.uint8))
    with pytest.raises(rt.ModelError, match="indices into 3 vertices"):
        SurfaceGlb(np.array([[0, 1, 3]]), 3)
