"""Ellipse–tile binning (``tile_overlap="ellipse"``): the same render as binning to the whole radius
rectangle, with fewer intersections where Gaussians are thin and tilted."""
import math

import pytest
import torch
import warp as wp

from securegs_warp import rasterize
from securegs_warp.kernels.binning import MAX_TILES_PER_AXIS, pack_rect, unpack_rect
from securegs_warp.rasterizer import RasterOptions, RenderPlan
from securegs_warp.raster_cases import (
    TEST_DEVICE, assert_matches_reference, hard_scene, random_scene, render_with_grads,
)


def render(scene, **options):
    """(image, alpha, info) of ``scene`` on the test device with its options and ``options``."""
    kwargs = {**scene.kwargs, **options}
    tensors = [t.to(TEST_DEVICE) for t in (scene.means, scene.quats, scene.scales, scene.opacities, scene.colors,
                                            scene.viewmat, scene.K)]
    with torch.no_grad():
        return rasterize(*tensors, width=scene.width, height=scene.height,
                         background=scene.background.to(TEST_DEVICE), **kwargs)


def faint_scene(seed, **kwargs):
    """Random Gaussians whose opacities sit just above alpha_min (1/255 to 0.02): their ellipses at
    the threshold are small and a tile at the edge of the rectangle often holds no pixel that reaches it."""
    scene = random_scene(seed, n=120, width=48, height=40, **kwargs)
    g = torch.Generator().manual_seed(seed)
    scene.opacities = 1.0 / 255.0 + torch.rand(scene.opacities.shape, generator=g) * 0.016
    scene.opacities[::3] = torch.rand(scene.opacities[::3].shape, generator=g) * 0.95
    return scene


def tilted_needles(n=40, width=64, height=48, lengths=(0.8, 0.8)):
    """``n`` long thin Gaussians at 45° in the image plane, of lengths (scale along the needle) drawn
    in ``lengths``: their radius squares cover many tiles the needle never reaches."""
    g = torch.Generator().manual_seed(7)
    means = torch.cat([(torch.rand(n, 2, generator=g) - 0.5) * 1.5, torch.full((n, 1), 4.0)], dim=1)
    angle = math.pi / 8  # quaternion of a 45° turn about the optical axis
    quats = torch.tensor([math.cos(angle), 0.0, 0.0, math.sin(angle)]).repeat(n, 1)
    scales = torch.tensor([0.8, 0.01, 0.01]).repeat(n, 1)
    scales[:, 0] = lengths[0] + torch.rand(n, generator=g) * (lengths[1] - lengths[0])
    return hard_scene(means, quats=quats, scales=scales, opacities=torch.full((n,), 0.9), width=width,
                      height=height, K=torch.tensor([[40.0, 0, width / 2], [0, 40.0, height / 2], [0, 0, 1]]))


@pytest.mark.parametrize("seed,options", [(0, {}), (1, {"tile_size": 8}), (2, {"radius_rule": "3sigma"}),
                                          (3, {"antialiased": True, "tile_size": 32})])
def test_ellipse_binning_renders_what_rectangle_binning_renders(seed, options):
    scene = faint_scene(seed, **options)
    ellipse = render(scene, tile_overlap="ellipse")
    rectangle = render(scene, tile_overlap="rectangle")
    # A dropped (tile, Gaussian) pair is one every pixel of the tile skips (alpha < alpha_min), so the
    # blend sees the same Gaussians in the same order: bit-identical images.
    assert torch.equal(ellipse[0], rectangle[0]) and torch.equal(ellipse[1], rectangle[1])
    assert ellipse[2]["n_intersections"] < rectangle[2]["n_intersections"]


def test_ellipse_binning_gradients_match_rectangle_binning():
    scene = faint_scene(4)
    ellipse = render_with_grads(scene, tile_overlap="ellipse")
    rectangle = render_with_grads(scene, tile_overlap="rectangle")
    for a, b in zip(ellipse, rectangle):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("seed", [5, 6])
def test_ellipse_binning_matches_reference_on_faint_gaussians(seed):
    assert_matches_reference(faint_scene(seed, tile_overlap="ellipse"))


