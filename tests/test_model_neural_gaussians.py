"""Per-view decoding against a hand computation, and the visible-anchor prefilter."""

import math

import pytest
import torch

from securegs_warp.model import (
    AnchorModel,
    ScaffoldHeads,
    camera_center_from_viewmat,
    generate_neural_gaussians,
    visible_anchor_mask,
)
from securegs_warp.model.neural_gaussians import scale_gradient
from securegs_warp.train import volume_loss


def tiny_model_and_heads(use_feat_bank=False):
    g = torch.Generator().manual_seed(0)
    n, k, d = 3, 2, 4
    model = AnchorModel(
        xyz=torch.randn(n, 3, generator=g), feat=torch.randn(n, d, generator=g),
        offsets=torch.randn(n, k, 3, generator=g), scaling=torch.randn(n, 6, generator=g) * 0.5,
        rotation=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), opacity=torch.zeros(n, 1),
    )
    torch.manual_seed(0)
    heads = ScaffoldHeads(d, k, use_feat_bank=use_feat_bank, add_cov_dist=True)
    with torch.no_grad():
        # opacity: offset 0 gets tanh(+0.7) > 0, offset 1 tanh(-0.7) < 0, whatever the input
        heads.opacity_mlp[2].weight.zero_()
        heads.opacity_mlp[2].bias.copy_(torch.tensor([0.7, -0.7]))
    return model, heads


def hand_gaussians(model, heads, cam):
    """Scaffold-GS's generate_neural_gaussians written out one anchor and one offset at a time."""
    out = {key: [] for key in ("means", "quats", "scales", "opacities", "colors", "anchor_index")}
    k = model.n_offsets
    for a in range(model.num_anchors):
        x = model.xyz[a]
        view = x - cam
        dist = view.norm()
        view = view / dist
        f = model.feat[a]
        if heads.feature_bank_mlp is not None:
            w = heads.feature_bank_mlp(torch.cat([view, dist[None]])[None])[0]
            f = w[0] * f[::4].repeat(4) + w[1] * f[::2].repeat(2) + w[2] * f
        opacity = heads.opacity_mlp(torch.cat([f, view])[None])[0]
        cov = heads.cov_mlp(torch.cat([f, view, dist[None]])[None])[0].view(k, 7)
        color = heads.color_mlp(torch.cat([f, view])[None])[0].view(k, 3)
        scaling = torch.exp(model.scaling[a])
        for j in range(k):
            if opacity[j] <= 0:
                continue
            out["means"].append(x + model.offsets[a, j] * scaling[:3])
            out["quats"].append(cov[j, 3:7] / cov[j, 3:7].norm())
            out["scales"].append(scaling[3:] * torch.sigmoid(cov[j, :3]))
            out["opacities"].append(opacity[j])
            out["colors"].append(color[j])
            out["anchor_index"].append(torch.tensor(a))
    return {key: torch.stack(values) for key, values in out.items()}


def test_generation_matches_hand_computation():
    for use_feat_bank in (False, True):
        model, heads = tiny_model_and_heads(use_feat_bank)
        cam = torch.tensor([0.3, -2.0, 5.0])
        got = generate_neural_gaussians(model, heads, cam)
        expected = hand_gaussians(model, heads, cam)
        assert got["means"].shape == (3, 3)  # one of the two offsets of each anchor survives
        for key, value in expected.items():
            assert torch.allclose(got[key], value, atol=1e-6), key
        assert torch.allclose(got["quats"].norm(dim=1), torch.ones(3))
        assert got["neural_opacity"].shape == (6,)
        assert torch.equal(got["mask"], torch.tensor([True, False] * 3))
        assert torch.equal(got["mask"], got["neural_opacity"] > 0)
        assert torch.equal(got["opacities"], got["neural_opacity"][got["mask"]])


def test_visible_mask_selects_anchors_and_keeps_global_indices():
    model, heads = tiny_model_and_heads()
    cam = torch.tensor([0.0, 0.0, -4.0])
    visible = torch.tensor([False, True, True])
    got = generate_neural_gaussians(model, heads, cam, visible)
    assert torch.equal(got["anchor_index"], torch.tensor([1, 2]))
    assert got["neural_opacity"].shape == (4,) and got["mask"].shape == (4,)
    full = generate_neural_gaussians(model, heads, cam)
    assert torch.allclose(got["means"], full["means"][1:])
    assert torch.allclose(got["colors"], full["colors"][1:])


