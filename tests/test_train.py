"""Training: losses, the densification strategy's invariants, checkpoints, resume and the CLI."""
import dataclasses
import json

import pytest
import torch

from securegs_warp.cli import main
from securegs_warp.data import make_synthetic_scene
from securegs_warp.io import load_scaffold
from securegs_warp.raster_cases import TEST_DEVICE
from securegs_warp.rasterizer import RasterOptions
from securegs_warp.train import ScaffoldStrategy, ScaffoldTrainer, TrainConfig, photometric_loss, psnr, ssim, volume_loss
from securegs_warp.train.losses import batch_photometric_loss, batch_ssim
from securegs_warp.train.base import nonfinite_gradient_counts
from securegs_warp.render import camera_tensors

CPU_RASTER = RasterOptions(tile_size=8)
TINY = ["--width", "40", "--height", "30", "--train-views", "6", "--test-views", "2"]


@pytest.fixture(scope="module")
def tiny_scene():
    return make_synthetic_scene(width=40, height=30, n_train=6, n_test=2, n_points=600)


def test_ssim_and_psnr():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(20, 24, 3, generator=g)
    assert abs(float(ssim(a, a)) - 1.0) < 1e-6
    noise = torch.randn(20, 24, 3, generator=g)
    mild, strong = float(ssim((a + 0.1 * noise).clamp(0, 1), a)), float(ssim((a + 0.3 * noise).clamp(0, 1), a))
    assert 0.0 < strong < mild < 0.99
    assert abs(psnr(torch.full((4, 4, 3), 0.5), torch.full((4, 4, 3), 0.6)) - 20.0) < 1e-4
    with pytest.raises(ValueError, match="ssim"):
        ssim(a, a[:10])


def ssim_2d_float64(image, target):
    """3DGS's SSIM as it writes it: five convolutions with the 11×11 window, in float64."""
    x = torch.arange(11, dtype=torch.float64) - 5
    g = torch.exp(-(x**2) / (2 * 1.5**2))
    g = g / g.sum()
    c = image.shape[-1]
    w = (g[:, None] @ g[None, :]).expand(c, 1, 11, 11)
    a, b = (t.double().permute(2, 0, 1)[None] for t in (image, target))
    blur = lambda t: torch.nn.functional.conv2d(t, w, padding=5, groups=c)  # noqa: E731
    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b, cov = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2, blur(a * b) - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    return (((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))).mean()


@pytest.mark.parametrize("shape", [(20, 24, 3), (9, 33, 1), (31, 17, 4)])
def test_separable_ssim_is_the_2d_one(shape):
    g = torch.Generator().manual_seed(len(shape) + shape[0])
    a = torch.rand(shape, generator=g).to(TEST_DEVICE).requires_grad_(True)
    b = (a.detach().cpu() + 0.2 * torch.randn(shape, generator=g)).clamp(0, 1)
    a64 = a.detach().cpu().double().requires_grad_(True)
    value, ref = ssim(a, b.to(TEST_DEVICE)), ssim_2d_float64(a64, b)
    # float32 rounding only (measured ~2e-8 on the value, ~1e-6 relative on the gradient).
    assert abs(float(value.detach()) - float(ref.detach())) < 1e-6
    value.backward()
    ref.backward()
    assert float((a.grad.cpu().double() - a64.grad).abs().max()) < 1e-4 * float(a64.grad.abs().max())


def test_batch_ssim_gradient_is_each_image_s_2d_one():
    # Images of one batch are blurred apart (no window reaches across the image boundary) and each
    # gets its own share of the upstream gradient.
    g = torch.Generator().manual_seed(5)
    a = torch.rand(2, 13, 21, 4, generator=g).to(TEST_DEVICE).requires_grad_(True)
    b = (a.detach().cpu() + 0.3 * torch.randn(a.shape, generator=g)).clamp(0, 1)
    weights = torch.tensor([0.3, -1.7])
    (batch_ssim(a, b.to(TEST_DEVICE)) * weights.to(TEST_DEVICE)).sum().backward()
    for i in range(2):
        a64 = a[i].detach().cpu().double().requires_grad_(True)
        (float(weights[i]) * ssim_2d_float64(a64, b[i])).backward()
        assert float((a.grad[i].cpu().double() - a64.grad).abs().max()) < 1e-4 * float(a64.grad.abs().max())
    with pytest.raises(ValueError, match="targets detached"):
        batch_ssim(a, b.clone().requires_grad_(True))


