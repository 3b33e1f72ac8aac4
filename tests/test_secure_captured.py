"""The box frame's private decoding replayed from CUDA graphs (secure.captured), and its uncompacted
render rasterized from Warp graphs (RasterOptions.capture), render and differentiate as the same
decoding and render op by op. The comparison needs CUDA (SECUREGS_TEST_DEVICE=cuda on a GPU
machine); on the CPU the option leaves training unchanged and the graphs refuse CPU tensors."""
import dataclasses

import numpy as np
import pytest
import torch

from securegs_warp import raster_graph

from securegs_warp.config import SecureConfig, apply_overrides
from securegs_warp.data import make_synthetic_scene
from securegs_warp.raster_cases import TEST_DEVICE
from securegs_warp.rasterizer import RasterOptions
from securegs_warp.secure import SecureTrainer
from securegs_warp.secure.captured import CapturedRows
from securegs_warp.train import TrainConfig


@pytest.fixture(autouse=True)
def fresh_pool():
    """Each test sees only its own captured renders."""
    raster_graph._POOL.clear()
    yield
    raster_graph._POOL.clear()


def _trainer(device, capture=True, serving=60, robust=None, finish=0.0, latent=0, codes=0, code_scales=False):
    scene = make_synthetic_scene(hidden="mug", level="object", width=96, height=72, n_train=4, n_test=1,
                                 n_points=600, device=device)
    secure = apply_overrides(SecureConfig(payload="object", robust=robust, hidden_finish=finish),
                             {"strategy.mode": "cover", "hidden_offsets": 4, "hidden_width": 16,
                              "hidden_anchors": serving, "hidden_capture": capture, "hidden_latent": latent,
                              "hidden_codes": codes, "hidden_code_scales": code_scales})
    torch.manual_seed(0)
    return SecureTrainer(scene, TrainConfig(iterations=10, seed=0, raster=RasterOptions(tile_size=8)), secure,
                         device=device)


def _render_and_grads(t, capture, weights, compact=True, replay_raster=False, anchors=None):
    """The hidden render of training view 1 (of ``anchors``: robust training's perturbed ones) and
    the gradients of sum(weights · image) with respect to the anchor features and scalings and to
    the private heads' parameters."""
    for p in t.model.parameters():
        p.grad = None
    options = dataclasses.replace(t.config.raster, capture=replay_raster)
    out = t.model.render_hidden(t.scene.train[1], options, background=t.payloads[0].background,
                                feature_grad=0.1, capture=capture, compact=compact, anchors=anchors)
    (out["image"] * weights).sum().backward()
    private = t.model.secrets[0]
    named = {"feat": t.model.anchors.feat, "scaling": t.model.anchors.scaling,
             **{"private." + n: p for n, p in private.named_parameters()}}
    return out["image"].detach().clone(), {n: (None if p.grad is None else p.grad.clone()) for n, p in named.items()}


@pytest.mark.skipif(TEST_DEVICE != "cuda", reason="CUDA graphs: SECUREGS_TEST_DEVICE=cuda on a GPU machine")
@pytest.mark.parametrize("latent, codes, code_scales", [(0, 0, False), (4, 0, False), (0, 256, False), (0, 256, True)])
def test_the_replayed_decoding_renders_and_differentiates_as_the_eager_one(latent, codes, code_scales):
    t = _trainer("cuda", latent=latent, codes=codes, code_scales=code_scales)
    for _ in range(3):
        t.step()
    weights = torch.rand(t.scene.train[1].height, t.scene.train[1].width, 3, device="cuda")
    assert t.model._captured[0]._graphs, "training on CUDA did not take the replayed path"
    assert any(e.graphs for entries in raster_graph._POOL.values() for e in entries), \
        "training on CUDA did not replay the hidden rasterize"
    # Replays (uncompacted: with the rasterize replayed as well), the last after the parameters moved in place.
    for round_, compact in enumerate((True, False, True)):
        eager_image, eager = _render_and_grads(t, False, weights, compact)
        image, replayed = _render_and_grads(t, True, weights, compact, replay_raster=not compact)
        assert (image - eager_image).abs().max() < 1e-5, round_
        for name, g in eager.items():
            assert (g is None) == (replayed[name] is None), name
            if g is not None:
                scale = g.abs().max().clamp_min(1e-12)
                assert ((replayed[name] - g).abs().max() / scale) < 1e-4, (round_, name)
        with torch.no_grad():
            for p in t.model.secrets[0].parameters():
                p.add_(0.01 * torch.randn_like(p))
    # Training steps with the graphs keep the model finite and the hidden branch learning.
    before = t.evaluate_hidden()["psnr_hidden"]
    for _ in range(5):
        t.step()
    assert torch.isfinite(t.model.anchors.feat).all()
    assert t.evaluate_hidden()["psnr_hidden"] > before - 1.0


