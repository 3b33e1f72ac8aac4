"""Anchors: voxelisation, Scaffold-GS initialisation, pruning/adding with Adam state, growing."""

import math

import numpy as np
import pytest
import torch

from securegs_warp.model import (
    ANCHOR_PARAM_NAMES,
    AnchorModel,
    anchor_param_groups,
    growth_candidates,
    mean_sq_knn_distance,
    voxel_size_from_points,
    voxelize,
)


def brute_mean_sq_knn(points: np.ndarray, k: int = 3) -> np.ndarray:
    d2 = ((points[:, None, :] - points[None, :, :]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    return np.sort(d2, axis=1)[:, :k].mean(axis=1)


def test_voxelize_gives_unique_rounded_centres():
    rng = np.random.default_rng(0)
    points = rng.uniform(-1, 1, size=(2000, 3))
    voxel = 0.25
    centres = voxelize(torch.from_numpy(points), voxel)
    expected = np.unique(np.round(points / voxel), axis=0) * voxel
    assert centres.dtype == torch.float32
    assert torch.unique(centres, dim=0).shape[0] == centres.shape[0]
    np.testing.assert_allclose(centres.numpy(), expected.astype(np.float32))
    # every point lies within half a voxel of some centre
    dist = torch.cdist(torch.from_numpy(points).float(), centres).min(dim=1).values
    assert float(dist.max()) <= voxel * math.sqrt(3) / 2 + 1e-6


def test_voxel_size_is_scaffold_gs_median_of_mean_squared_3nn_distance():
    rng = np.random.default_rng(1)
    points = rng.uniform(0, 2, size=(101, 3))
    sq = brute_mean_sq_knn(points)
    np.testing.assert_allclose(mean_sq_knn_distance(torch.from_numpy(points)).numpy(), sq, rtol=1e-6)
    # torch.kthvalue(x, int(P * 0.5)): the 50th smallest of 101 values (1-based)
    assert voxel_size_from_points(torch.from_numpy(points)) == pytest.approx(np.sort(sq)[49], rel=1e-6)


def test_from_points_initialises_like_scaffold_gs():
    rng = np.random.default_rng(2)
    points = rng.uniform(0, 1, size=(400, 3))
    model = AnchorModel.from_points(points, voxel_size=0.1, feat_dim=32, n_offsets=10)
    n = model.num_anchors
    assert model.voxel_size == 0.1
    expected_xyz = np.unique(np.round(points / 0.1), axis=0) * 0.1
    np.testing.assert_allclose(model.xyz.detach().numpy(), expected_xyz.astype(np.float32))
    assert model.feat.shape == (n, 32) and not model.feat.any()
    assert model.offsets.shape == (n, 10, 3) and not model.offsets.any()
    expected_log = np.log(np.sqrt(np.maximum(brute_mean_sq_knn(model.xyz.detach().numpy().astype(np.float64)), 1e-7)))
    np.testing.assert_allclose(model.scaling.detach().numpy(), np.repeat(expected_log[:, None], 6, axis=1), rtol=1e-5)
    assert torch.equal(model.rotation, torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1))
    assert torch.allclose(torch.sigmoid(model.opacity), torch.full((n, 1), 0.1))
    assert [getattr(model, name).requires_grad for name in ANCHOR_PARAM_NAMES] == [True, True, True, True, False, False]


def test_from_points_derives_voxel_size_when_not_positive():
    points = torch.rand(300, 3, generator=torch.Generator().manual_seed(3))
    model = AnchorModel.from_points(points, voxel_size=0.0)
    assert model.voxel_size == pytest.approx(voxel_size_from_points(points))


def _model_with_adam(n=12, k=4, d=8, seed=0):
    g = torch.Generator().manual_seed(seed)
    model = AnchorModel(
        xyz=torch.randn(n, 3, generator=g), feat=torch.randn(n, d, generator=g),
        offsets=torch.randn(n, k, 3, generator=g), scaling=torch.randn(n, 6, generator=g) * 0.1 - 2,
        rotation=torch.randn(n, 4, generator=g), opacity=torch.randn(n, 1, generator=g),
    )
    mlp = torch.nn.Linear(3, 3)
    optimizer = torch.optim.Adam(
        anchor_param_groups(model, dict.fromkeys(ANCHOR_PARAM_NAMES, 1e-3))
        + [{"params": list(mlp.parameters()), "lr": 1e-3, "name": "mlp"}],
        eps=1e-15,
    )
    # one step with row-dependent gradients so that every row's moments differ
    loss = (model.xyz.sum(1) * torch.arange(n)).sum() + (model.feat ** 2).sum() + (model.offsets ** 3).sum() \
        + (model.scaling * torch.arange(n)[:, None]).sum() + mlp(model.xyz).sum()
    loss.backward()
    optimizer.step()
    return model, optimizer, mlp


def _moments(optimizer, param):
    state = optimizer.state[param]
    return state["exp_avg"].clone(), state["exp_avg_sq"].clone()


def test_prune_keeps_adam_state_row_aligned():
    model, optimizer, mlp = _model_with_adam()
    trained = [name for name in ANCHOR_PARAM_NAMES if getattr(model, name).requires_grad]
    before = {
        name: (getattr(model, name).detach().clone(), *_moments(optimizer, getattr(model, name))) for name in trained
    }
    mlp_state = _moments(optimizer, mlp.weight)
    prune = torch.zeros(model.num_anchors, dtype=torch.bool)
    prune[[0, 3, 7]] = True
    model.prune_anchors(prune, optimizer, max_log_gaussian_scale=None)

    keep = ~prune
    held = [p for group in optimizer.param_groups for p in group["params"]]
    for name in ANCHOR_PARAM_NAMES:
        assert any(p is getattr(model, name) for p in held), name
    for name in trained:
        value, exp_avg, exp_avg_sq = before[name]
        param = getattr(model, name)
        assert torch.equal(param.detach(), value[keep])
        assert torch.equal(optimizer.state[param]["exp_avg"], exp_avg[keep])
        assert torch.equal(optimizer.state[param]["exp_avg_sq"], exp_avg_sq[keep])
    assert torch.equal(optimizer.state[mlp.weight]["exp_avg"], mlp_state[0])
    assert not model.rotation.requires_grad and model.rotation.shape == (9, 4)
    # the optimizer still steps with the new shapes
    (model.xyz.sum() + model.feat.sum() + model.offsets.sum() + model.scaling.sum()).backward()
    optimizer.step()


def test_prune_clamps_log_gaussian_scale_like_scaffold_gs():
    model, optimizer, _ = _model_with_adam()
    with torch.no_grad():
        model.scaling[:, 3:] = 1.0
        model.scaling[:, :3] = 2.0
    model.prune_anchors(torch.zeros(model.num_anchors, dtype=torch.bool), optimizer)
    assert torch.all(model.scaling[:, 3:] == 0.05) and torch.all(model.scaling[:, :3] == 2.0)


def test_add_appends_rows_with_zero_moments():
    model, optimizer, _ = _model_with_adam()
    n, g = model.num_anchors, 5
    before = {name: _moments(optimizer, getattr(model, name)) for name in ("xyz", "feat", "offsets", "scaling")}
    rows = {
        "xyz": torch.rand(g, 3), "feat": torch.rand(g, model.feat_dim), "offsets": torch.zeros(g, model.n_offsets, 3),
        "scaling": torch.zeros(g, 6), "rotation": torch.rand(g, 4), "opacity": torch.zeros(g, 1),
    }
    model.add_anchors(**rows, optimizer=optimizer)
    assert model.num_anchors == n + g
    for name, (exp_avg, exp_avg_sq) in before.items():
        param = getattr(model, name)
        assert torch.equal(param.detach()[n:], rows[name])
        assert torch.equal(optimizer.state[param]["exp_avg"][:n], exp_avg)
        assert not optimizer.state[param]["exp_avg"][n:].any()
        assert torch.equal(optimizer.state[param]["exp_avg_sq"][:n], exp_avg_sq)
    with pytest.raises(ValueError, match="feat must have shape"):
        model.add_anchors(**{**rows, "feat": torch.rand(g, model.feat_dim + 1)})


def _grid_scene(voxel=0.1):
    """Anchors on a 3x3x3 grid of coarse (16-voxel) cells' centres, one Gaussian per anchor far out."""
    centres = torch.stack(torch.meshgrid(*[torch.arange(3.0)] * 3, indexing="ij"), -1).reshape(-1, 3) * 16 * voxel
    n, k = centres.shape[0], 4
    gaussians = centres[:, None, :].repeat(1, k, 1) + 0.01  # inside their own anchor's cell
    return centres, gaussians, n, k


def test_growth_candidates_never_duplicate_existing_anchors():
    voxel = 0.1
    anchors, gaussians, n, k = _grid_scene(voxel)
    g = torch.Generator().manual_seed(0)
    # push many Gaussians to random places: some land in occupied cells, some in empty ones
    gaussians = gaussians + torch.randn(n, k, 3, generator=g) * 2.0
    feat = torch.randn(n, 8, generator=g)
    out = growth_candidates(anchors, feat, gaussians, torch.ones(n * k), torch.ones(n * k, dtype=torch.bool),
                            0.5, voxel, generator=g)
    assert out.xyz.shape[0] > 0
    assert out.feat.shape == (out.xyz.shape[0], 8)
    for xyz, cell in zip(out.xyz, out.cell_size):
        assert not torch.any(torch.all(torch.round(anchors / cell) == torch.round(xyz / cell), dim=1))
    assert torch.unique(out.xyz, dim=0).shape[0] == out.xyz.shape[0]
    assert torch.cdist(out.xyz, anchors).min() > 0
    rows = out.anchor_rows(k)
    assert torch.allclose(rows["scaling"], torch.log(out.cell_size)[:, None].repeat(1, 6))
    assert torch.allclose(torch.sigmoid(rows["opacity"]), torch.full((out.xyz.shape[0], 1), 0.1))


def test_growth_feature_is_max_of_parents_and_respects_thresholds():
    voxel = 0.1
    anchors, gaussians, n, k = _grid_scene(voxel)
    target = torch.tensor([5.0, 5.0, 5.0]) * 16 * voxel  # an empty coarse cell
    gaussians = gaussians.clone()
    gaussians[0] = target  # all k Gaussians of anchors 0 and 1 move there
    gaussians[1] = target + 0.02
    feat = torch.zeros(n, 2)
    feat[0] = torch.tensor([1.0, -3.0])
    feat[1] = torch.tensor([-2.0, 4.0])
    grads = torch.ones(n * k)
    mask = torch.ones(n * k, dtype=torch.bool)
    seeded = torch.Generator().manual_seed
    out = growth_candidates(anchors, feat, gaussians, grads, mask, 0.5, voxel, generator=seeded(1))
    assert out.xyz.shape[0] == 1
    assert torch.allclose(out.xyz[0], target) and out.cell_size[0] == pytest.approx(16 * voxel)
    assert torch.equal(out.feat[0], torch.tensor([1.0, 4.0]))
    # per-Gaussian thresholds: anchor 0 and 1's Gaussians above their threshold -> nothing grows
    threshold = torch.full((n * k,), 0.5)
    threshold[: 2 * k] = 2.0
    none = growth_candidates(anchors, feat, gaussians, grads, mask, threshold, voxel, generator=seeded(1))
    assert none.xyz.shape == (0, 3)
    # masked-out Gaussians are never candidates
    none = growth_candidates(anchors, feat, gaussians, grads, torch.zeros_like(mask), 0.5, voxel)
    assert none.xyz.shape == (0, 3)


def test_growth_skips_finer_levels_when_the_coarsest_adds_nothing():
    """Scaffold-GS's `if length_inc == 0: if i > 0: continue`: reproduced on purpose."""
    voxel = 0.1
    anchors, gaussians, n, k = _grid_scene(voxel)
    # Gaussians 3 voxels away from their anchor: same coarse (16-voxel) cell, new 1-voxel cell.
    gaussians = gaussians + 3 * voxel
    out = growth_candidates(anchors, torch.zeros(n, 4), gaussians, torch.full((n * k,), 100.0),
                            torch.ones(n * k, dtype=torch.bool), 0.5, voxel, generator=torch.Generator().manual_seed(0))
    assert out.xyz.shape == (0, 3)
