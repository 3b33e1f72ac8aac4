"""Built-in synthetic scenes, rendered by Warp ray casting, with objects or scenes to hide in them.

A scene is a procedural textured mesh (:mod:`.meshes`) lit by a directional light plus ambient,
with hard shadows. Cameras look at the centre from a band of the upper hemisphere (training) and
from a ring inside that band (test). The sparse point cloud stands in for COLMAP's: points seen in
the training images, with position noise and the colour the images show there.

The hidden payload is rendered from exactly the same cameras:

- a hidden object (a built-in one or a user's mesh), placed so that it sinks partly into a scene
  object, as in SecureGS, where hidden objects overlap the original scene's point cloud; at
  "object" level it is rendered alone over a background colour (with alpha), at "scene" level the
  scene and object meshes are ray cast together;
- or a whole second scene.
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import warp as wp

from ..kernels import raycast
from .cameras import Camera, SceneData, cameras_looking_at, hemisphere_positions, intrinsics_from_fov, orbit_positions
from .errors import DataError
from .meshes import HIDDEN_OBJECTS, MESH_SUFFIXES, Material, TriMesh, box, check_up_axis, cylinder, lathe, load_mesh
from .meshes import merge, place
from .meshes import rotation_z, sphere, torus

# Independent random streams of one seed, so that e.g. choosing another hidden object leaves the
# public views and points unchanged. (Noise textures take their seeds from the seed directly.)
_STREAM_CAMERAS, _STREAM_POINTS, _STREAM_HIDDEN_POINTS = range(3)

# Camera rig around the scene's centre: training views on a hemisphere band, test views on a ring
# at an elevation inside the band (interpolation between training views, not extrapolation).
_TARGET = (0.0, 0.0, 0.5)
_RADIUS = 4.0
_TRAIN_ELEVATIONS = (12.0, 50.0)
_TEST_ELEVATION = 30.0


@dataclass(frozen=True)
class Lighting:
    """Directional light toward unit vector `direction`, an ambient floor, optional hard shadows."""

    direction: tuple[float, float, float]
    ambient: float = 0.35
    shadows: bool = True


@dataclass
class Layout:
    """A procedural scene: mesh, the boxes (2, 3) hidden objects may rest on, sky colour, light."""

    mesh: TriMesh
    hosts: list[np.ndarray]
    sky: tuple[float, float, float]
    lighting: Lighting


def room(seed: int) -> Layout:
    """A walled room (10 x 10, walls 3 high) with a crate in the middle and shapes around it."""
    noise_seed = int(seed) * 16
    floor = box((10.4, 10.4, 0.2), Material("checker", (0.82, 0.74, 0.6), (0.45, 0.32, 0.22), scale=1.5), (0, 0, -0.1))
    walls = [
        box((10.4, 0.2, 3.0), Material("stripes", (0.25, 0.4, 0.7), (0.9, 0.9, 0.85), scale=1.2, axis=(1, 0, 0)),
            (0, 5.1, 1.5)),
        box((10.4, 0.2, 3.0), Material("noise", (0.75, 0.55, 0.45), (0.95, 0.85, 0.7), scale=1.5, seed=noise_seed),
            (0, -5.1, 1.5)),
        box((0.2, 10.4, 3.0),
            Material("gradient", (0.2, 0.5, 0.5), (0.85, 0.9, 0.8), scale=1 / 3.0, origin=(0, 0, -1.5)), (5.1, 0, 1.5)),
        box((0.2, 10.4, 3.0), Material("checker", (0.55, 0.65, 0.45), (0.85, 0.85, 0.8), scale=0.8), (-5.1, 0, 1.5)),
    ]
    crate_size = np.array([1.4, 1.0, 0.7])
    crate = box(crate_size, Material("rings", (0.5, 0.3, 0.12), (0.8, 0.6, 0.35), scale=6.0, axis=(0, 1, 0),
                                     origin=(0.3, 0, -0.9), seed=noise_seed + 1), (0, 0, 0.35))
    shapes = [
        sphere(0.5, Material("stripes", (0.95, 0.55, 0.1), (0.98, 0.9, 0.4), scale=3.0), (1.8, -1.1, 0.5)),
        cylinder(0.35, 1.3, Material("gradient", (0.6, 0.1, 0.3), (0.95, 0.75, 0.8), scale=1 / 1.3), (-1.7, 1.3, 0.0)),
        box((0.7, 0.7, 0.7), Material("checker", (0.2, 0.2, 0.25), (0.9, 0.9, 0.9), scale=4.0)).transformed(
            rotation_z(30.0), translation=(-1.6, -1.5, 0.35)),
        cylinder(0.45, 1.0, Material("noise", (0.15, 0.45, 0.2), (0.7, 0.85, 0.4), scale=3.0, seed=noise_seed + 2),
                 (1.5, 1.7, 0.0), top_radius=0.0),
        torus(0.35, 0.12, Material("solid", (0.3, 0.35, 0.75))).transformed(translation=(0.2, -2.3, 0.12)),
    ]
    crate_box = np.stack([[-0.7, -0.5, 0.0], [0.7, 0.5, 0.7]])
    return Layout(merge([floor, *walls, crate, *shapes]), [crate_box], (0.62, 0.75, 0.9), Lighting((-0.45, -0.3, 0.84)))


def garden(seed: int) -> Layout:
    """A lawn inside a square hedge, with a fountain, stone pillars, bushes and a bench."""
    noise_seed = int(seed) * 16 + 8
    stone = Material("noise", (0.45, 0.45, 0.45), (0.8, 0.78, 0.72), scale=4.0, seed=noise_seed)
    hedge = Material("noise", (0.05, 0.25, 0.05), (0.25, 0.5, 0.15), scale=3.0, seed=noise_seed + 1)
    bush = Material("noise", (0.1, 0.35, 0.1), (0.5, 0.7, 0.2), scale=4.0, seed=noise_seed + 2)
    parts = [
        box((12.4, 12.4, 0.2), Material("noise", (0.25, 0.5, 0.15), (0.5, 0.7, 0.25), scale=1.2, seed=noise_seed + 3),
            (0, 0, -0.1)),
        box((11.0, 0.6, 1.6), hedge, (0, 5.5, 0.8)),
        box((11.0, 0.6, 1.6), hedge, (0, -5.5, 0.8)),
        box((0.6, 11.0, 1.6), hedge, (5.5, 0, 0.8)),
        box((0.6, 11.0, 1.6), hedge, (-5.5, 0, 0.8)),
        lathe([(0.0, 0.0), (1.0, 0.0), (1.05, 0.45), (0.9, 0.45), (0.85, 0.3), (0.0, 0.3)], stone),
        cylinder(0.12, 0.9, stone, (0, 0, 0.3)),
        sphere(0.25, Material("solid", (0.35, 0.55, 0.85)), (0, 0, 1.2)),
        cylinder(0.25, 1.8, stone, (2.5, 2.0, 0.0)),
        cylinder(0.25, 1.8, stone, (-2.6, 2.1, 0.0)),
        cylinder(0.25, 1.8, stone, (0.0, -2.9, 0.0)),
        sphere(0.6, bush, (2.4, -1.8, 0.45)),
        sphere(0.5, bush, (-2.2, -1.6, 0.4)),
        box((1.6, 0.5, 0.45), Material("stripes", (0.55, 0.3, 0.15), (0.8, 0.55, 0.3), scale=6.0, axis=(1, 0, 0)),
            (-2.0, 0.2, 0.225)),
    ]
    basin_box = np.stack([[-1.0, -1.0, 0.0], [1.0, 1.0, 0.45]])
    return Layout(merge(parts), [basin_box], (0.55, 0.72, 0.95), Lighting((0.5, -0.35, 0.79)))


SCENES = {"room": room, "garden": garden}
SCENE_ALIASES = {"default": "room", "synthetic": "room"}


@dataclass
class Samples:
    """A camera's supersampled render, (H*s, W*s) per array: face id (-1: miss), distance along
    the ray (-1: miss), world hit point (0 on a miss), RGB and coverage."""

    face: np.ndarray
    distance: np.ndarray
    point: np.ndarray
    rgb: np.ndarray
    alpha: np.ndarray
    supersample: int

    def image(self) -> tuple[np.ndarray, np.ndarray]:
        """Box-filtered pixels: RGB (H, W, 3) and alpha (H, W, 1), both float32 in [0, 1]."""
        s = self.supersample
        hs, ws = self.alpha.shape

        def pool(x):
            return x.reshape(hs // s, s, ws // s, s, -1).mean(axis=(1, 3), dtype=np.float64).astype(np.float32)

        return pool(self.rgb), pool(self.alpha)

    def sample_hits(self, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Up to `count` distinct samples that hit the mesh: world points (k, 3) and their RGB (k, 3)."""
        hits = np.flatnonzero(self.face.reshape(-1) >= 0)
        chosen = rng.choice(hits, size=min(count, len(hits)), replace=False)
        return self.point.reshape(-1, 3)[chosen], self.rgb.reshape(-1, 3)[chosen]


