"""Synthetic scene generator: determinism, hidden payloads overlapping the scene, image sanity,
points on the surfaces the training views see."""
import numpy as np
import pytest
import warp as wp

from securegs_warp.data import DataError, load_scene, make_synthetic_scene
from securegs_warp.data.meshes import HIDDEN_OBJECTS, load_mesh
from securegs_warp.data.synthetic import SCENES

SMALL = dict(width=48, height=36, n_train=8, n_test=2)


@pytest.fixture(scope="module")
def plain():
    return make_synthetic_scene(seed=0, **SMALL)


@pytest.fixture(scope="module", params=sorted(HIDDEN_OBJECTS))
def with_object(request):
    return make_synthetic_scene(hidden=request.param, level="object", seed=0, **SMALL)


def all_images(scene):
    for camera in scene.cameras:
        yield camera.image
        yield camera.alpha
        if camera.hidden is not None:
            yield camera.hidden
            yield camera.hidden_alpha


def test_default_scene_shape(plain):
    scene = make_synthetic_scene(n_points=100)
    assert (len(scene.train), len(scene.test)) == (32, 8)
    camera = scene.train[0]
    assert camera.image.shape == (96, 128, 3) and camera.alpha.shape == (96, 128, 1)
    assert scene.points.shape == (100, 3) and scene.hidden_kind is None and camera.hidden is None
    assert scene.name == "room" and plain.background.shape == (3,)


def test_same_seed_same_arrays_other_seed_differs(plain):
    again = make_synthetic_scene(seed=0, **SMALL)
    other = make_synthetic_scene(seed=1, **SMALL)
    arrays = [[*all_images(scene), scene.points, scene.colors, scene.train[0].viewmat] for scene in (plain, again)]
    for a, b in zip(*arrays):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(plain.points, other.points)
    assert all(not np.array_equal(a.image, b.image) for a, b in zip(plain.train, other.train))
    assert not np.array_equal(plain.train[0].viewmat, other.train[0].viewmat)


def test_hidden_choice_leaves_public_views_unchanged(plain, with_object):
    for a, b in zip(plain.cameras, with_object.cameras):
        np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(plain.points, with_object.points)


def test_images_in_range_without_nan(with_object):
    garden = make_synthetic_scene("garden", hidden="scene", **SMALL)
    for scene in (with_object, garden):
        for image in all_images(scene):
            assert np.isfinite(image).all() and image.min() >= 0.0 and image.max() <= 1.0


def test_hidden_object_overlaps_the_scene(with_object):
    scene = with_object
    crate_low, crate_high = SCENES["room"](0).hosts[0]
    # Partly inside the crate the object stands on: overlapping, not swallowed.
    inside = np.all((scene.hidden_points > crate_low) & (scene.hidden_points < crate_high), axis=1).mean()
    assert 0.01 < inside < 0.6
    low, high = scene.hidden_bbox
    assert np.all(low < crate_high) and np.all(high > crate_low)
    assert np.all(scene.hidden_points >= low - 1e-5) and np.all(scene.hidden_points <= high + 1e-5)
    # The public point cloud has points in the hidden object's region (its bounding box grown by 10%).
    margin = 0.1 * (high - low)
    assert np.all((scene.points > low - margin) & (scene.points < high + margin), axis=1).sum() >= 5
    assert scene.hidden_kind == "object" and scene.hidden_level == "object"


def test_object_level_alpha_nonempty_in_most_views(with_object):
    cameras = with_object.cameras
    covered = [c.hidden_alpha.mean() for c in cameras]
    assert sum(0.005 < c < 0.5 for c in covered) >= 0.9 * len(cameras)
    for camera in cameras:
        # Where the object is absent, the hidden view is the plain background colour.
        empty = camera.hidden_alpha[..., 0] == 0
        background = np.broadcast_to(with_object.hidden_background, (empty.sum(), 3))
        np.testing.assert_array_equal(camera.hidden[empty], background)


@pytest.mark.parametrize("shadows", [False, True])
def test_scene_level_differs_only_where_the_object_is(shadows):
    public = make_synthetic_scene(shadows=shadows, **SMALL)
    alone = make_synthetic_scene(hidden="robot", level="object", shadows=shadows, **SMALL)
    inside = make_synthetic_scene(hidden="robot", level="scene", shadows=shadows, **SMALL)
    assert inside.hidden_level == "scene"
    changed_views = 0
    for camera, alone_view, inside_view in zip(public.cameras, alone.cameras, inside.cameras):
        footprint = alone_view.hidden_alpha[..., 0] > 0
        outside = ~footprint
        if shadows:  # the object may only darken the rest, by its shadow
            assert np.all(inside_view.hidden[outside] <= camera.image[outside] + 1e-6)
        else:
            np.testing.assert_array_equal(inside_view.hidden[outside], camera.image[outside])
        differs = np.abs(inside_view.hidden - camera.image).max(axis=2) > 1e-3
        changed_views += differs[footprint].mean() > 0.3
        np.testing.assert_array_equal(inside_view.image, camera.image)
    assert changed_views >= 0.8 * len(public.cameras)


