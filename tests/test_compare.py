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


def _run_folder(path, xyz, seed, hidden=None, mode=None, iterations=400):
    """A minimal securegs train (mode None) or hide run folder: config.json and the point cloud's
    positions, all that ``read_run_anchors`` reads."""
    import json

    from securegs_warp.config import RunConfig, SceneSpec, TrainConfig, to_dict
    from securegs_warp.io.gs_ply import write_vertex_ply
    secure = None if mode is None else apply_overrides(SecureConfig(), {"strategy.mode": mode})
    config = RunConfig(scene=SceneSpec(hidden=hidden), train=TrainConfig(iterations=iterations, seed=seed),
                       secure=secure)
    (path / ("model" if mode is None else "public")).mkdir(parents=True)
    (path / "config.json").write_text(json.dumps(to_dict(config)))
    write_vertex_ply(path / ("model" if mode is None else "public") / "point_cloud.ply", ("x", "y", "z"), xyz)
    return path


def test_read_run_anchors_gives_a_plain_run_and_its_containers_one_cover(tmp_path):
    from securegs_warp.compare import BASELINE, read_run_anchors
    xyz = np.random.default_rng(0).normal(size=(50, 3)).astype(np.float32)
    plain = read_run_anchors(_run_folder(tmp_path / "plain", xyz, seed=3))
    mug = read_run_anchors(_run_folder(tmp_path / "mug", xyz, seed=3, hidden="mug", mode="cover"))
    rdo = read_run_anchors(_run_folder(tmp_path / "rdo", xyz, seed=3, hidden="bunny.obj", mode="rdo"))
    assert plain[1] == BASELINE and mug[1] == "SecureGS (cover)" and rdo[1] == "SecureGS"
    assert plain[0] == mug[0] == rdo[0]  # the hidden object is no part of the cover
    assert read_run_anchors(_run_folder(tmp_path / "s4", xyz, seed=4))[0] != plain[0]
    assert read_run_anchors(_run_folder(tmp_path / "long", xyz, seed=3, iterations=800))[0] != plain[0]
    np.testing.assert_array_equal(plain[2], xyz.astype(np.float64))
    with pytest.raises(ValueError, match="nothing: not a readable securegs train / hide run"):
        read_run_anchors(tmp_path / "nothing")
    (tmp_path / "mug" / "public" / "point_cloud.ply").write_bytes(b"not a ply")
    with pytest.raises(ValueError, match="mug: not a readable securegs train / hide run"):
        read_run_anchors(tmp_path / "mug")


def test_audit_auc_script_pairs_run_folders_by_cover(tmp_path):
    """scripts/audit_auc.py over train / hide run folders: one run per cover, the containers scored
    against the other covers' plain models only, and a container without its plain model refused."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    rng = np.random.default_rng(1)
    folders = []
    for seed in range(3):
        scene = rng.uniform(-1, 1, size=(400, 3)).astype(np.float32)
        # The containers carry a dense clump: the audit must find them more suspicious (AUC 1).
        clump = rng.normal(scale=0.01, size=(120, 3)).astype(np.float32) + 0.5
        folders += [_run_folder(tmp_path / f"plain_s{seed}", scene, seed),
                    _run_folder(tmp_path / f"hide_s{seed}", np.concatenate([scene, clump]), seed, "mug", "cover")]
    script = Path(__file__).resolve().parents[1] / "scripts" / "audit_auc.py"
    out = tmp_path / "auc.json"
    done = subprocess.run([sys.executable, str(script), *map(str, folders), "--with-reference", "--json", str(out)],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    result = json.loads(out.read_text())
    # Three covers: each model against the two other covers' plain models.
    assert len(result["SecureGS (cover)"]["scores"]) == len(result["Scaffold-GS baseline"]["scores"]) == 6
    assert result["SecureGS (cover)"]["auc"] == 1.0
    lone = _run_folder(tmp_path / "hide_s9", np.zeros((10, 3), np.float32), 9, "mug", "cover")
    done = subprocess.run([sys.executable, str(script), str(folders[0]), str(lone)], capture_output=True, text=True)
    assert done.returncode != 0 and "hide_s9: no plain model of that scene, seed and budget" in done.stderr
    twin = _run_folder(tmp_path / "again_s0", np.zeros((10, 3), np.float32), 0, "bunny.obj", "cover")
    done = subprocess.run([sys.executable, str(script), *map(str, folders), str(twin)], capture_output=True, text=True)
    assert done.returncode != 0 and "a second 'SecureGS (cover)'" in done.stderr and "hide_s0" in done.stderr
