"""The config tree: one name per option, round trips through JSON, overrides by name, and resuming
with other options refused with the field named."""
import json
import math
from types import SimpleNamespace

import pytest

from securegs_warp.cli import main
from securegs_warp.config import (
    HeadsConfig,
    RunConfig,
    SceneSpec,
    SecureConfig,
    TrainConfig,
    apply_overrides,
    field_paths,
    first_difference,
    from_dict,
    resolve_field,
    to_dict,
)
from securegs_warp.rasterizer import RasterOptions
from securegs_warp.strategies import RegionAwareStrategy
from securegs_warp.train.trainer import ScaffoldTrainer

TINY = ["--width", "40", "--height", "30", "--train-views", "6", "--test-views", "2"]


def test_round_trip_through_json():
    config = RunConfig(
        scene=SceneSpec(width=40, hidden="mug"),
        train=TrainConfig(iterations=7, heads=HeadsConfig(feature_bank=True), raster=RasterOptions(tile_size=8)),
        secure=SecureConfig(payload="bits:8", hidden_weight=2.0,
                            strategy=RegionAwareStrategy(hidden_tau_scale=float("inf"))))
    back = from_dict(RunConfig, json.loads(json.dumps(to_dict(config))))
    assert back == config and first_difference(back, config) is None
    assert math.isinf(back.secure.strategy.hidden_tau_scale)
    assert from_dict(RunConfig, to_dict(RunConfig())).secure is None


def test_a_config_recorded_before_a_field_existed_keeps_what_its_run_did():
    """A recorded secure section without bits_from was trained with the bits projected from the
    start (RECORDED_BEFORE), whatever the default is now; a config that names it keeps its value."""
    data = to_dict(RunConfig(secure=SecureConfig()))
    assert data["secure"]["bits_from"] == SecureConfig().bits_from == "growth-end"
    del data["secure"]["bits_from"]
    assert from_dict(RunConfig, data).secure.bits_from == "start"
    data["secure"]["bits_from"] = "growth-end"
    assert from_dict(RunConfig, data).secure.bits_from == "growth-end"


def test_every_leaf_field_has_one_name():
    paths = field_paths(RunConfig(secure=SecureConfig()))
    assert "train.raster.tile_size" in paths and "secure.strategy.r_down" in paths
    leaves = [p.rsplit(".", 1)[-1] for p in paths]
    # names that repeat are ambiguous as bare names and must be given as paths (seed: scene and training)
    assert sorted({n for n in leaves if leaves.count(n) > 1}) == ["seed"]
    assert resolve_field(RunConfig(secure=SecureConfig()), "r_down") == "secure.strategy.r_down"
    assert resolve_field(RunConfig(secure=SecureConfig()), "strategy.r_down") == "secure.strategy.r_down"
    assert resolve_field(RunConfig(secure=SecureConfig()), "raster.fast_math") == "train.raster.fast_math"
    with pytest.raises(ValueError, match="unknown option"):
        resolve_field(RunConfig(secure=SecureConfig()), "down")  # a tail is whole names, not letters
    with pytest.raises(ValueError, match="ambiguous"):
        resolve_field(RunConfig(secure=SecureConfig()), "seed")


def test_overrides_convert_and_check_values():
    config = apply_overrides(RunConfig(secure=SecureConfig()),
                             {"iterations": "12", "tile_size": "8", "hidden_weight": "none", "hdger": "false",
                              "train.offset_lr": "0.1,0.01"})
    assert config.train.iterations == 12 and config.train.raster.tile_size == 8
    assert config.secure.hidden_weight is None and config.secure.hdger is False
    assert config.train.offset_lr == (0.1, 0.01)
    for overrides, message in (({"iterations": "0"}, "iterations must be >= 1"),
                               ({"iterations": "2.5"}, "not a valid int"),
                               ({"tile_size": "12"}, "tile_size must be 8, 16 or 32"),
                               ({"hdger": "maybe"}, "not a valid bool"),
                               ({"nonsense": 1}, "unknown option 'nonsense'"),
                               ({"scene.hidden_yaw": "inf"}, "hidden_yaw must be finite"),
                               ({"scene.hidden_size": "nan"}, "hidden_size must be > 0 and finite"),
                               ({"scene.hidden_position": "0,0,inf"}, r"hidden_position must be x,y,z \(finite\)")):
        with pytest.raises(ValueError, match=message):
            apply_overrides(RunConfig(secure=SecureConfig()), overrides)