@pytest.mark.skipif(TEST_DEVICE != "cuda", reason="CUDA graphs: SECUREGS_TEST_DEVICE=cuda on a GPU machine")
@pytest.mark.parametrize("robust", ["prune-random:0.5+noise-feat:0.3", "prune-random:0.5+noise-feat:0.3+noise-xyz:0.01"])
def test_robust_training_replays_the_hidden_branch_and_matches_op_by_op(robust):
    """Robust training's dropout keeps the serving rows (``keep``), feature noise changes values
    only, and position noise serves as many rows by rank: the hidden branch is replayed as without
    attacks, with the same render and gradients."""
    from securegs_warp.secure.robust import perturb
    t = _trainer("cuda", robust=robust)
    for _ in range(3):
        t.step()
    assert t.model._captured[0]._graphs, "robust training did not replay the decoder"
    assert any(e.graphs for entries in raster_graph._POOL.values() for e in entries), \
        "robust training did not replay the hidden rasterize"
    weights = torch.rand(t.scene.train[1].height, t.scene.train[1].width, 3, device="cuda")
    anchors = perturb(t.model.anchors, t.robust, torch.Generator().manual_seed(1))
    assert not anchors.keep.all()
    assert (anchors.xyz is t.model.anchors.xyz) == ("noise-xyz" not in robust)
    eager_image, eager = _render_and_grads(t, False, weights, False, anchors=anchors)
    image, replayed = _render_and_grads(t, True, weights, False, replay_raster=True, anchors=anchors)
    assert (image - eager_image).abs().max() < 1e-5
    for name, g in eager.items():
        assert (g is None) == (replayed[name] is None), name
        if g is not None:
            assert ((replayed[name] - g).abs().max() / g.abs().max().clamp_min(1e-12)) < 1e-4, name


def test_on_the_cpu_the_option_renders_op_by_op():
    t = _trainer("cpu")
    weights = torch.rand(t.scene.train[1].height, t.scene.train[1].width, 3)
    image, grads = _render_and_grads(t, True, weights)
    eager_image, eager = _render_and_grads(t, False, weights)
    assert torch.equal(image, eager_image)
    assert all(torch.equal(grads[n], g) for n, g in eager.items() if g is not None)
    assert not t.model._captured


class _FakeGraphs:
    """Stands in for torch.cuda.make_graphed_callables on the CPU: counts captures and replays,
    and runs the module op by op, so that CapturedRows' rules can be checked without a GPU."""

    def __init__(self):
        self.captures = self.replays = 0

    def __call__(self, module, samples, allow_unused_input=False):
        self.captures += 1
        forward = module.forward

        def replay(*args):
            self.replays += 1
            return forward(*args)
        module.forward = replay
        return module


@pytest.fixture
def rows(monkeypatch):
    fake = _FakeGraphs()
    monkeypatch.setattr(torch.cuda, "make_graphed_callables", fake)
    t = _trainer("cpu")
    private = t.model.secrets[0]
    xyz = t.model.anchors.xyz[:7].detach()
    feat = t.model.anchors.feat[:7].detach().requires_grad_(True)
    log_scaling = t.model.anchors.scaling[:7].detach().requires_grad_(True)
    return CapturedRows(private), fake, private, (xyz, feat, log_scaling, torch.zeros(3))


def test_a_graph_decodes_the_same_rows_and_is_captured_once(rows):
    captured, fake, private, args = rows
    from securegs_warp.model.neural_gaussians import decode_rows
    want = decode_rows(private.decoder, private.hidden_offsets, *args)
    for _ in range(3):
        got = captured(*args)
        assert all(torch.equal(a, b) for a, b in zip(got, want))
        sum(o.sum() for o in got).backward()
        for p in private.parameters():
            p.grad = None
    assert (fake.captures, fake.replays) == (1, 3)


