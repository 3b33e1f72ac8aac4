"""Procedural meshes, hidden objects, placement, surface sampling and loading a user's mesh file."""
import numpy as np
import pytest
import trimesh

from securegs_warp.data import DataError
from securegs_warp.data.meshes import (
    HIDDEN_OBJECTS, Material, box, cylinder, lathe, load_mesh, merge, place, sphere, torus,
)

GREY = Material()


def face_normals(mesh):
    a, b, c = (mesh.vertices[mesh.faces[:, k]].astype(np.float64) for k in range(3))
    return np.cross(b - a, c - a)


@pytest.mark.parametrize("mesh, centre", [
    (box((1.0, 2.0, 0.5), GREY, center=(1, 2, 3)), (1, 2, 3)),
    (sphere(0.7, GREY, center=(0, 1, 0)), (0, 1, 0)),
    (cylinder(0.4, 1.0, GREY, base=(0, 0, 1)), (0, 0, 1.5)),
    (cylinder(0.4, 1.0, GREY, top_radius=0.0), (0, 0, 0.3)),
])
def test_convex_primitives_wind_outward(mesh, centre):
    normals = face_normals(mesh)
    outward = mesh.vertices[mesh.faces].mean(axis=1) - np.asarray(centre)
    assert np.all(np.linalg.norm(normals, axis=1) > 1e-9)  # no degenerate triangles
    assert np.all(np.einsum("ij,ij->i", normals, outward) > 0)
    # Shading normals agree with the winding.
    vertex_normals = mesh.normals[mesh.faces].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", normals, vertex_normals) > 0)
    np.testing.assert_allclose(np.linalg.norm(mesh.normals, axis=1), 1.0, atol=1e-5)


def test_sphere_and_lathe_geometry():
    mesh = sphere(0.7, GREY, center=(0, 1, 0))
    np.testing.assert_allclose(np.linalg.norm(mesh.vertices - [0, 1, 0], axis=1), 0.7, atol=1e-6)
    np.testing.assert_allclose(mesh.normals, (mesh.vertices - [0, 1, 0]) / 0.7, atol=1e-5)
    # A crease sharper than 40 degrees keeps separate normals: the cylinder's side normals are horizontal.
    can = cylinder(0.4, 1.0, GREY)
    side = np.abs(np.linalg.norm(can.vertices[:, :2], axis=1) - 0.4) < 1e-6
    assert np.any(np.abs(can.normals[side, 2]) > 0.99) and np.any(np.abs(can.normals[side, 2]) < 1e-6)
    # A cone's tip keeps its slanted normals; only a smooth pole gets the axial one.
    cone = cylinder(0.45, 1.0, GREY, top_radius=0.0)
    tip = np.abs(cone.vertices[:, 2] - 1.0) < 1e-6
    np.testing.assert_allclose(cone.normals[tip, 2], 0.45 / np.hypot(0.45, 1.0), atol=1e-6)
    # A gentle turn is smoothed: both segments share the averaged normal at the joint.
    bend = lathe([(0.5, 0.0), (0.5, 1.0), (0.4, 2.0)], GREY, segments=8)
    joint = np.abs(bend.vertices[:, 2] - 1.0) < 1e-6
    assert joint.sum() == 16 and np.unique(np.round(bend.normals[joint], 5), axis=0).shape[0] == 8


def test_partial_torus_and_merge():
    handle = torus(1.0, 0.1, GREY, arc_degrees=180.0)
    assert handle.vertices[:, 0].min() > -0.11 and handle.vertices[:, 0].max() == pytest.approx(1.1, abs=1e-6)
    a, b = box((1, 1, 1), Material("checker")), sphere(1.0, Material("noise"))
    merged = merge([a, b])
    assert len(merged.vertices) == len(a.vertices) + len(b.vertices)
    assert [m.texture for m in merged.materials] == ["checker", "noise"]
    np.testing.assert_array_equal(merged.face_material, [0] * len(a.faces) + [1] * len(b.faces))
    np.testing.assert_array_equal(merged.vertices[merged.faces[len(a.faces):]], b.vertices[b.faces])


def test_surface_samples_are_uniform_on_the_surface():
    mesh = box((2.0, 1.0, 1.0), GREY)
    points = mesh.sample_surface(20000, np.random.default_rng(0))
    on_face = np.isclose(np.abs(points), [1.0, 0.5, 0.5], atol=1e-6)
    assert np.all(on_face.any(axis=1)) and np.all(np.abs(points) <= [1.0 + 1e-6, 0.5 + 1e-6, 0.5 + 1e-6])
    # Areas: the two x faces are 1 each, the four others 2 each, total 10.
    np.testing.assert_allclose(on_face.mean(axis=0), [0.2, 0.4, 0.4], atol=0.02)