@wp.kernel
def closest_surface_distance(mesh_id: wp.uint64, points: wp.array(dtype=wp.vec3), out: wp.array(dtype=float)):
    k = wp.tid()
    query = wp.mesh_query_point_no_sign(mesh_id, points[k], 1.0e6)
    out[k] = wp.length(points[k] - wp.mesh_eval_position(mesh_id, query.face, query.u, query.v))


def surface_distance(mesh, points):
    """Distance (N,) from each point to the closest point of a TriMesh."""
    warp_mesh = wp.Mesh(wp.array(mesh.vertices, dtype=wp.vec3), wp.array(mesh.faces.reshape(-1), dtype=wp.int32))
    out = wp.zeros(len(points), dtype=float)
    wp.launch(closest_surface_distance, dim=len(points), inputs=[warp_mesh.id, wp.array(points, dtype=wp.vec3), out])
    return out.numpy()


def test_sparse_points_lie_near_surfaces(plain):
    mesh = SCENES["room"](0).mesh
    exact = make_synthetic_scene(point_noise=0.0, n_points=500, **SMALL)
    assert surface_distance(mesh, exact.points).max() < 1e-4
    distance = surface_distance(mesh, plain.points)
    sigma = 0.02
    # |N(0, sigma)| across the surface: median 0.67 sigma; noise was added, and is small.
    assert 0.3 * sigma < np.median(distance) < 1.0 * sigma and np.quantile(distance, 0.99) < 4 * sigma
    assert plain.colors.min() >= 0 and plain.colors.max() <= 1 and plain.colors.std() > 0.05


def test_hidden_scene(plain):
    scene = make_synthetic_scene(hidden="scene", **SMALL)
    assert (scene.hidden_kind, scene.hidden_level, scene.hidden_name) == ("scene", None, "garden")
    for public, camera in zip(plain.cameras, scene.cameras):
        np.testing.assert_array_equal(public.image, camera.image)
        assert np.abs(camera.hidden - camera.image).mean() > 0.1
        assert camera.hidden_alpha.mean() > 0.8
    assert make_synthetic_scene("garden", hidden="room", **SMALL).hidden_name == "room"


def test_user_mesh_and_placement(tmp_path):
    (tmp_path / "tetra.obj").write_text("v 0 0 0\nv 2 0 0\nv 0 2 0\nv 0 0 4\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    scene = make_synthetic_scene(hidden=str(tmp_path / "tetra.obj"), hidden_position=(1.0, -0.5, 0.2), hidden_size=0.8,
                                 **SMALL)
    assert scene.hidden_name == "tetra"
    low, high = scene.hidden_bbox
    np.testing.assert_allclose(high - low, [0.4, 0.4, 0.8], atol=1e-6)
    np.testing.assert_allclose([(low[0] + high[0]) / 2, (low[1] + high[1]) / 2, low[2]], [1.0, -0.5, 0.2], atol=1e-6)
    assert sum(c.hidden_alpha.mean() > 0 for c in scene.cameras) >= 8
    # The same file read as y-up (glTF's axis, many OBJ exporters'): its y side now stands along +z.
    upright = make_synthetic_scene(hidden=str(tmp_path / "tetra.obj"), hidden_position=(1.0, -0.5, 0.2),
                                   hidden_size=0.8, hidden_up="y", **SMALL)
    low, high = upright.hidden_bbox
    np.testing.assert_allclose(high - low, [0.4, 0.8, 0.4], atol=1e-6)
    np.testing.assert_allclose([(low[0] + high[0]) / 2, (low[1] + high[1]) / 2, low[2]], [1.0, -0.5, 0.2], atol=1e-6)
    # +y onto +z, not onto -z: the file's y apex (0, 2, 0) is the top of the turned mesh, and its
    # z apex (0, 0, 4) now points along -y (a right-handed turn about x).
    turned = load_mesh(tmp_path / "tetra.obj", up="y").vertices
    assert turned[2, 2] == pytest.approx(turned[:, 2].max()) and turned[3, 1] == pytest.approx(turned[:, 1].min())
    with pytest.raises(DataError, match="up axis must be one of z, y, not 'x'"):
        make_synthetic_scene(hidden=str(tmp_path / "tetra.obj"), hidden_up="x", **SMALL)
    with pytest.raises(DataError, match="hidden_up 'y' turns a mesh file"):
        make_synthetic_scene(hidden="mug", hidden_up="y", **SMALL)
    # Placed where no training camera sees it, or too small to cover a pixel: refused, not hidden
    # as blank targets that every render matches.
    for where in ({"hidden_position": (100.0, 0.0, 0.0)}, {"hidden_position": (0.0, 0.0, -50.0)},
                  {"hidden_size": 1e-4}):
        with pytest.raises(DataError, match="covers no pixel of the .* training views"):
            make_synthetic_scene(hidden=str(tmp_path / "tetra.obj"), **where, **SMALL)
    # Composited into the scene, under the floor or inside the crate: it projects into the views
    # but nothing of it shows, and the hidden views equal the cover's.
    for where in ((0.0, 0.0, -3.0), (0.0, 0.0, 0.05)):
        with pytest.raises(DataError, match="covers no pixel of the .* training views"):
            make_synthetic_scene(hidden="mug", level="scene", hidden_position=where, hidden_size=0.5, **SMALL)