class MeshRenderer:
    """A TriMesh uploaded to a Warp device (BVH built once), rendered from any camera."""

    def __init__(self, mesh: TriMesh, device=None):
        self.device = wp.get_device(device) if device is not None else wp.get_preferred_device()
        self.mesh_data = mesh
        upload = dict(device=self.device)
        self.indices = wp.array(mesh.faces.reshape(-1), dtype=wp.int32, **upload)
        self.mesh = wp.Mesh(points=wp.array(mesh.vertices, dtype=wp.vec3, **upload), indices=self.indices)
        self.normals = wp.array(mesh.normals, dtype=wp.vec3, **upload)
        self.uvw = wp.array(mesh.uvw, dtype=wp.vec3, **upload)
        self.colors = wp.array(mesh.colors, dtype=wp.vec3, **upload)
        self.face_material = wp.array(mesh.face_material, dtype=wp.int32, **upload)
        self.materials = wp.array([_warp_material(m) for m in mesh.materials], dtype=raycast.Material, **upload)
        low, high = mesh.bounds
        # Shadow rays start this far off the surface: far enough to miss the surface they leave,
        # close enough not to skip a blocker that touches it.
        self.shadow_bias = 1e-4 * float(np.max(high - low))

    def render(self, camera: Camera, lighting: Lighting, background, supersample: int) -> Samples:
        """Ray cast and shade `camera`'s view of the mesh; misses show `background` (3,)."""
        shape = (camera.height * supersample, camera.width * supersample)
        upload = dict(device=self.device)
        distance = wp.empty(shape, dtype=wp.float32, **upload)
        face = wp.empty(shape, dtype=wp.int32, **upload)
        bary = wp.empty(shape, dtype=wp.vec2, **upload)
        point = wp.zeros(shape, dtype=wp.vec3, **upload)
        normal = wp.empty(shape, dtype=wp.vec3, **upload)
        rgb = wp.empty(shape, dtype=wp.vec3, **upload)
        alpha = wp.empty(shape, dtype=wp.float32, **upload)
        K = camera.K
        wp.launch(
            raycast.cast_camera_rays,
            dim=shape,
            inputs=[
                self.mesh.id, self.indices, self.normals,
                wp.mat33(camera.viewmat[:3, :3].T.astype(np.float32)), wp.vec3(camera.center),
                wp.vec4(K[0, 0], K[1, 1], K[0, 2], K[1, 2]), supersample, 1.0e6,
            ],
            outputs=[distance, face, bary, point, normal],
            **upload,
        )
        light = np.asarray(lighting.direction, dtype=np.float32)
        wp.launch(
            raycast.shade_hits,
            dim=shape,
            inputs=[
                self.mesh.id, self.indices, self.uvw, self.colors, self.face_material, self.materials,
                face, bary, point, normal,
                wp.vec3(light / np.linalg.norm(light)), lighting.ambient, wp.vec3(*background),
                int(lighting.shadows), self.shadow_bias,
            ],
            outputs=[rgb, alpha],
            **upload,
        )
        # Copies: on the CPU, numpy() views the Warp buffers, which are freed with them.
        arrays = [array.numpy().copy() for array in (face, distance, point, rgb, alpha)]
        return Samples(*arrays, supersample)


