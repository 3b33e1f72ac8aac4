"""Camera conventions, camera paths, the containers' validation, and reading image files."""
import imageio.v3 as iio
import numpy as np
import pytest

from securegs_warp.data import Camera, DataError, SceneData
from securegs_warp.data.cameras import (
    cameras_looking_at, composite, hemisphere_positions, intrinsics_from_fov, look_at, orbit_positions, read_image,
    resize_image, resize_view,
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


def test_palette_transparency_is_read_as_alpha(tmp_path):
    # Size-optimised PNGs keep transparency in the palette, not in an alpha channel.
    from PIL import Image

    rgba = np.zeros((4, 4, 4), dtype=np.uint8)
    rgba[..., 0], rgba[:2, :, 3] = 255, 255
    Image.fromarray(rgba, "RGBA").quantize(colors=4).save(tmp_path / "palette.png")
    rgb, alpha = read_image(tmp_path / "palette.png")
    np.testing.assert_array_equal(alpha[..., 0], rgba[..., 3] / 255.0)
    np.testing.assert_array_equal(rgb[:2, :, 0], 1.0)


def test_resizing_an_object_keeps_its_edge_colour():
    # A red object on transparent black: shrunk, then composited, its edge stays red over the
    # background, as the full-size composite shrunk does (no dark rim from the transparent black).
    rgb = np.zeros((8, 8, 3), dtype=np.float32)
    alpha = np.zeros((8, 8, 1), dtype=np.float32)
    rgb[:, :5, 0], alpha[:, :5] = 1.0, 1.0
    background = np.array([1.0, 1.0, 1.0], dtype=np.float32)
    small_rgb, small_alpha = resize_view(rgb, alpha, (4, 4))
    np.testing.assert_allclose(composite(small_rgb, small_alpha, background),
                               resize_image(composite(rgb, alpha, background), (4, 4)), atol=1e-6)
    assert resize_view(rgb, None, (4, 4))[1] is None


def test_resize_is_an_area_average():
    pixels = np.random.default_rng(0).random((6, 8, 2)).astype(np.float32)
    np.testing.assert_allclose(resize_image(pixels, (4, 3)), pixels.reshape(3, 2, 4, 2, 2).mean(axis=(1, 3)), atol=1e-6)
    assert resize_image(None, (4, 3)) is None and resize_image(pixels, (8, 6)) is pixels


def _rotated(angle):
    c, s = np.cos(angle), np.sin(angle)
    viewmat = np.eye(4)
    viewmat[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    viewmat[:3, 3] = [0.5, -1.0, 4.0]
    return viewmat


def _changed(matrix, index, value):
    matrix = np.array(matrix, dtype=np.float64)
    matrix[index] = value
    return matrix


GOOD_K = intrinsics_from_fov(60, 4, 3)
NOT_ROTATION = r"camera 'bad\.png': viewmat's 3x3 block is not a rotation \(.*\); expected an orthonormal matrix"


@pytest.mark.parametrize("viewmat, K, expected", [
    pytest.param(_changed(_rotated(0.3), (0, 3), np.nan), GOOD_K,
                 r"camera 'bad\.png': viewmat has non-finite entries .*nan.*; expected finite numbers",
                 id="viewmat-nan"),
    pytest.param(_changed(_rotated(0.3), (1, 1), np.inf), GOOD_K, r"viewmat has non-finite entries", id="viewmat-inf"),
    pytest.param(_rotated(0.3), _changed(GOOD_K, (0, 2), np.nan),
                 r"camera 'bad\.png': K has non-finite entries .*; expected finite numbers", id="K-nan"),
    pytest.param(_rotated(0.3), _changed(GOOD_K, (0, 0), 0.0),
                 r"camera 'bad\.png': K has fx=0, fy=3\.4641; expected positive focal lengths", id="fx-zero"),
    pytest.param(_rotated(0.3), _changed(GOOD_K, (1, 1), -2.0), r"K has fx=3\.4641, fy=-2; expected positive",
                 id="fy-negative"),
    pytest.param(_rotated(0.3) @ np.diag([2.0, 2.0, 2.0, 1.0]), GOOD_K, NOT_ROTATION, id="scaled"),
    pytest.param(_rotated(0.3) @ np.diag([1.0, -1.0, 1.0, 1.0]), GOOD_K, NOT_ROTATION + ".*", id="reflection"),
    pytest.param(_changed(_rotated(0.3), (0, 2), 0.01), GOOD_K, NOT_ROTATION, id="sheared"),
    pytest.param(_changed(np.eye(4), (slice(0, 3), slice(0, 3)), 0.0), GOOD_K, NOT_ROTATION, id="singular"),
    pytest.param(_changed(_rotated(0.3), (3, 2), 1.0), GOOD_K,
                 r"camera 'bad\.png': viewmat bottom row is \[0, 0, 1, 1\]; expected \[0, 0, 0, 1\]", id="bottom-row"),
    pytest.param(_changed(_rotated(0.3), (3, 3), 2.0), GOOD_K, r"bottom row is \[0, 0, 0, 2\]", id="bottom-scale"),
])
def test_camera_rejects_unusable_pose_or_intrinsics(viewmat, K, expected):
    with pytest.raises(DataError, match=expected) as caught:
        Camera("bad.png", viewmat, K, 4, 3)
    assert "\n" not in str(caught.value)


def test_reflection_is_named_by_its_determinant():
    with pytest.raises(DataError, match=r"\(determinant -1\)"):
        Camera("bad.png", np.diag([1.0, -1.0, 1.0, 1.0]), GOOD_K, 4, 3)


def test_camera_size_must_be_positive():
    with pytest.raises(DataError, match=r"camera 'bad\.png': size 0x3; expected at least 1x1 pixels"):
        Camera("bad.png", np.eye(4), GOOD_K, 0, 3)


def test_camera_accepts_float32_rounded_rotations():
    """Poses arrive as float32 or rounded to a few digits: rotations to within 1e-3 are accepted."""
    viewmat = np.round(_rotated(0.3), 5).astype(np.float32)
    camera = Camera("ok.png", viewmat, GOOD_K, 4, 3)
    np.testing.assert_array_equal(camera.viewmat, viewmat)
    Camera("ok.png", _changed(_rotated(0.3), (0, 2), 2e-4), GOOD_K, 4, 3)


def test_camera_record_with_a_bad_pose_is_a_data_error():
    record = Camera("c.png", _rotated(0.3), GOOD_K, 4, 3).to_record()
    record["viewmat"][0] *= 3  # scales the rotation's first row
    with pytest.raises(DataError, match=r"camera 'c\.png': viewmat's 3x3 block is not a rotation"):
        Camera.from_record(record)


def test_project_maps_the_target_to_the_principal_point_and_reports_depth():
    K = intrinsics_from_fov(60.0, 64, 48)
    camera = Camera("c", look_at((3.0, 0.0, 1.0), (0.0, 0.0, 1.0)), K, 64, 48)
    uv, depth = camera.project(np.array([[0.0, 0.0, 1.0], [6.0, 0.0, 1.0], [0.0, 0.0, 2.0]]))
    np.testing.assert_allclose(uv[0], K[:2, 2], atol=1e-6)
    np.testing.assert_allclose(depth[:2], [3.0, -3.0], atol=1e-6)  # in front; behind the camera
    assert uv[2, 1] < K[1, 2]  # higher in the world is higher in the image (OpenCV: v grows downwards)
