"""COLMAP reader: binary and text models written here round trip exactly; bad input is a DataError."""
import struct

import imageio.v3 as iio
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from securegs_warp.data import DataError, load_colmap, load_scene

MODEL_IDS = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2, "OPENCV_FISHEYE": 5}
WIDTH, HEIGHT = 8, 6


def make_model(rng, n_images=10):
    """Two cameras, n_images posed images (ids shuffled against name order), a few points."""
    cameras = [
        (3, "PINHOLE", WIDTH, HEIGHT, [7.5, 6.5, 4.25, 2.75]),
        (7, "SIMPLE_PINHOLE", WIDTH, HEIGHT, [5.0, 4.0, 3.0]),
    ]
    ids = rng.permutation(n_images) + 1
    images = []
    for index in range(n_images):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        keypoints = [(rng.random() * WIDTH, rng.random() * HEIGHT, int(rng.integers(-1, 5))) for _ in range(index % 3)]
        camera_id = cameras[index % 2][0]
        images.append((int(ids[index]), q, rng.normal(size=3), camera_id, f"img_{index:02d}.png", keypoints))
    points = [(11 + k, rng.normal(size=3), rng.integers(0, 256, 3), 0.5, [(1, 0), (2, 3)][: k % 3]) for k in range(5)]
    return cameras, images, points


def write_binary(sparse, cameras, images, points):
    sparse.mkdir(parents=True, exist_ok=True)
    data = struct.pack("<Q", len(cameras))
    for camera_id, model, width, height, params in cameras:
        data += struct.pack("<iiQQ", camera_id, MODEL_IDS[model], width, height)
        data += struct.pack(f"<{len(params)}d", *params)
    (sparse / "cameras.bin").write_bytes(data)
    data = struct.pack("<Q", len(images))
    for image_id, q, t, camera_id, name, keypoints in images:
        data += struct.pack("<i7di", image_id, *q, *t, camera_id) + name.encode() + b"\0"
        data += struct.pack("<Q", len(keypoints)) + b"".join(struct.pack("<ddq", *kp) for kp in keypoints)
    (sparse / "images.bin").write_bytes(data)
    data = struct.pack("<Q", len(points))
    for point_id, xyz, rgb, error, track in points:
        data += struct.pack("<Q3d3Bd", point_id, *xyz, *rgb, error) + struct.pack("<Q", len(track))
        data += b"".join(struct.pack("<ii", *element) for element in track)
    (sparse / "points3D.bin").write_bytes(data)


def write_text(sparse, cameras, images, points):
    sparse.mkdir(parents=True, exist_ok=True)
    lines = ["# Camera list with one line of data per camera:"]
    lines += [f"{c} {m} {w} {h} " + " ".join(repr(float(p)) for p in params) for c, m, w, h, params in cameras]
    (sparse / "cameras.txt").write_text("\n".join(lines) + "\n")
    lines = ["# Image list with two lines of data per image:"]
    for image_id, q, t, camera_id, name, keypoints in images:
        pose = [repr(float(v)) for v in (*q, *t)]
        lines.append(" ".join([str(image_id), *pose, str(camera_id), name]))
        lines.append(" ".join(f"{x!r} {y!r} {p}" for x, y, p in keypoints))  # empty when there are none
    (sparse / "images.txt").write_text("\n".join(lines) + "\n")
    lines = ["# 3D point list"]
    for point_id, xyz, rgb, error, track in points:
        fields = [point_id, *map(repr, map(float, xyz)), *map(int, rgb), error, *[v for e in track for v in e]]
        lines.append(" ".join(map(str, fields)))
    (sparse / "points3D.txt").write_text("\n".join(lines) + "\n")


def write_images(folder, images, rng, size=(WIDTH, HEIGHT), channels=3):
    folder.mkdir(parents=True, exist_ok=True)
    pixels = {}
    for *_, name, _ in images:
        pixels[name] = rng.integers(0, 256, (size[1], size[0], channels), dtype=np.uint8)
        iio.imwrite(folder / name, pixels[name])
    return pixels


