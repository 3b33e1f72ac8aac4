"""SecureGS: payloads, private heads, region-aware densification, the release/key split, reveal."""
import collections
import dataclasses
import json
import warnings

import numpy as np
import pytest
import torch

from securegs_warp.cli import main
from securegs_warp.config import FINISH_ROBUST_RECIPE, apply_overrides
from securegs_warp.data import make_synthetic_scene
from securegs_warp.io import anchor_ply_properties
from securegs_warp.io.gs_ply import read_vertex_ply
from securegs_warp.keys import KeyFileError
from securegs_warp.secure import PayloadSpec, SecureConfig, SecureTrainer
from securegs_warp.secure.container import KeyFile, open_container, save_container
from securegs_warp.secure.security import exposure
from securegs_warp.rasterizer import RasterOptions
from securegs_warp.strategies import RegionAwareStrategy
from securegs_warp.train import TrainConfig

RDO = RegionAwareStrategy(mode="rdo")  # the paper's density strategy (an object's default is the cover mode)

CPU_RASTER = RasterOptions(tile_size=8)
TINY = ["--width", "40", "--height", "30", "--train-views", "6", "--test-views", "2"]


@pytest.fixture(scope="module")
def hidden_scene():
    return make_synthetic_scene(hidden="mug", level="object", width=40, height=30, n_train=6, n_test=2, n_points=600)


@pytest.fixture(scope="module")
def trained(hidden_scene):
    """A container hiding the mug and 48 bits, trained briefly with frequent RDO updates. Its 600
    points occupy too few cells of the default 16-voxel bit grid for 48 bits
    (test_a_message_longer_than_the_grid_carries_is_warned_of): a 4-voxel grid gives every bit voters."""
    trainer = SecureTrainer(hidden_scene, TrainConfig(iterations=60, raster=CPU_RASTER),
                            SecureConfig(payload="object+bits:48", strategy=RDO, bit_cell_voxels=4.0))
    s = trainer.strategy
    s.start_stat, s.update_from, s.update_interval, s.update_until = 0, 0, 10, 60
    s.dbscan_min_samples = 4
    history = [trainer.step() for _ in range(60)]
    return trainer, history


def test_payload_spec_parsing():
    spec = PayloadSpec.parse("object+bits:48")
    assert (spec.kind, spec.bits) == ("object", 48)
    spec = PayloadSpec.parse("image:builtin@3")
    assert (spec.kind, spec.image, spec.image_view) == ("image", "builtin", 3)
    assert PayloadSpec.parse("bits:01101").bit_string == "01101"
    # The last @ starts the view: a file name may hold an @ of its own.
    assert (PayloadSpec.parse("image:me@2x.png@2").image, PayloadSpec.parse("image:me@2x.png@2").image_view) == \
        ("me@2x.png", 2)
    assert (PayloadSpec.parse("image:logo.png").image, PayloadSpec.parse("image").image) == ("logo.png", "builtin")
    for bad, match in (("bits:0", "length"), ("bits:300", "length"), ("sound", "unknown payload"), ("", "empty"),
                       ("image:@3", "file name is empty"), ("image:logo.png@", "training view index"),
                       ("image:logo.png@x", "training view index")):
        with pytest.raises(ValueError, match=match):
            PayloadSpec.parse(bad)


def test_builtin_emblem_is_the_same_picture_at_every_resolution():
    """The emblem at twice the size, averaged over 2×2 blocks, is the emblem: its checker cells
    scale with the image, so a 1080p image payload is no finer than a 96-pixel one."""
    from securegs_warp.secure.payload import builtin_emblem

    small, large = builtin_emblem(96, 128), builtin_emblem(192, 256)
    pooled = large.reshape(96, 2, 128, 2, 3).mean(axis=(1, 3))
    # A pixel on an edge pools two colours, so it may differ by up to half the largest contrast
    # (0.8); a pattern that does not scale (4-px cells at both sizes) pools cells to grey: 12% differ.
    differs = np.abs(pooled - small).max(axis=-1) > 0.3
    assert differs.mean() < 0.02


def test_object_payload_needs_hidden_views():
    scene = make_synthetic_scene(width=24, height=18, n_train=3, n_test=1, n_points=200)
    with pytest.raises(ValueError, match="hidden views"):
        SecureTrainer(scene, TrainConfig(iterations=5, raster=CPU_RASTER), SecureConfig(payload="object"))


def test_density_mode_defaults_to_cover_for_an_object_or_bits_alone_and_rdo_otherwise(hidden_scene):
    config = TrainConfig(iterations=2, raster=CPU_RASTER)
    modes = {payload: SecureTrainer(hidden_scene, config, SecureConfig(payload=payload)).strategy.mode
             for payload in ("object+bits:48", "image", "bits:16", "bits:16,bits:8", "image,bits:8", "image,object")}
    assert modes == {"object+bits:48": "cover", "image": "rdo", "bits:16": "cover", "bits:16,bits:8": "cover",
                     "image,bits:8": "rdo", "image,object": "cover"}
    assert SecureTrainer(hidden_scene, config, SecureConfig(payload="object", strategy=RDO)).strategy.mode == "rdo"
    with pytest.raises(ValueError, match="density mode must be one of"):
        RegionAwareStrategy(mode="paper")


def test_private_heads_mirror_public_shapes(trained):
    trainer, _ = trained
    public = {k: v.shape for k, v in trainer.model.heads.state_dict().items()}
    private = {k: v.shape for k, v in trainer.model.private.decoder.state_dict().items()}
    assert public == private
    d, k = trainer.model.anchors.feat_dim, trainer.model.anchors.n_offsets
    assert trainer.model.private.offset_mlp[0].weight.shape == (d, d + 3)
    assert trainer.model.private.offset_mlp[-1].weight.shape == (3 * k, d)
    assert trainer.model.private.bits.directions.shape == (48, d)


def test_rdo_grows_a_hidden_set_and_finds_its_box(trained, hidden_scene):
    trainer, history = trained
    state = trainer.strategy_state
    n = trainer.model.anchors.num_anchors
    assert state["is_hidden"].shape == (n,) and state["hid_grad_accum"].shape == (n * trainer.model.anchors.n_offsets,)
    assert sum(h.get("grown_hidden", 0) for h in history) > 0
    assert int(state["is_hidden"].sum()) > 0
    box = state["bbox"]
    assert not torch.isnan(box).any()
    # The box of the dense hidden anchors overlaps the hidden object's true box.
    true_lo, true_hi = (torch.as_tensor(v) for v in hidden_scene.hidden_bbox)
    assert (torch.minimum(box[3:], true_hi) > torch.maximum(box[:3], true_lo)).all()
    # Inside the box public growth uses τ_fix / r_down.
    tau = trainer.strategy.public_threshold(trainer.model.anchors, state)
    assert torch.isclose(tau.min(), torch.tensor(trainer.strategy.grad_threshold / trainer.strategy.r_down))
    assert history[-1]["psnr_hidden"] > history[0]["psnr_hidden"] + 3


def test_hidden_learnt_compares_the_render_with_a_flat_image(trained, hidden_scene):
    """An untrained hidden branch scores no better than a flat image of each target's mean colour;
    the trained one does. For an image payload, whose emblem fills the frame, the flat image (not
    the bare background, 5 dB lower there) is what an untrained branch must be held against."""
    config = TrainConfig(iterations=60, raster=CPU_RASTER)
    fresh = SecureTrainer(hidden_scene, config, SecureConfig(payload="object+bits:48", strategy=RDO))
    before, after = fresh.evaluate_hidden(), trained[0].evaluate_hidden()
    assert before["psnr_hidden_flat"] == pytest.approx(after["psnr_hidden_flat"])  # same targets
    assert before["hidden_learnt"] is False and after["hidden_learnt"] is True
    assert after["psnr_hidden"] > after["psnr_hidden_flat"] + 1.0
    image = SecureTrainer(hidden_scene, config, SecureConfig(payload="image")).evaluate_hidden()
    assert image["hidden_learnt"] is False