def _warp_material(material: Material):
    """The kernel's struct for a Material (axis normalised so that scale keeps its meaning)."""
    out = raycast.Material()
    out.texture = raycast.TEXTURES[material.texture]
    out.color_a = wp.vec3(*material.color_a)
    out.color_b = wp.vec3(*material.color_b)
    out.scale = float(material.scale)
    axis = np.asarray(material.axis, dtype=np.float64)
    out.axis = wp.vec3(*(axis / np.linalg.norm(axis)))
    out.origin = wp.vec3(*material.origin)
    out.seed = int(material.seed)
    return out


def _scene_layout(name: str, seed: int) -> tuple[str, Layout]:
    """Canonical name and layout of a built-in scene; DataError for an unknown name."""
    canonical = SCENE_ALIASES.get(name, name)
    if canonical not in SCENES:
        raise DataError(f"unknown synthetic scene {name!r}; built-in scenes: {sorted(SCENES) + sorted(SCENE_ALIASES)}")
    return canonical, SCENES[canonical](seed)


@dataclass
class _Payload:
    """What is hidden: its kind, level and name, its own geometry (for hidden_bbox and
    hidden_points), and the mesh, background and lighting its views are rendered with."""

    kind: str
    level: str | None
    name: str
    geometry: TriMesh
    rendered: TriMesh
    background: tuple[float, float, float]
    lighting: Lighting


