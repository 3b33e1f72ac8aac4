"""rasterize against the float64 dense reference: images and every input gradient, random scenes,
every option variant, and the hard cases that must stay finite and exact."""
import math

import numpy as np
import pytest
import torch

from securegs_warp import RasterOptions, UnknownOptionError, rasterize, rasterizer, reference
from securegs_warp.rasterizer import TRANSMITTANCE_FLOOR
from securegs_warp.raster_cases import (
    DIFF_INPUTS, aniso_scales, assert_matches_reference, hard_scene, intrinsics, layered_scene, random_scene,
    render_both, render_with_grads,
)


# ---------------------------------------------------------------------------------------------
# Random scenes and option variants

# Both ways the blending kernels read a batch of Gaussians (RasterOptions.gather).
GATHERS = pytest.mark.parametrize("gather", ["fields", "packed"])


@GATHERS
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_scenes_match_reference(seed, gather):
    assert_matches_reference(random_scene(seed, n=80, gather=gather))


@GATHERS
# The backward's gradient rows (6 + C + 1 words with the reference's depth) are summed over a CUDA
# warp in chunks of up to 32 values: 8 words, 23, 33 (a chunk of 32 and one of 1) and 47 (32 + 15).
@pytest.mark.parametrize("channels", [1, 16, 26, 40])
def test_channel_counts(channels, gather):
    assert_matches_reference(random_scene(3, n=50, channels=channels, gather=gather))


@GATHERS
@pytest.mark.parametrize("tile_size", [8, 32])
def test_tile_sizes(tile_size, gather):
    assert_matches_reference(random_scene(4, n=50, tile_size=tile_size, gather=gather))


def test_three_sigma_radius():
    assert_matches_reference(random_scene(5, n=50, radius_rule="3sigma"))


def test_antialiased():
    assert_matches_reference(random_scene(6, n=50, scale=(0.001, 0.1), antialiased=True))


def test_changed_thresholds():
    assert_matches_reference(random_scene(7, n=80, alpha_min=0.02, alpha_max=0.99, transmittance_min=0.05,
                                          eps2d=0.1, near_plane=3.5, far_plane=4.6))


def test_expected_depth_is_accumulated_over_alpha():
    s = random_scene(8, n=40)
    args = (s.means, s.quats, s.scales, s.opacities, s.colors, s.viewmat, s.K, s.width, s.height)
    _, alpha, info_acc = rasterize(*args, render_depth="accumulated")
    _, _, info_exp = rasterize(*args, render_depth="expected")
    assert torch.allclose(info_exp["depth"], info_acc["depth"] / alpha.clamp_min(1e-10))
    covered = alpha[..., 0] > 0.5
    assert covered.any()
    d = info_exp["depth"][..., 0][covered]
    assert float(d.min()) > 2.0 and float(d.max()) < 6.5  # depths of the scene, 4 ± 1.2 ± extent


def test_info_outputs():
    s = random_scene(9, n=30)
    s.means[0] = torch.tensor([0.0, 0.0, -1.0])  # behind the camera
    _, _, info = rasterize(s.means, s.quats, s.scales, s.opacities, s.colors, s.viewmat, s.K, s.width, s.height)
    assert info["radii"].shape == (30, 2) and info["radii"].dtype == torch.int32
    assert (info["radii"][0] == 0).all()
    assert (info["radii"] > 0).all(dim=1).sum() > 20
    assert info["n_intersections"] > 0
    ref2d, _, ref_depth, _, ref_radii = reference.project(s.means.double(), s.quats.double(), s.scales.double(),
                                                          s.opacities.double(), s.viewmat.double(), s.K.double(),
                                                          s.width, s.height)
    vis = info["radii"][:, 0] > 0
    assert torch.equal(vis, ref_radii[:, 0] > 0)
    assert torch.allclose(info["means2d"][vis].double(), ref2d[vis], atol=1e-4)
    assert torch.allclose(info["depths"][vis].double(), ref_depth[vis], atol=1e-6)


