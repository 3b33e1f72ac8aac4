"""Plain 3DGS on this engine: the model, its PLY, 3DGS's densification, training, resume and the CLI."""
import json
import math

import numpy as np
import plyfile
import pytest
import torch

from securegs_warp.cli import main
from securegs_warp.config import GaussiansConfig, RunConfig, SecureConfig, TrainConfig
from securegs_warp.data import make_synthetic_scene
from securegs_warp.gaussians import GAUSSIAN_PARAM_NAMES, GaussianModel, sh_basis
from securegs_warp.io import read_3dgs_ply
from securegs_warp.rasterizer import RasterOptions
from securegs_warp.strategies import GaussianStrategy
from securegs_warp.train import GaussianTrainer

CPU_RASTER = RasterOptions(tile_size=8)
TINY = ["--width", "40", "--height", "30", "--train-views", "6", "--test-views", "2"]


@pytest.fixture(scope="module")
def tiny_scene():
    return make_synthetic_scene(width=40, height=30, n_train=6, n_test=2, n_points=600)


def _random_model(n=5, sh_degree=3, channels=3, seed=0) -> GaussianModel:
    g = torch.Generator().manual_seed(seed)
    rest = 0 if sh_degree is None else (sh_degree + 1) ** 2 - 1
    return GaussianModel(torch.randn(n, 3, generator=g), torch.randn(n, 3, generator=g) - 3,
                         torch.randn(n, 4, generator=g), torch.randn(n, generator=g),
                         torch.randn(n, channels, generator=g), torch.randn(n, rest, channels, generator=g),
                         sh_degree=sh_degree)


@pytest.mark.parametrize("sh_degree,channels", [(3, 3), (1, 3), (0, 3), (None, 16)])
def test_ply_round_trip_is_exact(tmp_path, sh_degree, channels):
    model = _random_model(sh_degree=sh_degree, channels=channels)
    model.save(tmp_path / "m")
    back = GaussianModel.load(tmp_path / "m", sh=sh_degree is not None)
    assert back.sh_degree == sh_degree
    for name in GAUSSIAN_PARAM_NAMES:
        expected = getattr(model, name).detach()
        if name == "quats":  # stored normalised, as 3DGS viewers expect
            expected = torch.nn.functional.normalize(expected, dim=1)
        assert torch.allclose(getattr(back, name), expected, atol=1e-6), name


def test_ply_is_the_standard_3dgs_layout(tmp_path):
    model = _random_model(sh_degree=3)
    model.save_ply(tmp_path / "p.ply")
    names = [p.name for p in plyfile.PlyData.read(str(tmp_path / "p.ply"))["vertex"].properties]
    assert names == (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                     + [f"f_rest_{i}" for i in range(45)] + ["opacity", "scale_0", "scale_1", "scale_2",
                                                             "rot_0", "rot_1", "rot_2", "rot_3"])
    # 3DGS writes features_rest transposed: all of red's 15 coefficients, then green's, then blue's.
    vertex = plyfile.PlyData.read(str(tmp_path / "p.ply"))["vertex"]
    assert np.allclose(vertex["f_rest_15"], model.features_rest[:, 0, 1].detach().numpy(), atol=1e-6)
    # The degree-0 reader of exports sees the same Gaussians.
    plain = read_3dgs_ply(tmp_path / "p.ply")
    assert torch.allclose(plain["opacities"], torch.sigmoid(model.opacity_logits.detach()), atol=1e-6)


def test_ply_with_a_wrong_coefficient_count_is_refused(tmp_path):
    model = _random_model(sh_degree=1)
    model.save_ply(tmp_path / "p.ply")
    with pytest.raises(ValueError, match="raw feature field"):
        GaussianModel.load(tmp_path / "p.ply", sh=False)
    with pytest.raises(ValueError, match="features_rest must have shape"):
        GaussianModel(*(getattr(model, n).detach() for n in GAUSSIAN_PARAM_NAMES[:5]), torch.zeros(5, 5, 3),
                      sh_degree=1)


def test_sh_colours_match_the_degree_zero_colour_and_vary_with_view():
    model = _random_model(n=50, sh_degree=3)
    center = torch.tensor([0.0, 0.0, -5.0])
    dc_only = (0.28209479177387814 * model.features_dc + 0.5).clamp_min(0)
    assert torch.allclose(model.colors(center, sh_degree=0), dc_only)
    assert not torch.allclose(model.colors(center), model.colors(torch.tensor([5.0, 0.0, 0.0])))
    # The basis is orthonormal on the sphere: its Gram matrix by Monte Carlo is close to identity / 4π.
    dirs = torch.nn.functional.normalize(torch.randn(200_000, 3, generator=torch.Generator().manual_seed(1)), dim=1)
    basis = sh_basis(3, dirs)
    gram = basis.T @ basis / dirs.shape[0] * 4 * math.pi
    assert torch.allclose(gram, torch.eye(16), atol=0.03)


