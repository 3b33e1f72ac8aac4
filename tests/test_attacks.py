"""Attacks on a release (securegs_warp.attacks), their scores (robustness), ``securegs attack`` and
robust training (SecureConfig.robust)."""
import json

import pytest
import torch

from securegs_warp import attacks as A
from securegs_warp.cli import main
from securegs_warp.config import SecureConfig, TrainConfig
from securegs_warp.data import make_synthetic_scene
from securegs_warp.model import AnchorModel, ScaffoldHeads
from securegs_warp.rasterizer import RasterOptions
from securegs_warp.robustness import score_release, summarize_draws, sweep
from securegs_warp.scaffold_model import ScaffoldModel
from securegs_warp.secure import SecureTrainer
from securegs_warp.secure.container import KeyViews, open_container
from securegs_warp.raster_cases import TEST_DEVICE
from securegs_warp.secure.robust import PerturbedAnchors, parse_robust, perturb

CPU_RASTER = RasterOptions(tile_size=8)
TINY = ["--width", "40", "--height", "30", "--train-views", "6", "--test-views", "2"]


def tiny_model(n=200, d=8, k=4, seed=0) -> ScaffoldModel:
    g = torch.Generator().manual_seed(seed)
    anchors = AnchorModel(xyz=torch.rand(n, 3, generator=g) * 2 - 1, feat=torch.randn(n, d, generator=g),
                          offsets=torch.randn(n, k, 3, generator=g) * 0.1, scaling=torch.full((n, 6), -2.5),
                          rotation=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), opacity=torch.zeros(n, 1))
    torch.manual_seed(seed)
    return ScaffoldModel(anchors, ScaffoldHeads(d, k))


@pytest.fixture(scope="module")
def scene():
    return make_synthetic_scene(hidden="mug", level="object", width=24, height=18, n_train=4, n_test=2, n_points=300)


def ctx(scene, seed=0):
    return A.AttackContext(scene.test, CPU_RASTER, None, torch.Generator().manual_seed(seed))


@pytest.mark.parametrize("text", ["prune", "prune-random", "prune-random:1", "prune-random:-0.1", "noise-feat:x",
                                  "sor:16", "sor:0:2", "quantize:0", "quantize:17", "half:1", "finetune:2.5",
                                  "noise-xyz:nan", ""])
def test_bad_specs_are_refused_listing_the_valid_ones(text):
    with pytest.raises(ValueError, match="valid: prune-random:F, prune-opacity:F") as e:
        A.Attack.parse(text)
    assert "\n" not in str(e.value)


def test_specs_parse_to_typed_arguments():
    assert A.Attack.parse("sor:16:1.5") == A.Attack("sor", (16, 1.5))
    assert A.Attack.parse("quantize:8").args == (8,) and A.Attack.parse("half").args == ()
    assert A.Attack.parse("prune-random:0.2").text == "prune-random:0.2"
    assert [a.changes_heads for a in A.parse_attacks(["half", "finetune:3", "noise-feat:0.1"])] == [True, True, False]
    with pytest.raises(ValueError, match="no attack"):
        A.parse_attacks([])


@pytest.mark.parametrize("name", ["prune-random", "prune-opacity", "purify"])
def test_pruning_attacks_remove_the_fraction(scene, name):
    model = tiny_model()
    report = A.apply_attack(model, A.Attack.parse(f"{name}:0.25"), ctx(scene))
    assert (report["anchors_before"], report["anchors_after"]) == (200, 150)
    assert model.anchors.feat.shape == (150, 8) and model.anchors.offsets.shape == (150, 4, 3)


def test_prune_opacity_removes_the_most_transparent_anchors(scene):
    model = tiny_model()
    opacity = A.anchor_opacity(model, scene.test)
    A.apply_attack(model, A.Attack.parse("prune-opacity:0.5"), ctx(scene))
    assert model.anchors.num_anchors == 100
    assert float(A.anchor_opacity(model, scene.test).min()) >= float(opacity.median()) - 1e-6