def test_hidden_render_of_the_public_view_reuses_its_visibility_test(hidden_scene, monkeypatch):
    """The hidden render of the step's own view decodes the public render's visible anchors, as
    it would have found them itself; the visibility test then runs once per step, not twice."""
    import securegs_warp.render as render_module

    # The anchor frame decodes the visible anchors (the cover mode's box frame decodes its serving ones).
    trainer = SecureTrainer(hidden_scene, TrainConfig(iterations=10, raster=CPU_RASTER),
                            SecureConfig(payload="object+bits:48", strategy=RegionAwareStrategy(mode="rdo")))
    cam = hidden_scene.train[2]
    public = trainer.render(cam, camera_index=2)
    shared = trainer.render_hidden(cam, camera_index=2, visible=public["gaussians"]["visible_mask"])
    own = trainer.render_hidden(cam, camera_index=2)
    assert public["gaussians"]["visible_mask"].any() and not public["gaussians"]["visible_mask"].all()
    for key in ("image", "alpha"):
        assert torch.equal(shared[key], own[key])
    calls = []
    original = render_module.visible_anchor_mask
    monkeypatch.setattr(render_module, "visible_anchor_mask", lambda *a, **k: calls.append(1) or original(*a, **k))
    trainer.step()
    assert len(calls) == 1


@pytest.mark.parametrize("options", [{}, {"radius_rule": "3sigma", "tile_overlap": "rectangle"},
                                     {"antialiased": True}, {"gather": "fields"}])
def test_the_uncompacted_hidden_render_is_the_compacted_one(hidden_scene, options):
    """The cover mode's training renders the hidden Gaussians that fail the opacity test at opacity 0
    (no host read of how many passed): the same image and the same gradients, whatever the options
    (the blending skips any Gaussian below alpha_min)."""
    raster = RasterOptions(tile_size=8, **options)
    trainer = SecureTrainer(hidden_scene, TrainConfig(iterations=10, raster=raster), SecureConfig(payload="object"))
    trainer.step()
    cam = hidden_scene.train[1]
    weights = torch.rand(cam.height, cam.width, 3, generator=torch.Generator().manual_seed(0))
    results = []
    for compact in (True, False):
        for p in trainer.model.parameters():
            p.grad = None
        out = trainer.render_hidden(cam, 1, compact=compact)
        ((out["image"] * weights).sum() + trainer.regularizer(out)).backward()
        results.append((out, {n: p.grad.clone() for n, p in trainer.model.named_parameters() if p.grad is not None}))
    (kept, kept_grads), (rows, row_grads) = results
    assert rows["gaussians"]["opacities"].shape[0] > kept["gaussians"]["opacities"].shape[0] > 0
    assert torch.equal(rows["image"], kept["image"])
    assert set(row_grads) == set(kept_grads) and "secrets.0.offset_mlp.0.weight" in kept_grads
    for name, g in kept_grads.items():
        assert (row_grads[name] - g).abs().max() <= 1e-5 * g.abs().max().clamp_min(1e-12), name


def test_perturbed_positions_serve_as_many_rows_by_rank(hidden_scene):
    """Position noise moves anchors across the serving radius: robust training then serves the
    anchors nearest the box as they now lie, as many as the radius serves unperturbed, so the row
    count stays fixed (the captured decoding replays) while the set follows the moved anchors."""
    from securegs_warp.secure.robust import perturb

    trainer = SecureTrainer(hidden_scene, TrainConfig(iterations=10, raster=CPU_RASTER),
                            SecureConfig(payload="object", robust="noise-xyz:0.5", hidden_anchors=64))
    trainer.step()
    model, private = trainer.model, trainer.model.secrets[0]
    anchors = perturb(model.anchors, trainer.robust, torch.Generator().manual_seed(0))
    assert anchors.xyz is not model.anchors.xyz and model.fixed_rows(0)
    served = private.serving_index(model.anchors.xyz)
    assert 0 < len(served) < model.anchors.num_anchors
    mask, index, _ = model._decoding_rows(private, anchors, hidden_scene.train[1])
    assert len(index) == len(served) and int(mask.sum()) == len(index) and torch.equal(mask.nonzero()[:, 0], index)
    distance = private.box_distance(anchors.xyz)
    assert distance[mask].max() <= distance[~mask].min()
    assert not torch.equal(index, served)  # the noise moved some anchors in or out


def test_robust_dropout_keeps_the_box_frames_rows_and_renders_as_leaving_them_out(hidden_scene):
    """Robust training drops anchors by ``keep``: in the box frame their rows stay (at opacity 0, a
    fixed row count that graphs can replay) and the render and gradients are those of leaving the
    dropped anchors out of the decoding, compacted or not."""
    from securegs_warp.render import render_view
    from securegs_warp.secure.robust import perturb

    trainer = SecureTrainer(hidden_scene, TrainConfig(iterations=10, raster=CPU_RASTER),
                            SecureConfig(payload="object", robust="prune-random:0.6+noise-feat:0.3"))
    trainer.step()
    model, private, cam = trainer.model, trainer.model.secrets[0], hidden_scene.train[1]
    anchors = perturb(model.anchors, trainer.robust, torch.Generator().manual_seed(3))
    serving = private.serving_mask(model.anchors.xyz)
    assert anchors.xyz is model.anchors.xyz and model.fixed_rows(0)
    assert (serving & ~anchors.keep).any() and (serving & anchors.keep).any()
    weights = torch.rand(cam.height, cam.width, 3, generator=torch.Generator().manual_seed(0))
    results = {}
    for how in ("rows", "compacted", "left out"):
        for p in model.parameters():
            p.grad = None
        if how == "left out":
            out = render_view(anchors, private.decoder, cam, trainer.payloads[0].background, trainer.config.raster,
                              camera_index=1, offset_source=private.hidden_offsets,
                              anchor_source=private.anchor_source, feature_grad=trainer.current_feature_grad(),
                              scaling_grad=trainer.gradient_shares()[1], anchor_mask=serving & anchors.keep)
        else:
            out = trainer.render_hidden(cam, 1, anchors=anchors, compact=how == "compacted")
        ((out["image"] * weights).sum() + trainer.regularizer(out)).backward()
        results[how] = (out, {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None})
    k = private.decoder.n_offsets
    assert results["rows"][0]["gaussians"]["opacities"].shape[0] == int(serving.sum()) * k
    reference, reference_grads = results["left out"]
    assert reference["image"].abs().max() > 0
    for how in ("rows", "compacted"):
        out, grads = results[how]
        assert torch.equal(out["image"], reference["image"]), how
        assert set(grads) == set(reference_grads), how
        for name, g in reference_grads.items():
            assert (grads[name] - g).abs().max() <= 1e-5 * g.abs().max().clamp_min(1e-12), (how, name)


def test_a_replayed_hidden_render_that_overflows_skips_its_step_and_training_goes_on(hidden_scene, monkeypatch):
    """The replayed hidden rasterize (CUDA's path, run here by the CPU's direct launches) whose
    capacity a view overflows: that step is skipped (no parameter moves), the capacity grows to what
    the view needed, and the following steps train without raising."""
    from securegs_warp import raster_graph
    monkeypatch.setattr(raster_graph, "HEADROOM", 1.0)
    monkeypatch.setattr(raster_graph, "SLACK", 0)
    monkeypatch.setattr(SecureTrainer, "replays_hidden_raster", lambda self, *args: True)
    monkeypatch.setattr(raster_graph, "_POOL", collections.OrderedDict())  # this test's renders only
    # No robust training: its dropout would change the intersections a view needs from step to step.
    trainer = SecureTrainer(hidden_scene, TrainConfig(iterations=20, raster=CPU_RASTER, densify=False),
                            SecureConfig(payload="object", robust=None))
    assert "incomplete_renders" not in trainer.step()
    (entry,) = [e for entries in raster_graph._POOL.values() for e in entries]
    entry.plan.allocate_intersections(64)  # less than any view of the scene needs
    params = [p for group in trainer.optimizer.param_groups for p in group["params"]]
    before = [p.detach().clone() for p in params]
    assert trainer.step()["incomplete_renders"] == 1
    assert all(torch.equal(p, old) for p, old in zip(params, before))
    for _ in range(4):
        assert "incomplete_renders" not in trainer.step()
    assert entry.plan.capacity > 64 and trainer.step_count == 6
    assert not all(torch.equal(p, old) for p, old in zip(params, before))