def test_tilted_needles_need_far_fewer_intersections():
    scene = tilted_needles()
    ellipse = render(scene, tile_overlap="ellipse")
    rectangle = render(scene, tile_overlap="rectangle")
    assert torch.equal(ellipse[0], rectangle[0])
    assert (ellipse[2]["radii"] > 0).all()
    # A 45° needle crosses a band about 3 tiles wide of its square of roughly 6×6 tiles.
    assert ellipse[2]["n_intersections"] <= 0.6 * rectangle[2]["n_intersections"], (
        ellipse[2]["n_intersections"], rectangle[2]["n_intersections"])
    assert_matches_reference(scene)


def test_needles_past_the_tile_mask_bin_as_those_within_it():
    # Rectangles of more than binning.MASK_TILES tiles are tested again when their keys are written,
    # smaller ones read the count pass's bit mask: with lengths from 0.2 to 3 at tiles of 8 both
    # kinds render here, and each must bin exactly the tiles the rectangle binning's image needs.
    from securegs_warp.kernels.binning import MASK_TILES

    scene = tilted_needles(n=60, width=160, height=120, lengths=(0.2, 3.0))
    scene.kwargs["tile_size"] = 8
    ellipse = render(scene, tile_overlap="ellipse")
    rectangle = render(scene, tile_overlap="rectangle")
    radii = ellipse[2]["radii"].float()
    tiles = (2 * radii[:, 0] / 8 + 1) * (2 * radii[:, 1] / 8 + 1)  # about the rectangle's tiles
    assert (tiles < MASK_TILES / 2).any() and (tiles > 2 * MASK_TILES).any()
    assert torch.equal(ellipse[0], rectangle[0]) and torch.equal(ellipse[1], rectangle[1])
    assert ellipse[2]["n_intersections"] <= 0.6 * rectangle[2]["n_intersections"]


@wp.kernel
def _rect_round_trip(rects: wp.array(dtype=wp.vec4i), out: wp.array(dtype=wp.vec4i)):
    i = wp.tid()
    out[i] = unpack_rect(pack_rect(rects[i]))


def test_a_span_keeps_every_tile_coordinate_up_to_the_limit():
    # Each coordinate has 16 bits of one int64, the last one its sign bit's: the extremes and a mix.
    M = MAX_TILES_PER_AXIS
    wp.init()
    rects = torch.tensor([[0, 0, 0, 0], [M, M, M, M], [0, M, 1, M - 1], [M, 0, M, 0], [1234, 65, 40000, 32768]],
                         dtype=torch.int32)
    w_rects = wp.from_torch(rects.to(TEST_DEVICE), dtype=wp.vec4i)
    out = wp.zeros(rects.shape[0], dtype=wp.vec4i, device=w_rects.device)
    wp.launch(_rect_round_trip, dim=rects.shape[0], inputs=[w_rects, out], device=w_rects.device)
    assert torch.equal(wp.to_torch(out).cpu(), rects)


def test_each_tiles_list_runs_front_to_back_with_ties_in_gaussian_order():
    # The lists come from two stable sorts (the Gaussians by depth, then the intersections by tile
    # id): they must be those of one sort of (tile, depth, Gaussian) keys. Four depths only, so that
    # most neighbours in a tile's list tie.
    scene = random_scene(5, n=150, width=48, height=40)
    g = torch.Generator().manual_seed(5)
    scene.means[:, 2] = 3.0 + torch.randint(0, 4, (150,), generator=g).float() * 0.5
    inputs = {name: getattr(scene, name).to(TEST_DEVICE).float().contiguous()
              for name in ("means", "quats", "scales", "opacities", "colors", "background")}
    inputs.update(color_table=inputs["colors"], viewmat=scene.viewmat.to(TEST_DEVICE).reshape(16),
                  K=scene.K.to(TEST_DEVICE).reshape(9))
    plan = RenderPlan(inputs, scene.width, scene.height, RasterOptions(tile_size=8), with_grads=False)
    with plan.scoped():
        plan.project_and_count()
        count = int(plan.ends[-1])
        plan.allocate_intersections(count)
        plan.sort_intersections(count, padded=False)
    tiles = wp.to_torch(plan.keys)[:count].long().cpu()
    ids = wp.to_torch(plan.values)[:count].long().cpu()
    depths = plan.out["depths"].cpu()[ids]
    order = sorted(range(count), key=lambda k: (int(tiles[k]), float(depths[k]), int(ids[k])))
    assert order == list(range(count))
    same_tile = tiles[1:] == tiles[:-1]
    assert int((same_tile & (depths[1:] == depths[:-1])).sum()) > 10  # ties were there to order