def test_anchor_contribution_sums_alpha_weights(scene):
    """Σ over anchors of T·α over the pixels is the rendered alpha summed over the image."""
    model = tiny_model()
    cam = scene.test[0]
    total = A.anchor_contribution(model, [cam], CPU_RASTER).sum()
    with torch.no_grad():
        alpha = model.render(cam, CPU_RASTER)["alpha"].sum()
    assert float(alpha) > 1.0
    assert float(total) == pytest.approx(float(alpha), rel=1e-3)


def test_purify_prunes_an_isolated_transparent_cluster_first(scene):
    model = tiny_model()
    with torch.no_grad():  # 20 anchors far from the rest, with features that decode no opacity
        model.anchors.xyz[:20] = torch.tensor([30.0, 30.0, 30.0]) + torch.rand(20, 3)
    mask = A.purify_mask(model, scene.test, 0.1, CPU_RASTER)
    assert mask[:20].all() and int(mask.sum()) == 20


def test_noise_scale_is_relative_to_each_column(scene):
    model = tiny_model(n=4000)
    with torch.no_grad():
        model.anchors.feat[:, 0] *= 10.0
    before = model.anchors.feat.detach().clone()
    A.apply_attack(model, A.Attack.parse("noise-feat:0.1"), ctx(scene))
    delta_std = (model.anchors.feat.detach() - before).std(dim=0) / before.std(dim=0)
    assert torch.allclose(delta_std, torch.full_like(delta_std, 0.1), rtol=0.1)
    xyz, offsets = model.anchors.xyz.detach().clone(), model.anchors.offsets.detach().clone()
    A.apply_attack(model, A.Attack.parse("noise-xyz:0"), ctx(scene))
    assert torch.equal(model.anchors.xyz, xyz) and torch.equal(model.anchors.offsets, offsets)


def test_quantize_leaves_2_to_the_b_levels_per_column(scene):
    model = tiny_model(n=500)
    xyz = model.anchors.xyz.detach().clone()
    A.apply_attack(model, A.Attack.parse("quantize:3"), ctx(scene))
    for c in range(3):
        assert 2 < len(torch.unique(model.anchors.xyz[:, c])) <= 8
    step = (xyz.max(0).values - xyz.min(0).values) / 7
    assert ((model.anchors.xyz - xyz).abs() <= step / 2 + 1e-6).all()
    assert torch.equal(model.anchors.scaling, torch.full((500, 6), -2.5))  # a constant column stays


def test_half_rounds_anchors_and_mlps_to_float16(scene):
    model = tiny_model()
    A.apply_attack(model, A.Attack.parse("half"), ctx(scene))
    for t in (model.anchors.feat, model.heads.opacity_mlp[0].weight):
        assert t.dtype == torch.float32 and torch.equal(t, t.half().float())


def test_sor_removes_the_far_points():
    xyz = torch.cat([torch.rand(100, 3), torch.tensor([[10.0, 10, 10], [-9.0, 0, 0]])])
    mask = A.sor_mask(xyz, 8, 2.0)
    assert mask[-2:].all() and not mask[:-2].any()


def test_attacks_compose_left_to_right(scene):
    """Pruning after quantisation keeps quantised values; quantising after pruning re-spreads the levels
    over the survivors' range: the two orders give different models."""
    one, two = tiny_model(), tiny_model()
    A.apply_attacks(one, A.parse_attacks(["quantize:2", "prune-random:0.5"]), ctx(scene))
    A.apply_attacks(two, A.parse_attacks(["prune-random:0.5", "quantize:2"]), ctx(scene))
    assert one.anchors.num_anchors == two.anchors.num_anchors == 100
    assert all(len(torch.unique(one.anchors.feat[:, c])) <= 4 for c in range(8))
    assert not torch.equal(one.anchors.feat, two.anchors.feat)


def test_export_roundtrip_is_not_applicable_and_finetune_needs_the_scene(scene):
    model = tiny_model()
    report = A.apply_attack(model, A.Attack.parse("export-roundtrip"), ctx(scene))
    assert report["applicable"] is False and "3DGS PLY" in report["reason"] and model.anchors.num_anchors == 200
    with pytest.raises(ValueError, match="--scene"):
        A.apply_attacks(model, A.parse_attacks(["finetune:2"]), ctx(scene))