@pytest.mark.parametrize("mode", ["cover", "rdo"])
def test_training_compacts_the_hidden_render_only_where_the_strategy_reads_it(hidden_scene, mode):
    trainer = SecureTrainer(hidden_scene, TrainConfig(iterations=10, raster=CPU_RASTER),
                            SecureConfig(payload="object", strategy=RegionAwareStrategy(mode=mode)))
    seen = []
    render = trainer.model.render_hidden
    trainer.model.render_hidden = lambda *a, **k: seen.append(k["compact"]) or render(*a, **k)
    trainer.step()
    trainer.evaluate_hidden()
    assert seen[0] == (mode != "cover") and all(seen[1:])  # evaluation renders what a key holder renders


def test_bits_are_decoded_exactly(trained):
    trainer, _ = trained
    assert trainer.evaluate_hidden()["bit_accuracy"] == 1.0


@pytest.mark.parametrize("length", [1, 256])
def test_bit_lengths_1_and_256(length):
    """Each anchor carries one bit, so 256 bits need thousands of anchors (a bit without a voter
    would read 0; evaluate_hidden counts them). The keyed grid deals its N occupied cells among the
    L bits at random, so a bit has no voter with probability about L·exp(−N/L): 0.3% of keys at
    3,000 anchors, ~1e-11 at 8,000."""
    scene = make_synthetic_scene(width=40, height=30, n_train=4, n_test=1, n_points=8000)
    trainer = SecureTrainer(scene, TrainConfig(iterations=30, raster=CPU_RASTER, densify=False),
                            SecureConfig(payload=f"bits:{length}"))
    assert trainer.model.private.decoder is None  # a bit payload renders nothing hidden
    for _ in range(30):
        trainer.step()
    metrics = trainer.evaluate_hidden()
    assert metrics["bit_accuracy"] == 1.0 and metrics["bits_without_voters"] == 0


def test_a_message_longer_than_the_grid_carries_is_warned_of():
    """Each occupied cell of the keyed grid carries one bit: 256 bits over a 600-point scene's cells
    leave bits without voters, and the run says so when the projection begins, naming the option."""
    scene = make_synthetic_scene(width=40, height=30, n_train=4, n_test=1, n_points=600)
    trainer = SecureTrainer(scene, TrainConfig(iterations=2, raster=CPU_RASTER, densify=False),
                            SecureConfig(payload="bits:256"))
    with pytest.warns(UserWarning, match=r"of the message's 256 bits fall in no occupied cell.*--bit-cell"):
        trainer.step()
    assert trainer.evaluate_hidden()["bits_without_voters"] > 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        trainer.step()  # said once, when the projection begins


