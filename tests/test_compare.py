"""The side-by-side runner's logic (securegs_warp.compare): variants, region errors, release size."""
import math

import numpy as np
import pytest
import torch

from securegs_warp.compare import RegionErrors, parse_variant, release_mb
from securegs_warp.config import SecureConfig, apply_overrides
from securegs_warp.data import Camera
from securegs_warp.model import AnchorModel, ScaffoldHeads
from securegs_warp.scaffold_model import ScaffoldModel


def test_variant_sets_fields_by_name():
    base = SecureConfig(payload="object")
    label, config = parse_variant("rdo", base)
    assert label == "SecureGS" and config == apply_overrides(base, {"strategy.mode": "rdo"})
    label, config = parse_variant("global:r_down=2:hidden_weight=1:hdger=false:strategy.hidden_growth_at=public", base)
    assert config.strategy.mode == "global" and config.strategy.r_down == 2.0 and config.hidden_weight == 1.0
    assert config.hdger is False and config.strategy.hidden_growth_at == "public" and config.payload == "object"
    assert label.startswith("SecureGS (global, r_down=2")
    assert math.isinf(parse_variant("rdo:hidden_tau_scale=inf", base)[1].strategy.hidden_tau_scale)
    # A value with colons of its own (a robust spec) stays whole.
    _, config = parse_variant("cover:robust=prune-random:0.3+noise-feat:0.3:bit_margin=0.25", base)
    assert config.robust == "prune-random:0.3+noise-feat:0.3" and config.bit_margin == 0.25


@pytest.mark.parametrize("text, message", [
    ("turbo", "mode must be one of"),
    ("rdo:lambda=1", "unknown option 'lambda'"),
    ("rdo:r_down", "not FIELD=VALUE"),
    ("rdo:", "not FIELD=VALUE"),
    ("rdo:r_down=abc", "not a valid float"),
    ("rdo:r_down=0.5", "r_down must be >= 1"),
    ("rdo:hidden_feature_grad=2", r"hidden_feature_grad must lie in \[0, 1\]"),
])
def test_bad_variants_are_refused_with_the_field_named(text, message):
    with pytest.raises(ValueError, match=message):
        parse_variant(text, SecureConfig())


def test_region_errors_split_the_error_at_the_hidden_footprint():
    """A render wrong by 0.1 inside the footprint (columns 0-9 of 40) and by 0.01 outside: the two
    regions' PSNRs are 20 and 40 dB once the footprint's 1-pixel dilation is accounted for."""
    h, w = 8, 40
    target = np.full((h, w, 3), 0.5, np.float32)
    alpha = np.zeros((h, w, 1), np.float32)
    alpha[:, :10] = 1.0
    cam = Camera("c", np.eye(4), np.eye(3), w, h, image=target, hidden_alpha=alpha)
    render = torch.full((h, w, 3), 0.51)
    render[:, :11] = 0.6  # the footprint dilated by max(1, w // 100) = 1 pixel
    regions = RegionErrors()
    regions(cam, render)
    psnr = regions.psnr()
    assert psnr["psnr_public_on_hidden"] == pytest.approx(20.0, abs=1e-3)
    assert psnr["psnr_public_off_hidden"] == pytest.approx(40.0, abs=1e-3)
    assert len(regions.per_view) == 1
    empty = RegionErrors()
    full = np.ones((h, w, 1), np.float32)
    empty(Camera("c", np.eye(4), np.eye(3), w, h, image=target, hidden_alpha=full), render)
    assert empty.psnr()["psnr_public_off_hidden"] is None  # a hidden scene covers every pixel


def test_release_size_counts_the_release_files():
    n, d, k = 50, 8, 4
    anchors = AnchorModel(torch.zeros(n, 3), torch.zeros(n, d), torch.zeros(n, k, 3), torch.zeros(n, 6),
                          torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.zeros(n, 1))
    size = release_mb(ScaffoldModel(anchors, ScaffoldHeads(d, k)))
    assert n * (6 + 3 * k + d + 11) * 4 / 1e6 < size < 1.0  # the PLY's float32 rows plus the MLP files


def test_read_report_reads_what_secure_vs_baseline_writes(tmp_path):
    from securegs_warp.compare import BASELINE, read_report, write_report
    exposure = {"surface_fraction": 0.1, "coverage": 0.2, "surface_density": 0.3}
    meta = {"device": "cpu", "width": 8, "height": 6, "iterations": 2, "hidden": "mug", "payload": "object"}
    write_report(tmp_path, meta, {BASELINE: {"psnr_public": 20.0, "exposure": exposure}})
    xyz = np.arange(6, dtype=np.float32).reshape(2, 3)
    np.savez_compressed(tmp_path / "anchor_clouds.npz", hidden_points=xyz, scene_points=xyz, **{BASELINE: xyz})
    report, clouds = read_report(tmp_path)
    assert report["meta"] == meta and report["rows"][BASELINE]["psnr_public"] == 20.0
    np.testing.assert_array_equal(clouds[BASELINE], xyz)
    np.savez_compressed(tmp_path / "anchor_clouds.npz", hidden_points=xyz)
    with pytest.raises(ValueError, match="lacks the anchors of Scaffold-GS baseline"):
        read_report(tmp_path)
    with pytest.raises(ValueError, match="not a secure_vs_baseline.py output folder"):
        read_report(tmp_path / "nothing")