@pytest.mark.parametrize("spec", ["prune-random:0.2", "prune-opacity:0.2", "noise-xyz:0.01", "noise-feat:0.1",
                                  "noise-offset:0.1", "sor:8:1", "quantize:6", "half", "purify:0.2",
                                  "export-roundtrip", "finetune:1"])
def test_draws_randomly_names_the_attacks_that_read_the_random_source(scene, spec):
    generator = torch.Generator().manual_seed(0)
    context = A.AttackContext(scene.test, CPU_RASTER, None, generator, scene, TrainConfig(iterations=1))
    before = generator.get_state()
    A.apply_attack(tiny_model(d=32, k=10), A.Attack.parse(spec), context)
    assert A.Attack.parse(spec).draws_randomly == (not torch.equal(generator.get_state(), before))


def test_finetune_changes_the_public_mlps_only_through_training(scene):
    model = tiny_model(d=32, k=10)
    before = model.heads.color_mlp[0].weight.detach().clone()
    context = A.AttackContext(scene.test, CPU_RASTER, None, torch.Generator().manual_seed(0), scene,
                              TrainConfig(iterations=1))
    A.apply_attack(model, A.Attack.parse("finetune:2"), context)
    assert not torch.equal(model.heads.color_mlp[0].weight, before) and model.anchors.num_anchors == 200


# ---------------------------------------------------------------------------------------------
# Robust training
# ---------------------------------------------------------------------------------------------


def test_robust_option_accepted_and_refused():
    assert SecureConfig(robust="prune-random:0.3+noise-feat:0.2+quantize:8").robust
    for bad, why in (("noise-offset:0.1", "public offsets"), ("sor:8:1", "cannot be trained against"),
                     ("prune-random:0.3+prune-random:0.1", "twice"), ("noise:0.1", "valid:")):
        with pytest.raises(ValueError, match=why):
            SecureConfig(robust=bad)
    # a mistyped or malformed attack is answered with the attacks robust training takes, not all
    for bad in ("noise:0.1", "prune-random:lots"):
        with pytest.raises(ValueError, match="^finish_robust: .*valid: prune-random:F") as refused:
            SecureConfig(finish_robust=bad)
        assert "sor" not in str(refused.value) and "half" not in str(refused.value)


def test_hide_refuses_a_bad_robust_option_in_one_line(tmp_path, capsys):
    assert main(["hide", "--out", str(tmp_path / "r"), "--robust", "noise-offset:0.1", *TINY]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "public offsets" in err and "\n" not in err
    assert not (tmp_path / "r").exists()


def test_perturb_draws_up_to_the_strength_and_keeps_rows():
    model = tiny_model(n=1000)
    view = perturb(model.anchors, parse_robust("prune-random:0.4+noise-feat:0.5"), torch.Generator().manual_seed(1))
    assert isinstance(view, PerturbedAnchors) and view.num_anchors == 1000
    dropped = int((~view.keep).sum())
    assert 0 < dropped <= 400
    assert view.xyz is model.anchors.xyz
    assert 0 < float((view.feat - model.anchors.feat).detach().std() / model.anchors.feat.detach().std()) <= 0.5
    view.feat.sum().backward()  # noise is additive: the parameter gets the perturbed values' gradient
    assert torch.equal(model.anchors.feat.grad, torch.ones_like(model.anchors.feat))


def test_robust_prune_opacity_drops_the_least_opaque_decoded_anchors():
    model = tiny_model(n=10)
    opacity = torch.tensor([5.0, 1.0, float("nan"), 3.0, 0.5, 4.0, float("nan"), 2.0, 6.0, 7.0])
    g = torch.Generator().manual_seed(0)
    while True:  # the fraction is drawn in [0, 0.5]: wait for a draw that drops 2 of the 8 decoded
        view = perturb(model.anchors, parse_robust("prune-opacity:0.5"), g, opacity)
        if int((~view.keep).sum()) == 2:
            break
    assert (~view.keep).nonzero()[:, 0].tolist() == [1, 4]


def test_mean_neighbour_distance_among_a_subset():
    xyz = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0], [10.0, 0, 0]])
    among = torch.tensor([True, True, False, False])
    assert A.mean_neighbour_distance(xyz, 1, among).tolist() == [1.0, 1.0, 2.0, 9.0]
    assert A.mean_neighbour_distance(xyz, 1).tolist() == [1.0, 1.0, 2.0, 7.0]


