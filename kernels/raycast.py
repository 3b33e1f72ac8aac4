"""Ray casting and shading of a triangle mesh, for the synthetic scene generator.

Two passes over a camera's supersampled pixel grid (``H*s`` rows, ``W*s`` columns, ``s``
samples per pixel side, sample ``(i, j)`` at pixel coordinates ``((j + 0.5) / s, (i + 0.5) / s)``):

1. :func:`cast_camera_rays` finds the closest hit of every sample's ray on a ``wp.Mesh`` and writes
   its distance, face id, barycentrics, world position and shading normal.
2. :func:`shade_hits` evaluates the hit face's procedural texture, lights it with a directional
   light plus ambient (a second ray toward the light gives hard shadows) and writes RGB and coverage.

Textures are solid (3-D) textures evaluated at the hit's *texture coordinate* ``uvw``: a per-vertex
point interpolated like the position, which the mesh builder keeps in each object's own frame so
that a texture moves with its object. Everything here is pure Warp, so it runs on CPU or CUDA.
"""
import warp as wp

# Texture kinds; meshes name them by string (see TEXTURES), kernels branch on the integer.
TEXTURE_SOLID = wp.constant(0)
TEXTURE_CHECKER = wp.constant(1)
TEXTURE_STRIPES = wp.constant(2)
TEXTURE_NOISE = wp.constant(3)
TEXTURE_GRADIENT = wp.constant(4)
TEXTURE_RINGS = wp.constant(5)
TEXTURE_VERTEX = wp.constant(6)

TEXTURES = {
    "solid": TEXTURE_SOLID,  # color_a everywhere
    "checker": TEXTURE_CHECKER,  # 3-D checkerboard of cells 1/scale wide
    "stripes": TEXTURE_STRIPES,  # soft-edged bands across `axis`, `scale` bands per unit
    "noise": TEXTURE_NOISE,  # fractal Perlin noise blending color_a and color_b
    "gradient": TEXTURE_GRADIENT,  # color_a at `origin` to color_b at 1/scale along `axis`
    "rings": TEXTURE_RINGS,  # wood-like rings around the line through `origin` along `axis`
    "vertex": TEXTURE_VERTEX,  # per-vertex colours (meshes loaded from files)
}


@wp.struct
class Material:
    """One procedural texture; see TEXTURES for what each field means per kind."""

    texture: wp.int32
    color_a: wp.vec3
    color_b: wp.vec3
    scale: wp.float32
    axis: wp.vec3
    origin: wp.vec3
    seed: wp.int32


@wp.func
def fractal_noise(seed: wp.int32, p: wp.vec3) -> float:
    """Three octaves of Perlin noise at p (one feature per unit at the first octave), in [0, 1]."""
    state = wp.rand_init(seed)
    total = float(0.0)
    amplitude = float(0.5)
    frequency = float(1.0)
    for _octave in range(3):
        total += amplitude * wp.noise(state, p * frequency)
        amplitude *= 0.5
        frequency *= 2.0
    # Perlin noise stays within about ±0.7 in practice; the octave weights sum to 0.875.
    return wp.clamp(0.5 + 0.8 * total, 0.0, 1.0)


@wp.func
def texture_color(m: Material, p: wp.vec3, vertex_color: wp.vec3) -> wp.vec3:
    """Albedo of material m at texture coordinate p."""
    t = float(0.0)
    if m.texture == TEXTURE_SOLID:
        return m.color_a
    elif m.texture == TEXTURE_VERTEX:
        return vertex_color
    elif m.texture == TEXTURE_CHECKER:
        q = (p - m.origin) * m.scale
        parity = int(wp.floor(q[0])) + int(wp.floor(q[1])) + int(wp.floor(q[2]))
        t = float(parity & 1)
    elif m.texture == TEXTURE_STRIPES:
        s = wp.sin(2.0 * wp.pi * wp.dot(p - m.origin, m.axis) * m.scale)
        # Soft edges: bands a Gaussian model can fit without aliasing at low resolution.
        t = wp.smoothstep(-0.35, 0.35, s)
    elif m.texture == TEXTURE_NOISE:
        t = fractal_noise(m.seed, (p - m.origin) * m.scale)
    elif m.texture == TEXTURE_GRADIENT:
        t = wp.clamp(wp.dot(p - m.origin, m.axis) * m.scale, 0.0, 1.0)
    elif m.texture == TEXTURE_RINGS:
        d = p - m.origin
        radial = wp.length(d - wp.dot(d, m.axis) * m.axis)
        wobble = 0.3 * fractal_noise(m.seed, d * 2.0)
        t = 0.5 + 0.5 * wp.sin(2.0 * wp.pi * (radial * m.scale + wobble))
    return m.color_a * (1.0 - t) + m.color_b * t


