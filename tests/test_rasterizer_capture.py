"""``RasterOptions.capture``: the fixed-capacity render replayed from Warp graphs (CUDA) or run
directly (CPU) gives the eager op's images, outputs and gradients; a non-finite input raises; an
overflow of the capacity grows it, and raises where the caller did not ask ``info["complete"]``."""
import pytest
import torch

from securegs_warp import rasterize
from securegs_warp import raster_graph
from securegs_warp.raster_cases import DIFF_INPUTS, TEST_DEVICE, random_scene


def render(scene, capture, backward=True, seed=5, **options):
    """[image, alpha, radii, means2d, conics, depths, opacities, then each input's gradient], n_intersections."""
    leaves = {name: getattr(scene, name).detach().clone().to(TEST_DEVICE).requires_grad_(backward)
              for name in DIFF_INPUTS}
    image, alpha, info = rasterize(**leaves, viewmat=scene.viewmat.to(TEST_DEVICE), K=scene.K.to(TEST_DEVICE),
                                   width=scene.width, height=scene.height, capture=capture,
                                   **{**scene.kwargs, **options})
    out = [image, alpha] + [info[k] for k in ("radii", "means2d", "conics", "depths", "opacities")]
    if backward:
        g = torch.Generator().manual_seed(seed)
        ((image * torch.randn(image.shape, generator=g).to(TEST_DEVICE)).sum()
         + (alpha * torch.randn(alpha.shape, generator=g).to(TEST_DEVICE)).sum()).backward()
        out += [leaves[name].grad for name in DIFF_INPUTS] + [info["means2d_grad"]]
    return [t.detach().cpu() for t in out], int(info["n_intersections"])


def assert_gradients_close(x, y):
    """Gradients to float32 accumulation. On CUDA they are summed by atomics in no fixed order, so an
    element's rounding error follows the size of the terms summed into it, which an element that
    cancels to near zero does not show; the tensor's largest gradient stands in for that size."""
    torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-6 + 1e-5 * float(y.abs().max() if y.numel() else 0))


def assert_same(captured, eager):
    """Forward outputs bit for bit; gradients by ``assert_gradients_close``."""
    (a, n_a), (b, n_b) = captured, eager
    assert n_a == n_b
    for x, y in zip(a[:7], b[:7]):
        assert torch.equal(x, y)
    for x, y in zip(a[7:], b[7:]):
        assert_gradients_close(x, y)


@pytest.fixture(autouse=True)
def fresh_pool():
    raster_graph._POOL.clear()
    yield
    raster_graph._POOL.clear()


@pytest.mark.parametrize("options", [{}, {"tile_size": 8, "render_depth": "accumulated"},
                                     {"tile_overlap": "rectangle", "color_storage": "float16"},
                                     {"gather": "fields", "render_depth": "accumulated"}])
def test_captured_matches_eager(options):
    scene = random_scene(11, n=70, **options)
    eager = render(scene, False)
    assert_same(render(scene, True), eager)  # the first call runs the launches directly
    assert_same(render(scene, True), eager)  # on CUDA a replay of the captured graphs


def test_repeated_renders_reuse_one_entry_with_new_inputs():
    first, second = random_scene(12, n=70), random_scene(13, n=70)
    render(first, True)
    assert_same(render(second, True), render(second, False))
    assert [len(v) for v in raster_graph._POOL.values()] == [1]


def test_a_gaussian_culled_after_a_render_of_its_entry_has_zero_outputs():
    # No render clears the per-Gaussian outputs: the projection writes every row, a culled
    # Gaussian's as zeros. Gaussians in view in one render of an entry and behind the camera, or
    # off the image, in the next must not keep the first render's values.
    first, second = random_scene(16, n=70), random_scene(16, n=70)
    second.means[0::7, 2] = -1.0
    second.means[3::7, 0] = 50.0
    culled = torch.zeros(70, dtype=torch.bool)
    culled[0::7] = culled[3::7] = True
    in_view, _ = render(first, True)
    assert (in_view[2][culled] > 0).all()
    captured, eager = render(second, True), render(second, False)
    assert_same(captured, eager)
    for out in captured[0][2:7]:
        assert (out[culled] == 0).all()
    assert (captured[0][2][~culled] > 0).any()