# Where a hidden object goes when no position is given: centred on the layout's first host box, its
# bottom this fraction of its height below the box's top. "stand": sunk by a tenth, most of its
# surface in empty space (the hard case for geometric security); "sink": half inside the host, as
# the paper's hidden objects overlap the cover's geometry; "float": in mid-air above the host.
PLACEMENTS = {"stand": 0.1, "sink": 0.5, "float": -0.5}


def _place_object(mesh: TriMesh, layout: Layout, position, size: float, yaw: float, placement: str) -> TriMesh:
    """The hidden object placed at `position` (its bottom centre), or on the layout's first host box
    as `placement` (PLACEMENTS) says."""
    if position is not None:
        return place(mesh, position, size, yaw)
    low, high = layout.hosts[0]
    placed = place(mesh, (0.5 * (low[0] + high[0]), 0.5 * (low[1] + high[1]), 0.0), size, yaw)
    return placed.transformed(translation=(0.0, 0.0, high[2] - PLACEMENTS[placement] * float(placed.bounds[1, 2])))


def _hidden_payload(hidden, level: str, scene_name: str, layout: Layout, lighting: Lighting, seed: int,
                    position, size: float, yaw: float, up: str, placement: str, background) -> _Payload:
    """Resolve make_synthetic_scene's `hidden` argument (see there) into a _Payload."""
    if isinstance(hidden, str) and (hidden == "scene" or SCENE_ALIASES.get(hidden, hidden) in SCENES):
        other = "garden" if scene_name == "room" else "room"
        name, hidden_layout = _scene_layout(other if hidden == "scene" else hidden, seed)
        hidden_lighting = replace(hidden_layout.lighting, shadows=lighting.shadows)
        return _Payload("scene", None, name, hidden_layout.mesh, hidden_layout.mesh, hidden_layout.sky, hidden_lighting)
    if isinstance(hidden, TriMesh):
        name, mesh = "mesh", hidden
    elif hidden in HIDDEN_OBJECTS:
        name, mesh = hidden, HIDDEN_OBJECTS[hidden]()
    elif Path(hidden).suffix.lower() in MESH_SUFFIXES:
        name, mesh = Path(hidden).stem, load_mesh(hidden, up=up)
    else:
        raise DataError(
            f"unknown hidden payload {hidden!r}: use one of the objects {sorted(HIDDEN_OBJECTS)}, 'scene' or a scene "
            f"name {sorted(SCENES)}, or a mesh file ({', '.join(MESH_SUFFIXES)})"
        )
    placed = _place_object(mesh, layout, position, size, yaw, placement)
    if level == "object":
        return _Payload("object", level, name, placed, placed, tuple(background), lighting)
    return _Payload("object", level, name, placed, merge([layout.mesh, placed]), layout.sky, lighting)