def test_unknown_fields_in_a_file_are_named():
    data = to_dict(RunConfig())
    data["train"]["heads"]["feature_bankk"] = True
    with pytest.raises(ValueError, match="train.heads.feature_bankk"):
        from_dict(RunConfig, data)


def test_resume_with_other_options_is_refused_naming_the_field(tmp_path, capsys):
    out = tmp_path / "run"
    args = ["hide", "--out", str(out), "--iterations", "3", "--quiet", "--payload", "bits:8", *TINY]
    assert main(args) == 0
    capsys.readouterr()
    assert main(args + ["--resume", "--mode", "global"]) == 2
    assert "secure.strategy.mode" in capsys.readouterr().err
    assert main(args + ["--resume", "--iterations", "4"]) == 2
    assert "train.iterations" in capsys.readouterr().err
    assert main(args + ["--resume"]) == 0  # the same options resume (here: already finished)


def test_set_reaches_any_field_and_names_bad_ones(tmp_path, capsys):
    out = tmp_path / "run"
    args = ["train", "--out", str(out), "--iterations", "2", "--quiet", *TINY]
    assert main(args + ["--set", "mlp_offset_lr=0.001,0.0001", "--set", "train.feature_lr=0.005"]) == 0
    saved = json.loads((out / "config.json").read_text())
    assert saved["train"]["mlp_offset_lr"] == [0.001, 0.0001] and saved["train"]["feature_lr"] == 0.005
    capsys.readouterr()
    assert main(args + ["--force", "--set", "no_such_field=1"]) == 2
    assert "no_such_field" in capsys.readouterr().err
    assert main(args + ["--force", "--set", "feature_lr"]) == 2
    assert "FIELD=VALUE" in capsys.readouterr().err
    assert main(args + ["--force", "--set", "feature_lr=fast"]) == 2
    assert "train.feature_lr" in capsys.readouterr().err


def test_robust_training_is_on_by_default_only_for_an_object_in_the_cover_mode():
    from securegs_warp.config import BIT_MARGIN, FINISH_FRACTION, ROBUST_BIT_MARGIN, ROBUST_RECIPE

    secure = SecureConfig()
    assert secure.robust_spec(["object", None], "cover") == ROBUST_RECIPE
    assert secure.margin(["object", None], "cover") == ROBUST_BIT_MARGIN
    # not where it was not measured: the RDO mode, or an image decoded from the visible anchors
    for kinds, mode in ((["object"], "rdo"), (["image"], "rdo"), (["image", "object"], "cover"), ([None], "rdo")):
        assert secure.robust_spec(kinds, mode) is None and secure.margin(kinds, mode) == BIT_MARGIN
    off = apply_overrides(secure, {"robust": "none"})
    assert off.robust is None and off.resolved(["object"], "cover") == apply_overrides(
        off, {"bit_margin": "1", "hidden_finish": str(FINISH_FRACTION), "finish_robust": "none"})
    # an explicit recipe keeps the margin the run asked for, or the plain default
    given = apply_overrides(secure, {"robust": "noise-feat:0.2"})
    assert given.robust_spec([None], "rdo") == "noise-feat:0.2" and given.margin([None], "rdo") == BIT_MARGIN
    assert apply_overrides(given, {"bit_margin": "2"}).margin(["object"], "cover") == 2.0
    with pytest.raises(ValueError, match="robust"):
        apply_overrides(secure, {"robust": "noise-offset:0.1"})