@wp.func
def interpolate(values: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32), f: int, b: wp.vec2) -> wp.vec3:
    """Barycentric interpolation of a per-vertex vec3 over face f (Warp's convention: b weights
    the face's first and second vertex, 1 - b[0] - b[1] the third)."""
    v0 = values[indices[3 * f + 0]]
    v1 = values[indices[3 * f + 1]]
    v2 = values[indices[3 * f + 2]]
    return b[0] * v0 + b[1] * v1 + (1.0 - b[0] - b[1]) * v2


@wp.kernel
def cast_camera_rays(
    mesh: wp.uint64,
    indices: wp.array(dtype=wp.int32),
    vertex_normals: wp.array(dtype=wp.vec3),
    cam_to_world: wp.mat33,
    center: wp.vec3,
    intrinsics: wp.vec4,
    supersample: int,
    max_distance: float,
    distance: wp.array2d(dtype=wp.float32),
    face: wp.array2d(dtype=wp.int32),
    bary: wp.array2d(dtype=wp.vec2),
    point: wp.array2d(dtype=wp.vec3),
    normal: wp.array2d(dtype=wp.vec3),
):
    """Closest hit of each sample's ray; one thread per sample, launched over (H*s, W*s).

    cam_to_world: rotation (3, 3) from OpenCV camera axes to world; center: camera position;
    intrinsics: (fx, fy, cx, cy) in pixels. Outputs, each (H*s, W*s): distance along the unit ray
    (-1 on a miss), face id (-1 on a miss), barycentrics, world hit point, and the unit shading
    normal (vertex normals interpolated, turned toward the camera when the ray hits a back face).
    """
    i, j = wp.tid()
    x = (float(j) + 0.5) / float(supersample)
    y = (float(i) + 0.5) / float(supersample)
    ray_cam = wp.vec3((x - intrinsics[2]) / intrinsics[0], (y - intrinsics[3]) / intrinsics[1], 1.0)
    ray = wp.normalize(cam_to_world * ray_cam)
    hit = wp.mesh_query_ray(mesh, center, ray, max_distance)
    if not hit.result:
        distance[i, j] = -1.0
        face[i, j] = -1
        return
    b = wp.vec2(hit.u, hit.v)
    n = wp.normalize(interpolate(vertex_normals, indices, hit.face, b))
    if hit.sign < 0.0:
        n = -n
    distance[i, j] = hit.t
    face[i, j] = hit.face
    bary[i, j] = b
    point[i, j] = center + hit.t * ray
    normal[i, j] = n


@wp.kernel
def shade_hits(
    mesh: wp.uint64,
    indices: wp.array(dtype=wp.int32),
    uvw: wp.array(dtype=wp.vec3),
    vertex_colors: wp.array(dtype=wp.vec3),
    face_material: wp.array(dtype=wp.int32),
    materials: wp.array(dtype=Material),
    face: wp.array2d(dtype=wp.int32),
    bary: wp.array2d(dtype=wp.vec2),
    point: wp.array2d(dtype=wp.vec3),
    normal: wp.array2d(dtype=wp.vec3),
    light_dir: wp.vec3,
    ambient: float,
    background: wp.vec3,
    shadows: int,
    shadow_bias: float,
    rgb: wp.array2d(dtype=wp.vec3),
    alpha: wp.array2d(dtype=wp.float32),
):
    """Colour of each sample from the outputs of cast_camera_rays, all (H*s, W*s).

    light_dir: unit vector toward the light. Radiance = albedo * (ambient + (1 - ambient) *
    max(0, n.l) * lit), clamped to [0, 1], where lit is 0 when `shadows` is set and a ray from the
    hit toward the light (started shadow_bias off the surface) meets the mesh. Misses get
    `background` and alpha 0; hits alpha 1.
    """
    i, j = wp.tid()
    f = face[i, j]
    if f < 0:
        rgb[i, j] = background
        alpha[i, j] = 0.0
        return
    b = bary[i, j]
    # Evaluate the solid texture a hair inside the surface (against the face's winding normal in
    # texture space) so that a face lying exactly on a checker or stripe boundary does not flicker.
    t0 = uvw[indices[3 * f + 0]]
    t1 = uvw[indices[3 * f + 1]]
    t2 = uvw[indices[3 * f + 2]]
    inward = -wp.normalize(wp.cross(t1 - t0, t2 - t0))
    p_tex = interpolate(uvw, indices, f, b) + 1.0e-4 * inward
    albedo = texture_color(materials[face_material[f]], p_tex, interpolate(vertex_colors, indices, f, b))

    n = normal[i, j]
    lambert = wp.max(wp.dot(n, light_dir), 0.0)
    if shadows != 0 and lambert > 0.0:
        if wp.mesh_query_ray_anyhit(mesh, point[i, j] + shadow_bias * n, light_dir, 1.0e6):
            lambert = 0.0
    shade = ambient + (1.0 - ambient) * lambert
    c = albedo * shade
    rgb[i, j] = wp.vec3(wp.clamp(c[0], 0.0, 1.0), wp.clamp(c[1], 0.0, 1.0), wp.clamp(c[2], 0.0, 1.0))
    alpha[i, j] = 1.0