@pytest.fixture
def scene(tmp_path):
    rng = np.random.default_rng(0)
    model = make_model(rng)
    pixels = write_images(tmp_path / "images", model[1], rng)
    return tmp_path, model, pixels, rng


@pytest.mark.parametrize("writer", [write_binary, write_text])
def test_round_trip(scene, writer):
    root, (cameras, images, points), pixels, _ = scene
    writer(root / "sparse" / "0", cameras, images, points)
    data = load_colmap(root)

    assert [c.name for c in data.test] == ["img_00.png", "img_08.png"]  # sorted names, index % 8 == 0
    assert sorted(c.name for c in data.train) == [f"img_{i:02d}.png" for i in range(10) if i % 8]
    by_name = {c.name: c for c in data.cameras}
    for image_id, q, t, camera_id, name, _ in images:
        view = by_name[name]
        rotation = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()  # scipy: scalar last
        np.testing.assert_allclose(view.viewmat[:3, :3], rotation, atol=1e-6)
        np.testing.assert_array_equal(view.viewmat[:3, 3], t.astype(np.float32))
        np.testing.assert_array_equal(view.viewmat[3], [0, 0, 0, 1])
        np.testing.assert_allclose(view.center, -rotation.T @ t, atol=1e-5)
        pinhole, simple = [[7.5, 0, 4.25], [0, 6.5, 2.75], [0, 0, 1]], [[5, 0, 4], [0, 5, 3], [0, 0, 1]]
        np.testing.assert_array_equal(view.K, pinhole if camera_id == 3 else simple)
        assert (view.width, view.height) == (WIDTH, HEIGHT)
        np.testing.assert_array_equal(view.image, pixels[name].astype(np.float32) / 255)
        assert view.alpha is None and view.hidden is None
    np.testing.assert_array_equal(data.points, np.stack([p[1] for p in points]).astype(np.float32))
    np.testing.assert_array_equal(data.colors, np.stack([p[2] for p in points]).astype(np.float32) / 255)
    assert data.hidden_kind is None


def test_binary_preferred_and_sparse_without_0(scene):
    root, (cameras, images, points), _, _ = scene
    write_binary(root / "sparse", cameras, images, points)
    # A text model beside the binary one, with other points: the binary one must win.
    write_text(root / "sparse", cameras, images, points[:2])
    assert len(load_colmap(root).points) == len(points)


def test_downscale_and_hidden_views(scene):
    root, (cameras, images, points), _, rng = scene
    write_binary(root / "sparse" / "0", cameras, images, points)
    hidden = write_images(root / "hidden", images, rng, channels=4)
    data = load_colmap(root, downscale=2, hidden_dir=root / "hidden", hidden_background=(0.0, 0.0, 0.0))
    view = data.train[0]
    assert (view.width, view.height) == (4, 3) and view.image.shape == (3, 4, 3)
    pinhole = view.K if view.K[0, 0] != view.K[1, 1] else data.train[1].K
    np.testing.assert_allclose(pinhole, [[3.75, 0, 2.125], [0, 3.25, 1.375], [0, 0, 1]])
    rgba = hidden[view.name].astype(np.float64) / 255
    pool = lambda a: a.reshape(3, 2, 4, 2, a.shape[-1]).mean(axis=(1, 3))  # 2x2 box filter  # noqa: E731
    np.testing.assert_allclose(view.hidden_alpha[..., 0], pool(rgba)[..., 3], atol=1e-5)
    # over black, composited at full size and then shrunk (the colour weighted by its alpha)
    np.testing.assert_allclose(view.hidden, pool(rgba[..., :3] * rgba[..., 3:]), atol=1e-5)
    assert data.hidden_kind == "object" and data.hidden_level == "object"