def test_two_renders_in_flight_keep_their_own_state():
    a_scene, b_scene = random_scene(14, n=70), random_scene(15, n=70)
    leaves = []
    for scene in (a_scene, b_scene):
        inputs = {name: getattr(scene, name).detach().clone().requires_grad_(True) for name in DIFF_INPUTS}
        image, alpha, _ = rasterize(**inputs, viewmat=scene.viewmat, K=scene.K, width=scene.width,
                                    height=scene.height, capture=True)
        leaves.append((inputs, image, alpha))
    # Both forwards before either backward, as a public and a hidden render in one step.
    assert [len(v) for v in raster_graph._POOL.values()] == [2]
    for (inputs, image, alpha), scene in zip(leaves, (a_scene, b_scene)):
        (image.sum() + alpha.sum()).backward()
        ref = {name: getattr(scene, name).detach().clone().requires_grad_(True) for name in DIFF_INPUTS}
        ref_image, ref_alpha, _ = rasterize(**ref, viewmat=scene.viewmat, K=scene.K, width=scene.width,
                                            height=scene.height)
        (ref_image.sum() + ref_alpha.sum()).backward()
        assert torch.equal(image, ref_image)
        for name in DIFF_INPUTS:
            assert_gradients_close(inputs[name].grad, ref[name].grad)


def raises_by_the_next_call(first, bad, error, match):
    """Render ``first`` captured, then ``bad`` of the same shape: the following call of that shape
    raises (a replay is checked after it ran)."""
    render(first, True, backward=False)
    render(bad, True, backward=False)
    with pytest.raises(error, match=match):
        render(bad, True, backward=False)


# Past the capacity's headroom and slack: ~70 small Gaussians, then 70 that cover the whole image.
SMALL = dict(seed=16, n=70, width=320, height=240, scale=(0.01, 0.02), tile_size=8)
LARGE = {**SMALL, "scale": (1.0, 2.0)}


def test_capacity_overflow_raises_where_nobody_asked():
    raises_by_the_next_call(random_scene(**SMALL), random_scene(**LARGE), RuntimeError, "capacity")
    # The capacity grew: the same render again is whole.
    large = random_scene(**LARGE)
    assert_same(render(large, True), render(large, False))


def test_capacity_overflow_told_by_complete_then_grown():
    small, large = random_scene(**SMALL), random_scene(**LARGE)
    render(small, True, backward=False)
    leaves = {name: getattr(large, name).detach().clone().to(TEST_DEVICE) for name in DIFF_INPUTS}
    args = dict(viewmat=large.viewmat.to(TEST_DEVICE), K=large.K.to(TEST_DEVICE), width=large.width,
                height=large.height, capture=True, **large.kwargs)
    overflowed, _, info = rasterize(**leaves, **args)
    assert info["complete"]() is False
    eager = render(large, False)
    assert not torch.equal(overflowed.cpu(), eager[0][0])  # it lacked intersections
    (entry,) = [e for entries in raster_graph._POOL.values() for e in entries]
    capacity = entry.plan.capacity
    # Asked, the overflow does not raise: the next render of the shape grows the capacity, is whole
    # and says so.
    _, _, info = rasterize(**leaves, **args)
    assert info["complete"]() is True
    assert [e for entries in raster_graph._POOL.values() for e in entries] == [entry]
    assert entry.plan.capacity > capacity
    assert_same(render(large, True), eager)


def test_complete_raises_for_a_non_finite_input_naming_it():
    bad = random_scene(17, n=70)
    bad.scales[3, 1] = float("nan")
    _, _, info = rasterize(**{name: getattr(bad, name) for name in DIFF_INPUTS}, viewmat=bad.viewmat, K=bad.K,
                           width=bad.width, height=bad.height, capture=True)
    with pytest.raises(ValueError, match="scales"):
        info["complete"]()


@pytest.mark.parametrize("name, index, value, options, match", [
    ("means", (2, 0), float("inf"), {}, "means"), ("quats", (5, 3), float("nan"), {}, "quats"),
    ("opacities", (4,), -float("inf"), {}, "opacities"), ("colors", (1, 2), float("nan"), {}, "colors"),
    ("background", (0,), float("inf"), {}, "background"), ("viewmat", (0, 3), float("nan"), {}, "viewmat"),
    ("K", (0, 0), float("inf"), {}, "K"),
    # Finite in float32, infinite in the float16 table the blending reads.
    ("colors", (1, 2), 7e4, {"color_storage": "float16"}, r"colors \(as float16: \|value\| > 65504\)"),
])
def test_each_checked_input_is_named_by_a_replay(name, index, value, options, match):
    """The replay's own check (a kernel in its graph, float32 and float16 tables): a render of the
    same shape before it builds the graph, so that on CUDA the bad render is a replay."""
    def complete(scene):
        tensors = {key: getattr(scene, key).to(TEST_DEVICE) for key in (*DIFF_INPUTS, "viewmat", "K")}
        _, _, info = rasterize(**tensors, width=scene.width, height=scene.height, capture=True, **scene.kwargs)
        return info["complete"]()

    assert complete(random_scene(17, n=70, **options))
    bad = random_scene(17, n=70, **options)
    getattr(bad, name)[index] = value
    # Anchored: the bad input alone is named.
    with pytest.raises(ValueError, match=rf"in: {match}$"):
        complete(bad)