@pytest.mark.parametrize("value", [0.0, 1.0])
def test_ssim_of_flat_images_is_one_with_a_finite_gradient(value):
    # Zero variance everywhere: only C1 and C2 keep the quotient defined.
    a = torch.full((12, 16, 3), value, requires_grad=True)
    s = ssim(a, torch.full((12, 16, 3), value))
    s.backward()
    assert abs(s.item() - 1.0) < 1e-6 and bool(torch.isfinite(a.grad).all())


def test_schedule_scales_with_run_length():
    s = ScaffoldStrategy.for_iterations(3000)
    assert (s.start_stat, s.update_from, s.update_until) == (50, 150, 1500)
    assert s.update_interval == 20  # floor: growing needs enough views per interval


def _train(scene, iterations, steps=None, **config):
    trainer = ScaffoldTrainer(scene, TrainConfig(iterations=iterations, raster=CPU_RASTER, **config))
    for _ in range(iterations if steps is None else steps):
        trainer.step()
    return trainer


def test_strategy_keeps_statistics_aligned_with_anchors(tiny_scene):
    # min_opacity is per view and summed over an anchor's k Gaussians. At 0.5, whether any anchor
    # falls below it within 40 steps hangs on the seed and on the machine's float rounding; 1 is
    # far enough inside the initial opacities that pruning does not.
    strategy = ScaffoldStrategy(start_stat=0, update_from=0, update_interval=5, update_until=100,
                                grad_threshold=1e-5, min_opacity=1.0)
    trainer = ScaffoldTrainer(tiny_scene, TrainConfig(iterations=40, raster=CPU_RASTER), strategy=strategy)
    grown = pruned = 0
    for _ in range(40):
        changed = trainer.step()
        grown += changed.get("grown", 0)
        pruned += changed.get("pruned", 0)
        n, k = trainer.model.anchors.num_anchors, trainer.model.anchors.n_offsets
        state = trainer.strategy_state
        assert state["grad_accum"].shape == (n * k,) and state["anchor_denom"].shape == (n,)
        for group in trainer.optimizer.param_groups:
            for p in group["params"]:
                moments = trainer.optimizer.state.get(p, {})
                if "exp_avg" in moments:
                    assert moments["exp_avg"].shape == p.shape, group.get("name")
    assert grown > 0 and pruned > 0  # a low threshold grows, a high min opacity prunes
    xyz = trainer.model.anchors.xyz
    assert torch.unique(xyz, dim=0).shape[0] == xyz.shape[0]  # growing never duplicates an anchor


def test_the_schedule_window():
    # start_stat < step <= update_until (Scaffold-GS's ends before update_until: design.md says why not).
    strategy = ScaffoldStrategy(start_stat=0, update_from=0, update_interval=5, update_until=10)
    assert [s for s in range(12) if strategy.gathers_at(s)] == list(range(1, 11))


def test_learning_rate_pairs_are_checked():
    with pytest.raises(ValueError, match=r"mlp_cov_lr must be positive \(or all 0: frozen\), got \(0.004, 0.0\)"):
        TrainConfig(mlp_cov_lr=(0.004, 0.0))
    assert TrainConfig(feature_lr=0.0).feature_lr == 0.0


def test_training_reduces_loss(tiny_scene):
    trainer = ScaffoldTrainer(tiny_scene, TrainConfig(iterations=60, raster=CPU_RASTER))
    before = trainer.evaluate(timing_repeats=1)["psnr"]
    for _ in range(60):
        trainer.step()
    after = trainer.evaluate(timing_repeats=1)["psnr"]
    assert after > before + 3.0, (before, after)