def test_a_second_call_before_the_backward_decodes_op_by_op(rows):
    captured, fake, private, args = rows
    first = captured(*args)
    second = captured(*args)  # the graph's buffers still hold the first call's activations
    assert fake.replays == 1
    sum(o.sum() for o in first).backward()
    for p in private.parameters():
        p.grad = None
    captured(*args)
    assert fake.replays == 2
    del second


def test_a_call_whose_outputs_are_dropped_frees_its_graph(rows):
    captured, fake, private, args = rows
    out = captured(*args)
    del out
    captured(*args)
    assert fake.replays == 2


def test_a_parameter_holding_a_gradient_or_replaced_is_not_replayed_over(rows):
    captured, fake, private, args = rows
    sum(o.sum() for o in captured(*args)).backward()
    captured(*args)  # gradients not yet set to None: the replay would overwrite them
    assert fake.replays == 1
    for p in private.parameters():
        p.grad = None
    layer = private.offset_mlp[0]
    layer.weight = torch.nn.Parameter(layer.weight.detach().clone())
    captured(*args)
    assert (fake.captures, fake.replays) == (2, 2)


def test_training_replays_the_decoder_at_every_hidden_step(monkeypatch):
    """The rules' guards must not turn training itself back to op by op: with the graphs standing
    in, every training step's hidden render is a replay."""
    from securegs_warp.secure import captured
    fake = _FakeGraphs()
    monkeypatch.setattr(torch.cuda, "make_graphed_callables", fake)
    monkeypatch.setattr(captured, "replayable", lambda t: True)
    op_by_op = []
    decode = captured.decode_rows
    monkeypatch.setattr(captured, "decode_rows", lambda *a, **k: op_by_op.append(1) or decode(*a, **k))
    t = _trainer("cpu")
    for _ in range(12):  # past feature_grad_until: the features' gradient share drops to 0, a new shape
        t.step()
    assert fake.replays == 12 and len(op_by_op) == fake.replays
    assert fake.captures == 2


@pytest.mark.skipif(TEST_DEVICE != "cuda", reason="a checkpoint on CUDA: SECUREGS_TEST_DEVICE=cuda on a GPU machine")
def test_a_run_on_cuda_resumes_into_its_finishing_phase(tmp_path):
    """A CUDA run's checkpoint loads back onto CUDA (the random state goes back to the host), and
    its finishing phase (SecureConfig.hidden_finish) trains the replayed hidden branch."""
    t = _trainer("cuda", finish=1.0)
    for _ in range(t.config.iterations):
        t.step()
    t.save_checkpoint(tmp_path / "run.pt")
    before = t.evaluate_hidden()["psnr_hidden"]
    resumed = _trainer("cuda", finish=1.0)
    resumed.load_checkpoint(tmp_path / "run.pt")
    assert resumed.step_count == t.config.iterations
    while resumed.step_count < resumed.total_steps:
        assert resumed.step()["phase"] == "finish"
    assert resumed.model._captured[0]._graphs, "the finishing phase did not replay the decoder"
    assert torch.isfinite(torch.cat([p.flatten() for p in resumed.model.secrets[0].parameters()])).all()
    assert resumed.evaluate_hidden()["psnr_hidden"] > before - 1.0


def _phase_from_checkpoint(path, robust=None, replayed=True, monkeypatch=None):
    """A trainer resumed from a joint run's checkpoint at ``path``, its finishing phase run to the
    end (replayed from CUDA graphs, or op by op), and its hidden PSNR."""
    from securegs_warp.secure import hidden_graph
    if not replayed:
        monkeypatch.setattr(hidden_graph, "replayable", lambda trainer, phase: False)
    t = _trainer("cuda", robust=robust, finish=1.0)
    t.load_checkpoint(path)
    stats = [t.step() for _ in range(t.finish_steps)]
    assert all(s["phase"] == "finish" and "nonfinite_grads" not in s for s in stats)
    return t, stats