@pytest.mark.parametrize("options", [{}, {"gather": "fields"}, {"color_storage": "float16"}])
def test_losses_of_different_outputs_on_one_entry(options):
    """Losses of the image and alpha, of the image alone, then of alpha alone, on one pooled entry: an
    output the loss does not use reaches the op as None, and its gradient buffer, written by an
    earlier backward, must not leak into the next one."""
    scene = random_scene(21, n=70, **options)
    losses = {"both": lambda image, alpha: image.square().sum() + (3 * alpha).sum(),
              "image": lambda image, alpha: image.square().sum(),
              "alpha": lambda image, alpha: alpha.sum()}

    def gradients(capture, loss):
        leaves = {name: getattr(scene, name).clone().to(TEST_DEVICE).requires_grad_(True) for name in DIFF_INPUTS}
        image, alpha, info = rasterize(**leaves, viewmat=scene.viewmat.to(TEST_DEVICE), K=scene.K.to(TEST_DEVICE),
                                       width=scene.width, height=scene.height, capture=capture, **scene.kwargs)
        losses[loss](image, alpha).backward()
        return [leaves[name].grad.cpu() for name in DIFF_INPUTS] + [info["means2d_grad"].cpu()]

    for loss in ("both", "image", "alpha", "both"):
        for x, y in zip(gradients(True, loss), gradients(False, loss)):
            assert_gradients_close(x, y)


def test_a_float64_default_dtype_changes_nothing():
    """The entry's buffers are float32 whatever torch's default dtype is."""
    scene = random_scene(22, n=70)
    default = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    try:
        assert_same(render(scene, True), render(scene, False))
    finally:
        torch.set_default_dtype(default)


def test_non_finite_input_raises_naming_it():
    scene = random_scene(17, n=70)
    bad = random_scene(17, n=70)
    bad.scales[3, 1] = float("nan")
    raises_by_the_next_call(scene, bad, ValueError, "scales")


def test_no_gaussians():
    scene = random_scene(18, n=0)
    assert_same(render(scene, True), render(scene, False))


def test_pool_keeps_at_most_max_shapes():
    for n in range(20, 20 + raster_graph.MAX_SHAPES + 2):
        render(random_scene(19, n=n), True, backward=False)
    assert len(raster_graph._POOL) == raster_graph.MAX_SHAPES
    # The most recent shapes stay.
    assert [key[1] for key in raster_graph._POOL] == list(range(22, 22 + raster_graph.MAX_SHAPES))


@pytest.mark.parametrize("capture", [False, True])
def test_a_second_backward_of_one_render_is_refused(capture):
    # The first backward releases the render's buffers (or its pooled entry): a second one, which
    # retain_graph=True would otherwise allow, must say so instead of failing on a released object.
    scene = random_scene(3, n=30)
    leaves = {name: getattr(scene, name).detach().clone().to(TEST_DEVICE).requires_grad_() for name in DIFF_INPUTS}
    image, _, _ = rasterize(**leaves, viewmat=scene.viewmat.to(TEST_DEVICE), K=scene.K.to(TEST_DEVICE),
                            width=scene.width, height=scene.height, capture=capture, **scene.kwargs)
    image.sum().backward(retain_graph=True)
    with pytest.raises(RuntimeError, match="backward has already run"):
        image.sum().backward()


@pytest.mark.parametrize("capture", [False, True])
def test_more_intersections_than_the_sort_holds_are_refused(capture, monkeypatch):
    # The real bound (2³⁰ intersections) needs gigabytes to reach; a lowered one takes the same path.
    monkeypatch.setattr("securegs_warp.rasterizer.MAX_SORTED", 64)
    with pytest.raises(ValueError, match="tile intersections exceed what the sort can hold"):
        render(random_scene(4, n=60), capture=capture, backward=False)