@pytest.mark.skipif(TEST_DEVICE != "cuda", reason="device draws: SECUREGS_TEST_DEVICE=cuda on a GPU machine")
def test_perturb_draws_on_the_anchors_device_reproducibly():
    anchors, attacks = tiny_model(n=1000).to("cuda").anchors, parse_robust("prune-random:0.5+noise-feat:0.3")
    one, two = (perturb(anchors, attacks, torch.Generator().manual_seed(4)) for _ in range(2))
    assert one.keep.is_cuda and torch.equal(one.keep, two.keep) and torch.equal(one.feat, two.feat)
    assert not one.keep.all() and not torch.equal(one.feat, anchors.feat)


def test_robust_training_perturbs_only_the_hidden_branch(scene, monkeypatch):
    import securegs_warp.scaffold_model as scaffold_model
    import securegs_warp.secure.model as secure_model

    seen = {}
    for module, branch in ((scaffold_model, "public"), (secure_model, "hidden")):
        real = module.render_view

        def spy(anchors, *args, real=real, branch=branch, **kwargs):
            seen[branch] = (anchors, kwargs.get("anchor_mask"), kwargs.get("keep"))
            return real(anchors, *args, **kwargs)

        monkeypatch.setattr(module, "render_view", spy)
    trainer = SecureTrainer(scene, TrainConfig(iterations=2, raster=CPU_RASTER),
                            SecureConfig(payload="object+bits:8", robust="prune-random:0.5+noise-feat:0.3"))
    trainer.step()
    public, hidden = seen["public"], seen["hidden"]
    assert public == (trainer.model.anchors, None, None)
    assert isinstance(hidden[0], PerturbedAnchors)
    keep = hidden[0].keep
    # The box frame decodes its serving anchors and drops by keep (their Gaussians stay out).
    assert hidden[1] is not None and hidden[2] is keep and (hidden[1] & ~keep).any() and not keep.all()
    assert not torch.equal(hidden[0].feat.detach(), trainer.model.anchors.feat.detach())


# ---------------------------------------------------------------------------------------------
# Scores and the command line
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def container(tmp_path_factory):
    out = tmp_path_factory.mktemp("attack") / "c"
    assert main(["hide", "--out", str(out), "--iterations", "3", "--quiet", "--payload", "object+bits:0b1011",
                 "--device", "cpu", *TINY]) == 0
    return out


def test_attack_cli_json(container, tmp_path, capsys):
    args = ["attack", str(container / "public"), "--key", str(container / "key.safetensors"), "--attack",
            "prune-random:0.2", "--attack", "half", "--out", str(tmp_path / "a"), "--json", "--device", "cpu",
            "--scene", "synthetic", "--hide", "mug", *TINY]
    capsys.readouterr()
    assert main(args) == 0
    result = json.loads(capsys.readouterr().out)
    assert [r["attack"] for r in result["attacks"]] == ["prune-random:0.2", "half"]
    for part in ("before", "after"):
        assert {"psnr_hidden", "ssim_hidden", "bit_accuracy", "psnr_public", "psnr_hidden_truth"} <= set(result[part])
    assert result["before"]["psnr_hidden"] is None and result["after"]["psnr_hidden"] > 0
    assert result["after"]["anchors"] == result["before"]["anchors"] - round(0.2 * result["before"]["anchors"])
    assert result["fingerprint_matches"] is False and 0 <= result["after"]["bit_accuracy"] <= 1
    assert (tmp_path / "a" / "point_cloud.ply").is_file()
    # the key refuses the half-precision release everywhere else
    with pytest.raises(Exception, match="another|container"):
        open_container(tmp_path / "a", container / "key.safetensors")
    assert main(args) == 2  # --out holds a release now: --force replaces it
    assert main(args + ["--force"]) == 0


