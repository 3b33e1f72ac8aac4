"""The model and training sections of scripts/accuracy_vs_time.py (securegs_warp.benchmark) on a tiny
scene: rows carry the columns their plot and table need, and the training section's checkpoints
count iterations in order."""
import argparse

import pytest

from securegs_warp import benchmark as avt


@pytest.fixture(scope="module")
def args():
    return argparse.Namespace(iterations=2, width=24, height=18, train_views=3, test_views=1, rounds=1, points=200,
                              device="cpu")


def test_training_section_rows(args):
    rows = avt.training_section(args)
    spec = avt.SECTIONS["training"]
    assert [row["point"] for row in rows] == ["1 it", "2 it"]
    assert all(isinstance(row[spec.x], float) and isinstance(row[spec.y], float) for row in rows)
    assert rows[0]["train_s"] < rows[1]["train_s"]


def test_model_section_rows_and_outputs(args, tmp_path, monkeypatch):
    monkeypatch.setattr(avt, "MODEL_KNOBS", {"default": {}, "k=5": {"n_offsets": 5}})
    rows = avt.model_section(args)
    spec = avt.SECTIONS["model"]
    assert [row["point"] for row in rows] == ["default", "features float16 storage", "k=5"]
    assert all(row[spec.x] > 0 and row["gaussians"] > 0 for row in rows)
    assert abs(rows[1]["test_psnr_db"] - rows[0]["test_psnr_db"]) < 1.0
    pytest.importorskip("matplotlib")
    table = avt.write(rows, tmp_path, "title")
    assert "- render_ms:" in table and (tmp_path / "accuracy_vs_time.png").stat().st_size > 0


def test_float16_feature_point_renders_rounded_features_and_restores_them(args):
    """The float16-storage point evaluates the model with rounded features (the render changes) and
    leaves the trained features exactly as they were."""
    import torch

    scene = avt.synthetic_scene(args)
    trainer = avt.make_trainer(scene, args)
    with torch.no_grad():
        torch.manual_seed(0)
        trainer.model.anchors.feat.copy_(torch.randn_like(trainer.model.anchors.feat) + 1 / 3)
    before = trainer.model.anchors.feat.detach().clone()
    full = avt.held_out(trainer, 1)
    half = avt.held_out_with_float16_features(trainer, 1)
    assert torch.equal(trainer.model.anchors.feat.detach(), before)
    assert half["test_psnr_db"] != full["test_psnr_db"]
