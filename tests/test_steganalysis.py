"""Steganalysis (secure.steganalysis, securegs audit), the box-frame hiding mode and the placement
of hidden objects in the synthetic scene."""
import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from securegs_warp.cli import main
from securegs_warp.config import SceneSpec, SecureConfig, apply_overrides
from securegs_warp.data import make_synthetic_scene
from securegs_warp.rasterizer import RasterOptions
from securegs_warp.secure import SecureTrainer
from securegs_warp.secure.container import open_container
from securegs_warp.secure.steganalysis import (SURFACE_OPACITY, audit, auc_by_model, detection_auc, leakage,
                                              sliced_wasserstein, surface_opacity)
from securegs_warp.train import TrainConfig

TINY = ["--width", "40", "--height", "30", "--train-views", "6", "--test-views", "2"]


def _room_like(rng, n=6000):
    """Anchors on the six faces of a 10-unit box: a scene's walls and floor."""
    pts = rng.uniform(0.0, 10.0, (n, 3))
    axis = rng.integers(0, 3, n)
    pts[np.arange(n), axis] = rng.choice([0.0, 10.0], n)
    return pts


def test_a_planted_cluster_is_found_and_boxed():
    rng = np.random.default_rng(0)
    walls = _room_like(rng)
    plain = audit({"xyz": walls})
    planted = np.concatenate([walls, rng.normal((6.0, 4.0, 5.0), 0.2, (400, 3))])
    found = audit({"xyz": planted})
    assert found["score"] > 2 * plain["score"]
    lo, hi = map(np.array, found["suspicious_box"])
    assert ((lo <= (6.0, 4.0, 5.0)) & ((6.0, 4.0, 5.0) <= hi)).all() and (hi - lo).max() < 3.0


def test_a_uniform_cloud_scores_low_and_auc_is_chance_between_alike_models():
    rng = np.random.default_rng(1)
    scores = [audit({"xyz": rng.uniform(0, 10, (5000, 3))})["score"] for _ in range(6)]
    planted = [audit({"xyz": np.concatenate([rng.uniform(0, 10, (5000, 3)),
                                             rng.normal(5.0, 0.2, (300, 3))])})["score"] for _ in range(3)]
    assert max(scores) < min(planted)
    assert detection_auc(planted, scores) == 1.0
    assert 0.2 <= detection_auc(scores[:3], scores[3:]) <= 0.8


def test_auc_over_runs_with_and_without_a_reference():
    rng = np.random.default_rng(4)
    runs = []
    for _ in range(3):
        walls = _room_like(rng, 3000)
        runs.append({"plain": walls, "alike": _room_like(rng, 3000),
                     "traced": np.concatenate([walls, rng.normal((6.0, 4.0, 5.0), 0.2, (300, 3))])})
    for with_reference in (False, True):
        result = auc_by_model(runs, "plain", with_reference)
        assert result["traced"]["auc"] == 1.0 and "auc" not in result["plain"]
        assert len(result["traced"]["scores"]) == (6 if with_reference else 3)
    with pytest.raises(ValueError, match="plain model"):
        auc_by_model([{"traced": runs[0]["traced"]}], "plain")
    # Runs of one cover (their plain models one training, whatever they hide) are not each other's
    # references: with runs 0 and 1 of one cover, each is audited against run 2's plain model only.
    result = auc_by_model(runs, "plain", True, covers=["a", "a", "b"])
    assert len(result["traced"]["scores"]) == 1 + 1 + 2
    with pytest.raises(ValueError, match="at least two covers"):
        auc_by_model(runs, "plain", True, covers=["a", "a", "a"])


def test_sliced_wasserstein_tells_a_shifted_distribution():
    rng = np.random.default_rng(2)
    a, b = rng.normal(size=(2000, 8)), rng.normal(size=(2000, 8))
    assert sliced_wasserstein(a, b) < 0.05 < sliced_wasserstein(a, b + 0.5)


@pytest.fixture(scope="module")
def scene():
    return make_synthetic_scene(hidden="mug", level="object", width=40, height=30, n_train=6, n_test=2, n_points=600)


