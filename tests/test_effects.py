"""Effects on demand: what a scene and a request infer, and each specialised variant against the
general one with that effect neutral."""

import numpy as np
import pytest
import torch

from securegs_warp.data import Camera, SceneData
from securegs_warp.effects import Effects, heads_with_neutral_effects, infer_scene_effects
from securegs_warp.model import AnchorModel, ScaffoldHeads
from securegs_warp.render import render_view
from securegs_warp.secure.heads import PrivateHeads
from securegs_warp.secure.payload import PayloadSpec
from securegs_warp.train.trainer import TrainConfig

D, K = 8, 4  # feature width, offsets per anchor
W, H = 32, 24
# tile 8 is the CPU trainer's setting; all renders here share it so the kernels compile once per flag set
TILE = {"tile_size": 8}


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


def render(heads, effects=Effects(), background=None, **options):
    return render_view(tiny_model(), heads, camera(), background, effects=effects, **TILE, **options)


# --- inference ---------------------------------------------------------------------------------------

def scene(background=None, hidden_kind=None, n_cams=3):
    cams = [camera() for _ in range(n_cams)]
    return SceneData("s", cams, [], np.zeros((4, 3)), np.zeros((4, 3)), background=background,
                     hidden_kind=hidden_kind)


def test_blender_scene_on_white_asks_for_a_background():
    effects = infer_scene_effects(scene(background=np.ones(3, np.float32)))
    assert effects.background == (1.0, 1.0, 1.0)
    assert "bg" in effects.describe()
    assert torch.equal(effects.background_tensor(), torch.ones(3))


def test_scene_without_payload_has_no_hidden_branch():
    effects = infer_scene_effects(scene())
    assert effects.hidden == frozenset() and effects.background is None and effects.describe() == "base"


def test_payload_gives_hidden_branches_and_public_request_drops_them():
    effects = infer_scene_effects(scene(hidden_kind="object"), PayloadSpec.parse("object+bits:16"))
    assert effects.hidden == {"object", "bits"}
    assert effects.describe() == "hidden-bits+hidden-object"
    public = effects.for_request(private=False)
    assert public.hidden == frozenset()
    assert effects.for_request(private=True).hidden == {"object", "bits"}


def test_rgb_only_request_writes_no_depth():
    effects = Effects(depth="expected")
    assert effects.for_request().depth is None and effects.for_request().raster_options() == {}
    assert effects.for_request(depth=True).raster_options() == {"render_depth": "expected"}
    assert Effects().for_request(depth=True).depth == "accumulated"


def test_config_effects_follow_the_train_config():
    config = TrainConfig(use_feat_bank=True, appearance_dim=4, add_cov_dist=True)
    effects = infer_scene_effects(scene(n_cams=5), config=config)
    assert effects.config_fields() == {"use_feat_bank": True, "appearance_dim": 4, "add_opacity_dist": False,
                                       "add_cov_dist": True, "add_color_dist": False}
    assert effects.head_kwargs()["num_cameras"] == 5


@pytest.mark.parametrize("kwargs, message", [
    ({"appearance_dim": 4}, "num_cameras"),
    ({"depth": "median"}, "depth"),
    ({"hidden": {"object", "scene"}}, "at most one"),
    ({"hidden": {"video"}}, "unknown hidden"),
    ({"background": (1.0, 1.0)}, "3 values"),
])
def test_bad_combinations_are_named(kwargs, message):
    with pytest.raises(ValueError, match=message):
        Effects(**kwargs)


# --- specialised variant == general variant with the effect neutral ---------------------------------

def test_depth_off_equals_depth_on_image_and_alpha():
    plain = plain_heads()
    off = render(plain)
    for mode in ("accumulated", "expected"):
        on = render(plain, Effects(depth=mode))
        assert on["info"]["depth"].shape == (H, W, 1) and "depth" not in off["info"]
        assert torch.allclose(on["image"], off["image"], atol=1e-6)
        assert torch.allclose(on["alpha"], off["alpha"], atol=1e-6)
    assert off["alpha"].max() > 0.5  # the scene is actually seen


def test_black_background_equals_no_background():
    plain = plain_heads()
    none = render(plain)
    black = render(plain, background=Effects(background=(0.0, 0.0, 0.0)).background_tensor())
    assert torch.allclose(black["image"], none["image"], atol=1e-6)


@pytest.mark.parametrize("effects", [
    Effects(feature_bank=True),
    Effects(opacity_dist=True, cov_dist=True, color_dist=True),
    Effects(appearance_dim=4, num_cameras=3),
], ids=lambda e: e.describe())
def test_head_effect_with_neutral_weights_equals_plain_heads(effects):
    plain = plain_heads()
    general = heads_with_neutral_effects(plain, effects)
    reference, result = render(plain), render(general, camera_index=2)
    assert torch.allclose(result["image"], reference["image"], atol=1e-6)
    assert torch.allclose(result["alpha"], reference["alpha"], atol=1e-6)


def test_bits_only_payload_builds_no_hidden_decoder_and_renders_as_plain():
    effects = infer_scene_effects(scene(), PayloadSpec.parse("bits:16"))
    assert effects.hidden == {"bits"}
    plain = plain_heads()
    private = PrivateHeads(plain, **effects.private_head_kwargs(bits=16))
    assert private.decoder is None and private.offset_mlp is None and private.n_bits == 16
    public = render(plain, effects.for_request(private=False))
    assert torch.equal(public["image"], render(plain_heads())["image"])
