"""Blender (NeRF-synthetic) reader: pose convention, RGBA compositing, random points, errors."""
import json

import imageio.v3 as iio
import numpy as np
import pytest

from securegs_warp.data import DataError, load_blender, load_scene

WIDTH, HEIGHT, ANGLE_X = 16, 12, 0.8


def blender_c2w(eye, right, up):
    """Camera-to-world in Blender camera axes: columns right, up, backward (camera looks down -z)."""
    c2w = np.eye(4)
    backward = np.cross(right, up)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, backward, eye
    return c2w


@pytest.fixture
def scene(tmp_path):
    rng = np.random.default_rng(0)
    poses = {
        "train": [blender_c2w((0, -4, 0), (1, 0, 0), (0, 0, 1)), blender_c2w((4, 0, 1), (0, 1, 0), (0, 0, 1))],
        "test": [blender_c2w((0, 4, 0), (-1, 0, 0), (0, 0, 1))],
    }
    pixels = {}
    for split, c2ws in poses.items():
        (tmp_path / split).mkdir()
        frames = []
        for k, c2w in enumerate(c2ws):
            rgba = rng.integers(0, 256, (HEIGHT, WIDTH, 4), dtype=np.uint8)
            rgba[0, 0, 3], rgba[0, 1, 3] = 0, 255
            iio.imwrite(tmp_path / split / f"r_{k}.png", rgba)
            pixels[f"{split}/r_{k}.png"] = rgba
            frames.append({"file_path": f"./{split}/r_{k}", "rotation": 0.0, "transform_matrix": c2w.tolist()})
        (tmp_path / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": ANGLE_X, "frames": frames}))
    return tmp_path, pixels


def project(camera, point):
    """Pixel coordinates and camera-space depth of a world point."""
    x_cam = camera.viewmat[:3, :3] @ point + camera.viewmat[:3, 3]
    uvw = camera.K @ x_cam
    return uvw[:2] / uvw[2], x_cam[2]


def test_pose_convention(scene):
    root, _ = scene
    data = load_blender(root)
    assert [c.name for c in data.train] == ["train/r_0.png", "train/r_1.png"]
    assert [c.name for c in data.test] == ["test/r_0.png"]
    front = data.train[0]  # at (0, -4, 0) looking along +y, z up
    np.testing.assert_allclose(front.center, [0, -4, 0], atol=1e-6)
    focal = 0.5 * WIDTH / np.tan(0.5 * ANGLE_X)
    np.testing.assert_allclose(front.K, [[focal, 0, WIDTH / 2], [0, focal, HEIGHT / 2], [0, 0, 1]], rtol=1e-6)
    (u, v), depth = project(front, np.zeros(3))
    assert depth == pytest.approx(4.0) and (u, v) == pytest.approx((WIDTH / 2, HEIGHT / 2))
    (u, v), depth = project(front, np.array([0.5, 0.0, 0.0]))  # to the right in the world
    assert depth == pytest.approx(4.0)
    assert (u, v) == pytest.approx((WIDTH / 2 + focal * 0.125, HEIGHT / 2))
    (u, v), _ = project(front, np.array([0.0, 0.0, 0.5]))  # up in the world: up in the image (smaller v)
    assert v == pytest.approx(HEIGHT / 2 - focal * 0.125) and u == pytest.approx(WIDTH / 2)
    side = data.train[1]  # at (4, 0, 1) looking along -x
    (_, _), depth = project(side, np.array([0.0, 0.0, 1.0]))
    assert depth == pytest.approx(4.0)
    (_, _), behind = project(side, np.array([8.0, 0.0, 1.0]))
    assert behind < 0


def test_rgba_composited_and_alpha_kept(scene):
    root, pixels = scene
    for background in [(1.0, 1.0, 1.0), (0.0, 0.25, 0.0)]:
        view = load_blender(root, background=background).train[0]
        rgba = pixels["train/r_0.png"].astype(np.float32) / 255
        np.testing.assert_allclose(view.alpha, rgba[..., 3:], atol=1e-7)
        over = rgba[..., :3] * rgba[..., 3:] + np.array(background) * (1 - rgba[..., 3:])
        np.testing.assert_allclose(view.image, over, atol=1e-6)
        np.testing.assert_allclose(view.image[0, 0], background)  # alpha 0: the background alone
        np.testing.assert_allclose(view.image[0, 1], rgba[0, 1, :3])  # alpha 1: the colour alone


def test_downscale(scene):
    root, _ = scene
    view = load_blender(root, downscale=2).train[0]
    assert (view.width, view.height) == (8, 6) and view.image.shape == (6, 8, 3) and view.alpha.shape == (6, 8, 1)
    assert view.K[0, 0] == pytest.approx(0.25 * WIDTH / np.tan(0.5 * ANGLE_X)) and view.K[0, 2] == 4.0


def test_random_points_in_the_box_from_the_seed(scene):
    root, _ = scene
    a, b = load_blender(root, seed=1), load_blender(root, seed=1)
    c = load_blender(root, seed=2, n_points=500, bound=0.5)
    assert a.points.shape == (100_000, 3) and np.abs(a.points).max() <= 1.3 and np.abs(a.points).max() > 1.29
    assert a.colors.min() >= 0 and a.colors.max() <= 1
    np.testing.assert_array_equal(a.points, b.points)
    assert c.points.shape == (500, 3) and np.abs(c.points).max() <= 0.5
    np.testing.assert_array_equal(a.background, [1, 1, 1])


def test_val_split_when_no_test_split(scene):
    root, _ = scene
    (root / "transforms_test.json").rename(root / "transforms_val.json")
    assert [c.name for c in load_blender(root).test] == ["test/r_0.png"]
    (root / "transforms_val.json").unlink()
    assert load_blender(root).test == []


def test_load_scene_dispatches_to_blender(scene):
    root, _ = scene
    assert len(load_scene(root, n_points=10).train) == 2


def test_errors(scene, tmp_path):
    root, _ = scene
    with pytest.raises(DataError, match="missing.*not found"):
        load_blender(root / "missing")
    (root / "test" / "r_0.png").unlink()
    with pytest.raises(DataError, match=r"test[/\\]r_0\.png: image file not found"):
        load_blender(root)
    (root / "transforms_test.json").write_text("{not json")
    with pytest.raises(DataError, match="transforms_test.json: not valid JSON"):
        load_blender(root)
    (root / "transforms_test.json").write_text(json.dumps({"frames": []}))
    with pytest.raises(DataError, match="transforms_test.json: needs 'camera_angle_x'"):
        load_blender(root)
    (root / "transforms_test.json").write_text(json.dumps({"camera_angle_x": 0.5, "frames": [{"file_path": "x"}]}))
    with pytest.raises(DataError, match="transforms_test.json: frame 0 needs 'file_path' and a numeric"):
        load_blender(root)
    (root / "transforms_train.json").unlink()
    with pytest.raises(DataError, match="transforms_train.json not found"):
        load_blender(root)


def _edit_train(root, edit):
    """Rewrite transforms_train.json with edit(meta) applied (edit changes meta in place)."""
    path = root / "transforms_train.json"
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))