def test_offset_source_replaces_the_stored_offsets():
    model, heads = tiny_model_and_heads()
    cam = torch.zeros(3)
    seen = {}

    def constant(inputs):
        seen["feat"] = inputs.feat
        return torch.full((inputs.xyz.shape[0], model.n_offsets, 3), 0.25)

    got = generate_neural_gaussians(model, heads, cam, offset_source=constant)
    assert torch.allclose(got["means"], model.xyz + 0.25)
    assert seen["feat"].shape == (3, 4)
    assert got["means"].requires_grad


def look_at_origin_viewmat(distance=5.0):
    """Camera on -z looking at +z (OpenCV), world origin at depth `distance`."""
    viewmat = torch.eye(4)
    viewmat[2, 3] = distance
    return viewmat


def test_visible_anchor_mask_frustum_and_margin():
    K = torch.tensor([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    xyz = torch.tensor([
        [0.0, 0.0, 0.0],    # centre of the image
        [0.0, 0.0, -6.0],   # behind the camera
        [10.0, 0.0, 0.0],   # far off to the right (u = 250)
        [2.7, 0.0, 0.0],    # just off the right edge (u = 104) but wide enough to reach it
        [2.7, 0.0, 0.0],    # same place, tiny: invisible
    ])
    n = xyz.shape[0]
    scaling = torch.full((n, 6), math.log(0.01))
    scaling[3, :3] = math.log(0.2)  # 3 sigma = 0.6 world units = 12 px at depth 5
    model = AnchorModel(xyz, torch.zeros(n, 4), torch.zeros(n, 2, 3), scaling,
                        torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.zeros(n, 1))
    mask = visible_anchor_mask(model, look_at_origin_viewmat(), K, 100, 100)
    assert mask.tolist() == [True, False, False, True, False]


def test_camera_center_from_viewmat():
    angle = 0.3
    R = torch.tensor([[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]])
    center = torch.tensor([1.0, 2.0, -3.0])
    viewmat = torch.eye(4)
    viewmat[:3, :3] = R
    viewmat[:3, 3] = -R @ center
    assert torch.allclose(camera_center_from_viewmat(viewmat), center, atol=1e-6)


def test_scaled_gradient_is_the_detach_formula():
    g = torch.Generator().manual_seed(1)
    x = torch.randn(5, 4, generator=g, requires_grad=True)
    upstream = torch.randn(5, 4, generator=g)
    for factor in (0.1, 0.37):
        y = scale_gradient(x, factor)
        assert torch.equal(y, x.detach())
        grad, = torch.autograd.grad(y, x, upstream)
        reference = x.detach() + factor * (x - x.detach())
        ref_grad, = torch.autograd.grad(reference, x, upstream)
        assert torch.equal(grad, ref_grad)
    assert scale_gradient(x, 1.0) is x and not scale_gradient(x, 0.0).requires_grad


def test_uncompacted_rows_hold_the_kept_gaussians_and_zero_opacity_elsewhere():
    model, heads = tiny_model_and_heads()
    cam = torch.tensor([0.3, -2.0, 5.0])
    visible = torch.tensor([True, False, True])
    kept = generate_neural_gaussians(model, heads, cam, visible)
    rows = generate_neural_gaussians(model, heads, cam, visible, anchor_index=torch.tensor([0, 2]), compact=False)
    assert kept["compacted"] and not rows["compacted"]
    assert rows["means"].shape == (4, 3) and torch.equal(rows["mask"], torch.tensor([True, False] * 2))
    assert torch.equal(rows["anchor_index"], torch.tensor([0, 0, 2, 2]))
    for key in ("means", "quats", "scales", "colors", "opacities", "anchor_index"):
        assert torch.equal(rows[key][rows["mask"]], kept[key]), key
    assert torch.equal(rows["opacities"][~rows["mask"]], torch.zeros(2))
    assert torch.allclose(volume_loss(rows["scales"], rows["mask"]), volume_loss(kept["scales"]))


def test_anchor_index_needs_the_mask_it_indexes():
    model, heads = tiny_model_and_heads()
    with pytest.raises(ValueError, match="visible_mask"):
        generate_neural_gaussians(model, heads, torch.zeros(3), anchor_index=torch.tensor([0, 2]))