@pytest.mark.skipif(TEST_DEVICE != "cuda", reason="CUDA graphs: SECUREGS_TEST_DEVICE=cuda on a GPU machine")
def test_the_replayed_finishing_phase_trains_the_key_as_the_eager_one(tmp_path, monkeypatch):
    """Without attacks nothing in the phase is random: replayed from CUDA graphs (hidden_graph)
    after its warm-up steps, it leaves the private heads where the phase op by op leaves them, up
    to float rounding, and reports the same losses."""
    from securegs_warp.secure import hidden_graph
    t = _trainer("cuda", finish=1.0)
    for _ in range(t.config.iterations):
        t.step()
    t.save_checkpoint(tmp_path / "joint.pt")
    replayed, replayed_stats = _phase_from_checkpoint(tmp_path / "joint.pt")
    assert replayed._graphs[hidden_graph.FINISH].ready and t.finish_steps > hidden_graph.WARMUP
    eager, eager_stats = _phase_from_checkpoint(tmp_path / "joint.pt", replayed=False, monkeypatch=monkeypatch)
    assert eager._graphs[hidden_graph.FINISH] is None
    for (name, a), b in zip(replayed.model.secrets[0].named_parameters(), eager.model.secrets[0].parameters()):
        assert (a - b).abs().max() <= 1e-4 * b.abs().max().clamp_min(1e-3), name
    for a, b in zip(replayed_stats, eager_stats):
        assert abs(a["loss"] - b["loss"]) <= 1e-4 * abs(b["loss"]) and abs(a["psnr"] - b["psnr"]) < 0.01


@pytest.mark.skipif(TEST_DEVICE != "cuda", reason="CUDA graphs: SECUREGS_TEST_DEVICE=cuda on a GPU machine")
def test_the_replayed_finishing_phase_draws_new_attacks_every_step(tmp_path):
    """With the phase's attacks the replays draw a new dropout and noise each time (the graphs
    advance the device's generator): the losses differ from step to step, the release stays as
    it was, and the key still renders the object."""
    from securegs_warp.secure import hidden_graph
    robust = "prune-random:0.5+noise-feat:0.3"
    t = _trainer("cuda", robust=robust, finish=1.0)
    for _ in range(t.config.iterations):
        t.step()
    t.save_checkpoint(tmp_path / "joint.pt")
    before = t.evaluate_hidden()["psnr_hidden"]
    release = [p.detach().clone() for p in (*t.model.anchors.parameters(), *t.model.heads.parameters())]
    resumed, stats = _phase_from_checkpoint(tmp_path / "joint.pt", robust=robust)
    graph = resumed._graphs[hidden_graph.FINISH]
    assert graph.ready
    first, second = (graph.run(resumed.step_count, 0)[0].item() for _ in range(2))
    assert first != second  # the same parameters and view, other attacks
    resumed.model.zero_grad(set_to_none=True)
    assert all(torch.equal(a, b) for a, b in
               zip(release, (*resumed.model.anchors.parameters(), *resumed.model.heads.parameters())))
    assert resumed.evaluate_hidden()["psnr_hidden"] > before - 1.0


def _hidden_gradients(t):
    """The gradients the hidden branch left: anchor features and scalings, the private heads'."""
    return [t.model.anchors.feat.grad.clone(), t.model.anchors.scaling.grad.clone(),
            *[p.grad.clone() for p in t.model.secrets[0].parameters()]]


@pytest.mark.skipif(TEST_DEVICE != "cuda", reason="CUDA graphs: SECUREGS_TEST_DEVICE=cuda on a GPU machine")
def test_a_replayed_joint_step_gives_the_hidden_branchs_gradients_op_by_op():
    """Without attacks: the joint run's hidden branch replayed from its CUDA graph (hidden_graph:
    the serving rows gathered, their gradients added back into the anchors') gives the hidden loss
    and the gradients of the anchor features and scalings and of the private heads that the branch
    op by op gives, at the same parameters and view."""
    from securegs_warp.secure import hidden_graph
    t = _trainer("cuda")
    stats = [t.step() for _ in range(hidden_graph.WARMUP + 2)]
    assert all("nonfinite_grads" not in s and "incomplete_renders" not in s for s in stats)
    graph = t._graphs[hidden_graph.JOINT]
    assert graph.ready
    step = t.step_count + 1
    for view in (1, 2):
        t.model.zero_grad(set_to_none=True)
        loss, _, _ = graph.run(step, view)
        graph.scatter(t.model.anchors)
        loss, replayed = loss.item(), _hidden_gradients(t)
        t.model.zero_grad(set_to_none=True)
        renders = []
        t._hidden_losses(view, renders, step, None, None, 1.0)
        eager_loss = t.image_losses(renders)
        eager_loss.backward()
        assert abs(loss - eager_loss.item()) <= 1e-5 * abs(eager_loss.item())
        for got, want in zip(replayed, _hidden_gradients(t)):
            assert (got - want).abs().max() <= 1e-4 * want.abs().max().clamp_min(1e-12)
    t.model.zero_grad(set_to_none=True)