def test_cover_mode_grows_no_anchor_for_the_hidden_object(scene):
    """In the cover mode the anchors are the plain model's: no Γ_hid, no box, growth and pruning
    from the public render alone; the private heads decode k_hid Gaussians in the object's box."""
    secure = apply_overrides(SecureConfig(payload="object"), {"strategy.mode": "cover", "hidden_offsets": 4,
                                                              "hidden_width": 16, "hidden_anchors": 50})
    trainer = SecureTrainer(scene, TrainConfig(iterations=20, raster=RasterOptions(tile_size=8)), secure)
    s = trainer.strategy
    s.start_stat, s.update_from, s.update_interval, s.update_until = 0, 0, 5, 20
    stats = [trainer.step() for _ in range(20)]
    assert int(trainer.strategy_state["is_hidden"].sum()) == 0
    assert torch.isnan(trainer.strategy_state["bbox"]).all()
    assert sum(st.get("grown_hidden", 0) for st in stats) == 0
    private = trainer.model.private
    assert (private.frame, private.n_offsets, private.width, private.serving) == ("box", 4, 16, 50)
    out = trainer.render_hidden(scene.train[0], 0)
    g = out["gaussians"]
    # The 50 anchors nearest the box serve: the radius lies between the 50th and the next one out.
    distance = private.box_distance(trainer.model.anchors.xyz).detach().sort().values
    assert distance[49] < private.serving_radius.item() < distance[50]
    assert int(g["visible_mask"].sum()) == 50 and g["neural_opacity"].shape[0] == 50 * 4
    lo, hi = private.box[0] - private.box[1], private.box[0] + private.box[1]
    assert ((g["means"] >= lo - 1e-5) & (g["means"] <= hi + 1e-5)).all()


def test_box_frame_options_are_in_the_key_and_reveal_rebuilds_them(tmp_path):
    out = tmp_path / "c"
    assert main(["hide", "--out", str(out), "--iterations", "4", "--quiet", "--payload", "object", "--mode", "cover",
                 "--hidden-offsets", "3", "--hidden-width", "8", "--hidden-anchors", "40",
                 "--hidden-encoding", "2", "--hidden-depth", "2", "--hidden-latent", "3", "--hidden-codes", "64",
                 *TINY]) == 0
    model, meta = open_container(out / "public", out / "key.safetensors")
    assert meta["heads"]["frame"] == "box" and (meta["heads"]["n_hidden"], meta["heads"]["width"]) == (3, 8)
    assert (meta["heads"]["encoding"], meta["heads"]["depth"], meta["heads"]["latent"]) == (2, 2, 3)
    # The latent grid trained (it starts at zero) and came back from the key.
    grid = model.private.latent_grid.grid
    assert grid.shape == (1, model.private.feat_dim, 3, 3, 3) and grid.abs().max() > 0
    # So did the codes.
    assert meta["heads"]["codes"] == 64
    assert model.private.codes.table.shape == (64, model.private.feat_dim) and model.private.codes.table.abs().max() > 0
    assert model.private.serving == 40 and model.private.box[1].min() > 0
    # F_o† reads the feature and 3 (1 + 2·2) encoded coordinates, through two hidden layers.
    linears = [m for m in model.private.offset_mlp if isinstance(m, torch.nn.Linear)]
    assert [m.in_features for m in linears] == [model.private.feat_dim + 15, 8, 8]
    revealed = tmp_path / "r"
    assert main(["reveal", str(out / "public"), "--key", str(out / "key.safetensors"), "--out", str(revealed)]) == 0
    assert any(p.name.startswith("hidden_") for p in (revealed / "renders").iterdir())


def test_a_key_written_before_the_encoding_and_depth_rebuilds_the_one_layer_offset_mlp():
    from securegs_warp.model import ScaffoldHeads
    from securegs_warp.secure.heads import PrivateHeads

    metadata = PrivateHeads(ScaffoldHeads(8, 2), frame="box", n_hidden=2, width=8).describe()
    for name in ("encoding", "depth"):
        metadata.pop(name)
    private = PrivateHeads(ScaffoldHeads(8, 2), **metadata)
    assert [m.in_features for m in private.offset_mlp if isinstance(m, torch.nn.Linear)] == [8 + 3, 8]