def test_means2d_grad_for_densification():
    s = random_scene(10, n=30)
    means = s.means.clone().requires_grad_(True)
    image, _, info = rasterize(means, s.quats, s.scales, s.opacities, s.colors, s.viewmat, s.K, s.width, s.height)
    image.sum().backward()
    g = info["means2d_grad"]
    assert g.shape == (30, 2) and torch.isfinite(g).all()
    visible = info["radii"][:, 0] > 0
    assert (g[visible].norm(dim=1) > 0).any() and (g[~visible] == 0).all()


@pytest.mark.parametrize("capture", [False, True])
def test_renders_without_background_share_one_that_stays_zero(capture):
    """Renders given no background read one kept zero tensor: a render, and its backward with a
    gradient on the background's place, must leave it zero; and the image matches an explicit zero
    background's."""
    s = random_scene(11, n=30)
    leaves = [t.clone().requires_grad_(True) for t in (s.means, s.quats, s.scales, s.opacities, s.colors)]
    image, _, _ = rasterize(*leaves, s.viewmat, s.K, s.width, s.height, capture=capture)
    (image * 2.0).sum().backward()
    kept = rasterizer._zero_background(s.colors.shape[1], s.means.device)
    assert kept is rasterizer._zero_background(s.colors.shape[1], s.means.device)
    assert torch.equal(kept, torch.zeros_like(kept))
    explicit, _, _ = rasterize(*leaves, s.viewmat, s.K, s.width, s.height, background=torch.zeros(s.colors.shape[1]),
                               capture=capture)
    assert torch.equal(image, explicit)


# ---------------------------------------------------------------------------------------------
# Hard cases: each must be finite and match the reference


def _grid_means(n, depth=3.0, spread=1.0, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=g) - 0.5) * 2 * spread + torch.tensor([0.0, 0.0, depth])


def test_scales_from_1e_minus7_to_1e3():
    n = 40
    scales = torch.logspace(-7, 3, n)[:, None] * torch.tensor([1.0, 0.7, 1.3])
    scales = scales[torch.randperm(n, generator=torch.Generator().manual_seed(0))]
    assert_matches_reference(hard_scene(_grid_means(n, depth=4.0), scales=scales))


def test_antialiased_screen_covering_gaussian():
    # Deviations of ~1e9 px and more: det(Σ) overflows float32, and the antialiasing ratio must not
    # turn into inf / inf (a NaN opacity that culls the Gaussian and NaN gradients).
    means = torch.tensor([[0.0, 0.0, 3.0], [0.3, 0.2, 4.0], [5.0, 0.0, 3.0]])
    for scale in (1e6, 1e9, 1e12):
        scales = torch.tensor([[scale, scale * 0.7, scale * 1.3], [0.2, 0.1, 0.3], [0.2, 0.1, 0.3]])
        ours, _ = assert_matches_reference(hard_scene(means, scales=scales, opacities=torch.tensor([0.3, 0.7, 0.7]),
                                                      antialiased=True))
        assert all(torch.isfinite(ours[f"grad_{name}"]).all() for name in ("means", "quats", "scales"))


@pytest.mark.parametrize("radius_rule", ["opacity_aware", "3sigma"])
def test_large_gaussians_centred_off_screen(radius_rule):
    # Centres left of the image whose footprints reach far into it: a radius capped at the image's
    # size would stop their tiles short of where they still blend (or cull them).
    means = torch.tensor([[-1.4, 0.0, 1.0], [-1.9, 0.3, 1.0], [0.0, -2.0, 1.2]])
    ours, ref = assert_matches_reference(hard_scene(means, quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(3, 1),
                                                    scales=torch.tensor([1.0, 0.6, 0.8]).repeat(3, 1),
                                                    opacities=torch.full((3,), 0.9),
                                                    radius_rule=radius_rule))
    assert float(ref["alpha"][12, 20]) > 0.1


def test_anisotropy_1e6():
    n = 30
    g = torch.Generator().manual_seed(1)
    scales = torch.tensor([0.3, 3e-7, 0.3]).repeat(n, 1)[:, torch.randperm(3, generator=g)]
    assert_matches_reference(hard_scene(_grid_means(n), scales=scales))