def test_view_dependent_colour_sends_a_gradient_to_the_means():
    # As in 3DGS and gsplat, the view direction of SH degree ≥ 1 depends on the mean.
    model = _random_model(n=20, sh_degree=2)
    model.colors(torch.tensor([0.0, 0.0, -5.0])).sum().backward()
    assert model.means.grad is not None and model.means.grad.abs().sum() > 0


def test_raw_feature_field_renders_c_channels(tiny_scene):
    model = _random_model(n=200, sh_degree=None, channels=16)
    with torch.no_grad():
        model.means.copy_(torch.as_tensor(tiny_scene.points[:200]))
    out = model.render(tiny_scene.train[0], CPU_RASTER)
    assert out["image"].shape == (30, 40, 16)
    assert torch.equal(out["gaussians"]["colors"], model.features_dc)


# -- densification -----------------------------------------------------------------------------


def _densify_case():
    """Four Gaussians: 0 small with a high gradient (clone), 1 large with a high gradient (split),
    2 small with a low gradient (kept), 3 with a low gradient and opacity below prune_opa (pruned)."""
    n = 4
    log_scales = torch.log(torch.tensor([[0.005] * 3, [0.5, 0.2, 0.1], [0.005] * 3, [0.005] * 3]))
    quats = torch.tensor([[1.0, 0, 0, 0], [0.8, 0.6, 0, 0], [1.0, 0, 0, 0], [1.0, 0, 0, 0]])
    opacity = torch.logit(torch.tensor([0.5, 0.6, 0.7, 0.001]))
    model = GaussianModel(torch.arange(n * 3, dtype=torch.float32).view(n, 3), log_scales, quats, opacity,
                          torch.rand(n, 3), sh_degree=1)
    optimizer = torch.optim.Adam([{"params": [getattr(model, p)], "name": p} for p in GAUSSIAN_PARAM_NAMES])
    for p in model.parameters():  # give every Gaussian Adam moments so their rows can be followed
        p.grad = torch.ones_like(p)
    optimizer.step()
    strategy = GaussianStrategy(scene_scale=1.0)  # grow_scale3d 0.01: scale 0.005 small, 0.5 large
    state = strategy.initialize_state(model)
    state["grad2d"] += torch.tensor([0.001, 0.001, 0.0001, 0.0001]) * 3
    state["count"] += 3
    return model, optimizer, strategy, state


def test_refine_clones_small_splits_large_and_prunes_transparent():
    model, optimizer, strategy, state = _densify_case()
    before = {name: getattr(model, name).detach().clone() for name in GAUSSIAN_PARAM_NAMES}
    changed = strategy.refine(model, optimizer, state, step=600, generator=torch.Generator().manual_seed(0))
    assert changed == {"cloned": 1, "split": 1, "pruned": 1}
    # Rows: kept originals 0 and 2 (1 was split, 3 pruned), the clone of 0, then 1's two children.
    assert model.num_gaussians == 5
    assert torch.equal(model.means[:2], before["means"][[0, 2]])
    assert torch.equal(model.means[2], before["means"][0])  # the clone: an exact copy
    assert torch.equal(model.features_rest[2], before["features_rest"][0])
    children = model.means[3:].detach()
    assert torch.allclose(model.log_scales[3:], (before["log_scales"][1] - math.log(1.6)).expand(2, 3))
    assert not torch.equal(children[0], children[1])
    # Children are samples of the parent: within a few of its (rotated) standard deviations.
    assert ((children - before["means"][1]).norm(dim=1) < 4 * 0.5).all()
    # Adam's moments stay row-aligned: old rows keep theirs, new rows start at zero.
    moments = optimizer.state[model.means]["exp_avg"]
    assert moments.shape == (5, 3) and (moments[:2] != 0).all() and (moments[2:] == 0).all()
    assert all(v.shape[0] == 5 and not v.any() for v in state.values())


def test_large_gaussians_are_pruned_only_after_the_first_reset():
    model, optimizer, strategy, _ = _densify_case()
    with torch.no_grad():
        model.log_scales[1] = math.log(0.5)  # above prune_scale3d (0.1) · scene scale
    assert strategy.prune(model, optimizer, step=strategy.reset_every) == 1  # only the transparent one
    assert strategy.prune(model, optimizer, step=strategy.reset_every + 1) == 1  # now the large one
    assert model.num_gaussians == 2


