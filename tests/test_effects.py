"""Effects on demand: a run builds only the heads, branches and raster outputs its config and scene
ask for; and each specialised variant equals the general one with that effect neutral."""

import numpy as np
import pytest
import torch

from securegs_warp.data import Camera
from securegs_warp.config import HeadsConfig, SecureConfig, TrainConfig
from securegs_warp.data import make_synthetic_scene
from securegs_warp.model import AnchorModel, ScaffoldHeads
from securegs_warp.rasterizer import RasterOptions
from securegs_warp.render import render_view
from securegs_warp.scaffold_model import build_heads, neutral_heads
from securegs_warp.secure import SecureTrainer
from securegs_warp.secure.heads import PrivateHeads
from securegs_warp.secure.keyed_bits import new_seed
from securegs_warp.secure.payload import PayloadSpec
from securegs_warp.train import ScaffoldTrainer

D, K = 8, 4  # feature width, offsets per anchor
W, H = 32, 24
# tile 8 is the CPU trainer's setting; all renders here share it so the kernels compile once per flag set
TILE = {"tile_size": 8}
CPU_RASTER = RasterOptions(**TILE)


def camera():
    K_ = np.array([[30.0, 0, W / 2], [0, 30.0, H / 2], [0, 0, 1]], dtype=np.float32)
    return Camera("cam", np.eye(4, dtype=np.float32), K_, W, H)


def tiny_model(n=64):
    """n anchors (n * K Gaussians) in front of the identity camera, about 3 units away."""
    g = torch.Generator().manual_seed(0)
    xyz = torch.rand(n, 3, generator=g) * torch.tensor([2.0, 1.5, 1.0]) - torch.tensor([1.0, 0.75, -2.5])
    return AnchorModel(
        xyz=xyz, feat=torch.randn(n, D, generator=g), offsets=torch.randn(n, K, 3, generator=g) * 0.5,
        scaling=torch.log(torch.full((n, 6), 0.1)), rotation=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        opacity=torch.zeros(n, 1),
    )


def plain_heads():
    torch.manual_seed(1)
    return ScaffoldHeads(D, K)


def render(heads, background=None, camera_index=None, **options):
    return render_view(tiny_model(), heads, camera(), background, RasterOptions(**TILE, **options),
                       camera_index=camera_index)


# --- what a run builds ------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def hidden_scene():
    return make_synthetic_scene(hidden="mug", level="object", width=24, height=18, n_train=3, n_test=1,
                                n_points=300)


def test_background_only_where_the_scene_has_one(hidden_scene):
    """A scene with a known background (the synthetic sky, NeRF-synthetic white) is composited over
    it; one without (photographs) renders over black, which costs nothing."""
    config = TrainConfig(iterations=2, raster=CPU_RASTER)
    assert torch.equal(ScaffoldTrainer(hidden_scene, config).background, torch.as_tensor(hidden_scene.background))
    hidden_scene.background, saved = None, hidden_scene.background
    try:
        assert ScaffoldTrainer(hidden_scene, config).background is None
    finally:
        hidden_scene.background = saved


def test_payload_gives_hidden_branches_and_the_public_render_runs_none(hidden_scene):
    trainer = SecureTrainer(hidden_scene, TrainConfig(iterations=2, raster=CPU_RASTER),
                            SecureConfig(payload="object+bits:16"))
    private = trainer.model.private
    assert private.decoder is not None and private.offset_mlp is not None and private.n_bits == 16
    plain = ScaffoldTrainer(hidden_scene, TrainConfig(iterations=2, raster=CPU_RASTER))
    plain.model.anchors.load_state_dict(trainer.model.anchors.state_dict())
    plain.model.heads.load_state_dict(trainer.model.heads.state_dict())
    with torch.no_grad():  # the public render of a container is a plain Scaffold-GS render
        assert torch.equal(trainer.render(hidden_scene.test[0])["image"], plain.render(hidden_scene.test[0])["image"])


def test_rgb_only_render_writes_no_depth():
    assert RasterOptions().render_depth is None
    assert "depth" not in render(plain_heads())["info"]
    assert render(plain_heads(), render_depth="expected")["info"]["depth"].shape == (H, W, 1)


def test_heads_follow_the_heads_config():
    heads = build_heads(HeadsConfig(feat_dim=D, n_offsets=K, feature_bank=True, appearance_dim=4, cov_dist=True),
                        num_cameras=5)
    assert heads.use_feat_bank and heads.embedding_appearance.weight.shape == (5, 4)
    assert heads.cov_mlp[0].in_features == D + 4 and heads.opacity_mlp[0].in_features == D + 3
    plain = build_heads(HeadsConfig(feat_dim=D, n_offsets=K))
    assert not plain.use_feat_bank and plain.embedding_appearance is None
    assert plain.color_mlp[0].in_features == D + 3


@pytest.mark.parametrize("make, message", [
    (lambda: build_heads(HeadsConfig(appearance_dim=4)), "num_cameras"),
    (lambda: HeadsConfig(appearance_dim=-1), "appearance_dim"),
    (lambda: RasterOptions(render_depth="median"), "render_depth"),
    (lambda: PayloadSpec.parse("object+scene"), "at most one"),
    (lambda: PayloadSpec.parse("video"), "unknown payload"),
    (lambda: render(plain_heads(), background=torch.ones(2)), "background"),
])
def test_bad_combinations_are_named(make, message):
    with pytest.raises(ValueError, match=message):
        make()


# --- specialised variant == general variant with the effect neutral ---------------------------------

def test_depth_off_equals_depth_on_image_and_alpha():
    plain = plain_heads()
    off = render(plain)
    for mode in ("accumulated", "expected"):
        on = render(plain, render_depth=mode)
        assert on["info"]["depth"].shape == (H, W, 1) and "depth" not in off["info"]
        assert torch.allclose(on["image"], off["image"], atol=1e-6)
        assert torch.allclose(on["alpha"], off["alpha"], atol=1e-6)
    assert off["alpha"].max() > 0.5  # the scene is actually seen


def test_black_background_equals_no_background():
    plain = plain_heads()
    none = render(plain)
    black = render(plain, background=torch.zeros(3))
    assert torch.allclose(black["image"], none["image"], atol=1e-6)


@pytest.mark.parametrize("config", [
    HeadsConfig(feature_bank=True),
    HeadsConfig(opacity_dist=True, cov_dist=True, color_dist=True),
    HeadsConfig(appearance_dim=4),
], ids=["featbank", "distances", "appearance"])
def test_head_effect_with_neutral_weights_equals_plain_heads(config):
    plain = plain_heads()
    general = neutral_heads(plain, config, num_cameras=3)
    reference, result = render(plain), render(general, camera_index=2)
    assert torch.allclose(result["image"], reference["image"], atol=1e-6)
    assert torch.allclose(result["alpha"], reference["alpha"], atol=1e-6)


def test_bits_only_payload_builds_no_hidden_decoder_and_renders_as_plain():
    spec = PayloadSpec.parse("bits:16")
    assert spec.kind is None and spec.bits == 16
    plain = plain_heads()
    private = PrivateHeads(plain, message="01" * (spec.bits // 2), bit_seed=new_seed(), bit_cell=0.1,
                           hidden=spec.kind is not None)
    assert private.decoder is None and private.offset_mlp is None and private.n_bits == 16
    assert torch.equal(render(plain)["image"], render(plain_heads())["image"])