def test_unnormalised_and_near_zero_quaternions():
    n = 24
    g = torch.Generator().manual_seed(2)
    quats = torch.randn(n, 4, generator=g)
    quats[:6] *= 1e3
    quats[6:12] *= 1e-3
    quats[12:18] *= 1e-20
    quats[18:] = 0.0
    scales = torch.rand(n, 3, generator=g) * 0.3
    ours, _ = assert_matches_reference(hard_scene(_grid_means(n), quats=quats, scales=scales))
    assert torch.isfinite(ours["grad_quats"]).all()


def test_gaussians_behind_camera_and_at_near_plane():
    near = 0.01
    means = torch.tensor([
        [0.0, 0.0, -1.0], [0.1, 0.0, -near],  # behind the camera
        [0.0, 0.0, 0.0],  # in the camera centre
        [0.001, 0.001, near],  # exactly on the near plane
        [-0.002, 0.0, near * 1.001], [0.0, 0.003, near * 1.5],  # just in front of it
        [0.0, 0.0, near * 0.999],  # just behind it
        [0.2, 0.1, 2.0], [-0.3, 0.2, 3.0],
    ])
    scales = torch.tensor([0.001, 0.0005, 0.002]).repeat(9, 1)
    scales[7:] = torch.tensor([0.2, 0.1, 0.3])  # anisotropic, so that rotations matter
    ours, _ = assert_matches_reference(hard_scene(means, scales=scales, near_plane=near))
    _, _, info = rasterize(means, torch.randn(9, 4), scales, torch.full((9,), 0.7), torch.rand(9, 3), torch.eye(4),
                           intrinsics(30.0, 30.0, 16, 12), 32, 24)
    assert (info["radii"][[0, 1, 2, 6]] == 0).all()
    assert (info["radii"][3] > 0).all()


def test_far_outside_frustum_and_straddling_border():
    means = torch.tensor([
        [100.0, 0.0, 1.0], [-50.0, 80.0, 2.0], [0.0, -300.0, 1.0],  # far outside: clamped Jacobian
        [8.0, 0.0, 2.0], [0.0, -5.0, 1.5],  # large, just outside: reach into the image
        [1.05, 0.0, 2.0], [-1.07, 0.3, 2.0], [0.2, 0.79, 2.0], [-0.4, -0.8, 2.0],  # on the borders
    ])
    scales = torch.cat([aniso_scales(3, 30.0), aniso_scales(2, 6.0), aniso_scales(4, 0.2)])
    assert_matches_reference(hard_scene(means, scales=scales))


def test_opacities_exactly_zero_and_one():
    n = 30
    opac = torch.tensor([0.0, 1.0, 0.5]).repeat(10)
    ours, _ = assert_matches_reference(hard_scene(_grid_means(n), opacities=opac, scales=aniso_scales(n, 0.3)))
    assert (ours["grad_opacities"][0::3] == 0).all()  # culled


def test_opacity_exactly_at_alpha_min():
    # The opacity-aware radius takes sqrt(2 ln(o / alpha_min)), 0 at o == alpha_min, where sqrt's
    # adjoint is 0/0 unless guarded: the opacity gradients must stay finite (the rounded radius
    # carries none).
    n = 30
    alpha_min = torch.tensor(1.0 / 255.0, dtype=torch.float32)
    opac = torch.stack([alpha_min, torch.nextafter(alpha_min, torch.tensor(1.0)), torch.tensor(0.6)]).repeat(10)
    assert_matches_reference(hard_scene(_grid_means(n), opacities=opac, scales=aniso_scales(n, 0.3)))


@GATHERS
def test_hundreds_of_layers_on_one_pixel(gather):
    # 600 layers along the optical axis: a translucent stack crossing several 256-Gaussian batches,
    # then opaque layers that end it before the transmittance floor.
    scene = layered_scene(500, 100, width=16, height=16, jitter=0.01)
    scene.kwargs["gather"] = gather
    ours, ref = assert_matches_reference(scene)
    assert float(ref["alpha"].max()) > 0.999  # the stack really does saturate


