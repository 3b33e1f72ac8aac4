"""Textured triangle meshes: primitives, the built-in hidden objects, and loading a user's mesh.

A :class:`TriMesh` carries, per vertex, a position, a shading normal, a solid-texture coordinate
``uvw`` and a colour, and per face a material index into its own list of :class:`Material`.
``uvw`` starts as the vertex's position in the primitive's own frame and is left alone by
:meth:`TriMesh.transformed`, so a texture stays glued to its object wherever it is placed.
All objects are z-up.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..kernels.raycast import TEXTURES
from .errors import DataError

MESH_SUFFIXES = (".obj", ".ply", ".off", ".stl", ".glb")
UP_AXES = ("z", "y")  # a mesh file's up axis (load_mesh)


@dataclass(frozen=True)
class Material:
    """A procedural texture (kinds and field meanings: ``securegs_warp.kernels.raycast.TEXTURES``).

    scale is in features per unit of the object's own frame; axis and origin orient stripes,
    gradients and rings; seed picks the noise field.
    """

    texture: str = "solid"
    color_a: tuple[float, float, float] = (0.8, 0.8, 0.8)
    color_b: tuple[float, float, float] = (0.2, 0.2, 0.2)
    scale: float = 1.0
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    seed: int = 0

    def __post_init__(self):
        if self.texture not in TEXTURES:
            raise ValueError(f"unknown texture {self.texture!r}; known: {sorted(TEXTURES)}")


@dataclass
class TriMesh:
    """vertices, normals, uvw, colors: (V, 3) float32; faces: (F, 3) int32 counter-clockwise seen
    from outside; face_material: (F,) int32 indices into materials."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    uvw: np.ndarray
    colors: np.ndarray
    face_material: np.ndarray
    materials: list[Material] = field(default_factory=list)

    def __post_init__(self):
        for name in ("vertices", "normals", "uvw", "colors"):
            setattr(self, name, np.asarray(getattr(self, name), dtype=np.float32).reshape(-1, 3))
        self.faces = np.asarray(self.faces, dtype=np.int32).reshape(-1, 3)
        self.face_material = np.asarray(self.face_material, dtype=np.int32).reshape(-1)

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) min and max corner."""
        return np.stack([self.vertices.min(0), self.vertices.max(0)])

    def transformed(self, rotation=None, scale: float = 1.0, translation=(0.0, 0.0, 0.0)) -> TriMesh:
        """Copy moved by x -> scale * rotation @ x + translation (rotation (3, 3), default identity)."""
        rotation = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
        vertices = scale * self.vertices.astype(np.float64) @ rotation.T + np.asarray(translation, dtype=np.float64)
        return replace(self, vertices=vertices, normals=self.normals.astype(np.float64) @ rotation.T)

    def face_areas(self) -> np.ndarray:
        """(F,) triangle areas."""
        a, b, c = (self.vertices[self.faces[:, k]].astype(np.float64) for k in range(3))
        return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)

    def sample_surface(self, count: int, rng: np.random.Generator) -> np.ndarray:
        """(count, 3) float32 points uniformly distributed over the surface area."""
        areas = self.face_areas()
        chosen = rng.choice(len(areas), size=count, p=areas / areas.sum())
        r1, r2 = rng.random((2, count, 1))
        root = np.sqrt(r1)  # the square root makes the density uniform over each triangle
        a, b, c = (self.vertices[self.faces[chosen, k]].astype(np.float64) for k in range(3))
        return ((1.0 - root) * a + root * (1.0 - r2) * b + root * r2 * c).astype(np.float32)


def merge(meshes: list[TriMesh]) -> TriMesh:
    """One mesh holding all of `meshes`, faces in the given order."""
    vertex_offsets = np.cumsum([0] + [len(m.vertices) for m in meshes])
    material_offsets = np.cumsum([0] + [len(m.materials) for m in meshes])
    return TriMesh(
        vertices=np.concatenate([m.vertices for m in meshes]),
        faces=np.concatenate([m.faces + o for m, o in zip(meshes, vertex_offsets)]),
        normals=np.concatenate([m.normals for m in meshes]),
        uvw=np.concatenate([m.uvw for m in meshes]),
        colors=np.concatenate([m.colors for m in meshes]),
        face_material=np.concatenate([m.face_material + o for m, o in zip(meshes, material_offsets)]),
        materials=[material for m in meshes for material in m.materials],
    )


def _single_material(vertices, faces, normals, material: Material) -> TriMesh:
    """A primitive's mesh: uvw = its own vertex positions, one material, grey vertex colours."""
    vertices = np.asarray(vertices, dtype=np.float32)
    return TriMesh(
        vertices=vertices,
        faces=faces,
        normals=normals,
        uvw=vertices.copy(),
        colors=np.full_like(vertices, 0.5),
        face_material=np.zeros(len(faces), dtype=np.int32),
        materials=[material],
    )