def test_a_failing_attack_leaves_the_earlier_release(container, tmp_path, capsys):
    # --force replaces the earlier attacked release only once a new one exists: an attack that fails
    # (every anchor pruned) or leaves values no release can hold (feature noise past float32) keeps it.
    base = ["attack", str(container / "public"), "--key", str(container / "key.safetensors"), "--out",
            str(tmp_path / "a"), "--device", "cpu"]
    assert main(base + ["--attack", "prune-random:0.1"]) == 0
    before = (tmp_path / "a" / "point_cloud.ply").read_bytes()
    for spec, message in (("prune-random:0.9999", "every anchor"), ("noise-feat:1e40", "non-finite values")):
        capsys.readouterr()
        assert main(base + ["--attack", spec, "--force"]) == 2
        assert message in capsys.readouterr().err
        assert (tmp_path / "a" / "point_cloud.ply").read_bytes() == before


def test_an_identical_view_does_not_hide_the_others_loss():
    # One view an attack left untouched scores inf; capped view by view, the mean keeps the others.
    from securegs_warp.evaluation import image_metrics

    target = torch.rand(8, 8, 3, generator=torch.Generator().manual_seed(0))
    damaged = (target + 0.1).clamp(0, 1)
    metrics = image_metrics([(target, target), (damaged, target)], "cpu", with_lpips=False, psnr_cap=100.0)
    assert metrics["psnr"] < 100.0 and metrics["psnr"] == pytest.approx((100.0 + image_metrics(
        [(damaged, target)], "cpu", with_lpips=False)["psnr"]) / 2)


@pytest.mark.parametrize("payload, expected", [("object+bits:48", True), ("image:builtin@0", False),
                                               ("bits:48", False), (None, True)])
def test_only_an_object_or_scene_key_is_scored_against_the_scenes_hidden_views(payload, expected):
    meta = {} if payload is None else {"payload": payload}
    assert KeyViews.from_metadata(meta, "cpu").scene_targets is expected