def test_bits_are_read_from_the_anchor_features(hidden_scene):
    """The bit decoder has no bias, so it cannot output the message as a constant of its own: blank
    anchor features decode nothing, and the message is read from the features. Every anchor votes,
    so the message survives losing half of them (random pruning, as in the paper's robustness study)
    while every bit keeps voters, and every surviving voter agrees. The keyed grid deals cells to
    bits unevenly: over ~600 anchors a 16-voxel grid leaves some keys a bit with so few voters that
    the cut takes them all; a 4-voxel grid gives each bit many cells (docs/probes/half_cut_voters.py
    counts both; docs/results.md, "Keys that leave a bit without voters after a half-cut")."""
    config = TrainConfig(iterations=40, raster=CPU_RASTER, densify=False)
    trainer = SecureTrainer(hidden_scene, config, SecureConfig(payload="bits:16", bit_cell_voxels=4.0))
    for _ in range(config.iterations):
        trainer.step()
    bits, private = trainer.payload.bits.long(), trainer.model.private
    feat, xyz = trainer.model.anchors.feat.detach(), trainer.model.anchors.xyz
    assert torch.equal(private.decode_bits(feat, xyz), bits)
    half = torch.randperm(feat.shape[0], generator=torch.Generator().manual_seed(0))[: feat.shape[0] // 2]
    assert torch.equal(private.decode_bits(feat[half], xyz[half]), bits)
    vote, voters = private.bits.vote(feat[half], xyz[half])
    assert bool((voters > 0).all()) and torch.equal(vote, bits.to(vote.dtype))  # unanimous: every survivor agrees
    with torch.no_grad():
        assert float(private.bit_logits(torch.zeros_like(feat), xyz)[0].abs().max()) == 0.0
    assert not torch.equal(private.decode_bits(torch.zeros_like(feat), xyz), bits)  # all zeros: bits has ones


def test_release_is_plain_scaffold_gs_and_holds_no_private_tensor(trained, tmp_path):
    trainer, _ = trained
    public, _ = save_container(tmp_path, trainer.model, [KeyFile({"payload": "object"})])
    assert sorted(p.name for p in public.iterdir()) == ["color_mlp.pt", "cov_mlp.pt", "opacity_mlp.pt",
                                                        "point_cloud.ply"]
    names = [p.name for p in read_vertex_ply(public / "point_cloud.ply").properties]
    assert names == anchor_ply_properties(trainer.model.anchors.n_offsets, trainer.model.anchors.feat_dim)
    release = b"".join(p.read_bytes() for p in public.iterdir())
    for name, tensor in trainer.model.private.state_dict().items():
        raw = tensor.detach().float().contiguous().numpy().tobytes()
        for start in range(0, len(raw) - 32, max(4, (len(raw) // 64) // 4 * 4)):
            assert raw[start:start + 32] not in release, f"private tensor {name} found in the release"
    for word in (b"offset_mlp", b"bit_mlp", b"decoder"):
        assert word not in release


def test_key_opens_only_its_own_container(trained, tmp_path, hidden_scene):
    trainer, _ = trained
    public, (key,) = save_container(tmp_path / "a", trainer.model, [KeyFile({}, passphrase="s3cret")])
    opened, _ = open_container(public, key, "s3cret")
    assert opened.private is not None
    for a, b in zip(opened.private.state_dict().values(), trainer.model.private.state_dict().values()):
        assert torch.equal(a, b)
    with pytest.raises(KeyFileError, match="passphrase"):
        open_container(public, key, "wrong")
    with pytest.raises(KeyFileError, match="passphrase"):
        open_container(public, key, None)
    blob = bytearray(key.read_bytes())
    blob[-10] ^= 0x01
    (tmp_path / "tampered.sealed").write_bytes(bytes(blob))
    with pytest.raises(KeyFileError):
        open_container(public, tmp_path / "tampered.sealed", "s3cret")
    other = SecureTrainer(hidden_scene, TrainConfig(iterations=2, raster=CPU_RASTER, seed=1), SecureConfig(payload="object"))
    other_public, _ = save_container(tmp_path / "b", other.model, [KeyFile({})])
    with pytest.raises(KeyFileError, match="another container"):
        open_container(other_public, key, "s3cret")
    assert open_container(public)[0].private is None  # no key: the cover scene only


def test_exposure_measures_anchors_tracing_the_hidden_surface():
    g = np.random.default_rng(0)
    sphere = g.normal(size=(2000, 3))
    sphere = sphere / np.linalg.norm(sphere, axis=1, keepdims=True)
    scene = g.uniform(-5, 5, size=(2000, 3)) * np.array([1, 1, 0]) + np.array([0, 0, -3])  # a floor far below
    traced = exposure(sphere[::2] * 1.01, sphere, scene, radius=0.1)  # anchors on the hidden surface
    spread = exposure(g.uniform(-1.1, 1.1, size=(4000, 3)), sphere, scene, radius=0.1)  # anchors filling the box
    assert traced["surface_fraction"] > 0.95 and traced["coverage"] > 0.9
    assert spread["surface_fraction"] < 0.4


def test_cli_hide_reveal_demo(tmp_path, monkeypatch, capsys):
    out = tmp_path / "c"
    monkeypatch.setenv("KEYPASS", "correct horse")
    bad = ["hide", "--out", str(tmp_path / "bad"), "--iterations", "2", "--quiet", "--payload", "object", *TINY]
    assert main(bad + ["--hidden-feature-grad", "2"]) == 2
    assert main(bad + ["--hidden-tau-scale", "0.5"]) == 2
    assert main(bad + ["--hidden-scaling-grad", "-1"]) == 2
    assert not (tmp_path / "bad").exists()  # refused before the run folder is written
    assert main(["hide", "--out", str(out), "--iterations", "12", "--quiet", "--payload", "object+bits:8",
                 "--passphrase-env", "KEYPASS", "--hidden-tau-scale", "4", "--hidden-feature-grad", "0.5",
                 "--hidden-scaling-grad", "0", *TINY]) == 0
    record = json.loads((out / "config.json").read_text())["secure"]
    assert (record["strategy"]["hidden_tau_scale"], record["hidden_feature_grad"], record["hidden_scaling_grad"]) == (
        4.0, 0.5, 0.0)
    assert record["strategy"]["mode"] == "cover"  # the mode the object chose, not "chosen by the payload"
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("psnr_public", "ssim_public", "psnr_hidden", "ssim_hidden", "bit_accuracy", "fps_public",
                "fps_hidden", "size_mb_public", "train_seconds", "psnr_hidden_flat", "hidden_learnt"):
        assert key in metrics, key
    # the warning is printed exactly when the hidden render is not 1 dB better than a flat image
    warned = "warning: the hidden payload was not learnt" in capsys.readouterr().err
    assert warned == (not metrics["hidden_learnt"])
    assert (out / "key.sealed").is_file() and not (out / "key.safetensors").exists()
    assert sorted(p.name for p in (out / "renders").iterdir() if not p.name.startswith("test_")) == [
        "hidden_view_with_key.png", "hidden_view_without_key.png", "public_view.png"]

    revealed = tmp_path / "r"
    assert main(["reveal", str(out / "public"), "--key", str(out / "key.sealed"), "--passphrase-env", "KEYPASS",
                 "--out", str(revealed)]) == 0
    assert len(json.loads((revealed / "bits.json").read_text())["bits"]) == 8
    assert (revealed / "hidden_3dgs.ply").stat().st_size > 0
    assert any(p.name.startswith("hidden_") for p in (revealed / "renders").iterdir())

    keyless = tmp_path / "k"
    assert main(["reveal", str(out / "public"), "--out", str(keyless), "--scene", "synthetic", *TINY]) == 0
    assert not any(p.name.startswith("hidden_") for p in (keyless / "renders").iterdir())
    monkeypatch.setenv("KEYPASS", "wrong")
    assert main(["reveal", str(out / "public"), "--key", str(out / "key.sealed"), "--passphrase-env", "KEYPASS",
                 "--out", str(tmp_path / "w")]) == 2


def test_cli_resume_keeps_or_changes_the_finishing_phase(tmp_path, capsys):
    """`hide --resume` keeps the run's finishing phase unless --hidden-finish asks for another, which
    a run that has not begun its phase takes and one that has refuses."""
    out = tmp_path / "c"
    args = ["hide", "--out", str(out), "--iterations", "4", "--quiet", "--payload", "object", "--hidden-offsets",
            "2", "--hidden-width", "8", "--hidden-anchors", "40", *TINY]

    def recorded(name="hidden_finish"):
        return json.loads((out / "config.json").read_text())["secure"][name]

    def last_step():
        return json.loads((out / "log.jsonl").read_text().splitlines()[-1])["step"]

    assert main(args + ["--hidden-finish", "0"]) == 0
    assert (recorded(), last_step()) == (0.0, 4)
    assert recorded("finish_robust") == FINISH_ROBUST_RECIPE  # "auto", resolved for the record
    assert main(args + ["--resume"]) == 0  # not the default 0.25: the run's own 0
    assert (recorded(), last_step()) == (0.0, 4)
    assert main(args + ["--resume", "--hidden-finish", "0.5", "--finish-robust", "noise-feat:0.2"]) == 0
    assert (recorded(), last_step(), recorded("finish_robust")) == (0.5, 6, "noise-feat:0.2")
    assert json.loads((out / "log.jsonl").read_text().splitlines()[-1])["phase"] == "finish"
    capsys.readouterr()
    assert main(args + ["--resume", "--hidden-finish", "1"]) == 2
    assert "finishing phase with hidden_finish 0.5 (--hidden-finish)" in capsys.readouterr().err
    assert main(args + ["--resume", "--finish-robust", "none"]) == 2
    assert "finishing phase with finish_robust 'noise-feat:0.2' (--finish-robust)" in capsys.readouterr().err
    assert (recorded(), recorded("finish_robust")) == (0.5, "noise-feat:0.2")
    # left out, both are the run's own, not the defaults (which the phase begun would refuse)
    assert main(args + ["--resume"]) == 0
    assert (recorded(), recorded("finish_robust")) == (0.5, "noise-feat:0.2")


def test_without_hdger_offsets_are_explicit_and_follow_growth(hidden_scene, tmp_path):
    trainer = SecureTrainer(hidden_scene, TrainConfig(iterations=30, raster=CPU_RASTER),
                            SecureConfig(payload="object", hdger=False, strategy=RDO))
    s = trainer.strategy
    s.start_stat, s.update_from, s.update_interval, s.update_until = 0, 0, 10, 30
    assert trainer.model.private.offset_mlp is None
    for _ in range(30):
        trainer.step()
    model = trainer.model.anchors
    assert model.hidden_offsets.shape == model.offsets.shape  # rows added and removed with the anchors
    assert model.hidden_offsets.abs().sum() > 0  # trained
    moments = trainer.optimizer.state[model.hidden_offsets]
    assert moments["exp_avg"].shape == model.hidden_offsets.shape
    with pytest.raises(ValueError, match="HDGER"):
        save_container(tmp_path, trainer.model, [KeyFile({})])


def test_hidden_branch_switches(hidden_scene):
    """λ overrides the payload's default; hidden_feature_grad / hidden_scaling_grad scale the share of
    ℓ_hid's gradient that reaches the public anchor features f_v / scalings l_v (0: none), leaving
    the render itself and the private heads' gradients unchanged."""
    config = TrainConfig(iterations=5, raster=CPU_RASTER)
    with pytest.raises(ValueError, match="hidden_weight"):
        SecureTrainer(hidden_scene, config, SecureConfig(payload="object", hidden_weight=-1.0))
    for name in ("hidden_feature_grad", "hidden_scaling_grad"):  # refused before any training
        with pytest.raises(ValueError, match=name + r" must lie in \[0, 1\]"):
            SecureTrainer(hidden_scene, config, SecureConfig(payload="object", **{name: 2.0}))
    runs = {}
    for factors in ((1.0, 1.0), (0.5, 0.0), (0.0, 0.5)):
        trainer = SecureTrainer(hidden_scene, config, SecureConfig(payload="object", hidden_weight=3.0,
                                hidden_feature_grad=factors[0], hidden_scaling_grad=factors[1]))
        assert trainer.payload.weight == 3.0
        out = trainer.render_hidden(hidden_scene.train[0], camera_index=0)
        trainer.image_loss(out, trainer.payload.views[0]).backward()
        grad = lambda t: torch.zeros_like(t) if t.grad is None else t.grad  # noqa: E731
        runs[factors] = (out["image"].detach(), grad(trainer.model.anchors.feat), grad(trainer.model.anchors.scaling),
                         grad(trainer.model.private.offset_mlp[0].weight))
    image, feat, scaling, private = runs[(1.0, 1.0)]
    assert feat.abs().sum() > 0 and scaling.abs().sum() > 0
    for (f, s), (img, feat_f, scaling_f, private_f) in runs.items():
        assert torch.equal(img, image)  # same initialisation (seeded): same forward pass
        torch.testing.assert_close(feat_f, f * feat, rtol=1e-4, atol=1e-9)
        torch.testing.assert_close(scaling_f, s * scaling, rtol=1e-4, atol=1e-9)
        torch.testing.assert_close(private_f, private, rtol=1e-4, atol=1e-9)


def test_by_default_the_codes_carry_the_hidden_object_and_its_loss_moves_nothing_in_the_release(hidden_scene):
    """An object in the cover mode decodes through the key's private codes (BOX_FRAME_DEFAULTS) and,
    unless the shares are given, no ℓ_hid gradient reaches the public features or scalings, while
    the codes and the private heads get theirs; without codes (``hidden_codes=0``, or the anchor
    frame) the shares are GRADIENT_SHARES."""
    from securegs_warp.config import BOX_FRAME_DEFAULTS, GRADIENT_SHARES

    secure = SecureConfig()
    assert secure.gradient_shares("object", "cover") == (0.0, 0.0)
    assert secure.gradient_shares("image", "rdo") == GRADIENT_SHARES  # the anchor frame: no codes
    assert SecureConfig(hidden_codes=0).gradient_shares("object", "cover") == GRADIENT_SHARES
    assert SecureConfig(hidden_scaling_grad=0.5).gradient_shares("object", "cover") == (0.0, 0.5)
    trainer = SecureTrainer(hidden_scene, TrainConfig(iterations=5, raster=CPU_RASTER), SecureConfig(payload="object"))
    codes = trainer.model.private.codes
    assert (codes.rows, codes.cells) == (BOX_FRAME_DEFAULTS["codes"], BOX_FRAME_DEFAULTS["code_cells"])
    out = trainer.render_hidden(hidden_scene.train[0], camera_index=0)
    trainer.image_loss(out, trainer.payload.views[0]).backward()
    anchors = trainer.model.anchors
    for public in (anchors.feat, anchors.scaling):
        assert public.grad is None or not public.grad.any()
    assert codes.table.grad.abs().sum() > 0 and trainer.model.private.offset_mlp[0].weight.grad.abs().sum() > 0


# A run small enough to train twice in a test, with growth (on the CPU: CUDA's atomics sum in no
# fixed order, so there two runs of one seed differ).
SMALL_RUN = ["--width", "32", "--height", "24", "--train-views", "4", "--test-views", "1", "--iterations", "60",
             "--quiet", "--seed", "3", "--device", "cpu"]


def test_by_default_an_objects_release_is_the_plain_scaffold_gs_model_of_its_seed(tmp_path):
    """With the private codes (the default for an object) no hidden gradient reaches the release, and
    robust training draws from a stream of its own: a container hiding an object (no bits) publishes
    the point cloud that plain Scaffold-GS of the same seed writes, byte for byte, anchors grown
    included, and the same MLP weights (the MLP files differ in torch's per-save serialization id
    alone), whichever object it hides and where; without the codes (a share of the hidden gradient on
    the public features) the point cloud differs."""
    assert main(["train", "--out", str(tmp_path / "plain"), *SMALL_RUN]) == 0
    runs = {"mug": ["--hide", "mug"], "pawn": ["--hide", "pawn", "--placement", "sink"],
            "pawn_nocodes": ["--hide", "pawn", "--placement", "sink", "--hidden-codes", "0"]}
    for name, extra in runs.items():
        assert main(["hide", "--out", str(tmp_path / name), "--payload", "object", *SMALL_RUN, *extra]) == 0
    releases = {"plain": tmp_path / "plain" / "model", **{name: tmp_path / name / "public" for name in runs}}
    cloud = {name: (folder / "point_cloud.ply").read_bytes() for name, folder in releases.items()}
    assert cloud["plain"] == cloud["mug"] == cloud["pawn"] != cloud["pawn_nocodes"]
    weights = [open_container(releases[name])[0].heads.state_dict() for name in ("plain", "mug", "pawn")]
    for other in weights[1:]:
        assert other.keys() == weights[0].keys() and all(torch.equal(other[k], weights[0][k]) for k in other)
    log = [json.loads(line) for line in (tmp_path / "mug" / "log.jsonl").read_text().splitlines()]
    assert sum(row.get("grown", 0) for row in log) > 0  # the density strategy ran, and grew the same anchors


def test_bits_from_growth_end_leaves_the_plain_models_anchors(tmp_path):
    """By default (--bits-from growth-end) the bits are projected only once the density strategy has
    fixed the anchors: a container of an object and bits keeps the anchor positions that plain
    Scaffold-GS of its seed grew, float for float, and still reads its whole message."""
    with pytest.raises(ValueError, match="bits_from must be one of start, growth-end"):
        SecureConfig(bits_from="middle")
    assert main(["train", "--out", str(tmp_path / "plain"), *SMALL_RUN]) == 0
    assert main(["hide", "--out", str(tmp_path / "hide"), "--hide", "mug", "--payload", "object+bits:16", *SMALL_RUN]) == 0
    xyz = open_container(tmp_path / "hide" / "public")[0].anchors.xyz
    assert torch.equal(xyz, open_container(tmp_path / "plain" / "model")[0].anchors.xyz)
    assert json.loads((tmp_path / "hide" / "metrics.json").read_text())["bit_accuracy"] == 1.0


def test_the_bits_are_projected_from_the_step_bits_from_names(hidden_scene):
    """bits_from "start": every feature agrees with its bit by the margin after every step;
    "growth-end": not before the density strategy's last step (update_until), after every step from
    then on; a run that does not densify projects from the first step either way."""
    config = TrainConfig(iterations=8, raster=CPU_RASTER)
    trainers = {mode: SecureTrainer(hidden_scene, config, SecureConfig(payload="object+bits:16", bits_from=mode))
                for mode in ("start", "growth-end")}
    late = trainers["growth-end"]
    assert trainers["start"].bits_start == 0 and late.bits_start == late.strategy.update_until >= 2
    still = SecureTrainer(hidden_scene, dataclasses.replace(config, densify=False), SecureConfig(payload="bits:16"))
    assert still.bits_start == 0

    def agrees(trainer) -> bool:
        anchors, bits = trainer.model.anchors, trainer.model.private.bits
        feat = anchors.feat.detach()
        return torch.allclose(bits.project(feat, anchors.xyz, trainer.secure.bit_margin), feat, atol=1e-5)

    for step in range(1, config.iterations + 1):
        for trainer in trainers.values():
            trainer.step()
        assert agrees(trainers["start"]) and agrees(late) == (step > late.bits_start), step


def test_feature_grad_until_frees_the_public_features(hidden_scene):
    """After feature_grad_until of the run no ℓ_hid gradient reaches f_v; the private heads still get theirs."""
    config = TrainConfig(iterations=4, raster=CPU_RASTER)
    with pytest.raises(ValueError, match=r"feature_grad_until must lie in \[0, 1\]"):
        SecureTrainer(hidden_scene, config, SecureConfig(payload="object", feature_grad_until=1.5))
    trainer = SecureTrainer(hidden_scene, config, SecureConfig(payload="object", hidden_feature_grad=0.5,
                            feature_grad_until=0.5))
    # step() counts the step before the hidden loss runs: steps 1..4 of a 4-step run
    shares = []
    for step in range(1, 5):
        trainer.step_count = step
        shares.append(trainer.current_feature_grad())
    assert shares == [0.5, 0.5, 0.0, 0.0]
    feature_grads = {}
    for step in (2, 3):  # the last step with the share, the first without
        trainer.step_count = step
        trainer.optimizer.zero_grad(set_to_none=True)
        out = trainer.render_hidden(hidden_scene.train[0], camera_index=0)
        trainer.image_loss(out, trainer.payload.views[0]).backward()
        feat = trainer.model.anchors.feat.grad
        feature_grads[step] = 0.0 if feat is None else float(feat.abs().sum())
        assert trainer.model.private.offset_mlp[0].weight.grad.abs().sum() > 0  # the private heads learn on
    assert feature_grads[2] > 0 and feature_grads[3] == 0


def test_hidden_stride_trains_the_hidden_branch_every_nth_step_at_n_times_its_weight(hidden_scene, monkeypatch):
    """hidden_stride N: the hidden render joins the loss on steps N, 2N, ... only, weighted N·λ; the
    steps between are public-only, and the private heads get no gradient on them."""
    config = TrainConfig(iterations=6, raster=CPU_RASTER)
    with pytest.raises(ValueError, match="hidden_stride must be >= 1"):
        SecureTrainer(hidden_scene, config, SecureConfig(payload="object", hidden_stride=0))
    trainer = SecureTrainer(hidden_scene, config, SecureConfig(payload="object+bits:16", hidden_stride=3))
    weights, private_grads = [], []
    losses = trainer.image_losses

    def recording(renders):
        weights.append([w for _, _, w in renders])
        return losses(renders)

    monkeypatch.setattr(trainer, "image_losses", recording)
    step = trainer.optimizer.step

    def stepping(*args, **kwargs):
        g = trainer.model.private.offset_mlp[0].weight.grad
        private_grads.append(g is not None and bool(g.abs().sum() > 0))
        return step(*args, **kwargs)

    monkeypatch.setattr(trainer.optimizer, "step", stepping)
    results = [trainer.step() for _ in range(6)]
    lam = trainer.payload.weight
    assert weights == [[1.0], [1.0], [1.0, 3 * lam]] * 2
    assert private_grads == [False, False, True] * 2
    assert ["psnr_hidden" in r for r in results] == [False, False, True] * 2
    assert trainer.bit_accuracy() == 1.0  # the bits are projected after every step, hidden or not


def _release_state(trainer) -> dict:
    """Every tensor of the release (anchors and public heads), copied."""
    return {name: t.detach().clone() for name, t in
            [*trainer.model.anchors.state_dict().items(), *trainer.model.heads.state_dict().items()]}


def test_the_finishing_phase_trains_the_private_heads_alone_and_resumes(hidden_scene, tmp_path):
    """hidden_finish F: F·iterations more steps after the joint run, in which only the private heads
    move (the release, and with it the bits, stays as the joint run left it), at decaying learning
    rates; a checkpoint written in the phase resumes it to the same key."""
    config = TrainConfig(iterations=4, raster=CPU_RASTER)
    with pytest.raises(ValueError, match="hidden_finish must be >= 0"):
        SecureConfig(hidden_finish=-0.5)
    secure = SecureConfig(payload="object+bits:16", hidden_finish=1.0, hidden_offsets=2, hidden_width=8,
                          hidden_anchors=40)
    trainer = SecureTrainer(hidden_scene, config, secure)
    assert trainer.total_steps == 8
    for _ in range(4):
        assert "phase" not in trainer.step()
    trainer.save_checkpoint(tmp_path / "joint.pt")
    release = _release_state(trainer)
    private = {name: t.detach().clone() for name, t in trainer.model.private.state_dict().items()}
    bits = trainer.bit_accuracy()
    stats, rates = [], []
    for _ in range(2):
        stats.append(trainer.step())
        rates.append(trainer._finish_optimizer.param_groups[0]["lr"])
    assert [s["phase"] for s in stats] == ["finish"] * 2
    assert all(s["psnr"] == s["psnr_hidden"] for s in stats)
    assert rates[1] < rates[0]
    after = _release_state(trainer)
    assert all(torch.equal(release[name], after[name]) for name in release)
    moved = trainer.model.private.state_dict()
    assert any(not torch.equal(private[name], moved[name]) for name in private if "offset_mlp" in name)
    assert trainer.bit_accuracy() == bits
    # Frozen for the phase's steps only: afterwards the model trains like any other (an attack's fine-tuning).
    assert trainer.model.anchors.feat.requires_grad and all(p.requires_grad for p in trainer.model.heads.parameters())

    trainer.save_checkpoint(tmp_path / "run.pt")
    resumed = SecureTrainer(hidden_scene, config, secure)
    resumed.load_checkpoint(tmp_path / "run.pt")
    generator = trainer.generator.get_state()
    for t in (trainer, resumed):
        t.generator.set_state(generator)
        while t.step_count < t.total_steps:
            t.step()
    assert all(torch.equal(a, b) for a, b in zip(trainer.model.private.state_dict().values(),
                                                  resumed.model.private.state_dict().values()))
    assert all(torch.equal(t, _release_state(resumed)[name]) for name, t in _release_state(trainer).items())
    # The last step of the phase runs at the schedule's final rate.
    final = trainer._mlp_schedule(trainer._finish_optimizer.param_groups[0]["name"])[1]
    assert trainer._finish_optimizer.param_groups[0]["lr"] == pytest.approx(final)

    # A run that has not begun its phase may take one of another length; one that has, may not.
    longer = SecureTrainer(hidden_scene, config, dataclasses.replace(secure, hidden_finish=2.0))
    longer.load_checkpoint(tmp_path / "joint.pt")
    assert (longer.step_count, longer.total_steps) == (4, 12)
    assert longer.step()["phase"] == "finish"
    refused = SecureTrainer(hidden_scene, config, dataclasses.replace(secure, hidden_finish=2.0))
    with pytest.raises(ValueError, match=r"2 steps into a finishing phase with hidden_finish 1\.0"):
        refused.load_checkpoint(tmp_path / "run.pt")
    assert refused.step_count == 0  # refused before anything of the checkpoint was loaded
    with pytest.raises(ValueError, match="hidden_offsets differs"):
        SecureTrainer(hidden_scene, config, dataclasses.replace(secure, hidden_offsets=3)).load_checkpoint(
            tmp_path / "run.pt")

    # Bits alone have no hidden render: nothing to finish.
    assert SecureTrainer(hidden_scene, config, SecureConfig(payload="bits:16", hidden_finish=1.0)).total_steps == 4
    # By default an object in the cover mode gets FINISH_FRACTION; the paper's RDO, where it was not
    # measured, none.
    from securegs_warp.config import FINISH_FRACTION
    longer_run = TrainConfig(iterations=40, raster=CPU_RASTER)
    default = SecureTrainer(hidden_scene, longer_run, SecureConfig(payload="object+bits:16"))
    assert (default.secure.hidden_finish, default.total_steps) == (FINISH_FRACTION, 40 + round(40 * FINISH_FRACTION))
    assert SecureTrainer(hidden_scene, longer_run, SecureConfig(payload="object", strategy=RDO)).total_steps == 40


def test_the_finishing_phase_trains_against_its_own_attacks(hidden_scene, monkeypatch):
    """The joint run's hidden branch trains against ``robust``, the finishing phase's against
    ``finish_robust``; "auto" gives the phase FINISH_ROBUST_RECIPE only where ``robust`` "auto" chose
    ROBUST_RECIPE, and the joint run's attacks otherwise."""
    import securegs_warp.secure.trainer as trainer_module
    from securegs_warp.config import ROBUST_RECIPE

    auto = SecureConfig()
    assert auto.finish_robust_spec(["object", None], "cover") == FINISH_ROBUST_RECIPE
    assert auto.robust_spec(["object", None], "cover") == ROBUST_RECIPE
    assert auto.finish_robust_spec(["image"], "rdo") is None
    assert apply_overrides(auto, {"robust": "noise-feat:0.2"}).finish_robust_spec(["object"], "cover") == "noise-feat:0.2"
    assert apply_overrides(auto, {"robust": "none"}).finish_robust_spec(["object"], "cover") is None
    assert apply_overrides(auto, {"finish_robust": "none"}).finish_robust_spec(["object"], "cover") is None
    with pytest.raises(ValueError, match="^finish_robust: noise-offset:0.1 cannot be trained against"):
        SecureConfig(finish_robust="noise-offset:0.1")

    drawn = []
    perturb = trainer_module.perturb
    monkeypatch.setattr(trainer_module, "perturb",
                        lambda anchors, attacks, *a: drawn.append([x.text for x in attacks]) or perturb(anchors, attacks, *a))
    secure = SecureConfig(payload="object", robust="noise-feat:0.1", finish_robust="prune-random:0.9", hidden_finish=1.0,
                          hidden_offsets=2, hidden_width=8, hidden_anchors=40)
    trainer = SecureTrainer(hidden_scene, TrainConfig(iterations=2, raster=CPU_RASTER), secure)
    for _ in range(3):
        trainer.step()
    assert drawn == [["noise-feat:0.1"], ["noise-feat:0.1"], ["prune-random:0.9"]]


def test_the_finishing_phase_keys_the_mean_of_its_late_weights_and_resumes_it(hidden_scene, tmp_path):
    """The key's private heads are the mean of their weights after each phase step past
    FINISH_AVERAGE_FROM of the phase, not the last step's; a checkpoint inside that window resumes
    the mean to the same key."""
    from securegs_warp.secure.trainer import FINISH_AVERAGE_FROM
    config = TrainConfig(iterations=4, raster=CPU_RASTER)
    secure = SecureConfig(payload="object", hidden_finish=1.0, hidden_offsets=2, hidden_width=8, hidden_anchors=40)
    trainer = SecureTrainer(hidden_scene, config, secure)
    while trainer.step_count < config.iterations:
        trainer.step()
    weights = lambda t: [p.detach().clone() for g in t._finishing_optimizer().param_groups for p in g["params"]]  # noqa: E731
    seen = {}
    fold = trainer._average_private

    def recording(step):
        seen[step] = weights(trainer)  # after the step's update, before the mean replaces them
        fold(step)

    trainer._average_private = recording
    while trainer.step_count < trainer.total_steps:
        trainer.step()
        if trainer.step_count == trainer.total_steps - 1:
            trainer.save_checkpoint(tmp_path / "late.pt")
    window = [step for step in seen if step > config.iterations + FINISH_AVERAGE_FROM * trainer.finish_steps]
    assert window == [7, 8]
    mean = [torch.stack([seen[step][i] for step in window]).mean(0) for i in range(len(seen[8]))]
    final = weights(trainer)
    assert all(torch.allclose(f, m, atol=1e-7) for f, m in zip(final, mean))
    assert any(not torch.allclose(f, last) for f, last in zip(final, seen[8]))

    resumed = SecureTrainer(hidden_scene, config, secure)
    resumed.load_checkpoint(tmp_path / "late.pt")
    while resumed.step_count < resumed.total_steps:
        resumed.step()
    assert all(torch.allclose(a, b, atol=1e-7) for a, b in zip(final, weights(resumed)))


def test_a_checkpoint_whose_private_heads_have_other_shapes_is_refused_by_name(hidden_scene, tmp_path, monkeypatch):
    """The same config can mean other private-head shapes across versions (a default changed): resuming
    names the first tensor whose shape differs instead of failing inside load_state_dict."""
    from securegs_warp.config import BOX_FRAME_DEFAULTS

    config = TrainConfig(iterations=4, raster=CPU_RASTER)
    secure = SecureConfig(payload="object", hidden_offsets=2, hidden_width=8, hidden_anchors=40)
    monkeypatch.setitem(BOX_FRAME_DEFAULTS, "encoding", 0)  # the default before it became 6
    old = SecureTrainer(hidden_scene, config, secure)
    old.step()
    old.save_checkpoint(tmp_path / "run.pt")
    monkeypatch.undo()
    fresh = SecureTrainer(hidden_scene, config, secure)
    anchors = fresh.model.anchors.xyz.detach().clone()
    with pytest.raises(ValueError, match=r"run\.pt: the checkpoint's private heads have other shapes.*offset_mlp"):
        fresh.load_checkpoint(tmp_path / "run.pt")
    # refused before anything was loaded: the trainer is as it was
    assert fresh.step_count == 0 and torch.equal(fresh.model.anchors.xyz.detach(), anchors)


def test_a_checkpoint_that_recorded_a_literal_message_still_resumes(hidden_scene, tmp_path):
    # Checkpoints of earlier versions hold the literal in their config; they are compared as recorded.
    config = TrainConfig(iterations=4, raster=CPU_RASTER)
    trainer = SecureTrainer(hidden_scene, config, SecureConfig(payload="bits:0b1011"))
    trainer.step()
    state = trainer.checkpoint_state()
    assert state["config"]["secure"]["payload"] == "bits:4"
    state["config"]["secure"]["payload"] = "bits:0b1011"
    fresh = SecureTrainer(hidden_scene, config, SecureConfig(payload="bits:0b1011"))
    fresh.restore(state, tmp_path / "run.pt")
    assert fresh.step_count == 1


def test_a_checkpoint_without_its_secrets_record_is_refused_in_words(hidden_scene, tmp_path):
    config = TrainConfig(iterations=4, raster=CPU_RASTER)
    secure = SecureConfig(payload="object+bits:8", hidden_offsets=2, hidden_width=8, hidden_anchors=40)
    trainer = SecureTrainer(hidden_scene, config, secure)
    trainer.step()
    state = trainer.checkpoint_state()
    del state["bit_seeds"]  # as an earlier version wrote it
    fresh = SecureTrainer(hidden_scene, config, secure)
    with pytest.raises(ValueError, match="another number of secrets.*earlier securegs-warp"):
        fresh.restore(state, tmp_path / "run.pt")
    assert fresh.step_count == 0


@pytest.mark.parametrize("growth_at", ["hidden", "public"])
def test_hidden_anchors_grow_where_the_hidden_gaussians_are(hidden_scene, growth_at):
    """Γ_hid growth proposes anchors at the hidden Gaussians' mean positions (∇_hid's own
    statistics); with hidden_growth_at="public", at the public offsets' positions as before."""
    trainer = SecureTrainer(hidden_scene, TrainConfig(iterations=5, raster=CPU_RASTER), SecureConfig(payload="object"))
    model, state, strategy = trainer.model.anchors, trainer.strategy_state, trainer.strategy
    strategy.hidden_growth_at = growth_at
    voxel = model.voxel_size
    target = model.xyz.detach().max(dim=0).values + 40 * voxel  # outside the scene: no public Gaussian near
    rows = slice(0, 8 * model.n_offsets)  # eight anchors' Gaussians all saw the hidden one there
    views = 100.0
    state["hid_grad_denom"][rows] = views
    state["hid_grad_accum"][rows] = views  # mean gradient 1 ≫ τ_fix
    state["hid_pos_accum"][rows] = views * target
    n_before = model.num_anchors
    grown = strategy.grow(model, trainer.optimizer, state, prefix="hid_", threshold=strategy.grad_threshold,
                          generator=trainer.generator, positions=strategy.hidden_positions(model, state))
    assert model.num_anchors == n_before + grown
    distance = (model.xyz.detach()[n_before:] - target).norm(dim=1)
    if growth_at == "hidden":  # quantised to the coarsest growth cell (16 voxels): within half its diagonal
        assert grown > 0 and float(distance.max()) <= 8 * voxel * 3 ** 0.5 + 1e-6
    else:  # the public Gaussians still sit on their anchors (zero offsets): nothing may appear out there
        assert grown == 0 or float(distance.min()) > 20 * voxel
    assert state["hid_pos_accum"].shape == (model.num_anchors * model.n_offsets, 3)
    assert float(state["hid_pos_accum"][rows].abs().sum()) == 0.0  # reset with the gradient statistics


@pytest.mark.parametrize("per_lambda", [True, False])
def test_hidden_gradient_statistic_is_per_unit_of_hidden_loss(hidden_scene, per_lambda):
    """∇_hid divides out λ by default, so Γ_hid grows from the hidden image's own error whatever the
    payload's weight; hidden_grad_per_lambda=False accumulates λ·∇ (Algorithm 1's ∇ℓ_total)."""
    accum = {}
    for weight in (1.0, 10.0):
        trainer = SecureTrainer(hidden_scene, TrainConfig(iterations=5, raster=CPU_RASTER), SecureConfig(
            payload="object", hidden_weight=weight,
            strategy=RegionAwareStrategy(mode="rdo", hidden_every=1, hidden_grad_per_lambda=per_lambda)))
        trainer.step()
        accum[weight] = trainer.strategy_state["hid_grad_accum"]
    assert accum[1.0].sum() > 0
    torch.testing.assert_close(accum[10.0], accum[1.0] * (1.0 if per_lambda else 10.0), rtol=1e-3, atol=1e-9)


@pytest.mark.parametrize("tau_scale", [1.0, 1e4])
def test_hidden_growth_threshold_scale(hidden_scene, tau_scale):
    """Γ_hid grows at τ_fix · hidden_tau_scale: a mean ∇_hid of 1 grows anchors at the paper's
    τ_fix and none at τ_fix · 10⁴ = 2; values below 1 are refused."""
    trainer = SecureTrainer(hidden_scene, TrainConfig(iterations=5, raster=CPU_RASTER), SecureConfig(
                            payload="object", strategy=RegionAwareStrategy(mode="rdo", hidden_tau_scale=tau_scale)))
    state, rows, views = trainer.strategy_state, slice(0, 8 * trainer.model.anchors.n_offsets), 100.0
    state["hid_grad_denom"][rows] = views
    state["hid_grad_accum"][rows] = views
    changed = trainer.strategy.adjust(trainer.model.anchors, trainer.optimizer, state, trainer.generator)
    assert (changed["grown_hidden"] > 0) == (tau_scale == 1.0)
    assert changed["hidden_anchors"] == changed["grown_hidden"]
    with pytest.raises(ValueError, match="hidden_tau_scale"):
        SecureTrainer(hidden_scene, TrainConfig(iterations=5, raster=CPU_RASTER), SecureConfig(
                      payload="object", strategy=RegionAwareStrategy(hidden_tau_scale=0.5)))


def test_a_mode_reading_hidden_rows_refuses_another_hidden_k(hidden_scene):
    with pytest.raises(ValueError, match=r"hidden_offsets = k \(10\), got 32"):
        SecureTrainer(hidden_scene, TrainConfig(iterations=5, raster=CPU_RASTER), SecureConfig(
                      payload="object", hidden_frame="box", strategy=RegionAwareStrategy(mode="rdo")))


def test_hidden_opacity_in_pruning_statistic_is_switchable(hidden_scene):
    """By default the hidden Gaussians' opacity counts toward keeping an anchor; with
    hidden_opacity_keeps=False pruning sees the public opacity alone (same first step otherwise)."""
    accum = {}
    for keeps in (True, False):
        trainer = SecureTrainer(hidden_scene, TrainConfig(iterations=5, raster=CPU_RASTER), SecureConfig(
                                payload="object", strategy=RegionAwareStrategy(mode="rdo", hidden_opacity_keeps=keeps)))
        trainer.step()
        accum[keeps] = trainer.strategy_state["opacity_accum"]
    assert (accum[True] >= accum[False]).all() and accum[True].sum() > accum[False].sum()


def test_anchors_robust_training_drops_get_no_hidden_opacity_credit(hidden_scene, monkeypatch):
    """In the box frame a dropped anchor's rows stay in the hidden decoding (``keep``); the pruning
    statistic must still credit it nothing from the hidden render, as when it was left out."""
    import securegs_warp.secure.model as secure_model
    real, accum, keeps = secure_model.render_view, {}, {}
    for credit in (True, False):
        def spy(anchors, *args, credit=credit, **kwargs):
            keeps[credit] = kwargs.get("keep")
            return real(anchors, *args, **kwargs)
        monkeypatch.setattr(secure_model, "render_view", spy)
        config = TrainConfig(iterations=5, raster=CPU_RASTER)
        trainer = SecureTrainer(hidden_scene, config, SecureConfig(
            payload="object", robust="prune-random:0.9", hidden_frame="box", hidden_offsets=config.heads.n_offsets,
            strategy=RegionAwareStrategy(mode="rdo", hidden_opacity_keeps=credit)))
        trainer.step()
        accum[credit] = trainer.strategy_state["opacity_accum"]
    dropped = ~keeps[True]
    assert torch.equal(keeps[True], keeps[False]) and dropped.any()
    assert torch.equal(accum[True][dropped], accum[False][dropped])
    assert accum[True].sum() > accum[False].sum()


def _write_blender_folder(scene, folder):
    """``scene``'s cameras and images as a NeRF-synthetic (Blender) data folder."""
    import imageio.v3 as iio

    flip = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV camera axes -> Blender's (y up, looking down -z)
    for split, cams in (("train", scene.train), ("test", scene.test)):
        (folder / split).mkdir(parents=True)
        frames = []
        for k, cam in enumerate(cams):
            iio.imwrite(folder / split / f"r_{k}.png", (cam.image * 255 + 0.5).astype(np.uint8))
            c2w = np.linalg.inv(cam.viewmat.astype(np.float64)) @ flip
            frames.append({"file_path": f"./{split}/r_{k}", "transform_matrix": c2w.tolist()})
        angle = 2 * np.arctan(cams[0].width / (2 * float(cams[0].K[0, 0])))
        (folder / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))


def test_reveal_needs_only_the_release_and_the_key(tmp_path, monkeypatch):
    """The key stores the cameras and what reveal needs: with the training data deleted (and any
    scene loading made to fail), reveal renders the hidden image and reads the bits."""
    data, out = tmp_path / "data", tmp_path / "c"
    _write_blender_folder(make_synthetic_scene(width=40, height=30, n_train=4, n_test=2, n_points=300), data)
    assert main(["hide", "--scene", str(data), "--payload", "image:builtin@1+bits:8", "--iterations", "6",
                 "--out", str(out), "--quiet"]) == 0
    import shutil

    import securegs_warp.data

    shutil.rmtree(data)

    def no_scene(*args, **kwargs):
        raise AssertionError("reveal must not load a scene")

    monkeypatch.setattr(securegs_warp.data, "load_scene", no_scene)
    revealed = tmp_path / "r"
    assert main(["reveal", str(out / "public"), "--key", str(out / "key.safetensors"), "--out", str(revealed)]) == 0
    assert len(json.loads((revealed / "bits.json").read_text())["bits"]) == 8
    hidden = sorted(p.name for p in (revealed / "renders").iterdir() if p.name.startswith("hidden_"))
    assert hidden == ["hidden_train_r_1.png"]  # the image payload's own view, named as in the data


def test_after_update_refits_serving_and_bits_when_anchors_change(hidden_scene):
    """after_update keeps the serving radius and each anchor's bit between densifications; when the
    anchors change (here half are pruned) both are fitted again: the radius is a fresh fit's and
    every remaining feature agrees with its bit by the margin."""
    config = TrainConfig(iterations=10, raster=CPU_RASTER, densify=False)
    trainer = SecureTrainer(hidden_scene, config, SecureConfig(payload="object+bits:16", hidden_anchors=64))
    private = trainer.model.private
    assert private.serves_by_radius and trainer.model.anchors.num_anchors > 2 * 64
    trainer.step()
    anchors = trainer.model.anchors
    radius = private.serving_radius.clone()
    drop = torch.zeros(anchors.num_anchors, dtype=torch.bool)
    drop[private.box_distance(anchors.xyz).argsort()[::2]] = True  # every other anchor, nearest the box first
    anchors.prune_anchors(drop, trainer.optimizer)
    with torch.no_grad():
        anchors.feat.mul_(-1.0)  # undo the projection: most anchors now disagree with their bit
    trainer.after_update(trainer.step_count + 1)
    refit = private.serving_radius.clone()
    private.fix_serving(anchors.xyz)
    assert torch.equal(refit, private.serving_radius) and not torch.equal(refit, radius)
    # The kept indices follow the refitted mask (and a new box).
    for _ in range(2):
        mask = private.serving_mask(anchors.xyz)
        assert mask.sum() == 64 and torch.equal(private.serving_index(anchors.xyz), mask.nonzero()[:, 0])
        private.set_box(private.box[0] - 0.5, private.box[0] + 0.2)
        private.fix_serving(anchors.xyz)
    logits, bit = private.bit_logits(anchors.feat.detach(), anchors.xyz)
    sign = trainer.payload.bits.float()[bit] * 2 - 1
    assert float((sign * logits).min()) >= trainer.secure.bit_margin - 1e-4