def test_the_latent_grid_reads_contracted_box_positions_and_starts_as_no_grid():
    from securegs_warp.model import ScaffoldHeads
    from securegs_warp.secure.heads import PrivateHeads

    private = PrivateHeads(ScaffoldHeads(2, 2), frame="box", n_hidden=2, width=8, latent=3)
    private.set_box([1.0, 1.0, 1.0], [3.0, 5.0, 7.0])  # centre (2, 3, 4), half-extent (1, 2, 3)
    feat = torch.randn(4, 2)
    xyz = torch.tensor([[2.0, 3.0, 4.0], [3.0, 3.0, 4.0], [2.0, 3.0, 1e6], [2.0, -1e6, 4.0]])
    log_scaling = torch.randn(4, 6)
    assert torch.equal(private.anchor_source(xyz, feat, log_scaling)[0], feat)  # zero at the start: the features themselves
    with torch.no_grad():
        # Channel 0 holds the x cell index, channel 1 the z cell index (grid axes: z, y, x).
        index = torch.arange(3.0)
        private.latent_grid.grid[0, 0] = index[None, None, :]
        private.latent_grid.grid[0, 1] = index[:, None, None]
    latent, scaling = private.anchor_source(xyz, torch.zeros(4, 2), log_scaling)
    assert scaling is log_scaling  # the grid feeds the features alone
    # The centre reads the middle cell; the box's face (p = 1) lies halfway out (u = p / (1 + |p|) = 0.5,
    # cell 1.5); far outside reaches the border cells, axis by axis.
    expected = torch.tensor([[1.0, 1.0], [1.5, 1.0], [1.0, 2.0], [1.0, 1.0]])
    assert (latent - expected).abs().max() < 1e-4, latent
    with pytest.raises(ValueError, match="frame='box'"):
        PrivateHeads(ScaffoldHeads(2, 2), latent=3)
    with pytest.raises(ValueError, match="hidden_latent"):
        SecureConfig(hidden_latent=1)


def test_each_anchor_reads_the_code_of_its_own_cell_and_the_codes_start_as_none():
    from securegs_warp.model import ScaffoldHeads
    from securegs_warp.secure.heads import CODE_CELLS, AnchorCodes, PrivateHeads

    private = PrivateHeads(ScaffoldHeads(2, 2), frame="box", n_hidden=2, width=8, codes=4096)
    private.set_box([-1.0, -1.0, -1.0], [1.0, 1.0, 1.0])
    cell = 2.0 / CODE_CELLS  # a cell's width in u = p / (1 + |p|), about its width in p near the centre
    xyz = torch.tensor([[0.1, 0.2, 0.3], [0.1 + 0.2 * cell, 0.2, 0.3], [0.1 + 4 * cell, 0.2, 0.3], [-0.5, 3.0, 20.0]])
    feat, log_scaling = torch.randn(4, 2), torch.randn(4, 6)
    assert torch.equal(private.anchor_source(xyz, feat, log_scaling)[0], feat)  # zero at the start: the features
    with torch.no_grad():
        private.codes.table.copy_(torch.arange(4096.0)[:, None].expand(4096, 2))

    def code_rows(where):
        return private.anchor_source(where, torch.zeros(len(where), 2), log_scaling[:len(where)])[0][:, 0]
    rows = code_rows(xyz)
    # One cell, one code; another cell its own (these three cells hash to three rows).
    assert rows[0] == rows[1] and len({rows[0].item(), rows[2].item(), rows[3].item()}) == 3
    # An anchor's code depends on its position alone: a release that lost anchors reads the same codes.
    assert torch.equal(code_rows(xyz[2:]), rows[2:])
    # Coarser cells share codes: with one cell an axis every anchor reads one row.
    one = AnchorCodes(2, 4096, cells=1)
    with torch.no_grad():
        one.table.copy_(torch.arange(4096.0)[:, None].expand(4096, 2))
    assert len(set(one(private.box_position(xyz))[:, 0].tolist())) == 1
    # Without the scale part the scalings are the public ones.
    assert private.anchor_source(xyz, feat, log_scaling)[1] is log_scaling
    # The hidden loss's gradient reaches the rows read, and no other.
    private.codes.table.grad = None
    code_rows(xyz).sum().backward()
    assert int((private.codes.table.grad.abs().sum(1) > 0).sum()) == 3
    with pytest.raises(ValueError, match="frame='box'"):
        PrivateHeads(ScaffoldHeads(2, 2), codes=8)
    with pytest.raises(ValueError, match="hidden_codes"):
        SecureConfig(hidden_codes=-1)