def test_masked_scene_images_are_their_colour_times_alpha(scene):
    # As 3DGS reads a masked capture: the renders (over black) are compared with rgb·alpha.
    root, (cameras, images, points), _, rng = scene
    write_binary(root / "sparse" / "0", cameras, images, points)
    rgba = write_images(root / "images", images, rng, channels=4)
    view = load_colmap(root).train[0]
    pixels = rgba[view.name].astype(np.float64) / 255
    np.testing.assert_allclose(view.image, pixels[..., :3] * pixels[..., 3:], atol=1e-6)


def test_presized_image_folder_is_used(scene):
    root, (cameras, images, points), _, rng = scene
    write_binary(root / "sparse" / "0", cameras, images, points)
    small = write_images(root / "images_2", images, rng, size=(4, 3))
    data = load_colmap(root, downscale=2)
    np.testing.assert_array_equal(data.train[0].image, small[data.train[0].name] / np.float32(255))


def test_load_scene_dispatches_to_colmap(scene):
    root, (cameras, images, points), _, _ = scene
    write_text(root / "sparse" / "0", cameras, images, points)
    assert len(load_scene(root).cameras) == len(images)


def test_missing_folder(tmp_path):
    with pytest.raises(DataError, match="nowhere.*not found"):
        load_colmap(tmp_path / "nowhere")


def test_missing_sparse_and_missing_file(scene):
    root, (cameras, images, points), _, _ = scene
    with pytest.raises(DataError, match="sparse"):
        load_colmap(root)
    write_binary(root / "sparse" / "0", cameras, images, points)
    (root / "sparse" / "0" / "points3D.bin").unlink()
    with pytest.raises(DataError, match="points3D.bin nor points3D.txt"):
        load_colmap(root)


@pytest.mark.parametrize("writer, file", [(write_binary, "cameras.bin"), (write_text, "cameras.txt")])
def test_unsupported_camera_model(scene, writer, file):
    root, (cameras, images, points), _, _ = scene
    cameras = [cameras[0], (7, "OPENCV_FISHEYE", WIDTH, HEIGHT, [5.0, 5.0, 4.0, 3.0, 0.1, 0.0, 0.0, 0.0])]
    writer(root / "sparse" / "0", cameras, images, points)
    with pytest.raises(DataError, match=rf"{file}.*camera 7 uses the OPENCV_FISHEYE camera model"):
        load_colmap(root)


def test_image_size_mismatch(scene):
    root, (cameras, images, points), _, rng = scene
    write_binary(root / "sparse" / "0", cameras, images, points)
    iio.imwrite(root / "images" / "img_03.png", rng.integers(0, 256, (HEIGHT, WIDTH + 1, 3), dtype=np.uint8))
    with pytest.raises(DataError, match=r"img_03\.png: image is 9x6 but COLMAP camera 7 \(SIMPLE_PINHOLE\) is 8x6"):
        load_colmap(root)


def test_missing_image_and_hidden_image(scene):
    root, (cameras, images, points), _, rng = scene
    write_binary(root / "sparse" / "0", cameras, images, points)
    write_images(root / "hidden", images[1:], rng)
    with pytest.raises(DataError, match=r"hidden[/\\]img_00\.png: hidden image not found"):
        load_colmap(root, hidden_dir=root / "hidden")
    (root / "images" / "img_05.png").unlink()
    with pytest.raises(DataError, match=r"img_05\.png: scene image not found"):
        load_colmap(root)


