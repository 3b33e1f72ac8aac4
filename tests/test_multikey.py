"""Several secrets in one release, each behind its own key: `securegs hide ... --and ...` end to end."""
import json

import pytest
import torch
from safetensors import safe_open

from securegs_warp.cli import main
from securegs_warp.config import SecureConfig, TrainConfig
from securegs_warp.keys import load_key
from securegs_warp.secure import SecureTrainer
from securegs_warp.secure.payload import parse_secrets

TINY = ["--width", "40", "--height", "30", "--train-views", "4", "--test-views", "1", "--quiet"]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A release hiding an object (key in the run folder), bits and an image (keys elsewhere), the
    last two sealed with passphrases of their own; and a release of one secret of the same scene."""
    root = tmp_path_factory.mktemp("multikey")
    mp = pytest.MonkeyPatch()
    mp.setenv("PASS_A", "alpha")
    mp.setenv("PASS_C", "gamma")
    try:
        assert main(["hide", "--out", str(root / "c"), "--iterations", "30", *TINY, "--payload", "object+bits:48",
                     "--hide", "mug", "--passphrase-env", "PASS_A",
                     "--and", "--payload", "bits:48", "--key-out", str(root / "b.key"),
                     "--and", "--payload", "image+bits:32", "--key-out", str(root / "c.key"),
                     "--passphrase-env", "PASS_C"]) == 0
    finally:
        mp.undo()
    # its secrets have different passphrases: the checkpoint, sealed with the first one's only, is gone
    assert not (root / "c" / "checkpoint.pt").exists()
    assert main(["hide", "--out", str(root / "other"), "--payload", "bits:48", "--iterations", "30", *TINY]) == 0
    assert (root / "other" / "checkpoint.pt").exists()  # one secret: kept (sealed or not like its key)
    return root


KEYS = {"a": ("c/key.sealed", "PASS_A", "alpha"), "b": ("b.key", None, None), "c": ("c.key", "PASS_C", "gamma")}


def key_args(runs, name, monkeypatch) -> list[str]:
    path, env, value = KEYS[name]
    if env is None:
        return ["--key", str(runs / path)]
    monkeypatch.setenv(env, value)
    return ["--key", str(runs / path), "--passphrase-env", env]


def verify(runs, release, name, capsys, monkeypatch) -> dict:
    capsys.readouterr()
    assert main(["verify", str(runs / release), *key_args(runs, name, monkeypatch), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_one_release_of_scaffold_gs_files_and_a_key_per_secret(runs):
    assert sorted(p.name for p in (runs / "c" / "public").iterdir()) == ["color_mlp.pt", "cov_mlp.pt",
                                                                        "opacity_mlp.pt", "point_cloud.ply"]
    metrics = json.loads((runs / "c" / "metrics.json").read_text())
    assert (metrics["payload"], metrics["payload_2"], metrics["payload_3"]) == (
        "object+bits:48", "bits:48", "image:builtin@0+bits:32")
    assert metrics["key_file"] == "key.sealed" and metrics["key_file_3"] == str(runs / "c.key")
    assert metrics["bit_accuracy"] == metrics["bit_accuracy_2"] == metrics["bit_accuracy_3"] == 1.0
    config = json.loads((runs / "c" / "config.json").read_text())
    assert config["secure"]["payload"] == "object+bits:48,bits:48,image:builtin@0+bits:32"


def test_each_key_reveals_and_verifies_its_own_secret(runs, capsys, monkeypatch, tmp_path):
    messages = {}
    for name, renders in (("a", {"hidden_test_000.png"}), ("b", set()), ("c", {"hidden_train_000.png"})):
        assert verify(runs, "c/public", name, capsys, monkeypatch)["present"] is True
        out = tmp_path / name
        assert main(["reveal", str(runs / "c" / "public"), *key_args(runs, name, monkeypatch), "--out", str(out)]) == 0
        assert {p.name for p in (out / "renders").glob("hidden_*")} == renders
        messages[name] = json.loads((out / "bits.json").read_text())["bits"]
    assert len(messages["a"]) == len(messages["b"]) == 48 and len(messages["c"]) == 32
    assert messages["a"] != messages["b"]


def test_keys_share_no_secret_and_name_no_other_secret(runs):
    metas, tensors = {}, {}
    for name, (path, _, passphrase) in KEYS.items():
        tensors[name], metas[name] = load_key(runs / path, passphrase)
    seeds = {m["heads"]["bit_seed"] for m in metas.values()}
    assert len(seeds) == 3
    assert [m["payload"] for m in metas.values()] == ["object+bits:48", "bits:48", "image:builtin@0+bits:32"]
    assert tensors["b"] == {}  # a bit payload's key holds its seed and message, no heads
    shared = set(tensors["a"]) & set(tensors["c"])  # the object's and the image's decoders: same shapes
    assert shared and not any(torch.equal(tensors["a"][n], tensors["c"][n]) for n in shared)
    plain = (runs / "b.key").read_bytes()
    for name in ("a", "c"):
        assert metas[name]["heads"]["bit_seed"].encode() not in plain
        assert metas[name]["heads"]["message"].encode() not in plain
    with safe_open(runs / "b.key", "pt") as f:
        assert "image_view" in json.loads(f.metadata()["metadata"])  # its own metadata, nothing of the others


def test_a_foreign_key_verifies_absent_and_is_refused_by_reveal(runs, capsys, monkeypatch, tmp_path):
    for name in KEYS:
        result = verify(runs, "other/public", name, capsys, monkeypatch)
        assert result["present"] is False and result["p_value"] > 1e-6
    other = runs / "other" / "key.safetensors"
    capsys.readouterr()
    assert main(["verify", str(runs / "c" / "public"), "--key", str(other), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["present"] is False
    assert main(["reveal", str(runs / "c" / "public"), "--key", str(other), "--out", str(tmp_path / "r")]) == 2
    assert "belongs to another container" in capsys.readouterr().err


def test_audit_and_attack_work_with_any_one_key(runs, capsys, monkeypatch, tmp_path):
    for name in KEYS:
        capsys.readouterr()
        assert main(["audit", str(runs / "c" / "public"), *key_args(runs, name, monkeypatch), "--json"]) == 0
        assert "score" in json.loads(capsys.readouterr().out)
        assert main(["attack", str(runs / "c" / "public"), *key_args(runs, name, monkeypatch), "--attack",
                     "prune-random:0.2", "--out", str(tmp_path / name), "--json"]) == 0
        after = json.loads(capsys.readouterr().out)["after"]
        assert after["bit_accuracy"] == 1.0


def test_bad_secret_options_get_one_line_errors(runs, capsys, monkeypatch, tmp_path):
    monkeypatch.setenv("PASS_B", "beta")
    out = ["hide", "--out", str(tmp_path / "x"), "--iterations", "2", *TINY]
    cases = {
        "--and at the end": (["--and"], "give its --payload"),
        "--and without a payload": (["--and", "--key-out", str(tmp_path / "k")], "give its --payload"),
        "--and without a key": (["--and", "--payload", "bits"], "needs its own --key-out"),
        "the same key twice": (["--payload", "bits", "--key-out", str(tmp_path / "k"), "--and", "--payload", "bits",
                                "--key-out", str(tmp_path / "k")], "same file"),
        "the first's default key": (["--payload", "bits", "--and", "--payload", "bits", "--key-out",
                                     str(tmp_path / "x" / "key.safetensors")], "same file"),
        "a key in the release": (["--payload", "bits", "--and", "--payload", "bits", "--key-out",
                                  str(tmp_path / "x" / "public" / "k")], "inside the release folder"),
        "a run option after --and": (["--and", "--payload", "bits", "--key-out", str(tmp_path / "k"), "--seed", "3"],
                                     "before the first --and"),
        "several secrets in one --payload": (["--payload", "bits,bits"], "names several secrets"),
        "two objects": (["--payload", "object", "--and", "--payload", "scene", "--key-out", str(tmp_path / "k")],
                        "at most one secret"),
        "a sealed later key only": (["--payload", "bits", "--and", "--payload", "bits", "--key-out",
                                     str(tmp_path / "k"), "--passphrase-env", "PASS_B"], "the first's is not"),
        "an existing key file": (["--payload", "bits", "--and", "--payload", "bits", "--key-out",
                                  str(runs / "b.key")], "exists; add --force"),
    }
    for name, (extra, message) in cases.items():
        capsys.readouterr()
        assert main([*out, *extra]) == 2, name
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1, (name, err)
    assert not (tmp_path / "x").exists() and not (tmp_path / "k").exists()  # refused before anything is written


def test_a_wrong_passphrase_opens_no_key(runs, capsys, monkeypatch, tmp_path):
    monkeypatch.setenv("PASS_C", "alpha")  # the first key's passphrase is not the third's
    assert main(["verify", str(runs / "c" / "public"), "--key", str(runs / "c.key"), "--passphrase-env",
                 "PASS_C"]) == 2
    assert "wrong passphrase" in capsys.readouterr().err


def test_checkpoint_restores_every_secret(tmp_path):
    from securegs_warp.data.synthetic import make_synthetic_scene
    from securegs_warp.rasterizer import RasterOptions

    scene = make_synthetic_scene(width=40, height=30, n_train=4, n_test=1)
    config = TrainConfig(iterations=4, raster=RasterOptions(tile_size=8))
    secure = SecureConfig(payload="bits:16,bits:24")
    trainer = SecureTrainer(scene, config, secure)
    trainer.step()
    trainer.save_checkpoint(tmp_path / "c.pt")
    resumed = SecureTrainer(scene, config, secure)
    resumed.load_checkpoint(tmp_path / "c.pt")
    assert resumed.bit_seeds == trainer.bit_seeds and len(set(trainer.bit_seeds)) == 2
    for i in range(2):
        assert torch.equal(resumed.payloads[i].bits, trainer.payloads[i].bits)
        assert torch.equal(resumed.model.decode_bits(secret=i), trainer.model.decode_bits(secret=i))
    with pytest.raises(ValueError, match="secure.payload differs"):
        SecureTrainer(scene, config, SecureConfig(payload="bits:16")).load_checkpoint(tmp_path / "c.pt")
    with pytest.raises(ValueError, match="several secrets|2 secrets"):
        _ = trainer.payload


def test_parse_secrets():
    assert [s.describe() for s in parse_secrets("object+bits:48,bits:8,image")] == [
        "object+bits:48", "bits:8", "image:builtin@0"]
    with pytest.raises(ValueError, match="at most one secret"):
        parse_secrets("object,scene")
    with pytest.raises(ValueError, match="empty payload"):
        parse_secrets("bits,")