def rotation_z(degrees: float) -> np.ndarray:
    """(3, 3) rotation about +z."""
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_x(degrees: float) -> np.ndarray:
    """(3, 3) rotation about +x."""
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def box(size, material: Material, center=(0.0, 0.0, 0.0)) -> TriMesh:
    """Axis-aligned box of `size` (3,) around `center`; 4 vertices per side so edges stay sharp."""
    half = 0.5 * np.asarray(size, dtype=np.float64)
    vertices, normals, faces = [], [], []
    for axis in range(3):
        u, v = (axis + 1) % 3, (axis + 2) % 3  # e_u x e_v = e_axis
        for sign in (1.0, -1.0):
            # Corners counter-clockwise seen from outside: swap the winding on the negative side.
            corners = [(-1, -1), (1, -1), (1, 1), (-1, 1)] if sign > 0 else [(-1, -1), (-1, 1), (1, 1), (1, -1)]
            base = len(vertices)
            for cu, cv in corners:
                point = np.zeros(3)
                point[axis], point[u], point[v] = sign * half[axis], cu * half[u], cv * half[v]
                vertices.append(point + np.asarray(center, dtype=np.float64))
                normals.append(np.eye(3)[axis] * sign)
            faces += [(base, base + 1, base + 2), (base, base + 2, base + 3)]
    return _single_material(vertices, faces, normals, material)


def lathe(profile, material: Material, segments: int = 32, crease_degrees: float = 40.0) -> TriMesh:
    """Surface of revolution about +z of a polyline `profile` (K, 2) of (radius, z) points.

    Walk the profile so that the outside is on its right (e.g. outward along the bottom, up the
    side, inward across the top): faces then wind counter-clockwise from outside. Normals are
    smooth across a profile vertex unless the profile turns by more than crease_degrees there.
    A point with radius 0 closes the surface on the axis.
    """
    profile = np.asarray(profile, dtype=np.float64)
    tangents = np.diff(profile, axis=0)
    seg_normals = np.stack([tangents[:, 1], -tangents[:, 0]], axis=1)  # (dr, dz) turned clockwise
    seg_normals /= np.linalg.norm(seg_normals, axis=1, keepdims=True)
    cos_crease = math.cos(math.radians(crease_degrees))

    def end_normal(segment: int, neighbour: int, radius: float) -> np.ndarray:
        own = seg_normals[segment]
        if 0 <= neighbour < len(seg_normals) and own @ seg_normals[neighbour] > cos_crease:
            blended = own + seg_normals[neighbour]
            return blended / np.linalg.norm(blended)
        # On the axis the neighbour is the segment's mirror image (-nr, nz): the same crease rule
        # against it gives a pole the axial normal (their blend) and leaves a cone's tip sharp.
        if radius == 0.0 and own[1] ** 2 - own[0] ** 2 > cos_crease:
            return np.array([0.0, math.copysign(1.0, own[1])])
        return own

    phi = 2.0 * np.pi * np.arange(segments) / segments
    cos_phi, sin_phi = np.cos(phi), np.sin(phi)
    columns = np.arange(segments)
    vertices, normals, faces = [], [], []
    for s in range(len(tangents)):
        ring_start = len(vertices)  # rings appended so far; this segment adds two
        for end, neighbour in ((s, s - 1), (s + 1, s + 1)):
            (r, z), (nr, nz) = profile[end], end_normal(s, neighbour, profile[end, 0])
            vertices.append(np.stack([r * cos_phi, r * sin_phi, np.full(segments, z)], axis=1))
            normals.append(np.stack([nr * cos_phi, nr * sin_phi, np.full(segments, nz)], axis=1))
        lower = ring_start * segments + columns
        upper = lower + segments
        lower_next = ring_start * segments + (columns + 1) % segments
        upper_next = lower_next + segments
        # Skip the triangles that collapse to a line where a ring has radius 0.
        if profile[s, 0] > 0.0:
            faces.append(np.stack([lower, lower_next, upper_next], axis=1))
        if profile[s + 1, 0] > 0.0:
            faces.append(np.stack([lower, upper_next, upper], axis=1))
    return _single_material(np.concatenate(vertices), np.concatenate(faces), np.concatenate(normals), material)