@pytest.mark.parametrize("name", sorted(HIDDEN_OBJECTS))
def test_hidden_objects_are_textured_composites_standing_on_the_origin(name):
    mesh = HIDDEN_OBJECTS[name]()
    low, high = mesh.bounds
    assert low[2] == pytest.approx(0.0, abs=1e-6) and 0.8 < high[2] <= 1.05
    assert len(mesh.materials) >= 2 or mesh.materials[0].texture != "solid"
    placed = place(mesh, (1.0, 2.0, 3.0), 0.5, yaw_degrees=90.0)
    low, high = placed.bounds
    assert (high - low).max() == pytest.approx(0.5, abs=1e-6)
    np.testing.assert_allclose([(low[0] + high[0]) / 2, (low[1] + high[1]) / 2, low[2]], [1, 2, 3], atol=1e-6)
    np.testing.assert_array_equal(placed.uvw, mesh.uvw)  # textures travel with the object


def test_load_obj_and_off(tmp_path):
    cube = trimesh.creation.box((2.0, 4.0, 8.0))
    for suffix in (".obj", ".off"):
        cube.export(tmp_path / f"cube{suffix}")
        mesh = load_mesh(tmp_path / f"cube{suffix}")
        low, high = mesh.bounds
        np.testing.assert_allclose(low, [-0.125, -0.25, 0.0], atol=1e-6)
        np.testing.assert_allclose(high, [0.125, 0.25, 1.0], atol=1e-6)
        assert len(mesh.faces) == 12 and mesh.materials[0].texture == "noise"
        np.testing.assert_array_equal(mesh.uvw, mesh.vertices)


def test_load_ply_keeps_vertex_colours(tmp_path):
    cube = trimesh.creation.box((1.0, 1.0, 1.0))
    colours = np.random.default_rng(0).integers(0, 256, (len(cube.vertices), 4), dtype=np.uint8)
    colours[:, 3] = 255
    cube.visual.vertex_colors = colours
    cube.export(tmp_path / "cube.ply")
    mesh = load_mesh(tmp_path / "cube.ply")
    assert mesh.materials[0].texture == "vertex"
    order = np.lexsort(cube.vertices.T)
    loaded_order = np.lexsort(mesh.vertices.T)
    np.testing.assert_allclose(mesh.colors[loaded_order], colours[order, :3] / 255.0, atol=1e-6)
    assert load_mesh(tmp_path / "cube.ply", Material("checker")).materials[0].texture == "checker"


TETRAHEDRON_WITH_UVS = """v 0 0 0
v 1 0 0
v 0 1 0
v 0 0 1
vt 0 0
vt 1 0
vt 0 1
usemtl Material
f 1/1 2/2 3/3
f 1/1 2/2 4/3
f 1/1 3/2 4/3
f 2/1 3/2 4/3
"""


def test_texture_coordinates_without_an_image(tmp_path):
    # What Blender exports by default: UVs and a material with a diffuse colour but no image. trimesh
    # calls it textured; it is coloured by Kd. Without the MTL file (missing, or never written) the file
    # holds no colour: the default noise material, not trimesh's grey placeholder.
    (tmp_path / "kd.mtl").write_text("newmtl Material\nKd 0.8 0.1 0.1\n")
    (tmp_path / "kd.obj").write_text("mtllib kd.mtl\n" + TETRAHEDRON_WITH_UVS)
    mesh = load_mesh(tmp_path / "kd.obj")
    assert mesh.materials[0].texture == "vertex"
    np.testing.assert_allclose(mesh.colors, np.tile([0.8, 0.1, 0.1], (len(mesh.vertices), 1)), atol=1 / 255)
    for text in ("mtllib missing.mtl\n", ""):
        (tmp_path / "bare.obj").write_text(text + TETRAHEDRON_WITH_UVS)
        assert load_mesh(tmp_path / "bare.obj").materials[0].texture == "noise"


def test_load_errors(tmp_path):
    with pytest.raises(DataError, match="absent.obj: mesh file not found"):
        load_mesh(tmp_path / "absent.obj")
    (tmp_path / "points.xyz").write_text("0 0 0\n")
    with pytest.raises(DataError, match=r"points.xyz: unsupported mesh type '.xyz'"):
        load_mesh(tmp_path / "points.xyz")
    (tmp_path / "junk.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1000\n")
    with pytest.raises(DataError, match="junk.ply: cannot read mesh"):
        load_mesh(tmp_path / "junk.ply")
    (tmp_path / "lines.obj").write_text("v 0 0 0\nv 1 0 0\nl 1 2\n")
    with pytest.raises(DataError, match="lines.obj: the file holds no triangles"):
        load_mesh(tmp_path / "lines.obj")
    for name, vertices in (("collinear", "v 0 0 0\nv 1 0 0\nv 2 0 0\n"), ("collapsed", "v 1 1 1\n" * 3)):
        (tmp_path / f"{name}.obj").write_text(vertices + "f 1 2 3\n")
        with pytest.raises(DataError, match=f"{name}.obj: the mesh's triangles have no area"):
            load_mesh(tmp_path / f"{name}.obj")


def test_unknown_texture():
    with pytest.raises(ValueError, match="unknown texture 'plaid'"):
        Material("plaid")