@pytest.mark.parametrize("file", ["cameras.bin", "images.bin", "points3D.bin"])
def test_truncated_binary(scene, file):
    root, (cameras, images, points), _, _ = scene
    sparse = root / "sparse" / "0"
    write_binary(sparse, cameras, images, points)
    data = (sparse / file).read_bytes()
    for cut in (3, len(data) // 2, len(data) - 1):
        (sparse / file).write_bytes(data[:cut])
        # (points3D.bin's point count is checked against the bytes left before its records are read)
        expected = (rf"{file}: truncated (file: .* at byte \d+, but the file has only {cut} bytes"
                    rf"|or damaged file: \d+ points need at least \d+ bytes)")
        with pytest.raises(DataError, match=expected):
            load_colmap(root)


def test_trailing_bytes_and_bad_text(scene):
    root, (cameras, images, points), _, _ = scene
    sparse = root / "sparse" / "0"
    write_binary(sparse, cameras, images, points)
    with open(sparse / "cameras.bin", "ab") as f:
        f.write(b"\0\0")
    with pytest.raises(DataError, match="cameras.bin: 2 unexpected bytes"):
        load_colmap(root)
    for path in sparse.iterdir():
        path.unlink()
    write_text(sparse, cameras, images, points)
    lines = (sparse / "points3D.txt").read_text().splitlines()
    fields = lines[1].split()
    fields[7] = "oops"  # the reprojection error
    (sparse / "points3D.txt").write_text("\n".join([lines[0], " ".join(fields), *lines[2:]]))
    with pytest.raises(DataError, match=r"points3D.txt:2: bad point line"):
        load_colmap(root)
    fields[7], fields[4] = "0.5", "300"  # a colour channel past 255
    (sparse / "points3D.txt").write_text("\n".join([lines[0], " ".join(fields), *lines[2:]]))
    with pytest.raises(DataError, match=r"points3D.txt:2: point .* colour .* 0..255"):
        load_colmap(root)
    (sparse / "points3D.txt").write_text("\n".join(lines))
    # images.txt without the keypoints line of each image would lose every other image
    image_lines = [line for line in (sparse / "images.txt").read_text().splitlines() if line and line[0].isdigit()]
    (sparse / "images.txt").write_text("\n".join(image_lines) + "\n")
    with pytest.raises(DataError, match=r"images.txt:2: expected the keypoints of image"):
        load_colmap(root)


def test_damaged_point_count_is_refused_before_allocating(scene):
    root, (cameras, images, points), _, _ = scene
    sparse = root / "sparse" / "0"
    write_binary(sparse, cameras, images, points)
    data = bytearray((sparse / "points3D.bin").read_bytes())
    data[:8] = struct.pack("<Q", 2**40)
    (sparse / "points3D.bin").write_bytes(bytes(data))
    with pytest.raises(DataError, match=r"points3D.bin: truncated or damaged file: 1099511627776 points"):
        load_colmap(root)


def test_image_with_unknown_camera(scene):
    root, (cameras, images, points), _, _ = scene
    write_binary(root / "sparse" / "0", cameras[:1], images, points)
    with pytest.raises(DataError, match="refers to camera 7, which is not in the model"):
        load_colmap(root)


def test_data_error_is_value_error():
    assert issubclass(DataError, ValueError)


def test_simple_radial_distortion_is_ignored_with_a_warning(scene):
    root, (cameras, images, points), _, _ = scene
    cameras = [cameras[0], (7, "SIMPLE_RADIAL", WIDTH, HEIGHT, [5.0, 4.0, 3.0, 0.1])]
    write_binary(root / "sparse" / "0", cameras, images, points)
    with pytest.warns(UserWarning, match="camera 7 is SIMPLE_RADIAL with k=0.1; the distortion is ignored"):
        data = load_colmap(root)
    radial = [c for c in data.cameras if c.K[0, 0] == c.K[1, 1]]
    assert len(radial) == 5
    np.testing.assert_array_equal(radial[0].K, [[5, 0, 4], [0, 5, 3], [0, 0, 1]])


def _with_point(points, index, xyz):
    return [p if k != index else (p[0], np.array(xyz, dtype=np.float64), *p[2:]) for k, p in enumerate(points)]


def _with_pose(images, index, q=None, t=None):
    def changed(image):
        image_id, q0, t0, *rest = image
        return (image_id, q0 if q is None else np.array(q, dtype=np.float64),
                t0 if t is None else np.array(t, dtype=np.float64), *rest)

    return [changed(image) if k == index else image for k, image in enumerate(images)]


@pytest.mark.parametrize("writer, file", [(write_binary, "points3D.bin"), (write_text, "points3D.txt")])
def test_empty_points3d(scene, writer, file):
    """Training places its anchors on the sparse points: a model without any cannot be trained."""
    root, (cameras, images, _), _, _ = scene
    writer(root / "sparse" / "0", cameras, images, [])
    with pytest.raises(DataError, match=rf"{file}: the model has no 3-D points; .*at least one"):
        load_colmap(root)


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("writer, where", [(write_binary, r"points3D\.bin: point 13 \(record 2\)"),
                                           (write_text, r"points3D\.txt:4: point 13")])
def test_non_finite_point(scene, writer, where, value):
    root, (cameras, images, points), _, _ = scene
    writer(root / "sparse" / "0", cameras, images, _with_point(points, 2, [0.5, value, 1.0]))
    with pytest.raises(DataError, match=rf"{where} has non-finite coordinates .*; expected finite x y z"):
        load_colmap(root)


@pytest.mark.parametrize("q", [[0.0, 0.0, 0.0, 0.0], [np.nan, 0.0, 0.0, 1.0], [1.0, np.inf, 0.0, 0.0],
                               [1e-30, 0.0, 0.0, 0.0]])
@pytest.mark.parametrize("writer, file", [(write_binary, "images.bin"), (write_text, "images.txt")])
def test_bad_quaternion(scene, writer, file, q):
    root, (cameras, images, points), _, _ = scene
    writer(root / "sparse" / "0", cameras, _with_pose(images, 3, q=q), points)
    expected = rf"{file}: image 'img_03\.png' \(id {images[3][0]}\) has rotation quaternion .*; expected a finite"
    with pytest.raises(DataError, match=expected):
        load_colmap(root)


@pytest.mark.parametrize("writer, file", [(write_binary, "images.bin"), (write_text, "images.txt")])
def test_non_finite_translation(scene, writer, file):
    root, (cameras, images, points), _, _ = scene
    writer(root / "sparse" / "0", cameras, _with_pose(images, 4, t=[0.0, np.nan, 1.0]), points)
    with pytest.raises(DataError, match=rf"{file}: image 'img_04\.png' .* has translation .*; expected finite"):
        load_colmap(root)


@pytest.mark.parametrize("camera, what", [
    ((3, "PINHOLE", WIDTH, HEIGHT, [0.0, 6.5, 4.25, 2.75]), "focal length"),
    ((3, "PINHOLE", WIDTH, HEIGHT, [7.5, -6.5, 4.25, 2.75]), "focal length"),
    ((3, "PINHOLE", WIDTH, HEIGHT, [7.5, 6.5, np.nan, 2.75]), "non-finite"),
    ((3, "SIMPLE_RADIAL", WIDTH, HEIGHT, [7.5, 4.0, 3.0, np.inf]), "non-finite"),
    ((3, "SIMPLE_PINHOLE", WIDTH, HEIGHT, [np.inf, 4.0, 3.0]), "non-finite"),
    ((3, "SIMPLE_PINHOLE", WIDTH, HEIGHT, [-5.0, 4.0, 3.0]), "focal length"),
])
@pytest.mark.parametrize("writer, file", [(write_binary, "cameras.bin"), (write_text, "cameras.txt")])
def test_bad_intrinsics(scene, writer, file, camera, what):
    root, (cameras, images, points), _, _ = scene
    writer(root / "sparse" / "0", [camera, cameras[1]], images, points)
    with pytest.raises(DataError, match=rf"{file}: camera 3 \({camera[1]}\) has {what}.*; expected"):
        load_colmap(root)
