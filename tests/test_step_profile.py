"""securegs_warp.step_profile: every section of a SecureGS and a Scaffold-GS step is timed at a tiny
size on the CPU (no timing is asserted, only that the sections are found and the patches undone)."""
from types import SimpleNamespace

import pytest
import torch

from securegs_warp import render as render_module
from securegs_warp import step_profile
from securegs_warp.config import SecureConfig, TrainConfig
from securegs_warp.data import make_synthetic_scene
from securegs_warp.rasterizer import RasterOptions, _Rasterize
from securegs_warp.secure.trainer import SecureTrainer
from securegs_warp.train import ScaffoldTrainer


def test_profile_steps_times_each_branch_and_restores_everything():
    scene = make_synthetic_scene(hidden="mug", level="object", width=24, height=18, n_train=2, n_test=1,
                                 n_points=200)
    config = TrainConfig(iterations=10, raster=RasterOptions.for_device("cpu"))
    originals = (torch.Tensor.__dict__["backward"], _Rasterize.__dict__["backward"], render_module.rasterize)
    results = {}
    for label, trainer in (("scaffold", ScaffoldTrainer(scene, config)),
                           ("secure", SecureTrainer(scene, config, SecureConfig(payload="object+bits:48")))):
        results[label] = step_profile.profile_steps(trainer, 1)
        assert trainer.step_count == 2  # one step with the timers, one without
        assert "step" not in vars(trainer) and "render" not in vars(trainer)
        assert "step" not in vars(trainer.optimizer)
    assert (torch.Tensor.__dict__["backward"], _Rasterize.__dict__["backward"], render_module.rasterize) == originals
    for label, result in results.items():
        sections = result["sections_ms"]
        assert list(sections) == list(step_profile.SECTIONS)
        assert all(v >= 0 for v in sections.values())
        for name in ("public heads", "public rasterize", "backward (autograd, MLPs)", "rasterize backward", "adam"):
            assert sections[name] > 0, (label, name)
        assert result["step_ms"] > 0 and result["profiled_step_ms"] > 0
    assert results["secure"]["sections_ms"]["hidden rasterize"] > 0
    assert results["scaffold"]["sections_ms"]["hidden rasterize"] == 0
    table = step_profile.profile_table(results, "title")
    assert "| hidden rasterize |" in table and "scaffold ms | secure ms" in table


def test_count_ops_finds_each_branch_and_restores_everything():
    import warp as wp

    scene = make_synthetic_scene(hidden="mug", level="object", width=24, height=18, n_train=2, n_test=1,
                                 n_points=200)
    config = TrainConfig(iterations=10, raster=RasterOptions.for_device("cpu"))
    launch = (wp.launch, wp.capture_launch)
    results = {}
    for label, trainer in (("scaffold", ScaffoldTrainer(scene, config)),
                           ("secure", SecureTrainer(scene, config, SecureConfig(payload="object+bits:48")))):
        trainer.step()
        results[label] = step_profile.count_ops(trainer, 2)
        assert trainer.step_count == 3 and "step" not in vars(trainer)
    assert (wp.launch, wp.capture_launch) == launch
    for label, result in results.items():
        per_step, total = result["per_step"], result["total"]
        assert list(per_step) == list(step_profile.SECTIONS) and list(total) == list(step_profile.COUNTS)
        for name in ("public heads", "image losses", "backward (autograd, MLPs)"):
            assert per_step[name]["aten ops"] > 0, (label, name)
        assert per_step["backward (autograd, MLPs)"]["autograd nodes"] > 0
        assert per_step["public rasterize"]["warp launches"] > 0 and per_step["rasterize backward"]["warp launches"] > 0
        assert total["cuda launches"] == 0  # a CPU run
        assert total["aten ops"] == sum(s["aten ops"] for s in per_step.values())
    secure, scaffold = results["secure"]["per_step"], results["scaffold"]["per_step"]
    assert secure["hidden heads"]["aten ops"] > 0 and scaffold["hidden heads"]["aten ops"] == 0
    assert secure["hidden rasterize"]["warp launches"] == scaffold["public rasterize"]["warp launches"]
    assert results["secure"]["total"]["aten ops"] > results["scaffold"]["total"]["aten ops"]
    table = step_profile.count_table(results, "title")
    assert "| hidden heads |" in table and "scaffold aten ops" in table and "| **step** |" in table


def test_the_sync_census_is_cuda_only_and_its_table_lists_each_place():
    trainer = SimpleNamespace(device=torch.device("cpu"))
    with pytest.raises(ValueError, match="CUDA"):
        step_profile.census_syncs(trainer, 1)
    census = {"lines": {"render.py:62": 2.0, "train/base.py:139": 1.0},
              "runtime": {"cudaStreamSynchronize <- aten::item": 1.5}}
    table = step_profile.census_table({"Scaffold-GS": census}, "title")
    assert "synchronising lines, 3.0 per step" in table and "| 2.0 | `render.py:62` |" in table
    assert "can block, 1.5 per step" in table and "`cudaStreamSynchronize <- aten::item`" in table