def test_resume_after_interruption_matches_uninterrupted_run(tiny_scene, tmp_path):
    straight = _train(tiny_scene, 24)
    first = _train(tiny_scene, 24, steps=13)
    first.save_checkpoint(tmp_path / "ckpt.pt")
    resumed = ScaffoldTrainer(tiny_scene, TrainConfig(iterations=24, raster=CPU_RASTER))
    resumed.load_checkpoint(tmp_path / "ckpt.pt")
    assert resumed.step_count == 13
    for _ in range(11):
        resumed.step()
    for name in ("xyz", "feat", "offsets", "scaling"):
        assert torch.allclose(getattr(resumed.model.anchors, name), getattr(straight.model.anchors, name), atol=1e-6), name
    cam = tiny_scene.test[0]
    with torch.no_grad():
        assert torch.allclose(resumed.render(cam)["image"], straight.render(cam)["image"], atol=1e-5)


def test_checkpoint_with_other_options_is_refused(tiny_scene, tmp_path):
    _train(tiny_scene, 4).save_checkpoint(tmp_path / "ckpt.pt")
    other = ScaffoldTrainer(tiny_scene, TrainConfig(iterations=5, raster=CPU_RASTER))
    with pytest.raises(ValueError, match="other training options"):
        other.load_checkpoint(tmp_path / "ckpt.pt")


def test_cli_train_eval_render_export_and_resume(tmp_path, monkeypatch):
    run = tmp_path / "run"
    args = ["train", "--out", str(run), "--iterations", "30", "--quiet", "--checkpoint-every", "10", *TINY]

    # Interrupt at step 17: a checkpoint is written and the exit code says so.
    real_step = ScaffoldTrainer.step

    def interrupted(self):
        if self.step_count == 17:
            raise KeyboardInterrupt
        return real_step(self)

    monkeypatch.setattr(ScaffoldTrainer, "step", interrupted)
    assert main(args) == 130
    monkeypatch.setattr(ScaffoldTrainer, "step", real_step)
    assert torch.load(run / "checkpoint.pt", weights_only=True)["step"] == 17
    assert main(args) == 2  # the folder holds a run: neither --resume nor --force given
    assert main(args + ["--resume"]) == 0

    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["psnr"] > 12 and 0 < metrics["ssim"] <= 1 and metrics["fps"] > 0 and metrics["size_mb"] > 0
    assert metrics["lpips"] is None or metrics["lpips"] >= 0
    assert metrics["split"] == "test"  # held-out views; "train" where a scene holds none out
    steps = [json.loads(line)["step"] for line in (run / "log.jsonl").read_text().splitlines()]
    assert steps[-1] == 30
    assert sorted(p.name for p in (run / "renders").iterdir()) == ["test_000.png", "test_001.png"]

    model, heads = load_scaffold(run / "model")
    assert model.num_anchors == metrics["anchors"]
    assert main(["eval", str(run)]) == 0
    assert json.loads((run / "eval.json").read_text())["psnr"] == pytest.approx(metrics["psnr"], abs=1e-4)
    assert main(["render", str(run), "--split", "train", "--out", str(tmp_path / "r")]) == 0
    assert len(list((tmp_path / "r" / "renders").iterdir())) == 6
    assert main(["export", str(run), "--out", str(tmp_path / "x.ply")]) == 0
    assert (tmp_path / "x.ply").stat().st_size > 1000


def test_cli_reports_bad_scene(tmp_path, capsys):
    assert main(["train", "--scene", str(tmp_path / "missing"), "--out", str(tmp_path / "r"), "--quiet"]) == 2
    assert "missing" in capsys.readouterr().err


@pytest.mark.parametrize("entries,expected", [
    ([1.0, -2.0], {}),
    ([3e38, 3e38], {}),  # finite, though their L1 norm overflows to inf: counted exactly, none bad
    ([float("nan"), 1.0], {"b": 1}),
    ([float("inf"), float("-inf")], {"b": 2}),  # their sum would be NaN, their count is 2
])
def test_nonfinite_gradient_counts(entries, expected):
    a, b = torch.nn.Parameter(torch.zeros(3)), torch.nn.Parameter(torch.zeros(2))
    a.grad, b.grad = torch.tensor([0.5, 1e30, -1e30]), torch.tensor(entries)
    optimizer = torch.optim.Adam([{"params": [a], "name": "a"}, {"params": [b], "name": "b"}])
    assert nonfinite_gradient_counts(optimizer) == expected