def sphere(radius: float, material: Material, center=(0.0, 0.0, 0.0), segments: int = 32) -> TriMesh:
    """Sphere as a lathe of a half circle, from the south pole up."""
    theta = np.linspace(-0.5 * np.pi, 0.5 * np.pi, segments // 2 + 1)
    profile = np.stack([radius * np.cos(theta), radius * np.sin(theta)], axis=1)
    profile[[0, -1], 0] = 0.0  # exactly on the axis, so the poles close
    return lathe(profile, material, segments).transformed(translation=center)


def cylinder(radius: float, height: float, material: Material, base=(0.0, 0.0, 0.0), top_radius=None) -> TriMesh:
    """Closed cylinder (or cone frustum when top_radius differs) standing on `base`."""
    top = radius if top_radius is None else top_radius
    profile = [(0.0, 0.0), (radius, 0.0), (top, height)] + ([(0.0, height)] if top > 0.0 else [])
    return lathe(profile, material).transformed(translation=base)


def torus(major: float, minor: float, material: Material, arc_degrees: float = 360.0, segments=32, sides=12) -> TriMesh:
    """Torus around +z in the xy-plane; with arc_degrees < 360 only the part within ±arc/2 of +x
    (a handle; its open ends are meant to sink into another surface)."""
    closed = arc_degrees >= 360.0
    arc = math.radians(min(arc_degrees, 360.0))
    rings = segments if closed else segments + 1
    u = (np.arange(rings) / segments - 0.5) * arc
    v = 2.0 * np.pi * np.arange(sides) / sides
    uu, vv = np.meshgrid(u, v, indexing="ij")
    direction = np.stack([np.cos(vv) * np.cos(uu), np.cos(vv) * np.sin(uu), np.sin(vv)], axis=-1)
    centre = np.stack([major * np.cos(uu), major * np.sin(uu), np.zeros_like(uu)], axis=-1)
    vertices = (centre + minor * direction).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(segments), np.arange(sides), indexing="ij")
    a = i * sides + j
    b = ((i + 1) % rings) * sides + j
    c = ((i + 1) % rings) * sides + (j + 1) % sides
    d = i * sides + (j + 1) % sides
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return _single_material(vertices, faces, direction.reshape(-1, 3), material)


def normalized(mesh: TriMesh) -> TriMesh:
    """Copy with its bottom centre (centre of the bounding box's lower face) at the origin and its
    largest bounding-box side 1."""
    low, high = mesh.bounds
    bottom_centre = np.array([(low[0] + high[0]) / 2, (low[1] + high[1]) / 2, low[2]])
    extent = float((high - low).max())
    if not extent > 0.0:
        raise DataError("mesh is degenerate: all its vertices coincide")
    return mesh.transformed(scale=1.0 / extent, translation=-bottom_centre / extent)


def place(mesh: TriMesh, position, size: float, yaw_degrees: float = 0.0) -> TriMesh:
    """Copy normalised, scaled so that its largest side is `size`, turned by yaw about z, with its
    bottom centre at `position`."""
    return normalized(mesh).transformed(rotation_z(yaw_degrees), size, position)


# The hidden objects: composite meshes with their own textures, bottom centre at the origin.


