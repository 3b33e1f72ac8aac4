"""Blending boxes (kernels/records.py ``blend_box``): the blending backward skips, for a whole warp, a
Gaussian whose box its pixels all miss. The box must hold every pixel centre that passes the
kernels' float32 test o·e^(−σ) >= alpha_min, or a gradient would lose a contribution; and it must be
tight enough to skip something. Skipping changes nothing: packed renders (which skip) equal
per-field renders (which cannot) bit for bit."""
import math

import pytest
import torch
import warp as wp

from securegs_warp.kernels.records import NO_BOX, blend_box
from securegs_warp.raster_cases import DIFF_INPUTS, random_scene, render_with_grads

ALPHA_MIN, ALPHA_MAX = 1.0 / 255.0, 0.999


@wp.kernel
def _boxes(xy: wp.array(dtype=wp.vec2), conics: wp.array(dtype=wp.vec3), opacities: wp.array(dtype=float),
           alpha_min: float, out: wp.array(dtype=wp.vec2)):
    i = wp.tid()
    out[i] = blend_box(xy[i], conics[i], opacities[i], alpha_min)


def gaussians(n: int, seed: int, anisotropy: float, centre_scale: float):
    """[n, 2] centres, [n, 3] conics (inverse of R·diag(s²)·Rᵀ + 0.3·I, as the projection's eps2d
    makes them), [n] opacities from alpha_min up."""
    g = torch.Generator().manual_seed(seed)
    angle = torch.rand(n, generator=g) * math.pi
    long = 0.3 + torch.rand(n, generator=g) * 6.0
    short = long / (1.0 + torch.rand(n, generator=g) * (anisotropy - 1.0))
    cos, sin = torch.cos(angle), torch.sin(angle)
    sxx = cos**2 * long**2 + sin**2 * short**2 + 0.3
    syy = sin**2 * long**2 + cos**2 * short**2 + 0.3
    sxy = cos * sin * (long**2 - short**2)
    det = sxx * syy - sxy**2
    conics = torch.stack([syy / det, -sxy / det, sxx / det], dim=1).float()
    xy = ((torch.rand(n, 2, generator=g) - 0.5) * 2 * centre_scale).float()
    opacities = (ALPHA_MIN + torch.rand(n, generator=g) * (1 - ALPHA_MIN)).float()
    opacities[:8] = torch.tensor([ALPHA_MIN, ALPHA_MIN * 1.001, 0.999, 1.0, 0.5, ALPHA_MIN * 0.99, 0.01, 0.2])
    return xy, conics, opacities


def boxes_of(xy, conics, opacities):
    out = wp.zeros(len(xy), dtype=wp.vec2, device="cpu")
    wp.launch(_boxes, dim=len(xy), device="cpu",
              inputs=[wp.from_torch(xy, dtype=wp.vec2), wp.from_torch(conics, dtype=wp.vec3),
                      wp.from_torch(opacities), ALPHA_MIN], outputs=[out])
    return wp.to_torch(out)


def passing_offsets(x, y, conic, opacity, reach):
    """Pixel-centre offsets (dx, dy) from (x, y), within ±reach px, that pass the kernels' test as
    they evaluate it in float32 (dx = x − (px + 0.5), same operation order)."""
    px = torch.arange(math.floor(x - reach), math.ceil(x + reach) + 1, dtype=torch.float32) + 0.5
    py = torch.arange(math.floor(y - reach), math.ceil(y + reach) + 1, dtype=torch.float32) + 0.5
    dx = (torch.tensor(x, dtype=torch.float32) - px)[None, :]
    dy = (torch.tensor(y, dtype=torch.float32) - py)[:, None]
    a, b, c = (torch.tensor(float(v), dtype=torch.float32) for v in conic)
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    # A compiler may fuse multiplies and adds (FMA): σ from float32 inputs computed exactly, then
    # rounded once, stands for any such contraction.
    exact = (0.5 * (a.double() * dx.double() ** 2 + c.double() * dy.double() ** 2)
             + b.double() * dx.double() * dy.double()).float()
    passed = torch.zeros_like(sigma, dtype=torch.bool)
    for s in (sigma, exact):
        alpha = torch.clamp(torch.tensor(float(opacity)) * torch.exp(-s), max=ALPHA_MAX)
        passed |= (s >= 0) & (alpha >= ALPHA_MIN)
    return dx.expand_as(passed)[passed], dy.expand_as(passed)[passed]


@pytest.mark.parametrize("anisotropy,centre_scale", [(1.0, 100.0), (30.0, 2000.0), (3000.0, 1e4)])
def test_every_passing_pixel_lies_in_the_box(anisotropy, centre_scale):
    xy, conics, opacities = gaussians(300, seed=int(anisotropy), anisotropy=anisotropy, centre_scale=centre_scale)
    boxes = boxes_of(xy, conics, opacities)
    bounded = 0
    for i in range(len(xy)):
        hx, hy = float(boxes[i, 0]), float(boxes[i, 1])
        if hx >= NO_BOX:
            continue
        bounded += 1
        reach = 1.5 * max(hx, hy, 0.0) + 3.0
        dx, dy = passing_offsets(float(xy[i, 0]), float(xy[i, 1]), conics[i], opacities[i], reach)
        if hx < 0:
            assert dx.numel() == 0, i  # below alpha_min: nothing passes, and the box is empty
            continue
        assert bool((dx.abs() <= hx).all() and (dy.abs() <= hy).all()), (i, hx, hy)
    assert bounded > len(xy) // 2  # boxes are the rule, not the exception


def test_an_opacity_a_rounding_error_below_alpha_min_keeps_its_centre():
    # The GPU's fast exp need not round e^0 to at most 1: such a Gaussian may still blend at its
    # centre, so its box must hold the centre rather than be empty.
    below = torch.nextafter(torch.tensor(ALPHA_MIN), torch.tensor(0.0))
    xy, conics, _ = gaussians(8, seed=9, anisotropy=2.0, centre_scale=10.0)
    boxes = boxes_of(xy, conics, torch.full((8,), float(below)))
    assert bool((boxes >= 0).all())
    far_below = boxes_of(xy, conics, torch.full((8,), ALPHA_MIN * 0.99))
    assert bool((far_below < 0).all())  # well below: nothing passes, and the box is empty


def test_boxes_are_tight_for_well_conditioned_gaussians():
    xy, conics, opacities = gaussians(200, seed=3, anisotropy=5.0, centre_scale=500.0)
    boxes = boxes_of(xy, conics, opacities)
    for i in range(8, len(xy)):
        a, b, c = (float(v) for v in conics[i])
        t = math.log(float(opacities[i]) / ALPHA_MIN)
        exact = math.sqrt(2 * t * c / (a * c - b * b)), math.sqrt(2 * t * a / (a * c - b * b))
        for got, want in zip(boxes[i].tolist(), exact):
            assert want <= got <= 1.01 * want + 0.1


@pytest.mark.parametrize("tile_size", [8, 16, 32])
def test_skipping_by_box_renders_what_reading_every_gaussian_renders(tile_size):
    # Small Gaussians, most of which miss most warps' rows of a tile.
    scene = random_scene(31, n=160, width=70, height=52, scale=(0.01, 0.08), tile_size=tile_size)
    fields = render_with_grads(scene, gather="fields")
    packed = render_with_grads(scene, gather="packed")
    for name, a, b in zip(["image", "alpha", *DIFF_INPUTS], fields, packed):
        assert torch.equal(a, b), name