def test_attack_recipes_have_one_spelling():
    """Two spellings of one recipe are one config (a resumed run compares its recorded recipe with
    the command's); the order stays, since the attacks draw their randomness in it."""
    from securegs_warp.config import RESUMABLE_CHANGES, recorded_phase

    given = apply_overrides(SecureConfig(), {"robust": "prune-random:0.30+noise-feat:.3",
                                             "finish_robust": "prune-random:5e-1"})
    assert (given.robust, given.finish_robust) == ("prune-random:0.3+noise-feat:0.3", "prune-random:0.5")
    assert given == apply_overrides(SecureConfig(), {"robust": "prune-random:0.3+noise-feat:0.3",
                                                     "finish_robust": "prune-random:0.5"})
    assert apply_overrides(SecureConfig(), {"robust": "noise-feat:0.3+prune-random:0.3"}).robust == \
        "noise-feat:0.3+prune-random:0.3"
    # a run recorded before the one spelling, or before finish_robust existed
    assert recorded_phase({"hidden_finish": 0.25, "finish_robust": "prune-random:0.50"})["finish_robust"] == \
        "prune-random:0.5"
    assert recorded_phase({"robust": "noise-feat:0.30"}) == {"hidden_finish": 0.0, "finish_robust": "noise-feat:0.3"}
    with pytest.raises(ValueError, match="finish_robust"):
        recorded_phase({"finish_robust": "prune-random:lots"})
    # every option a resumed run may change, and no other
    assert {f"secure.{name}" for name in recorded_phase({})} == set(RESUMABLE_CHANGES)
    # the short form only where it reads back as the same number
    exact = apply_overrides(SecureConfig(), {"robust": "noise-feat:0.1234567", "finish_robust": "prune-random:0.9999999"})
    assert (exact.robust, exact.finish_robust) == ("noise-feat:0.1234567", "prune-random:0.9999999")


def test_hide_records_the_robust_training_and_margin_it_chose(tmp_path, capsys):
    """config.json holds the resolved choice, so that a later default cannot change a resumed run;
    a run recorded without robust training (as every run before it was the default) resumes with
    --robust none, and without it is refused, naming the field."""
    runs = {}
    for payload, robust, margin, extra in (("object", "prune-random:0.3+noise-feat:0.3", 0.25, []),
                                           ("object", None, 1.0, ["--robust", "none"]),
                                           ("bits:8", None, 1.0, [])):
        out = tmp_path / f"run_{payload}_{len(extra)}"
        args = ["hide", "--out", str(out), "--iterations", "2", "--quiet", "--payload", payload, *TINY, *extra]
        assert main(args) == 0
        runs[(payload, len(extra))] = args
        saved = json.loads((out / "config.json").read_text())["secure"]
        assert (saved["robust"], saved["bit_margin"]) == (robust, margin)
        metrics = json.loads((out / "metrics.json").read_text())
        assert (metrics["robust"], metrics["bit_margin"]) == (robust, margin)
    capsys.readouterr()
    old = runs[("object", 2)][:-2]  # the run without robust training, resumed without the flag
    assert main(old + ["--resume"]) == 2
    assert "secure.robust" in capsys.readouterr().err
    assert main(old + ["--resume", "--robust", "none"]) == 0


def test_the_codes_and_the_latent_grid_train_on_schedules_of_their_own():
    """The codes (a key's per-anchor features) keep feature_lr by default; the latent grid decays."""
    held = SimpleNamespace(config=TrainConfig(feature_lr=0.005))
    assert ScaffoldTrainer._mlp_schedule(held, "private_codes") == (0.005, 0.005)
    view = SimpleNamespace(config=TrainConfig(code_lr=(0.02, 0.002), latent_lr=(0.006, 0.0006)))
    assert ScaffoldTrainer._mlp_schedule(view, "private_codes") == (0.02, 0.002)
    assert ScaffoldTrainer._mlp_schedule(view, "private2_codes") == (0.02, 0.002)
    assert ScaffoldTrainer._mlp_schedule(view, "private_latent") == (0.006, 0.0006)