def test_opacity_reset_clamps_and_clears_moments():
    model, optimizer, strategy, _ = _densify_case()
    strategy.reset_opacity(model, optimizer)
    assert torch.sigmoid(model.opacity_logits).max() <= 2 * strategy.prune_opa + 1e-6
    assert not optimizer.state[model.opacity_logits]["exp_avg"].any()


def test_schedule_scaling():
    s = GaussianStrategy().scaled_to(3000)
    assert (s.refine_start, s.refine_stop, s.refine_every) == (50, 1500, 20)
    assert s.reset_every == 600  # at least 30 refinements per reset
    full = GaussianStrategy().scaled_to(30_000)
    assert (full.refine_start, full.refine_stop, full.refine_every, full.reset_every) == (500, 15000, 100, 3000)


# -- training ----------------------------------------------------------------------------------


def _train(scene, iterations, steps=None, **gaussians):
    config = TrainConfig(iterations=iterations, raster=CPU_RASTER, model="3dgs",
                         gaussians=GaussiansConfig(**gaussians))
    trainer = GaussianTrainer(scene, config)
    for _ in range(iterations if steps is None else steps):
        trainer.step()
    return trainer


def test_training_raises_psnr_and_densifies(tiny_scene):
    trainer = GaussianTrainer(tiny_scene, TrainConfig(iterations=150, raster=CPU_RASTER, model="3dgs"))
    start = trainer.evaluate(timing_repeats=1)["psnr"]
    changes = [trainer.step() for _ in range(150)]
    end = trainer.evaluate(timing_repeats=1)
    # Measured on this scene: 12.5 dB at the start, 19.0 dB after 150 steps.
    assert end["psnr"] > 17.5 and end["psnr"] > start + 5.0
    assert sum(c.get("cloned", 0) + c.get("split", 0) for c in changes) > 0
    assert trainer.active_sh_degree() == 3 and end["gaussians"] == trainer.model.num_gaussians


def test_resume_matches_uninterrupted_run(tiny_scene, tmp_path):
    straight = _train(tiny_scene, 60)
    first = _train(tiny_scene, 60, steps=41)  # past a refinement (step 40) with its random splits
    first.save_checkpoint(tmp_path / "ckpt.pt")
    resumed = GaussianTrainer(tiny_scene, TrainConfig(iterations=60, raster=CPU_RASTER, model="3dgs"))
    resumed.load_checkpoint(tmp_path / "ckpt.pt")
    for _ in range(19):
        resumed.step()
    for name in GAUSSIAN_PARAM_NAMES:
        assert torch.allclose(getattr(resumed.model, name), getattr(straight.model, name), atol=1e-6), name
    other = GaussianTrainer(tiny_scene, TrainConfig(iterations=60, raster=CPU_RASTER, model="3dgs",
                                                    gaussians=GaussiansConfig(sh_degree=1)))
    with pytest.raises(ValueError, match="gaussians.sh_degree differs"):
        other.load_checkpoint(tmp_path / "ckpt.pt")


def test_secure_config_refuses_a_3dgs_model():
    with pytest.raises(ValueError, match="Scaffold-GS"):
        RunConfig(train=TrainConfig(model="3dgs"), secure=SecureConfig())
    with pytest.raises(ValueError, match="model must be one of"):
        TrainConfig(model="nerf")


def test_cli_train_eval_render_export(tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["train", "--model", "3dgs", "--sh-degree", "1", "--out", str(run), "--iterations", "40", "--quiet",
                 *TINY]) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    model = GaussianModel.load(run / "model")
    assert model.sh_degree == 1 and model.num_gaussians == metrics["gaussians"]
    assert metrics["psnr"] > 12 and metrics["size_mb"] > 0
    assert main(["eval", str(run)]) == 0
    assert json.loads((run / "eval.json").read_text())["psnr"] == pytest.approx(metrics["psnr"], abs=1e-4)
    assert main(["render", str(run), "--out", str(tmp_path / "r")]) == 0
    assert len(list((tmp_path / "r" / "renders").iterdir())) == 2
    assert main(["export", str(run), "--out", str(tmp_path / "e.ply")]) == 0
    assert read_3dgs_ply(tmp_path / "e.ply")["means"].shape[0] == model.num_gaussians
    assert main(["train", "--model", "nerf", "--out", str(tmp_path / "x"), *TINY]) == 2
    assert "model must be one of" in capsys.readouterr().err