def test_render_matches_camera(tiny_scene):
    viewmat, K = camera_tensors(tiny_scene.train[0], "cpu")
    assert viewmat.shape == (4, 4) and K.shape == (3, 3)
    # Kept per camera while its matrices keep their values; an edited camera gets fresh tensors.
    cam = dataclasses.replace(tiny_scene.train[0], viewmat=tiny_scene.train[0].viewmat.copy())
    kept = camera_tensors(cam, "cpu")
    assert camera_tensors(cam, "cpu") is kept and torch.equal(kept[0], viewmat)
    cam.viewmat[0, 3] += 1.0
    moved, same_k = camera_tensors(cam, "cpu")
    assert float(moved[0, 3] - viewmat[0, 3]) == 1.0 and torch.equal(same_k, K)


def test_nonfinite_gradients_skip_the_step(tiny_scene):
    """A step with an inf or NaN gradient entry (injected here with hooks, next to a huge finite
    one) changes nothing: no parameter, no Adam moment; it is reported with the groups at fault."""
    trainer = ScaffoldTrainer(tiny_scene, TrainConfig(iterations=10, raster=CPU_RASTER, densify=False))
    trainer.step()  # Adam has moments for every parameter
    poison = {"offsets": float("inf"), "feat": float("nan")}
    for name, value in poison.items():
        def inject(grad, value=value):
            grad = grad.clone()
            grad[0] = value
            grad[1] = 1e30
            return grad
        getattr(trainer.model.anchors, name).register_hook(inject)
    params = [p for group in trainer.optimizer.param_groups for p in group["params"]]
    before = [p.detach().clone() for p in params]
    second_moment = lambda p: trainer.optimizer.state[p].get("exp_avg_sq")  # noqa: E731 (None: no gradient yet)
    moments = [None if second_moment(p) is None else second_moment(p).clone() for p in params]
    assert sum(m is not None for m in moments) >= 4
    stats = trainer.step()
    d = trainer.model.anchors.feat_dim
    k = trainer.model.anchors.n_offsets
    assert stats["nonfinite_grads"] == 3 * k + d and stats["nonfinite_groups"] == ["feat", "offsets"]
    for p, old, moment in zip(params, before, moments):
        assert torch.equal(p, old)
        assert (moment is None and second_moment(p) is None) or torch.equal(second_moment(p), moment)
        assert p.grad is None
    assert "nonfinite_grads" not in ScaffoldTrainer(tiny_scene, TrainConfig(iterations=10, raster=CPU_RASTER)).step()


def test_a_render_that_lacked_intersections_skips_the_step(tiny_scene):
    """A captured render that overflowed its intersection capacity (``info["complete"]`` False) gave
    wrong gradients: its step changes no parameter and says so; the step counter still advances."""
    trainer = ScaffoldTrainer(tiny_scene, TrainConfig(iterations=10, raster=CPU_RASTER, densify=False))
    trainer.step()
    render = trainer.render

    def overflowed(*args, **kwargs):
        out = render(*args, **kwargs)
        out["info"]["complete"] = lambda: False
        return out
    trainer.render = overflowed
    params = [p for group in trainer.optimizer.param_groups for p in group["params"]]
    before = [p.detach().clone() for p in params]
    stats = trainer.step()
    assert stats["incomplete_renders"] == 1 and "nonfinite_grads" not in stats
    assert all(torch.equal(p, old) for p, old in zip(params, before))
    assert trainer.step_count == 2
    trainer.render = render
    stats = trainer.step()
    assert "incomplete_renders" not in stats
    assert not all(torch.equal(p, old) for p, old in zip(params, before))


def photometric_loss_single_image(image, target):
    """The image term as one [H, W, C] image at a time computed it (L1 mean + 3DGS's SSIM, λ 0.2)."""
    return 0.8 * (image - target).abs().mean() + 0.2 * (1.0 - ssim_2d_float64(image, target).float())