def test_the_key_records_its_serving_anchors_and_takes_back_those_an_attacker_shifted(container):
    """A box-frame key holds its serving anchors' positions as released and each one's reach (the
    distance to its nearest other anchor). Anchors shifted by less than half their reach decode from
    the recorded positions, so the hidden render is the unattacked one; one shifted beyond every
    entry's reach stays where it is and no longer serves, nor does an anchor the key never served that
    the attack moved into the serving radius; a key written without a record decodes the shifted
    positions."""
    from securegs_warp.secure.heads import REACH_MARGIN, PrivateHeads

    model, meta = open_container(container / "public", container / "key.safetensors")
    private, xyz = model.private, model.anchors.xyz.detach().clone()
    serving = private.serving_mask(xyz)
    record = private.anchor_record
    assert meta["heads"]["recorded"] == int(serving.sum()) == len(record) > 10
    assert torch.equal(record[:, :3], xyz[serving])
    others = torch.cdist(record[:, :3].double(), xyz.double())
    others[others == 0] = float("inf")
    assert torch.allclose(record[:, 3].double(), (1 - REACH_MARGIN) * others.min(dim=1).values, rtol=1e-5)
    assert model._key_anchors(private) is model.anchors  # unattacked: nothing to take back
    cam = make_synthetic_scene(hidden="mug", level="object", width=40, height=30, n_train=6, n_test=2).test[0]
    with torch.no_grad():
        unattacked = model.render_hidden(cam, CPU_RASTER)["image"]
        direction = torch.nn.functional.normalize(
            torch.randn(len(record), 3, generator=torch.Generator().manual_seed(0)))
        shifted = xyz.clone()
        shifted[serving] += 0.45 * record[:, 3:] * direction
        far = int(serving.nonzero()[0])
        outward = torch.nn.functional.normalize(xyz[far] - record[:, :3].mean(dim=0), dim=0)
        shifted[far] = xyz[far] + 2.0 * record[:, 3].max() * outward
        model.anchors.xyz.copy_(shifted)
        taken_back, rows = private.register(model.anchors.xyz)
        assert torch.cdist(shifted[far][None], record[:, :3]).squeeze(0).ge(record[:, 3]).all()  # beyond every reach
        assert torch.equal(taken_back[serving][1:], xyz[serving][1:]) and torch.equal(taken_back[far], shifted[far])
        assert rows.tolist() == serving.nonzero()[:, 0].tolist()[1:]  # every anchor paired but the far one
        shifted[far] = xyz[far] + 0.45 * record[0, 3] * direction[0]
        # An anchor the key never served, moved inside the serving radius away from every entry's reach.
        stray = int((~serving).nonzero()[0])
        box = private.box
        inside = box[0] + (box[1] - box[0]) * torch.rand(4096, 3, generator=torch.Generator().manual_seed(1))
        clear = torch.cdist(inside, record[:, :3]).gt(record[:, 3].max()).all(dim=1) \
            & (private.box_distance(inside) <= private.serving_radius)
        assert clear.any()
        shifted[stray] = inside[clear][0]
        older = PrivateHeads(model.heads, **{k: v for k, v in meta["heads"].items() if k != "recorded"})
        older.load_state_dict({k: v for k, v in private.state_dict().items() if k != "anchor_record"})
        bare = type(model)(model.anchors, model.heads, [older])  # the same key without its record
        model.anchors.xyz.copy_(shifted)
        assert stray not in private.register(model.anchors.xyz)[1].tolist()
        assert torch.equal(model.render_hidden(cam, CPU_RASTER)["image"], unattacked)
        assert not torch.equal(bare.render_hidden(cam, CPU_RASTER)["image"], unattacked)  # decodes the shifts
        alone = xyz.clone()  # the stray moved in alone, the served anchors untouched
        alone[stray] = shifted[stray]
        model.anchors.xyz.copy_(alone)
        positions, rows = private.register(model.anchors.xyz)
        assert positions is model.anchors.xyz and rows.tolist() == serving.nonzero()[:, 0].tolist()
        assert torch.equal(model.render_hidden(cam, CPU_RASTER)["image"], unattacked)
        positions, rows = older.register(model.anchors.xyz)
        assert positions is model.anchors.xyz and rows is None
        assert not torch.equal(bare.render_hidden(cam, CPU_RASTER)["image"], unattacked)  # the radius serves the stray
    with pytest.raises(ValueError, match="frame='box'"):
        PrivateHeads(ScaffoldHeads(2, 2), recorded=4)


def test_attack_cli_refuses_bad_specs(container, capsys):
    code = main(["attack", str(container / "public"), "--key", str(container / "key.safetensors"),
                 "--attack", "prune:0.2"])
    assert code == 2 and "valid: prune-random:F" in capsys.readouterr().err
    code = main(["attack", str(container / "public"), "--key", str(container / "key.safetensors"),
                 "--attack", "half", "--seed", str(2**70)])
    assert code == 2 and "--seed must fit a signed 64-bit integer" in capsys.readouterr().err


def test_sweep_rows_and_scores(container, scene):
    model, meta = open_container(container / "public", container / "key.safetensors")
    views = KeyViews.from_metadata(meta, "cpu")
    assert views.message.tolist() == [1, 0, 1, 1]
    rows = sweep({"c": model}, {"c": views}, None, {"prune-random": ["prune-random:0.1", "prune-random:0.5"]})
    assert [r["spec"] for r in rows] == ["none", "prune-random:0.1", "prune-random:0.5"]
    assert rows[0]["psnr_hidden"] is None and rows[0]["bit_accuracy"] == score_release(model, views)["bit_accuracy"]
    assert rows[1]["anchors"] > rows[2]["anchors"] and rows[1]["psnr_hidden"] > rows[2]["psnr_hidden"]