def test_scale_codes_add_to_the_hidden_gaussians_log_scales_alone():
    """With ``code_scales`` an anchor's code adds to its log scaling l_v[3:] (what the hidden
    Gaussians' scales multiply), not to l_v[:3]; zero at the start; a key records it."""
    from securegs_warp.model import ScaffoldHeads
    from securegs_warp.secure.heads import PrivateHeads

    private = PrivateHeads(ScaffoldHeads(2, 2), frame="box", n_hidden=2, width=8, codes=64, code_scales=True)
    private.set_box([-1.0, -1.0, -1.0], [1.0, 1.0, 1.0])
    xyz, feat, log_scaling = torch.randn(5, 3), torch.randn(5, 2), torch.randn(5, 6)
    same_feat, same_scaling = private.anchor_source(xyz, feat, log_scaling)
    assert torch.equal(same_feat, feat) and torch.equal(same_scaling, log_scaling)
    with torch.no_grad():
        private.codes.table.copy_(torch.arange(64.0)[:, None] * torch.tensor([1.0, 2.0, 10.0, 20.0, 30.0]))
    out_feat, out_scaling = private.anchor_source(xyz, feat, log_scaling)
    row = (out_feat - feat)[:, 0]
    assert torch.equal(out_scaling[:, :3], log_scaling[:, :3])
    assert torch.allclose(out_scaling[:, 3:] - log_scaling[:, 3:], row[:, None] * torch.tensor([10.0, 20.0, 30.0]))
    assert private.describe()["code_scales"] and not PrivateHeads(ScaffoldHeads(2, 2), frame="box",
                                                                   codes=8).describe()["code_scales"]
    with pytest.raises(ValueError, match="needs codes"):
        PrivateHeads(ScaffoldHeads(2, 2), frame="box", code_scales=True)
    with pytest.raises(ValueError, match="hidden_codes"):
        SecureConfig(hidden_codes=0, hidden_code_scales=True)
    with pytest.raises(ValueError, match="hidden_codes"):
        SecureConfig(hidden_codes=0, hidden_code_cells=64)


def test_the_exported_hidden_gaussians_are_those_the_latent_grid_renders(scene):
    """``hidden_gaussians`` (reveal's export, the audit's hidden surface) decodes with the key's latent
    grid, as its renders do."""
    secure = apply_overrides(SecureConfig(payload="object"), {"strategy.mode": "cover", "hidden_offsets": 4,
                                                              "hidden_width": 16, "hidden_anchors": 50,
                                                              "hidden_latent": 3})
    trainer = SecureTrainer(scene, TrainConfig(iterations=2, raster=RasterOptions(tile_size=8)), secure)
    model = trainer.model
    with torch.no_grad():
        model.private.latent_grid.grid.normal_()
        rendered = trainer.render_hidden(scene.train[0], 0)["gaussians"]
        exported = model.hidden_gaussians(scene.train[0])
    for name in ("means", "colors", "opacities"):
        assert exported[name].shape == rendered[name].shape and torch.allclose(exported[name], rendered[name],
                                                                               atol=1e-6), name


def _tiny_cover_key(tmp_path, *flags):
    """(model, key metadata) of a 4-step cover-mode container of a tiny object, hidden with ``flags``
    on top of a small private decoder, opened with its key."""
    out = tmp_path / "c"
    assert main(["hide", "--out", str(out), "--iterations", "4", "--quiet", "--payload", "object", "--mode", "cover",
                 "--hidden-offsets", "3", "--hidden-width", "8", "--hidden-anchors", "40", *flags, *TINY]) == 0
    return open_container(out / "public", out / "key.safetensors")


def _tiny_scene():
    """The scene ``_tiny_cover_key`` trains on (TINY's size and views)."""
    return make_synthetic_scene(hidden="mug", level="object", width=40, height=30, n_train=6, n_test=2)


def _tiny_view():
    return _tiny_scene().test[0]