def _set_frame(index, key, value):
    def edit(meta):
        meta["frames"][index][key] = value
    return edit


def _set_pose(index, change):
    def edit(meta):
        c2w = np.array(meta["frames"][index]["transform_matrix"])
        meta["frames"][index]["transform_matrix"] = change(c2w).tolist()
    return edit


def _drop(index, key):
    def edit(meta):
        del meta["frames"][index][key]
    return edit


FRAME = r"transforms_train\.json: frame 1"
POSE = rf"{FRAME}: transform_matrix's 3x3 block is not a rotation .*\(a rigid camera-to-world pose\)"
ANGLE = r"transforms_train\.json: 'camera_angle_x' must be .*a number of radians in \(0, π\)"


@pytest.mark.parametrize("edit, expected", [
    pytest.param(lambda m: m.update(frames=5),
                 r"transforms_train\.json: 'frames' is a number; expected a list of frame objects",
                 id="frames-not-a-list"),
    pytest.param(lambda m: m.update(frames={"a": 1}), r"'frames' is an object; expected a list", id="frames-object"),
    pytest.param(lambda m: m["frames"].__setitem__(1, "r_1.png"),
                 rf"{FRAME} is a string; expected an object with 'file_path' and 'transform_matrix'",
                 id="frame-not-object"),
    pytest.param(_drop(1, "transform_matrix"),
                 rf"{FRAME} needs 'file_path' and a numeric 'transform_matrix'; it has no 'transform_matrix' "
                 r"\(expected a 4x4 list", id="no-matrix"),
    pytest.param(_set_frame(1, "transform_matrix", "identity"),
                 rf"{FRAME}: 'transform_matrix' must be a 4x4 list of numbers \(4 rows of 4\)", id="matrix-string"),
    pytest.param(_set_frame(1, "transform_matrix", 5), rf"{FRAME}: 'transform_matrix' must be a 4x4 list",
                 id="matrix-number"),
    pytest.param(_set_frame(1, "transform_matrix", {"0": [1, 0, 0, 0]}), rf"{FRAME}: 'transform_matrix' must be a 4x4",
                 id="matrix-object"),
    pytest.param(_set_frame(1, "transform_matrix", np.eye(4)[:3].tolist()), rf"{FRAME}: 'transform_matrix' must be",
                 id="matrix-3x4"),
    pytest.param(_set_frame(1, "transform_matrix", [[1, 0, 0, 0], [0, 1, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
                 rf"{FRAME}: 'transform_matrix' must be a 4x4", id="matrix-ragged"),
    pytest.param(_set_frame(1, "transform_matrix", [["1", "0", "0", "0"]] + np.eye(4)[1:].tolist()),
                 rf"{FRAME}: 'transform_matrix' must be a 4x4 list of numbers", id="matrix-strings"),
    pytest.param(_set_frame(1, "transform_matrix", [[True, 0, 0, 0]] + np.eye(4)[1:].tolist()),
                 rf"{FRAME}: 'transform_matrix' must be a 4x4 list of numbers", id="matrix-bool"),
    pytest.param(_set_pose(1, lambda m: m * np.where(np.arange(16).reshape(4, 4) == 5, np.nan, 1.0)),
                 rf"{FRAME}: transform_matrix has non-finite entries \[.*nan.*\]; expected finite numbers", id="nan"),
    pytest.param(_set_pose(1, lambda m: np.where(np.arange(16).reshape(4, 4) < 12, 0.0, m)), POSE, id="singular"),
    pytest.param(_set_pose(1, lambda m: m @ np.diag([2.0, 2.0, 2.0, 1.0])), POSE, id="scaled"),
    pytest.param(_set_pose(1, lambda m: m @ np.diag([-1.0, 1.0, 1.0, 1.0])), POSE, id="reflection"),
    pytest.param(_set_pose(1, lambda m: m + np.triu(np.ones((4, 4)), 1) * 0.1 * (np.arange(4) < 3)[:, None]), POSE,
                 id="sheared"),
    pytest.param(_set_pose(1, lambda m: np.vstack([m[:3], [0.0, 0.0, 1.0, 1.0]])),
                 rf"{FRAME}: transform_matrix bottom row is \[0, 0, 1, 1\]; expected \[0, 0, 0, 1\]", id="bottom-row"),
    pytest.param(_drop(1, "file_path"), rf"{FRAME} needs .*; it has no 'file_path' \(expected the image path",
                 id="no-file-path"),
    pytest.param(_set_frame(1, "file_path", 7), rf"{FRAME}: 'file_path' is a number; expected a string",
                 id="file-path-int"),
    pytest.param(_set_frame(1, "file_path", ""), rf"{FRAME}: 'file_path' is empty; expected", id="file-path-empty"),
    pytest.param(lambda m: m.update(camera_angle_x="wide"), ANGLE, id="angle-string"),
    pytest.param(lambda m: m.update(camera_angle_x=[0.8]), ANGLE, id="angle-list"),
    pytest.param(lambda m: m.update(camera_angle_x=True), ANGLE, id="angle-bool"),
    pytest.param(lambda m: m.update(camera_angle_x=0), ANGLE, id="angle-zero"),
    pytest.param(lambda m: m.update(camera_angle_x=-0.5), ANGLE, id="angle-negative"),
    pytest.param(lambda m: m.update(camera_angle_x=float(np.pi)), ANGLE, id="angle-pi"),
    pytest.param(lambda m: m.update(camera_angle_x=40.0), ANGLE, id="angle-degrees"),
    pytest.param(lambda m: m.update(camera_angle_x=float("nan")), ANGLE, id="angle-nan"),
])
def test_bad_transforms(scene, edit, expected):
    """Each malformed part of a transforms file is a one-line DataError naming the file, the frame
    and what is valid, not a TypeError or KeyError from deep inside, nor a NaN camera."""
    root, _ = scene
    _edit_train(root, edit)
    with pytest.raises(DataError, match=expected) as caught:
        load_blender(root)
    assert "\n" not in str(caught.value)


def test_top_level_must_be_an_object(scene):
    root, _ = scene
    (root / "transforms_train.json").write_text("[1, 2]")
    with pytest.raises(DataError, match=r"transforms_train\.json: expected a JSON object with 'camera_angle_x' and "
                                        r"'frames', found an array"):
        load_blender(root)
    (root / "transforms_train.json").write_text('{"frames": []}', encoding="utf-16")
    with pytest.raises(DataError, match=r"transforms_train\.json: not valid JSON in UTF-8"):
        load_blender(root)


def test_nearly_rigid_poses_are_accepted(scene):
    """Poses written with a few digits are rigid only to their rounding: they load."""
    root, _ = scene
    _edit_train(root, _set_pose(1, lambda m: np.round(m @ np.array(
        [[np.cos(0.3), -np.sin(0.3), 0, 0], [np.sin(0.3), np.cos(0.3), 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), 5)))
    assert len(load_blender(root).train) == 2


def test_empty_training_frames(scene):
    root, _ = scene
    _edit_train(root, lambda m: m.update(frames=[]))
    with pytest.raises(DataError, match=r"transforms_train\.json: 'frames' is empty; expected at least one training"):
        load_blender(root)


def test_image_outside_the_scene_folder(scene, tmp_path_factory):
    """file_path may lead out of the scene folder; the camera is then named by its file_path."""
    root, pixels = scene
    outside = tmp_path_factory.mktemp("elsewhere") / "front.png"
    iio.imwrite(outside, pixels["train/r_0.png"])
    _edit_train(root, _set_frame(0, "file_path", str(outside)))
    assert load_blender(root).train[0].name == str(outside)