def test_batched_image_losses_are_the_separate_ones(tiny_scene):
    g = torch.Generator().manual_seed(3)
    images = torch.rand(2, 30, 40, 3, generator=g, requires_grad=True)
    targets = torch.rand(2, 30, 40, 3, generator=g)
    batched = batch_photometric_loss(images, targets)
    separate = torch.stack([photometric_loss(images[i], targets[i]) for i in range(2)])
    reference = torch.stack([photometric_loss_single_image(images[i], targets[i]) for i in range(2)])
    assert float((batched - separate).abs().max()) < 1e-6 and float((batched - reference).abs().max()) < 1e-6
    grad_batched, = torch.autograd.grad(batched.sum(), images)
    grad_separate, = torch.autograd.grad(separate.sum(), images)
    assert float((grad_batched - grad_separate).abs().max()) < 1e-6 * float(grad_separate.abs().max())
    # A trainer's weighted sum over renders, regularizer included, is the separate calls' sum.
    trainer = ScaffoldTrainer(tiny_scene, TrainConfig(iterations=10, raster=CPU_RASTER))
    out = trainer.render(tiny_scene.train[0])
    hidden = {**out, "image": out["image"].detach().flip(0)}
    target = trainer._targets[0]
    renders = [(out, target, 1.0), (hidden, target.flip(1), 0.3)]
    expected = trainer.image_loss(out, target) + 0.3 * trainer.image_loss(hidden, target.flip(1))
    assert abs(float(trainer.image_losses(renders)) - float(expected)) < 1e-6
    # Images of different shapes are summed one by one.
    small = {**out, "image": out["image"][:20]}
    renders = [(out, target, 1.0), (small, target[:20], 0.5)]
    expected = trainer.image_loss(out, target) + 0.5 * trainer.image_loss(small, target[:20])
    assert abs(float(trainer.image_losses(renders)) - float(expected)) < 1e-6


def test_volume_loss_is_the_mean_product_of_the_scales_with_its_gradient():
    scales = torch.tensor([[0.5, 2.0, 3.0], [0.0, 1.5, 4.0], [1.0, 1.0, 0.25]], requires_grad=True)
    volume_loss(scales).backward()
    reference = scales.detach().clone().requires_grad_(True)
    reference.prod(dim=1).mean().backward()
    assert torch.allclose(volume_loss(scales), reference.prod(dim=1).mean())
    assert torch.allclose(scales.grad, reference.grad)  # a zero factor included


def test_volume_loss_over_kept_rows_ignores_the_others_even_when_infinite():
    kept = torch.tensor([True, False, True])
    scales = torch.tensor([[0.5, 2.0, 3.0], [float("inf"), 1.5, 4.0], [1.0, 1.0, 0.25]], requires_grad=True)
    volume_loss(scales, kept).backward()
    reference = scales.detach()[kept].clone().requires_grad_(True)
    volume_loss(reference).backward()
    assert torch.allclose(volume_loss(scales, kept), volume_loss(reference))
    assert torch.equal(scales.grad[~kept], torch.zeros(1, 3))
    assert torch.allclose(scales.grad[kept], reference.grad)


def test_training_views_render_with_their_own_appearance_row(tmp_path):
    # With an appearance embedding, training view i trained with row i (Scaffold-GS's camera uid):
    # `securegs render --split train` draws it with that row, not row 0.
    import imageio.v3 as iio
    import numpy as np

    from securegs_warp.cli.train import background_of, load_run
    from securegs_warp.runs import png_name

    run = tmp_path / "run"
    assert main(["train", "--out", str(run), "--iterations", "20", "--appearance-dim", "8", "--quiet", "--width",
                 "48", "--height", "36", "--train-views", "4", "--test-views", "1"]) == 0
    assert main(["render", str(run), "--split", "train", "--out", str(tmp_path / "r")]) == 0
    model, config, _ = load_run(run, "cpu")
    scene = config.scene.load()
    with torch.no_grad():
        for i, cam in enumerate(scene.train):
            own = model.render(cam, config.train.raster, background=background_of(scene, "cpu"), camera_index=i)
            png = iio.imread(tmp_path / "r" / "renders" / png_name(cam.name)) / 255.0
            assert np.abs(png - own["image"].clamp(0, 1).numpy()).max() <= 1.0 / 255.0 + 1e-6, cam.name