def test_opaque_stack_down_to_the_transmittance_floor():
    # Forty opaque layers on one pixel with the least transmittance_min allowed: the transmittance
    # falls to float32's smallest normal numbers, from which the backward rebuilds the earlier ones.
    z = torch.linspace(2.0, 4.0, 40)
    means = torch.stack([torch.zeros_like(z), torch.zeros_like(z), z], 1)
    means[:, :2] += torch.randn(40, 2, generator=torch.Generator().manual_seed(3)) * 0.05
    assert_matches_reference(hard_scene(means, opacities=torch.ones(40), scales=aniso_scales(40, 0.5), width=8,
                                        height=8, transmittance_min=TRANSMITTANCE_FLOOR))
    # Below it the transmittance would turn subnormal and the gradients lose their precision.
    with pytest.raises(ValueError, match="transmittance_min.*subnormal"):
        RasterOptions(transmittance_min=0.0)


def test_coordinates_of_magnitude_1e4():
    offset = torch.tensor([1.0e4, -2.0e4, 1.5e4])
    viewmat = torch.eye(4)
    viewmat[:3, 3] = -offset
    assert_matches_reference(hard_scene(_grid_means(40) + offset, viewmat=viewmat))


def test_equal_depths():
    n = 30
    means = _grid_means(n)
    means[:, 2] = 3.0
    assert_matches_reference(hard_scene(means, scales=aniso_scales(n, 0.3)))


def test_fx_neq_fy_and_off_centre_principal_point():
    s = random_scene(11, n=60, width=36, height=28)
    s.K = intrinsics(40.0, 22.0, 9.3, 20.1)
    assert_matches_reference(s)


@pytest.mark.parametrize("size", [(1, 1), (37, 23), (17, 1)])
def test_odd_image_sizes(size):
    w, h = size
    s = random_scene(12, n=40, width=w, height=h)
    s.K = intrinsics(20.0, 20.0, w / 2, h / 2)
    s.means[:, 2] += 2.0
    assert_matches_reference(s)


@GATHERS
def test_no_gaussians(gather):
    s = random_scene(13, n=0, gather=gather)
    ours, _ = assert_matches_reference(s)
    assert torch.allclose(ours["image"], s.background.double().expand(s.height, s.width, 3))
    assert (ours["alpha"] == 0).all()


@pytest.mark.parametrize("name", ["means", "quats", "scales", "opacities", "colors", "viewmat", "K", "background"])
@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_non_finite_input_names_the_tensor(name, bad):
    s = random_scene(14, n=5)
    args = dict(means=s.means, quats=s.quats, scales=s.scales, opacities=s.opacities, colors=s.colors,
                viewmat=s.viewmat, K=s.K, width=s.width, height=s.height, background=s.background)
    args[name] = args[name].clone()
    args[name].view(-1)[0] = bad
    with pytest.raises(ValueError, match=rf"non-finite .*\b{name}\b"):
        rasterize(**args)


def test_bad_shapes_and_options_raise():
    s = random_scene(15, n=5)
    args = (s.means, s.quats, s.scales, s.opacities, s.colors, s.viewmat, s.K, s.width, s.height)
    with pytest.raises(ValueError, match="quats"):
        rasterize(s.means, s.quats[:, :3], *args[2:])
    with pytest.raises(ValueError, match="colors"):
        rasterize(*args[:4], s.colors[:3], *args[5:])
    with pytest.raises(ValueError, match="background"):
        rasterize(*args, background=torch.zeros(4))
    with pytest.raises(ValueError, match="tile_size"):
        rasterize(*args, tile_size=12)
    with pytest.raises(ValueError, match="width and height"):
        rasterize(*args[:7], 0, 10)
    with pytest.raises(ValueError, match="more than 65535 tiles of 8 pixels"):  # refused before any buffer
        rasterize(*args[:7], 8 * 65535 + 1, 10, tile_size=8)
    rasterize(*args[:7], 8 * 65535, 2, tile_size=8)  # the largest a span indexes
    with pytest.raises(TypeError):
        rasterize(*args, not_an_option=1)


def test_gradients_flow_from_any_subset_of_outputs():
    s = random_scene(16, n=20)
    means = s.means.clone().requires_grad_(True)
    _, alpha, _ = rasterize(means, s.quats, s.scales, s.opacities, s.colors, s.viewmat, s.K, s.width, s.height)
    alpha.sum().backward()  # image not used: its cotangent is absent
    assert torch.isfinite(means.grad).all() and means.grad.abs().sum() > 0


