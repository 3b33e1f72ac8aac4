"""Camera conventions, camera paths, the containers' validation, and reading image files."""
import imageio.v3 as iio
import numpy as np
import pytest

from securegs_warp.data import Camera, DataError, SceneData
from securegs_warp.data.cameras import (
    cameras_looking_at, hemisphere_positions, intrinsics_from_fov, look_at, orbit_positions, read_image, resize_image,
)


def test_look_at_opencv_axes():
    eye, target = np.array([3.0, -2.0, 1.5]), np.array([0.5, 0.5, 0.2])
    viewmat = look_at(eye, target)
    rotation = viewmat[:3, :3].astype(np.float64)
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-6)
    assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-6)
    to_camera = lambda p: rotation @ p + viewmat[:3, 3]  # noqa: E731
    np.testing.assert_allclose(to_camera(eye), 0.0, atol=1e-5)
    np.testing.assert_allclose(to_camera(target), [0, 0, np.linalg.norm(target - eye)], atol=1e-5)
    assert to_camera(target + [0, 0, 1])[1] < to_camera(target)[1]  # world up is image up: smaller y
    camera = Camera("c", viewmat, intrinsics_from_fov(60, 40, 30), 40, 30)
    np.testing.assert_allclose(camera.center, eye, atol=1e-5)
    with pytest.raises(ValueError, match="look along up"):
        look_at((0, 0, 5), (0, 0, 0))


def test_intrinsics_from_fov():
    K = intrinsics_from_fov(90.0, 200, 100)
    np.testing.assert_allclose(K, [[100, 0, 100], [0, 100, 50], [0, 0, 1]], atol=1e-4)


def test_camera_paths():
    target = np.array([1.0, 2.0, 0.5])
    eyes = hemisphere_positions(40, 4.0, target, (10.0, 60.0), phase=0.3)
    offsets = eyes - target
    np.testing.assert_allclose(np.linalg.norm(offsets, axis=1), 4.0, rtol=1e-6)
    elevation = np.degrees(np.arcsin(offsets[:, 2] / 4.0))
    assert elevation.min() > 10.0 and elevation.max() < 60.0 and elevation.max() - elevation.min() > 40.0
    azimuth = np.arctan2(offsets[:, 1], offsets[:, 0])
    assert np.histogram(azimuth, bins=4, range=(-np.pi, np.pi))[0].min() >= 8  # all around
    ring = orbit_positions(8, 3.0, 1.0, target)
    np.testing.assert_allclose(np.linalg.norm(ring[:, :2] - target[:2], axis=1), 3.0, rtol=1e-6)
    np.testing.assert_allclose(ring[:, 2], 1.5)
    cameras = cameras_looking_at(ring, target, intrinsics_from_fov(60, 16, 12), 16, 12, "ring")
    assert [c.name for c in cameras[:2]] == ["ring_000", "ring_001"]
    for camera in cameras:  # the target projects to the principal point
        p = camera.K @ (camera.viewmat[:3, :3] @ target + camera.viewmat[:3, 3])
        np.testing.assert_allclose(p[:2] / p[2], [8, 6], atol=1e-4)


def test_containers_validate_shapes():
    K = intrinsics_from_fov(60, 4, 3)
    with pytest.raises(DataError, match=r"camera 'a.png': image has shape \(4, 3, 3\), expected \(3, 4, 3\)"):
        Camera("a.png", np.eye(4), K, 4, 3, image=np.zeros((4, 3, 3)))
    with pytest.raises(DataError, match="hidden alpha"):
        Camera("a.png", np.eye(4), K, 4, 3, hidden_alpha=np.zeros((3, 4, 3)))
    with pytest.raises(DataError, match="viewmat must be 4x4"):
        Camera("a.png", np.eye(3), K, 4, 3)
    with pytest.raises(DataError, match="3 points but 2 colours"):
        SceneData("s", [], [], np.zeros((3, 3)), np.zeros((2, 3)))
    cameras = [Camera(str(k), look_at((x, 0, 0), (0, 1, 0)), K, 4, 3) for k, x in enumerate((-1.0, 1.0))]
    assert SceneData("s", cameras, [], np.zeros((0, 3)), np.zeros((0, 3))).cameras_extent == pytest.approx(1.1)


def test_read_image_formats(tmp_path):
    rng = np.random.default_rng(0)
    deep = rng.integers(0, 65536, (5, 7), dtype=np.uint16)  # 16-bit grey
    iio.imwrite(tmp_path / "deep.png", deep)
    rgb, alpha = read_image(tmp_path / "deep.png")
    assert alpha is None and rgb.dtype == np.float32 and rgb.shape == (5, 7, 3)
    np.testing.assert_allclose(rgb, np.repeat(deep[..., None], 3, axis=2) / 65535.0, atol=1e-7)
    grey_alpha = rng.integers(0, 256, (5, 7, 2), dtype=np.uint8)
    iio.imwrite(tmp_path / "la.png", grey_alpha)
    rgb, alpha = read_image(tmp_path / "la.png")
    np.testing.assert_allclose(rgb, np.repeat(grey_alpha[..., :1], 3, axis=2) / 255.0, atol=1e-7)
    np.testing.assert_allclose(alpha, grey_alpha[..., 1:] / 255.0, atol=1e-7)
    (tmp_path / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    with pytest.raises(DataError, match="broken.png: cannot read image"):
        read_image(tmp_path / "broken.png")
    with pytest.raises(DataError, match="nothing.png: image file not found"):
        read_image(tmp_path / "nothing.png")


def test_resize_is_an_area_average():
    pixels = np.random.default_rng(0).random((6, 8, 2)).astype(np.float32)
    np.testing.assert_allclose(resize_image(pixels, (4, 3)), pixels.reshape(3, 2, 4, 2, 2).mean(axis=(1, 3)), atol=1e-6)
    assert resize_image(None, (4, 3)) is None and resize_image(pixels, (8, 6)) is pixels