def test_sweep_draws_repeat_only_random_attacks(container):
    model, meta = open_container(container / "public", container / "key.safetensors")
    views = KeyViews.from_metadata(meta, "cpu")
    attacks = {"prune-random": ["prune-random:0.3"], "quantize": ["quantize:6"]}
    rows = sweep({"c": model}, {"c": views}, None, attacks, seed=4, draws=3)
    assert [(r["spec"], r["draw"]) for r in rows] == [("none", 0), ("prune-random:0.3", 0), ("prune-random:0.3", 1),
                                                     ("prune-random:0.3", 2), ("quantize:6", 0)]
    # draw d is the single run seeded seed + d; other draws prune other anchors
    alone = sweep({"c": model}, {"c": views}, None, {"prune-random": ["prune-random:0.3"]}, seed=5)
    assert alone[1]["psnr_hidden"] == rows[2]["psnr_hidden"]
    assert len({r["psnr_hidden"] for r in rows[1:4]}) == 3
    summary = {s["spec"]: s for s in summarize_draws(rows)}
    pruned = summary["prune-random:0.3"]
    assert pruned["draws"] == 3 and summary["quantize:6"]["draws"] == 1
    assert pruned["psnr_hidden_worst"] == min(r["psnr_hidden"] for r in rows[1:4])
    assert pruned["psnr_hidden_mean"] == pytest.approx(sum(r["psnr_hidden"] for r in rows[1:4]) / 3)
    assert pruned["against"] == "unattacked" and pruned["delta_mean"] is None  # no true hidden views without the scene
    with pytest.raises(ValueError, match="draws must be at least 1"):
        sweep({"c": model}, {"c": views}, None, attacks, draws=0)


def test_sweep_files_and_plot(tmp_path):
    pytest.importorskip("matplotlib")
    from securegs_warp.robustness import plot_sweep, write_sweep

    rows = [{"model": m, "attack": a, "spec": s, "strength": x, "psnr_hidden": None if a == "none" else 40.0 - 10 * x,
             "ssim_hidden": None, "psnr_hidden_truth": 30.0 - x, "ssim_hidden_truth": 0.9, "bit_accuracy": 1.0,
             "psnr_public": 28.0, "ssim_public": 0.9, "anchors": 100}
            for m in ("a", "b") for a, s, x in (("none", "none", 0.0), ("prune-random", "prune-random:0.1", 0.1),
                                               ("prune-random", "prune-random:0.2", 0.2), ("half", "half", 1.0))]
    table = write_sweep(tmp_path, rows, {"seed": 0})
    assert table.count("\n") == len(rows) + 1 and "| a | prune-random:0.1 | – | 39 |" in table
    # a second draw of one attack: the rows' table, then the mean and worst over the draws
    rows.append({**rows[1], "draw": 1, "psnr_hidden_truth": 28.9})
    table = write_sweep(tmp_path, rows, {"seed": 0})
    assert "Over the draws of each attack" in table
    assert "| a | prune-random:0.1 | 2 | truth | 29.4 | 28.9 | -0.6 | -1.1 | 1 |" in table
    assert (tmp_path / "robustness.csv").read_text().splitlines()[0].startswith("model,spec,draw,psnr_hidden")
    plot_sweep(tmp_path / "r.png", rows)
    assert (tmp_path / "r.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_perturb_with_device_drawn_attacks_reads_nothing_back():
    """Dropout and noise draw their strengths, masks and noise from ``draws`` alone, with no host
    read (what lets the finishing phase replay them from a CUDA graph); dropout drops exactly its
    drawn share."""
    model = tiny_model(n=1000)
    host, draws = torch.Generator().manual_seed(0), torch.Generator().manual_seed(1)
    state = host.get_state()
    with torch.profiler.profile() as prof:
        view = perturb(model.anchors, parse_robust("prune-random:0.4+noise-feat:0.5"), host, draws=draws)
    assert torch.equal(host.get_state(), state)
    reads = {"aten::item", "aten::_local_scalar_dense", "aten::nonzero"}
    assert not [e.name for e in prof.events() if e.name in reads]
    assert 0 < int((~view.keep).sum()) <= 400
    for share in (0.0, 0.25, 0.333, 1.0):  # a device count drops as many as a host one
        assert int(A.random_prune_mask(1000, torch.tensor(share), draws).sum()) == round(share * 1000)
        assert int(A.random_prune_mask(1000, share, draws).sum()) == round(share * 1000)