def test_the_hidden_dilation_is_in_the_key_and_leaves_the_public_render_alone(tmp_path):
    """--hidden-eps2d: the key's hidden renders dilate by its own eps2d, the public render by the
    options it is given, and a key without one renders as before."""
    model, meta = _tiny_cover_key(tmp_path, "--hidden-eps2d", "0.05")
    assert meta["heads"]["eps2d"] == 0.05 and model.private.eps2d == 0.05
    cam = _tiny_view()
    options = RasterOptions(tile_size=8)
    with torch.no_grad():
        own = model.render_hidden(cam, options)["image"]
        at_005 = model.render_hidden(cam, dataclasses.replace(options, eps2d=0.05))["image"]
        public = model.render(cam, options)["image"]
        model.private.eps2d = None  # as a key without its own dilation: the options' 0.3
        at_03 = model.render_hidden(cam, options)["image"]
        assert torch.equal(model.render(cam, options)["image"], public)
    assert torch.equal(own, at_005) and not torch.allclose(own, at_03)
    # A key written before the option existed holds no eps2d: its heads take the options' own.
    from securegs_warp.secure.heads import PrivateHeads
    described = {k: v for k, v in meta["heads"].items() if k != "eps2d"}
    assert PrivateHeads(model.heads, **described).eps2d is None
    with pytest.raises(ValueError, match="hidden_eps2d must be >= 0"):
        SecureConfig(hidden_eps2d=-1.0)


def test_farthest_points_spread_over_the_points_and_start_at_places_each_slot_on_one():
    """farthest_points picks one point of each far cluster before a second of any; start_at makes
    F_o†'s bias put hidden Gaussian j of an anchor at points[j] (exactly, with its weights zeroed);
    both refuse what they cannot do."""
    from securegs_warp.model import ScaffoldHeads
    from securegs_warp.secure.heads import PrivateHeads, farthest_points

    centres = torch.tensor([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, 5.0, 5.0]])
    clusters = (centres[:, None] + 0.01 * torch.randn(3, 50, 3)).reshape(-1, 3)
    picked = farthest_points(clusters, 3)
    assert sorted(torch.cdist(picked, centres).argmin(dim=1).tolist()) == [0, 1, 2]
    assert torch.equal(farthest_points(clusters, 3), picked)  # no random draw
    with pytest.raises(ValueError, match="cannot pick 151 of 150"):
        farthest_points(clusters, 151)
    heads = PrivateHeads(ScaffoldHeads(4, 2), frame="box", n_hidden=3, width=8, serving=10)
    heads.set_box(torch.tensor([-1.0, -2.0, 0.0]), torch.tensor([1.0, 2.0, 4.0]))
    points = torch.tensor([[0.5, -1.0, 1.0], [-0.2, 1.5, 3.0], [0.9, 0.0, 0.2]])
    heads.start_at(points)
    with torch.no_grad():
        heads.offset_mlp[-1].weight.zero_()
    raw = heads.offset_mlp(torch.randn(7, heads.offset_mlp[0].in_features)).view(7, 3, 3)
    placed = heads.box[0] + heads.box[1] * torch.tanh(raw)
    assert torch.allclose(placed, points.expand(7, 3, 3), atol=1e-5)
    with pytest.raises(ValueError, match=r"one point per hidden Gaussian of an anchor, \[3, 3\]"):
        heads.start_at(points[:2])
    with pytest.raises(ValueError, match="needs frame='box'"):
        PrivateHeads(ScaffoldHeads(4, 2)).start_at(points)
    with pytest.raises(ValueError, match="hidden_start must be one of"):
        SecureConfig(hidden_start="middle")


def test_a_container_trained_from_the_surface_start_decodes_nearer_the_object(tmp_path):
    """--hidden-start surface (the default) starts the hidden Gaussians on the object: after a few
    steps they lie nearer its surface than from --hidden-start centre, where they start near the box's
    centre."""
    scene = _tiny_scene()
    surface = torch.as_tensor(scene.hidden_points)
    cam = scene.test[0]
    distance = {}
    for start in ("surface", "centre"):
        model, _ = _tiny_cover_key(tmp_path / start, "--hidden-start", start)
        with torch.no_grad():
            means = model.hidden_gaussians(cam)["means"]
        distance[start] = float(torch.cdist(means, surface).min(dim=1).values.median())
    assert distance["surface"] < 0.5 * distance["centre"], distance


