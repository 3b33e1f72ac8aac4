"""The box frame's hidden renders trained on the part of the view its box reaches (secure.crop)."""
import numpy as np
import pytest
import torch

from securegs_warp.config import SecureConfig, apply_overrides
from securegs_warp.data import Camera, make_synthetic_scene
from securegs_warp.data.cameras import look_at
from securegs_warp.rasterizer import RasterOptions
from securegs_warp.secure import SecureTrainer, crop
from securegs_warp.train import TrainConfig


def _camera(eye, width=320, height=240, focal=300.0):
    K = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], dtype=np.float32)
    return Camera("c", look_at(eye, (0.0, 0.0, 0.0)), K, width, height)


def _project(cam, points):
    p = points @ cam.viewmat[:3, :3].T + cam.viewmat[:3, 3]
    return cam.K[0, 0] * p[:, 0] / p[:, 2] + cam.K[0, 2], cam.K[1, 1] * p[:, 1] / p[:, 2] + cam.K[1, 2]


def test_the_crop_is_tile_aligned_and_holds_the_box_and_its_margin():
    cam = _camera((6.0, 0.5, 1.0))
    box = np.array([[0.2, -0.1, 0.0], [0.3, 0.2, 0.25]])
    c = crop.box_crop(cam, box, tile=16)
    assert c is not None and 0 < c.share < crop.MAX_SHARE
    for s in (c.rows, c.cols):
        assert s.start % 16 == 0 and (s.stop % 16 == 0 or s.stop in (cam.width, cam.height))
    rng = np.random.default_rng(0)
    u, v = _project(cam, box[0] + (2 * rng.random((500, 3)) - 1) * box[1])
    assert (u >= c.cols.start + crop.MARGIN_PX).all() and (u <= c.cols.stop - crop.MARGIN_PX).all()
    assert (v >= c.rows.start + crop.MARGIN_PX).all() and (v <= c.rows.stop - crop.MARGIN_PX).all()
    # The cropped camera sees a point where the view sees it, less the rectangle's corner.
    uc, vc = _project(c.camera, box[:1])
    u0, v0 = _project(cam, box[:1])
    assert (uc - (u0 - c.cols.start), vc - (v0 - c.rows.start)) == pytest.approx((0.0, 0.0), abs=1e-3)
    assert c.share == pytest.approx(c.camera.width * c.camera.height / (cam.width * cam.height))


def test_views_the_box_fills_or_reaches_behind_are_rendered_whole():
    assert crop.box_crop(_camera((6.0, 0.5, 1.0)), np.array([[0.0, 0.0, 0.0], [2.0, 2.0, 2.0]]), 16) is None
    # a box around the camera itself reaches behind it
    assert crop.box_crop(_camera((6.0, 0.5, 1.0)), np.array([[6.0, 0.5, 1.0], [0.5, 0.5, 0.5]]), 16) is None
    # a box behind the camera's back
    assert crop.box_crop(_camera((6.0, 0.0, 0.0)), np.array([[12.0, 0.0, 0.0], [0.1, 0.1, 0.1]]), 16) is None


@pytest.fixture(scope="module")
def trainer():
    scene = make_synthetic_scene(hidden="mug", level="object", width=96, height=72, n_train=4, n_test=1, n_points=600)
    secure = apply_overrides(SecureConfig(payload="object"), {"strategy.mode": "cover", "hidden_offsets": 4,
                                                              "hidden_width": 16, "hidden_anchors": 60,
                                                              "hidden_crop": True,
                                                              # the crop and the whole view must read the same anchors
                                                              "robust": None})
    t = SecureTrainer(scene, TrainConfig(iterations=10, raster=RasterOptions(tile_size=8)), secure)
    for _ in range(3):
        t.step()
    return t


def test_the_cropped_hidden_render_is_the_views_own_pixels(trainer, monkeypatch):
    monkeypatch.setattr(crop, "MAX_SHARE", 1.0)
    trainer._crops = [type(k)() for k in trainer._crops]
    cam = trainer.scene.train[0]
    c = trainer._hidden_crop(0, 0)
    assert c is not None and c.share < 1.0
    with torch.no_grad():
        whole = trainer.render_hidden(cam, 0)["image"]
        part = trainer.render_hidden(c.camera, 0)["image"]
    assert torch.allclose(part, whole[c.rows, c.cols], atol=1e-4)
    background = trainer.payload.background
    outside = torch.ones(whole.shape[:2], dtype=torch.bool)
    outside[c.rows, c.cols] = False
    assert torch.allclose(whole[outside], background.expand_as(whole[outside]), atol=2e-3)


def test_the_cropped_loss_weighs_pixels_as_the_whole_view(trainer, monkeypatch):
    """The image term of the crop, weighed by its share, is the whole view's (outside it both are
    background); without the crop option the whole view is rendered."""
    monkeypatch.setattr(crop, "MAX_SHARE", 1.0)
    trainer._crops = [type(k)() for k in trainer._crops]
    losses = {}
    for name, use in (("crop", True), ("whole", False)):
        monkeypatch.setattr(trainer, "secure", apply_overrides(trainer.secure, {"hidden_crop": use}))
        renders, branches = [], {"public": ({"visible_mask": None}, None)}
        with torch.no_grad():
            trainer.extra_losses(0, renders, branches, step=3)
            out, target, weight = renders[0]
            losses[name] = trainer.image_losses([(out, target, 1.0)]).item()
        assert ("pixel_share" in out) == use
    assert losses["crop"] == pytest.approx(losses["whole"], rel=0.02)


def test_the_share_weighs_the_image_term_and_not_the_regulariser(trainer, monkeypatch):
    from securegs_warp.train.losses import photometric_loss

    monkeypatch.setattr(trainer, "regularizer", lambda out: torch.tensor(0.5))
    image, target = torch.rand(8, 8, 3), torch.rand(8, 8, 3)
    term = photometric_loss(image, target, trainer.config.ssim_weight).item()
    got = trainer.image_losses([({"image": image, "pixel_share": 0.25}, target, 2.0)]).item()
    assert got == pytest.approx(2.0 * (0.25 * term + 0.5), rel=1e-6)


def test_only_the_cover_mode_crops(monkeypatch):
    """Other modes grow anchors from the hidden render's screen-space gradients, which depend on the
    image size: they render whole views."""
    monkeypatch.setattr(crop, "MAX_SHARE", 1.0)
    scene = make_synthetic_scene(hidden="mug", level="object", width=96, height=72, n_train=2, n_test=1, n_points=300)
    secure = apply_overrides(SecureConfig(payload="object"), {"strategy.mode": "rdo", "hidden_frame": "box",
                                                              "hidden_offsets": 10, "hidden_width": 8,
                                                              "hidden_crop": True})  # rdo reads k = 10 rows
    t = SecureTrainer(scene, TrainConfig(iterations=4, raster=RasterOptions(tile_size=8)), secure)
    assert t.model.private.frame == "box" and t._hidden_crop(0, 0) is None