@pytest.mark.skipif(TEST_DEVICE != "cuda", reason="CUDA graphs: SECUREGS_TEST_DEVICE=cuda on a GPU machine")
def test_the_replayed_joint_run_draws_new_attacks_and_learns():
    """With robust training two replays at the same parameters and view draw other attacks (other
    losses), and a joint run whose hidden branch replays keeps the model finite and learns the object."""
    from securegs_warp.secure import hidden_graph
    t = _trainer("cuda", robust="prune-random:0.5+noise-feat:0.3")
    before = t.evaluate_hidden()["psnr_hidden"]
    stats = [t.step() for _ in range(t.config.iterations)]
    assert all("nonfinite_grads" not in s and "incomplete_renders" not in s for s in stats)
    graph = t._graphs[hidden_graph.JOINT]
    assert graph.ready
    first, second = (graph.run(t.step_count + 1, 1)[0].item() for _ in range(2))
    assert first != second
    t.model.zero_grad(set_to_none=True)
    assert torch.isfinite(t.model.anchors.feat).all()
    assert t.evaluate_hidden()["psnr_hidden"] > before + 1.0


def test_the_hidden_branch_replays_only_where_its_shapes_and_draws_are_fixed(monkeypatch):
    """hidden_graph.replayable: CUDA, the phase's attacks among those a replay draws, training views
    of one size and whole (uncropped) hidden views; anything else runs op by op."""
    from securegs_warp.secure import hidden_graph
    from securegs_warp.secure.robust import parse_robust
    t = _trainer("cpu", robust="prune-random:0.5+noise-feat:0.3", finish=1.0)
    phases = (hidden_graph.JOINT, hidden_graph.FINISH)
    assert not any(hidden_graph.replayable(t, phase) for phase in phases)  # the CPU
    monkeypatch.setattr(t, "device", torch.device("cuda"))
    assert all(hidden_graph.replayable(t, phase) for phase in phases)
    monkeypatch.setattr(t, "finish_robust", parse_robust("prune-random:0.5+noise-xyz:0.01"))
    assert hidden_graph.replayable(t, hidden_graph.JOINT) and not hidden_graph.replayable(t, hidden_graph.FINISH)
    monkeypatch.setattr(t, "robust", parse_robust("quantize:8"))
    assert not hidden_graph.replayable(t, hidden_graph.JOINT)
    monkeypatch.undo()
    monkeypatch.setattr(t, "device", torch.device("cuda"))
    monkeypatch.setattr(t, "secure", dataclasses.replace(t.secure, hidden_crop=True))
    assert not any(hidden_graph.replayable(t, phase) for phase in phases)
    monkeypatch.setattr(t, "secure", dataclasses.replace(t.secure, hidden_crop=False))
    views = list(t.scene.train)
    views[1] = dataclasses.replace(views[1], width=views[1].width // 2, image=None, alpha=None, hidden=None,
                                   hidden_alpha=None)
    monkeypatch.setattr(t.scene, "train", views)
    assert not any(hidden_graph.replayable(t, phase) for phase in phases)


def _rows_branch(t):
    """The hidden loss of training view 1 decoded from the serving rows gathered into fixed buffers
    (hidden_graph.ServingRows) and differentiated there, the rows' gradients added into the
    anchors': (loss, the anchors' feature and scaling gradients, the private heads' gradients)."""
    from securegs_warp.secure.hidden_graph import ServingRows
    anchors = t.model.anchors
    index = t.model.secrets[0].serving_index(anchors.xyz)
    rows = ServingRows(anchors, index, trained=True)
    renders = []
    t._hidden_losses(1, renders, 1, {0: rows.view}, None, 1.0)
    loss = t.image_losses(renders)
    loss.backward()
    rows.scatter(anchors, retain=False)
    assert rows.view.feat.grad is None
    return loss.detach(), anchors.feat.grad, anchors.scaling.grad, [p.grad for p in t.model.secrets[0].parameters()]