def test_packed_records_give_the_same_render_bit_for_bit():
    """gather="packed" reads the same float32 values as "fields" and adds them in the same order:
    bit-identical images and gradients, with depth, several channels and float16 colours (which
    stay outside the record)."""
    for scene in (random_scene(22, n=70, channels=5), layered_scene()):
        for fields in ({}, {"color_storage": "float16", "render_depth": "accumulated"}):
            apart = render_with_grads(scene, **fields, gather="fields")
            packed = render_with_grads(scene, **fields, gather="packed")
            for name, a, b in zip(["image", "alpha", *DIFF_INPUTS], apart, packed):
                assert torch.equal(a, b), (name, fields)
    with pytest.raises(ValueError, match="gather"):
        RasterOptions(gather="record")


def test_random_scenes_float64_consistency_with_itself():
    """The same inputs give bit-identical images twice (binning and sort are deterministic)."""
    s = random_scene(17, n=60)
    a, _ = render_both(s)
    b, _ = render_both(s)
    assert torch.equal(a["image"], b["image"])
    assert np.isfinite(a["image"].numpy()).all()


# ---------------------------------------------------------------------------------------------
# Options as a RasterOptions object, as keywords, or both


def _render(s, options=None, **overrides):
    return rasterize(s.means, s.quats, s.scales, s.opacities, s.colors, s.viewmat, s.K, s.width, s.height,
                     s.background, options, **overrides)


def test_options_object_and_keywords_give_the_same_render():
    s = random_scene(18, n=40)
    by_object = _render(s, RasterOptions(tile_size=8, radius_rule="3sigma"))
    by_keywords = _render(s, tile_size=8, radius_rule="3sigma")
    mixed = _render(s, RasterOptions(tile_size=32, radius_rule="3sigma"), tile_size=8)  # keywords win
    default = _render(s, tile_size=16, radius_rule="3sigma")
    for other in (by_keywords, mixed):
        assert torch.equal(by_object[0], other[0]) and torch.equal(by_object[1], other[1])
        assert by_object[2]["n_intersections"] == other[2]["n_intersections"]
    assert mixed[2]["tile_size"] == 8
    assert default[2]["tile_size"] == 16 and default[2]["n_intersections"] != by_object[2]["n_intersections"]


def test_unknown_option_keyword_names_it_and_lists_the_fields():
    s = random_scene(19, n=5)
    for call in (lambda: _render(s, tile_sise=8), lambda: _render(s, RasterOptions(), tile_sise=8)):
        with pytest.raises(ValueError, match=r"'tile_sise'.*tile_size.*color_storage") as raised:
            call()
        assert isinstance(raised.value, UnknownOptionError) and isinstance(raised.value, TypeError)
    with pytest.raises(ValueError, match="RasterOptions"):
        _render(s, {"tile_size": 8})
    with pytest.raises(ValueError, match="tile_size"):
        _render(s, RasterOptions(), tile_size=12)  # overrides are validated like the fields


def test_for_device_picks_the_tile_size():
    assert RasterOptions.for_device("cpu").tile_size == 8
    assert RasterOptions.for_device(torch.device("cpu"), fast_math=True) == RasterOptions(tile_size=8, fast_math=True)
    assert RasterOptions.for_device("cuda").tile_size == 16
    assert RasterOptions.for_device("cuda:0", tile_size=32).tile_size == 32
    assert RasterOptions.for_device("cpu", tile_size=16).tile_size == 16
    with pytest.raises(ValueError, match="tile_sise"):
        RasterOptions.for_device("cpu", tile_sise=8)


def test_render_without_gradients_is_the_same_render():
    """A render nothing differentiates allocates no gradients: same image, alpha and info."""
    s = random_scene(21, n=60)
    args = (s.means, s.quats, s.scales, s.opacities, s.colors, s.viewmat, s.K, s.width, s.height)
    with torch.no_grad():
        plain = rasterize(*args, background=s.background)
    means = s.means.clone().requires_grad_(True)
    graded = rasterize(means, *args[1:], background=s.background)
    assert not plain[0].requires_grad and graded[0].requires_grad
    for a, b in zip(plain[:2], graded[:2]):
        assert torch.equal(a, b)
    for key in ("radii", "means2d", "conics", "depths", "opacities"):
        assert torch.equal(plain[2][key], graded[2][key])
