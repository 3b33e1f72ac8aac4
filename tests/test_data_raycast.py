"""Warp ray casting and shading (kernels/raycast.py through MeshRenderer) against hand-computed values."""
import math

import numpy as np
import pytest

from securegs_warp.data.cameras import Camera, intrinsics_from_fov, look_at
from securegs_warp.data.meshes import Material, TriMesh, box, merge
from securegs_warp.data.synthetic import Lighting, MeshRenderer

SIZE = 33  # odd, so that the centre pixel's single sample lies on the optical axis
GREY = Material("solid", (0.6, 0.6, 0.6))
BACKGROUND = (0.1, 0.2, 0.3)


def camera(eye, target=(0.0, 0.0, 0.0), size=SIZE, fov=40.0, up=(0.0, 0.0, 1.0)):
    return Camera("probe", look_at(eye, target, up), intrinsics_from_fov(fov, size, size), size, size)


def test_hit_point_face_and_miss():
    samples = MeshRenderer(box((1, 1, 1), GREY)).render(camera((0, -5, 0)), Lighting((0, -1, 0)), BACKGROUND, 1)
    c = SIZE // 2
    np.testing.assert_allclose(samples.point[c, c], [0.0, -0.5, 0.0], atol=1e-5)
    assert samples.face[c, c] >= 0 and samples.alpha[c, c] == 1.0
    # The cube spans atan(0.5 / 4.5) = 6.3 degrees of the 20-degree half field of view: corners miss.
    assert samples.face[0, 0] == -1 and samples.alpha[0, 0] == 0.0
    np.testing.assert_allclose(samples.rgb[0, 0], BACKGROUND, atol=1e-7)
    half_width = 0.5 / 4.5 * (0.5 * SIZE / math.tan(math.radians(20.0)))  # the front face in pixels
    assert abs(int((samples.face[c] >= 0).sum()) - 2 * half_width) <= 2


@pytest.mark.parametrize("light", [(0.0, -1.0, 0.0), (0.0, -1.0, 1.0), (1.0, -1.0, 1.0), (0.0, 1.0, 0.0)])
def test_lambert_and_ambient(light):
    ambient = 0.25
    samples = MeshRenderer(box((1, 1, 1), GREY)).render(camera((0, -5, 0)), Lighting(light, ambient), BACKGROUND, 1)
    cosine = max(0.0, -light[1] / np.linalg.norm(light))  # the front face's normal is -y
    c = SIZE // 2
    np.testing.assert_allclose(samples.rgb[c, c], 0.6 * (ambient + (1 - ambient) * cosine), atol=1e-6)


def test_hard_shadow():
    scene = merge([box((6, 6, 0.2), GREY, center=(0, 0, -0.1)), box((1, 1, 0.2), GREY, center=(0, 0, 1.5))])
    view = camera((0, -4, 3), target=(0, 0, 0), size=65, fov=60)
    renderer = MeshRenderer(scene)
    lit, shadowed = (renderer.render(view, Lighting((0, 0, 1), 0.3, s), BACKGROUND, 1) for s in (False, True))
    on_ground = (lit.face >= 0) & (np.abs(lit.point[..., 2]) < 1e-4)
    below_box = on_ground & np.all(np.abs(lit.point[..., :2]) < 0.45, axis=-1)
    open_ground = on_ground & np.all(np.abs(lit.point[..., :2]) > 0.6, axis=-1)
    assert below_box.sum() > 20 and open_ground.sum() > 100
    np.testing.assert_allclose(shadowed.rgb[below_box], 0.6 * 0.3, atol=1e-6)  # ambient only
    np.testing.assert_allclose(shadowed.rgb[open_ground], 0.6, atol=1e-6)
    np.testing.assert_allclose(lit.rgb[below_box], 0.6, atol=1e-6)


def flat_square(material, colors=None):
    """A 2 x 2 square in the z = 0 plane, facing +z, whose uvw are its positions."""
    vertices = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=np.float32)
    return TriMesh(vertices, [[0, 1, 2], [0, 2, 3]], np.tile([0, 0, 1], (4, 1)), vertices,
                   np.full((4, 3), 0.5) if colors is None else colors, [0, 0], [material])


def render_flat(mesh):
    """Top-down render under full ambient light (shade factor 1, so rgb is the albedo)."""
    top_down = camera((0, 0, 3), size=41, fov=60, up=(0, 1, 0))
    samples = MeshRenderer(mesh).render(top_down, Lighting((0, 0, 1), 1.0), BACKGROUND, 1)
    hit = samples.face >= 0
    return samples.point[hit], samples.rgb[hit]


def test_checker_texture():
    a, b = (0.9, 0.1, 0.1), (0.1, 0.1, 0.9)
    points, rgb = render_flat(flat_square(Material("checker", a, b, scale=2.0)))
    # Cells are half a unit wide; the plane is sampled just below z = 0, i.e. in cell z = -1 (odd).
    parity = (np.floor(points[:, 0] * 2) + np.floor(points[:, 1] * 2) - 1).astype(int) % 2
    away_from_edges = np.all(np.abs(points[:, :2] * 2 - np.round(points[:, :2] * 2)) > 0.05, axis=1)
    expected = np.where(parity[:, None] == 1, b, a)
    np.testing.assert_allclose(rgb[away_from_edges], expected[away_from_edges], atol=1e-6)


def test_gradient_and_vertex_colors():
    a, b = (0.0, 0.2, 0.4), (1.0, 0.6, 0.2)
    points, rgb = render_flat(flat_square(Material("gradient", a, b, scale=0.5, axis=(1, 0, 0), origin=(-1, 0, 0))))
    t = np.clip((points[:, 0] + 1) * 0.5, 0, 1)[:, None]
    np.testing.assert_allclose(rgb, (1 - t) * np.array(a) + t * np.array(b), atol=1e-5)

    colors = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], dtype=np.float32)
    points, rgb = render_flat(flat_square(Material("vertex"), colors))
    lower = points[:, 1] - points[:, 0] < -0.05  # inside triangle (v0, v1, v2), away from the diagonal
    x, y = points[lower, 0], points[lower, 1]
    # Barycentric weights of (x, y) in the triangle (-1,-1), (1,-1), (1,1).
    w0, w2 = (1 - x) / 2, (y + 1) / 2
    expected = w0[:, None] * colors[0] + (1 - w0 - w2)[:, None] * colors[1] + w2[:, None] * colors[2]
    np.testing.assert_allclose(rgb[lower], expected, atol=1e-5)


def test_supersampled_image_is_the_box_filter():
    renderer = MeshRenderer(box((1, 1, 1), GREY))
    samples = renderer.render(camera((2, -4, 3), size=10), Lighting((0.3, -1, 1)), BACKGROUND, 3)
    rgb, alpha = samples.image()
    assert samples.rgb.shape == (30, 30, 3) and rgb.shape == (10, 10, 3) and alpha.shape == (10, 10, 1)
    np.testing.assert_allclose(rgb[4, 6], samples.rgb[12:15, 18:21].reshape(-1, 3).mean(0), atol=1e-6)
    np.testing.assert_allclose(alpha[4, 6, 0], samples.alpha[12:15, 18:21].mean(), atol=1e-6)
    assert 0 < alpha.mean() < 1
