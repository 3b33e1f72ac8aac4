"""Heads: Scaffold-GS's exact layer shapes, the feature bank, the input layout."""

import pytest
import torch
from torch import nn

from securegs_warp.model import ScaffoldHeads


def linear_shapes(module: nn.Sequential):
    return [(tuple(m.weight.shape), tuple(m.bias.shape)) for m in module if isinstance(m, nn.Linear)]


def test_default_head_shapes_match_scaffold_gs():
    heads = ScaffoldHeads(feat_dim=32, n_offsets=10)
    assert linear_shapes(heads.opacity_mlp) == [((32, 35), (32,)), ((10, 32), (10,))]
    assert linear_shapes(heads.cov_mlp) == [((32, 35), (32,)), ((70, 32), (70,))]
    assert linear_shapes(heads.color_mlp) == [((32, 35), (32,)), ((30, 32), (30,))]
    assert [type(m) for m in heads.opacity_mlp] == [nn.Linear, nn.ReLU, nn.Linear, nn.Tanh]
    assert [type(m) for m in heads.cov_mlp] == [nn.Linear, nn.ReLU, nn.Linear]
    assert [type(m) for m in heads.color_mlp] == [nn.Linear, nn.ReLU, nn.Linear, nn.Sigmoid]
    assert heads.feature_bank_mlp is None and heads.embedding_appearance is None
    assert sorted(heads.opacity_mlp.state_dict()) == ["0.bias", "0.weight", "2.bias", "2.weight"]


def test_optional_inputs_change_exactly_the_first_layer():
    heads = ScaffoldHeads(32, 10, use_feat_bank=True, appearance_dim=32, num_cameras=7,
                          add_opacity_dist=True, add_cov_dist=True, add_color_dist=True)
    assert linear_shapes(heads.opacity_mlp) == [((32, 36), (32,)), ((10, 32), (10,))]
    assert linear_shapes(heads.cov_mlp) == [((32, 36), (32,)), ((70, 32), (70,))]
    assert linear_shapes(heads.color_mlp) == [((32, 68), (32,)), ((30, 32), (30,))]
    assert linear_shapes(heads.feature_bank_mlp) == [((32, 4), (32,)), ((3, 32), (3,))]
    assert isinstance(heads.feature_bank_mlp[3], nn.Softmax) and heads.feature_bank_mlp[3].dim == 1
    assert heads.embedding_appearance.weight.shape == (7, 32)
    only_color = ScaffoldHeads(32, 10, add_color_dist=True)
    assert linear_shapes(only_color.opacity_mlp)[0][0] == (32, 35)
    assert linear_shapes(only_color.color_mlp)[0][0] == (32, 36)


def test_feature_bank_weights_sum_to_one_and_blend_as_scaffold_gs():
    torch.manual_seed(0)
    heads = ScaffoldHeads(8, 3, use_feat_bank=True)
    n = 5
    view = torch.nn.functional.normalize(torch.randn(n, 3), dim=1)
    dist = torch.rand(n, 1) * 4
    w = heads.bank_weights(view, dist)
    assert w.shape == (n, 3) and torch.all(w > 0)
    assert torch.allclose(w.sum(1), torch.ones(n))
    feat = torch.randn(n, 8)
    blended = heads.blend_features(feat, view, dist)
    for a in range(n):
        for c in range(8):
            # channel c reads channel 4*(c % 2) of the coarse level (8/4 = 2 channels, tiled 4x),
            # channel 2*(c % 4) of the middle level (4 channels, tiled 2x), and itself.
            expected = w[a, 0] * feat[a, 4 * (c % 2)] + w[a, 1] * feat[a, 2 * (c % 4)] + w[a, 2] * feat[a, c]
            assert torch.allclose(blended[a, c], expected, atol=1e-6)
    assert ScaffoldHeads(8, 3).blend_features(feat, view, dist) is feat


def test_forward_input_layout_and_output_shapes():
    torch.manual_seed(1)
    heads = ScaffoldHeads(8, 3, appearance_dim=4, num_cameras=2, add_opacity_dist=True)
    n = 6
    feat, view, dist = torch.randn(n, 8), torch.randn(n, 3), torch.rand(n, 1)
    opacity, cov, color = heads(feat, view, dist, camera_index=1)
    assert opacity.shape == (n, 3) and cov.shape == (n, 3, 7) and color.shape == (n, 3, 3)
    # inputs concatenated as [feature, view, distance] and [feature, view, appearance]
    assert torch.allclose(opacity, heads.opacity_mlp(torch.cat([feat, view, dist], 1)))
    appearance = heads.embedding_appearance.weight[1].expand(n, 4)
    assert torch.allclose(color.reshape(n, 9), heads.color_mlp(torch.cat([feat, view, appearance], 1)))
    assert torch.allclose(cov.reshape(n, 21), heads.cov_mlp(torch.cat([feat, view], 1)))
    with pytest.raises(ValueError, match="camera_index"):
        heads(feat, view, dist)


def test_invalid_options_are_refused():
    with pytest.raises(ValueError, match="divisible by 4"):
        ScaffoldHeads(30, 10, use_feat_bank=True)
    with pytest.raises(ValueError, match="num_cameras"):
        ScaffoldHeads(32, 10, appearance_dim=32)


@pytest.mark.parametrize("options", [{}, {"add_cov_dist": True}, {"width": 24}])
def test_shared_first_layer_is_each_head_on_its_own(options):
    """Heads that read one input run their first layers as one stacked matmul: the outputs and every
    gradient are those of each MLP applied on its own (Scaffold-GS's order), up to float rounding."""
    torch.manual_seed(0)
    heads = ScaffoldHeads(8, 4, **options)
    g = torch.Generator().manual_seed(1)
    feat = torch.randn(50, 8, generator=g, requires_grad=True)
    ob_view = torch.nn.functional.normalize(torch.randn(50, 3, generator=g), dim=1)
    ob_dist = torch.rand(50, 1, generator=g) + 1.0
    outputs = heads(feat, ob_view, ob_dist)
    with_view, with_dist = torch.cat([feat, ob_view], 1), torch.cat([feat, ob_view, ob_dist], 1)
    reference = (heads.opacity_mlp(with_view), heads.cov_mlp(with_dist if heads.add_cov_dist else with_view),
                 heads.color_mlp(with_view))
    params = [feat, *heads.parameters()]
    weights = [torch.randn(o.shape, generator=g) for o in outputs]
    grads = torch.autograd.grad(sum((o * w).sum() for o, w in zip(outputs, weights)), params)
    ref_grads = torch.autograd.grad(sum((r.reshape(o.shape) * w).sum()
                                        for r, o, w in zip(reference, outputs, weights)), params)
    for out, ref in zip(outputs, reference):
        assert float((out.reshape(ref.shape) - ref).abs().max()) < 1e-6
    for grad, ref in zip(grads, ref_grads):
        assert float((grad - ref).abs().max()) < 1e-5 * max(1.0, float(ref.abs().max()))