def mug() -> TriMesh:
    """A striped mug with a handle (about 1 tall)."""
    body = lathe(
        [(0.0, 0.0), (0.40, 0.0), (0.42, 0.95), (0.36, 0.95), (0.34, 0.10), (0.0, 0.10)],
        Material("stripes", (0.85, 0.12, 0.10), (0.96, 0.92, 0.82), scale=5.0),
    )
    # The handle's arc ends just inside the outer wall, so its open ends are buried in the body.
    handle_centre_x, handle_radius = 0.41, 0.25
    arc = 2.0 * math.degrees(math.acos((0.38 - handle_centre_x) / handle_radius))
    handle = torus(handle_radius, 0.06, Material("solid", (0.55, 0.05, 0.05)), arc_degrees=arc)
    handle = handle.transformed(rotation_x(90.0), translation=(handle_centre_x, 0.0, 0.5))
    return merge([body, handle])


def lamp() -> TriMesh:
    """A desk lamp: metal base and pole, a bulb, and an open checkered shade (about 1 tall)."""
    metal = Material("gradient", (0.25, 0.25, 0.3), (0.75, 0.72, 0.6), scale=1.2, origin=(0.0, 0.0, 0.0))
    base = lathe([(0.0, 0.0), (0.35, 0.0), (0.33, 0.06), (0.0, 0.08)], metal)
    pole = cylinder(0.03, 0.66, metal, base=(0.0, 0.0, 0.06))
    bulb = sphere(0.09, Material("solid", (1.0, 0.95, 0.7)), center=(0.0, 0.0, 0.72))
    shade = lathe([(0.40, 0.55), (0.20, 0.98)], Material("checker", (0.1, 0.45, 0.35), (0.95, 0.9, 0.75), scale=6.0))
    return merge([base, pole, bulb, shade])


def pawn() -> TriMesh:
    """A wooden chess pawn (about 1 tall)."""
    wood = Material("rings", (0.45, 0.25, 0.1), (0.85, 0.62, 0.35), scale=9.0, seed=7)
    body = lathe(
        [(0.0, 0.0), (0.32, 0.0), (0.32, 0.08), (0.25, 0.13), (0.17, 0.2), (0.11, 0.45), (0.2, 0.5), (0.2, 0.54),
         (0.09, 0.57), (0.0, 0.58)],
        wood,
    )
    return merge([body, sphere(0.18, wood, center=(0.0, 0.0, 0.72))])


def robot() -> TriMesh:
    """A toy robot: box legs, checkered body, head with red eyes, arms and an antenna (about 1 tall)."""
    dark = Material("solid", (0.2, 0.2, 0.24))
    orange = Material("solid", (0.95, 0.5, 0.1))
    parts = [
        box((0.12, 0.14, 0.35), dark, center=(-0.1, 0.0, 0.175)),
        box((0.12, 0.14, 0.35), dark, center=(0.1, 0.0, 0.175)),
        box((0.42, 0.28, 0.36), Material("checker", (0.15, 0.3, 0.8), (0.9, 0.9, 0.95), scale=8.0),
            center=(0.0, 0.0, 0.53)),
        box((0.26, 0.22, 0.2), Material("gradient", (0.5, 0.5, 0.55), (0.9, 0.9, 0.95), scale=5.0, origin=(0, 0, 0.72)),
            center=(0.0, 0.0, 0.82)),
        sphere(0.035, Material("solid", (1.0, 0.1, 0.1)), center=(-0.06, -0.11, 0.84), segments=12),
        sphere(0.035, Material("solid", (1.0, 0.1, 0.1)), center=(0.06, -0.11, 0.84), segments=12),
        cylinder(0.05, 0.34, orange, base=(-0.27, 0.0, 0.36)),
        cylinder(0.05, 0.34, orange, base=(0.27, 0.0, 0.36)),
        cylinder(0.012, 0.08, dark, base=(0.0, 0.0, 0.92)),
        sphere(0.03, orange, center=(0.0, 0.0, 1.0), segments=12),
    ]
    return merge(parts)