def test_bad_arguments():
    with pytest.raises(DataError, match="unknown synthetic scene 'attic'"):
        make_synthetic_scene("attic", **SMALL)
    with pytest.raises(DataError, match="unknown hidden payload 'teapot'"):
        make_synthetic_scene(hidden="teapot", **SMALL)
    with pytest.raises(DataError, match="level must be"):
        make_synthetic_scene(hidden="mug", level="pixel", **SMALL)
    with pytest.raises(DataError, match="missing.obj: mesh file not found"):
        make_synthetic_scene(hidden="missing.obj", **SMALL)
    with pytest.raises(DataError, match="not a built-in scene name"):
        load_scene("no/such/folder")


def test_load_scene_builds_builtin_names():
    assert load_scene("garden", **SMALL).name == "garden"
    assert load_scene("synthetic", **SMALL).name == "room"


def test_a_folder_that_holds_no_scene_does_not_hide_the_builtin_of_its_name(tmp_path, monkeypatch):
    """A study's output folder named "garden" in the working directory: the built-in garden still
    loads, by load_scene and by a run's SceneSpec; a folder of another name is refused as no scene."""
    from securegs_warp.config import SceneSpec

    monkeypatch.chdir(tmp_path)
    (tmp_path / "garden").mkdir()
    (tmp_path / "runs").mkdir()
    assert load_scene("garden", **SMALL).name == "garden"
    spec = SceneSpec(source="garden", **SMALL)
    assert spec.builtin and spec.source == "garden" and spec.load().name == "garden"
    with pytest.raises(DataError, match="neither a COLMAP folder"):
        load_scene("runs")


@pytest.mark.parametrize("argument, value, expected", [
    ("width", 0, r"width must be an integer >= 1, got 0"),
    ("height", -4, r"height must be an integer >= 1, got -4"),
    ("width", 12.5, r"width must be an integer >= 1, got 12\.5"),
    ("n_train", 0, r"n_train must be an integer >= 1, got 0"),
    ("n_test", 0, r"n_test must be an integer >= 1 \(metrics are measured on the held-out views\), got 0"),
    ("n_points", 0, r"n_points must be an integer >= 1 \(training places its anchors on the sparse points\), got 0"),
    ("supersample", 0, r"supersample must be an integer >= 1, got 0"),
    ("fov_degrees", 0.0, r"fov_degrees must be a number of degrees in \(0, 180\), got 0\.0"),
    ("fov_degrees", 180.0, r"fov_degrees must be a number of degrees in \(0, 180\)"),
    ("point_noise", -0.1, r"point_noise must be a finite number >= 0, got -0\.1"),
])
def test_out_of_range_arguments(argument, value, expected):
    """Each is a one-line DataError naming the argument and its valid range, raised before any
    rendering (not a Warp launch error, a division by zero, or a scene without test views)."""
    with pytest.raises(DataError, match=expected):
        make_synthetic_scene(**{**SMALL, argument: value})


def test_integral_counts_of_other_types_are_accepted():
    scene = make_synthetic_scene(width=np.int64(24), height=18.0, n_train=2, n_test=1, n_points=np.int32(50))
    assert scene.train[0].width == 24 and scene.train[0].height == 18 and len(scene.points) == 50