def test_the_hidden_branch_on_the_gathered_serving_rows_matches_the_branch_on_the_model():
    """What the replayed hidden branch computes, run op by op on the CPU: the serving rows gathered
    into buffers decode, render and differentiate as the branch on the whole model does, their
    gradients landing on the serving anchors' rows only."""
    t = _trainer("cpu")
    t.model.zero_grad(set_to_none=True)
    renders = []
    t._hidden_losses(1, renders, 1, None, None, 1.0)
    want = t.image_losses(renders)
    want.backward()
    want_grads = (t.model.anchors.feat.grad.clone(), t.model.anchors.scaling.grad.clone(),
                  [p.grad.clone() for p in t.model.secrets[0].parameters()])
    t.model.zero_grad(set_to_none=True)
    loss, feat, scaling, private = _rows_branch(t)
    assert torch.allclose(loss, want, rtol=1e-5)
    serving = t.model.secrets[0].serving_mask(t.model.anchors.xyz)
    assert feat[~serving].abs().max() == 0 and feat[serving].abs().max() > 0
    for got, expected in zip((feat, scaling, *private), (want_grads[0], want_grads[1], *want_grads[2])):
        assert torch.allclose(got, expected, rtol=1e-4, atol=1e-6 * expected.abs().max())


def test_attacks_on_the_serving_rows_drop_their_share_and_scale_noise_by_the_whole_model():
    """Dropout on the gathered rows drops the drawn fraction of them; feature noise on them is
    scaled by the spread of all anchors' features (PerturbedAnchors.spread), not of the rows'."""
    from securegs_warp.secure.hidden_graph import ServingRows
    from securegs_warp.secure.robust import parse_robust, perturb
    t = _trainer("cpu")
    anchors = t.model.anchors
    index = t.model.secrets[0].serving_index(anchors.xyz)
    rows = ServingRows(anchors, index, trained=False)
    assert torch.allclose(rows.view.spread["feat"], anchors.feat.detach().std(dim=0, keepdim=True))
    assert torch.equal(rows.view.feat, anchors.feat.detach()[index])
    draws = torch.Generator().manual_seed(3)
    dropped = [int((~perturb(rows.view, parse_robust("prune-random:0.8"), draws, None, draws).keep).sum())
               for _ in range(200)]
    assert max(dropped) <= 0.8 * len(index) + 1 and 0.35 < np.mean(dropped) / len(index) < 0.45  # u · 0.8
    rows.view.spread["feat"].fill_(2.0)
    noisy = [perturb(rows.view, parse_robust("noise-feat:1.0"), draws, None, draws).feat - rows.view.feat
             for _ in range(1000)]
    # σ = u · 2 with u uniform in [0, 1]: E[σ²] = 4 / 3 (the mean over 1000 draws within 0.15 at 4 s.d.).
    assert abs(torch.stack(noisy).pow(2).mean().item() - 4.0 / 3.0) < 0.15


def test_the_rows_gradients_add_to_what_the_anchors_hold():
    """scatter adds the rows' gradients into the serving anchors' rows of whatever gradient the
    anchors hold already; retained, the rows keep theirs (a graph's buffers), else they are cleared."""
    from securegs_warp.secure.hidden_graph import ServingRows
    t = _trainer("cpu")
    anchors = t.model.anchors
    index = t.model.secrets[0].serving_index(anchors.xyz)
    rows = ServingRows(anchors, index, trained=True)
    for retain in (True, False):
        rows.view.feat.grad = torch.ones_like(rows.view.feat)
        anchors.feat.grad = torch.full_like(anchors.feat, 2.0)
        rows.scatter(anchors, retain=retain)
        serving = torch.zeros(anchors.num_anchors, dtype=torch.bool).index_fill_(0, index, True)
        assert (anchors.feat.grad[serving] == 3.0).all() and (anchors.feat.grad[~serving] == 2.0).all()
        assert anchors.scaling.grad is None  # the rows' scalings held no gradient
        assert (rows.view.feat.grad is not None) == retain


def test_losses_taken_elsewhere_join_the_step_loss_as_numbers():
    """image_losses adds an entry's precomputed loss (a replayed hidden branch's) to the renders'
    own, and takes a list of such entries alone."""
    t = _trainer("cpu")
    out = t.render(t.scene.train[0], camera_index=0)
    own = t.image_losses([(out, t._targets[0], 1.0)])
    taken = ({"loss": torch.tensor(0.25), "info": {}}, None, 1.0)
    assert torch.allclose(t.image_losses([(out, t._targets[0], 1.0), taken]), own + 0.25)
    assert t.image_losses([taken, taken]).item() == 0.5