def _real(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_)) and math.isfinite(value)


def _count(name: str, value, why: str = "") -> int:
    """value as an int >= 1, or a DataError naming the argument and the valid range."""
    if not (_real(value) and value == int(value) and value >= 1):
        raise DataError(f"{name} must be an integer >= 1{why}, got {value!r}")
    return int(value)


def _check_arguments(width, height, n_train, n_test, n_points, supersample, fov_degrees, point_noise) -> tuple:
    """The counts as ints; a DataError naming the first argument out of its range."""
    counts = (
        _count("width", width),
        _count("height", height),
        _count("n_train", n_train),
        # Without a held-out view, metrics would quietly be measured on training views.
        _count("n_test", n_test, " (metrics are measured on the held-out views)"),
        _count("n_points", n_points, " (training places its anchors on the sparse points)"),
        _count("supersample", supersample),
    )
    if not (_real(fov_degrees) and 0.0 < fov_degrees < 180.0):
        raise DataError(f"fov_degrees must be a number of degrees in (0, 180), got {fov_degrees!r}")
    if not (_real(point_noise) and point_noise >= 0.0):
        raise DataError(f"point_noise must be a finite number >= 0, got {point_noise!r}")
    return counts


def make_synthetic_scene(
    name: str = "default",
    hidden: str | TriMesh | None = None,
    level: str = "object",
    width: int = 128,
    height: int = 96,
    n_train: int = 32,
    n_test: int = 8,
    seed: int = 0,
    *,
    hidden_position=None,
    hidden_size: float = 1.2,
    hidden_yaw: float = 0.0,
    hidden_up: str = "z",
    hidden_placement: str = "stand",
    hidden_background=(1.0, 1.0, 1.0),
    n_points: int = 4000,
    point_noise: float = 0.02,
    supersample: int = 2,
    shadows: bool = True,
    fov_degrees: float = 60.0,
    device=None,
) -> SceneData:
    """Render a built-in scene, and optionally a payload to hide in it, from the same cameras.

    name: "room" (alias "default") or "garden". hidden: None; a built-in object ("mug", "lamp",
    "pawn", "robot"), a mesh file path or a TriMesh (hidden_kind "object"); or "scene" (the other
    built-in scene) or a scene name (hidden_kind "scene", a whole scene hidden in this one).
    level: for objects, "object" (alone over hidden_background, with alpha) or "scene" (composited
    into the scene). hidden_position: world position of the object's bottom centre (default: sunk
    on the scene's central object as hidden_placement says: "stand", "sink" or "float", see
    PLACEMENTS); hidden_size: its largest side in world units (the room is 10 wide); hidden_yaw:
    degrees about z; hidden_up: a mesh file's up axis, "z" or "y" (see ``load_mesh``).
    width, height: image size; n_train views on a hemisphere band around the centre, n_test on a
    ring within the band. n_points noisy points (std point_noise) sampled from surfaces the
    training views see. supersample**2 rays per pixel. shadows: cast hard shadows. device: the Warp
    device to ray cast on (default wp.get_preferred_device()). Same arguments and seed, same arrays.
    Raises DataError for an unknown name, payload or level, or a count below 1 (width, height,
    n_train, n_test, n_points, supersample), fov_degrees outside (0, 180) or a negative point_noise.
    """
    if level not in ("object", "scene"):
        raise DataError(f"level must be 'object' or 'scene', not {level!r}")
    width, height, n_train, n_test, n_points, supersample = _check_arguments(
        width, height, n_train, n_test, n_points, supersample, fov_degrees, point_noise)
    if hidden_placement not in PLACEMENTS:
        raise DataError(f"hidden_placement must be one of {sorted(PLACEMENTS)}, not {hidden_placement!r}")
    check_up_axis(hidden_up)
    if hidden_up != "z" and not (isinstance(hidden, str) and Path(hidden).suffix.lower() in MESH_SUFFIXES):
        raise DataError(f"hidden_up {hidden_up!r} turns a mesh file; the hidden payload {hidden!r} is not one "
                        "(built-in objects stand on +z)")
    scene_name, layout = _scene_layout(name, seed)
    rng = [np.random.default_rng((int(seed), stream)) for stream in range(3)]
    K = intrinsics_from_fov(fov_degrees, width, height)
    phase = rng[_STREAM_CAMERAS].uniform(0.0, 2.0 * np.pi)
    train_eyes = hemisphere_positions(n_train, _RADIUS, _TARGET, _TRAIN_ELEVATIONS, phase)
    elevation = np.radians(_TEST_ELEVATION)
    # The ring starts a little off the spiral's first azimuth so that test views fall between training views.
    test_eyes = orbit_positions(n_test, _RADIUS * np.cos(elevation), _RADIUS * np.sin(elevation), _TARGET, phase + 0.3)
    train = cameras_looking_at(train_eyes, _TARGET, K, width, height, "train")
    test = cameras_looking_at(test_eyes, _TARGET, K, width, height, "test")
    lighting = replace(layout.lighting, shadows=shadows)

    # The sparse points stand in for COLMAP's: surface points the training views see, spread evenly
    # over the views, with the colour seen there and Gaussian position noise of std point_noise.
    # They are drawn view by view so that no supersampled render outlives its loop iteration.
    points_per_view = np.diff(np.linspace(0, n_points, n_train + 1).round().astype(int))
    renderer = MeshRenderer(layout.mesh, device)
    seen = []
    for index, camera in enumerate(train + test):
        view = renderer.render(camera, lighting, layout.sky, supersample)
        camera.image, camera.alpha = view.image()
        if index < n_train:
            seen.append(view.sample_hits(points_per_view[index], rng[_STREAM_POINTS]))
    points = np.concatenate([p for p, _ in seen])
    points += rng[_STREAM_POINTS].normal(0.0, point_noise, points.shape).astype(np.float32)
    colors = np.concatenate([c for _, c in seen])

    scene = SceneData(scene_name, train, test, points, colors, background=layout.sky)
    if hidden is None:
        return scene
    payload = _hidden_payload(hidden, level, scene_name, layout, lighting, seed, hidden_position, hidden_size,
                              hidden_yaw, hidden_up, hidden_placement, hidden_background)
    hidden_renderer = MeshRenderer(payload.rendered, device)
    for camera in train + test:
        view = hidden_renderer.render(camera, payload.lighting, payload.background, supersample)
        camera.hidden, camera.hidden_alpha = view.image()
    # An object no training view shows (placed outside the cameras' sight, too small to cover a
    # pixel, or inside or behind the scene's geometry) leaves the hidden targets blank, or equal to
    # the cover: refused, rather than trained on and scored as perfect. Alone ("object" level) its
    # own alpha says it; composited, whether the hidden view differs from the cover's anywhere.
    shown = ([float(c.hidden_alpha.max()) >= 1.0 / 255.0 for c in train] if level == "object"
             else [float(np.abs(c.hidden - c.image).max()) >= 1.0 / 255.0 for c in train])
    if payload.kind == "object" and not any(shown):
        low, high = payload.geometry.bounds
        raise DataError(f"the hidden object ({payload.name}, bounds {np.round(low.astype(float), 2).tolist()} to "
                        f"{np.round(high.astype(float), 2).tolist()}) covers no pixel of the {n_train} training views: nothing "
                        "of it could be hidden; place it where the cameras look (hidden_position, hidden_size)")
    scene.hidden_kind, scene.hidden_level, scene.hidden_name = payload.kind, payload.level, payload.name
    scene.hidden_background = np.asarray(payload.background, dtype=np.float32)
    scene.hidden_bbox = payload.geometry.bounds
    scene.hidden_points = payload.geometry.sample_surface(4096, rng[_STREAM_HIDDEN_POINTS])
    return scene