HIDDEN_OBJECTS = {"mug": mug, "lamp": lamp, "pawn": pawn, "robot": robot}


def check_up_axis(up: str) -> None:
    """DataError naming ``up`` unless it is one of UP_AXES."""
    if up not in UP_AXES:
        raise DataError(f"a mesh's up axis must be one of {', '.join(UP_AXES)}, not {up!r}")


def _file_colors(loaded) -> np.ndarray | None:
    """[V, 3] colours in [0, 1] from a loaded trimesh's own visuals, or None where the file holds
    none. trimesh calls any mesh with texture coordinates "textured", with or without an image: a
    material without an image (an OBJ's ``Kd`` alone, a glTF colour factor) colours every vertex with
    its main colour; the 2×2 placeholder image trimesh makes for a missing or absent MTL file is no
    colour of the file's."""
    visual = loaded.visual
    if visual.kind in ("vertex", "face"):
        return np.asarray(visual.vertex_colors, dtype=np.float32)[:, :3] / 255.0
    if visual.kind != "texture":
        return None
    material = visual.material
    image = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
    if image is not None and image.size[0] * image.size[1] <= 4 and len(image.getcolors()) == 1:
        return None
    if image is not None:
        try:
            return np.asarray(visual.to_color().vertex_colors, dtype=np.float32)[:, :3] / 255.0
        except (TypeError, ValueError, IndexError):
            pass  # trimesh cannot sample this texture: the material's main colour stands in
    main = np.asarray(material.main_color, dtype=np.float32)[:3] / 255.0
    return np.tile(main, (len(loaded.vertices), 1))


def load_mesh(path, material: Material | None = None, up: str = "z") -> TriMesh:
    """Read a user's mesh file (OBJ, PLY, OFF, STL or GLB, through trimesh), normalised (see
    :func:`normalized`). Vertex or face colours, or a texture baked to vertex colours, are kept
    when the file has them and no `material` is given; otherwise `material` (default: grey noise)
    textures it. up: the file's up axis (UP_AXES), turned onto the scenes' +z: none of these formats
    records it, and glTF and many OBJ exporters (and scanned meshes such as the Stanford bunny)
    use +y. Raises DataError naming the file when it is missing, of an unsupported type,
    unreadable, or holds no triangles or only triangles without area, or naming an unknown up axis.
    """
    import trimesh

    check_up_axis(up)
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: mesh file not found")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise DataError(f"{path}: unsupported mesh type {path.suffix!r}; supported: {', '.join(MESH_SUFFIXES)}")
    try:
        loaded = trimesh.load(path, force="mesh")
    except Exception as error:  # trimesh's parsers raise many types for malformed files
        raise DataError(f"{path}: cannot read mesh ({type(error).__name__}: {error})") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise DataError(f"{path}: the file holds no triangles")
    # The hidden views are ray-cast and its surface is sampled by area: a mesh of zero area (all
    # triangles collinear or collapsed) shows nothing and has no surface to sample.
    if not float(loaded.area) > 0.0:
        raise DataError(f"{path}: the mesh's triangles have no area (every one is collinear or collapsed)")

    colors = _file_colors(loaded) if material is None else None
    if colors is None:
        material = material or Material("noise", (0.35, 0.35, 0.38), (0.8, 0.78, 0.72), scale=6.0, seed=3)
    vertices = np.asarray(loaded.vertices, dtype=np.float32)
    mesh = TriMesh(
        vertices=vertices,
        faces=np.asarray(loaded.faces),
        normals=np.asarray(loaded.vertex_normals),
        uvw=vertices,
        colors=np.full_like(vertices, 0.5) if colors is None else colors,
        face_material=np.zeros(len(loaded.faces), dtype=np.int32),
        materials=[Material("vertex")] if colors is not None else [material],
    )
    normalized_mesh = normalized(mesh if up == "z" else mesh.transformed(rotation_x(90.0)))  # +y onto +z
    # Texture coordinates in the normalised frame, so a noise material's scale means the same for
    # every file whatever its units.
    normalized_mesh.uvw = normalized_mesh.vertices.copy()
    return normalized_mesh