def test_the_scale_gain_is_in_the_key_and_multiplies_the_hidden_gaussians_scales_alone(tmp_path):
    """--hidden-scale-gain: the key records its gain, the hidden Gaussians' scales are that many
    times those of a gain of 1 (their positions, colours and the public render unchanged), a key
    written before the gain existed opens with 1, and a gain below 1 is refused."""
    from securegs_warp.model import ScaffoldHeads
    from securegs_warp.secure.heads import PrivateHeads

    model, meta = _tiny_cover_key(tmp_path, "--hidden-scale-gain", "3")
    assert meta["heads"]["scale_gain"] == 3.0 and model.private.scale_gain == 3.0
    cam = _tiny_view()
    with torch.no_grad():
        gained = model.hidden_gaussians(cam)
        public = model.render(cam, RasterOptions(tile_size=8))["image"]
        model.private.scale_gain = 1.0
        plain = model.hidden_gaussians(cam)
        assert torch.equal(model.render(cam, RasterOptions(tile_size=8))["image"], public)
    assert torch.allclose(gained["scales"], 3.0 * plain["scales"], rtol=1e-5)
    for name in ("means", "colors", "opacities"):
        assert torch.equal(gained[name], plain[name]), name
    older = {k: v for k, v in meta["heads"].items() if k != "scale_gain"}
    assert PrivateHeads(model.heads, **older).scale_gain == 1.0
    # The anchor frame (no box, no codes) takes a gain too.
    anchor_frame = PrivateHeads(ScaffoldHeads(2, 2), scale_gain=2.0)
    log_scaling = torch.randn(5, 6)
    shifted = anchor_frame.anchor_source(torch.randn(5, 3), torch.randn(5, 2), log_scaling)[1]
    assert torch.equal(shifted[:, :3], log_scaling[:, :3])
    assert torch.allclose(shifted[:, 3:], log_scaling[:, 3:] + math.log(2.0))
    assert PrivateHeads(ScaffoldHeads(2, 2)).anchor_source is None
    with pytest.raises(ValueError, match="scale_gain must be >= 1"):
        PrivateHeads(ScaffoldHeads(2, 2), scale_gain=0.5)
    with pytest.raises(ValueError, match="hidden_scale_gain must be >= 1"):
        SecureConfig(hidden_scale_gain=0.5)


def test_a_key_with_scale_codes_opens_and_its_codes_scale_the_hidden_gaussians(tmp_path):
    """--hidden-codes with --hidden-code-scales and --hidden-code-cells: the key records them, opens
    with its table's scale columns and its cells, and the scale columns multiply the hidden
    Gaussians' scales (the release's are untouched); a key written before the cells were recorded
    opens with CODE_CELLS."""
    from securegs_warp.secure.heads import CODE_CELLS, PrivateHeads

    model, meta = _tiny_cover_key(tmp_path, "--hidden-codes", "64", "--hidden-code-scales", "--hidden-code-cells", "32",
                                  "--hidden-feature-grad", "0", "--hidden-scaling-grad", "0")
    assert meta["heads"]["codes"] == 64 and meta["heads"]["code_scales"] and meta["heads"]["code_cells"] == 32
    assert model.private.codes.cells == 32
    older = {k: v for k, v in meta["heads"].items() if k != "code_cells"}
    assert PrivateHeads(model.heads, **older).codes.cells == CODE_CELLS
    d = model.anchors.feat.shape[1]
    assert model.private.codes.table.shape == (64, d + 3)
    cam = _tiny_view()
    with torch.no_grad():
        before = model.hidden_gaussians(cam)["scales"]
        public = model.render(cam, RasterOptions(tile_size=8))["image"]
        model.private.codes.table[:, d:] += 0.5
        after = model.hidden_gaussians(cam)["scales"]
        assert torch.equal(model.render(cam, RasterOptions(tile_size=8))["image"], public)
    assert after.shape == before.shape and torch.allclose(after, before * math.exp(0.5), rtol=1e-5)


def test_the_box_encoding_holds_octaves_of_the_position():
    from securegs_warp.model import ScaffoldHeads
    from securegs_warp.secure.heads import PrivateHeads

    private = PrivateHeads(ScaffoldHeads(8, 2), frame="box", n_hidden=2, width=8, encoding=3)
    where = torch.tensor([[0.25, -0.5, 0.0]])
    code = private.encode(where)
    assert code.shape == (1, 21) and torch.equal(code[0, :3], where[0])
    # octave l of axis x: sin(2^l π x) at column 3 + 3l, cos at 12 + 3l
    for level in range(3):
        assert code[0, 3 + 3 * level].item() == pytest.approx(math.sin(2 ** level * math.pi * 0.25), abs=1e-6)
        assert code[0, 12 + 3 * level].item() == pytest.approx(math.cos(2 ** level * math.pi * 0.25), abs=1e-6)
    with pytest.raises(ValueError, match="frame='box'"):
        PrivateHeads(ScaffoldHeads(8, 2), encoding=2)


def test_serving_is_a_count_inside_the_box_and_its_radius_lies_between_anchors():
    from securegs_warp.model import ScaffoldHeads
    from securegs_warp.secure.heads import PrivateHeads

    private = PrivateHeads(ScaffoldHeads(8, 2), frame="box", serving=3, n_hidden=2, width=8)
    private.set_box([-1.0, -1.0, -1.0], [1.0, 1.0, 1.0])
    inside = torch.tensor([[0.5, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.9, 0.0], [0.0, 0.0, 0.3], [0.7, 0.7, 0.0]])
    outside = torch.tensor([[2.0, 0.0, 0.0], [0.0, 3.0, 0.0]])
    xyz = torch.cat([inside, outside])
    private.fix_serving(xyz)
    assert private.serving_mask(xyz).tolist() == [True, True, False, True, False, False, False]  # nearest the centre
    xyz[0] = torch.tensor([5.0, 0.0, 0.0])  # moved in place: the kept mask is not reused
    assert private.serving_mask(xyz).tolist() == [False, True, False, True, False, False, False]
    private.fix_serving(outside)  # fewer anchors than `serving`: every one serves
    assert private.serving_radius.item() == float("inf") and private.serving_mask(xyz).all()


def test_a_pruned_release_is_decoded_by_its_surviving_serving_anchors_only(tmp_path):
    """The key bounds the serving anchors by a radius: pruning some leaves the survivors serving and
    draws in none that the key never trained (a count would take the next nearest)."""
    out = tmp_path / "c"
    assert main(["hide", "--out", str(out), "--iterations", "4", "--quiet", "--payload", "object", "--mode", "cover",
                 "--hidden-offsets", "3", "--hidden-width", "8", "--hidden-anchors", "40", *TINY]) == 0
    pruned = tmp_path / "pruned"
    assert main(["attack", str(out / "public"), "--key", str(out / "key.safetensors"), "--attack", "prune-random:0.5",
                 "--out", str(pruned)]) == 0
    model, _ = open_container(out / "public", out / "key.safetensors")
    attacked, _ = open_container(pruned, out / "key.safetensors")
    before = {tuple(p) for p in model.anchors.xyz[model.private.serving_mask(model.anchors.xyz)].tolist()}
    after = {tuple(p) for p in attacked.anchors.xyz[attacked.private.serving_mask(attacked.anchors.xyz)].tolist()}
    assert len(before) >= 40 and after < before and len(after) < 0.8 * len(before)


def test_a_key_that_counted_its_serving_anchors_is_refused_by_name(tmp_path):
    from securegs_warp.keys import KeyFileError, load_key, save_key
    from securegs_warp.secure.container import release_fingerprint

    out = tmp_path / "c"
    assert main(["hide", "--out", str(out), "--iterations", "2", "--quiet", "--payload", "object", "--mode", "cover",
                 *TINY]) == 0
    tensors, metadata = load_key(out / "key.safetensors")
    del tensors["private.serving_radius"]
    model, _ = open_container(out / "public", out / "key.safetensors")
    save_key(out / "old.safetensors", tensors, metadata, release_fingerprint(model.heads))
    with pytest.raises(KeyFileError, match="serving anchors were counted"):
        open_container(out / "public", out / "old.safetensors")


def test_audit_command_prints_one_json_object(tmp_path, capsys):
    out = tmp_path / "c"
    assert main(["hide", "--out", str(out), "--iterations", "4", "--quiet", "--payload", "object", *TINY]) == 0
    capsys.readouterr()
    assert main(["audit", str(out / "public"), "--reference", str(out / "public"), "--key",
                 str(out / "key.safetensors"), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert {"score", "suspicious_box", "anchors", "attribute_distances"} <= set(report)
    assert set(report["attribute_distances"]) == {"features", "offsets", "scales", "opacities"}
    assert max(report["attribute_distances"].values()) < 1e-6  # the release against itself
    # Four steps leave no hidden Gaussian above SURFACE_OPACITY: the most opaque of the faint ones mark
    # the surface, and the leak is measured (the release against itself: a density ratio of 1). A
    # reference of another k and feature width is not comparable, not an error.
    assert 0 < report["surface_opacity"] < SURFACE_OPACITY and "leakage_note" not in report
    assert report["coverage"] is not None and report["density_ratio"] in (None, pytest.approx(1.0))
    other = tmp_path / "other"
    assert main(["train", "--out", str(other), "--iterations", "2", "--quiet", "--set", "train.heads.n_offsets=5",
                 "--set", "train.heads.feat_dim=16", *TINY]) == 0
    capsys.readouterr()
    assert main(["audit", str(out / "public"), "--reference", str(other / "model"), "--json"]) == 0
    distances = json.loads(capsys.readouterr().out)["attribute_distances"]
    assert distances["features"] is None and distances["offsets"] is None and distances["scales"] is not None


def test_leakage_counts_anchors_on_the_hidden_surface():
    rng = np.random.default_rng(3)
    sphere = rng.normal(size=(2000, 3))
    sphere = 5.0 + sphere / np.linalg.norm(sphere, axis=1, keepdims=True)  # the hidden surface, radius 1
    walls = _room_like(rng)
    reference = np.concatenate([walls, sphere[::100]])  # a plain model has a few anchors there by chance
    traced = np.concatenate([reference, sphere[1:1000:2] * 1.01 - 0.05])  # anchors grown on the surface
    leak = leakage(traced, sphere, reference)
    assert leak["coverage"] > 0.5 > leak["reference_coverage"] and leak["density_ratio"] > 10
    assert leakage(reference, sphere, reference)["density_ratio"] == pytest.approx(1.0)
    assert leakage(walls, sphere, walls)["density_ratio"] is None  # no reference anchor near it


def test_the_hidden_surface_is_marked_by_the_opaque_gaussians_or_the_most_opaque_of_faint_ones():
    """A Gaussian above SURFACE_OPACITY marks the surface; where none is that opaque (a thin or dark
    object drawn by many faint Gaussians) those above half the most opaque one's opacity do."""
    assert surface_opacity(np.array([0.1, 0.9, 0.3])) == SURFACE_OPACITY
    assert surface_opacity(np.array([0.1, 0.3, 0.2])) == pytest.approx(0.15)
    assert np.isnan(surface_opacity(np.zeros(0)))


@pytest.mark.parametrize("placement", ["stand", "sink", "float"])
def test_placement_puts_the_object_on_in_or_above_its_host(placement):
    spec = SceneSpec(hidden="pawn", width=16, height=12, n_train=2, n_test=1, hidden_placement=placement,
                     hidden_size=1.0, hidden_yaw=30.0)
    bbox = spec.load().hidden_bbox
    stand = SceneSpec(hidden="pawn", width=16, height=12, n_train=2, n_test=1, hidden_size=1.0).load().hidden_bbox
    shift = {"stand": 0.0, "sink": -0.4, "float": 0.6}[placement] * (stand[1, 2] - stand[0, 2])
    assert bbox[0, 2] == pytest.approx(stand[0, 2] + shift, abs=1e-4)


def test_hidden_position_flag_places_the_object(tmp_path):
    out = tmp_path / "c"
    assert main(["hide", "--out", str(out), "--iterations", "1", "--quiet", "--payload", "object", "--hide", "pawn",
                 "--hidden-position", "1,2,0.5", "--hidden-size", "0.8", *TINY]) == 0
    scene = json.loads((out / "config.json").read_text())["scene"]
    assert (scene["hidden_position"], scene["hidden_size"]) == ([1.0, 2.0, 0.5], 0.8)
    bbox = SceneSpec(**{**scene, "hidden_position": tuple(scene["hidden_position"])}).load().hidden_bbox
    assert np.allclose(0.5 * (bbox[0, :2] + bbox[1, :2]), (1.0, 2.0), atol=0.2) and bbox[0, 2] == pytest.approx(0.5)
