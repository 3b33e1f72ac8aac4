"""Key files: round trips, and a clear KeyFileError for every way a key can be unusable."""

import json
import os
import struct

import pytest
import torch
from safetensors.torch import load_file, save_file

from securegs_warp.keys import (
    SEALED_MAGIC,
    KeyFileError,
    container_fingerprint,
    load_key,
    save_key,
)

PASS = "correct horse battery staple"


def _heads():
    g = torch.Generator().manual_seed(0)
    return {
        "offset_mlp.0.weight": torch.randn(32, 35, generator=g),
        "offset_mlp.0.bias": torch.randn(32, generator=g),
        "opacity_mlp.2.bias": torch.randn(10, generator=g).to(torch.bfloat16),
        "bit_mlp.0.weight": torch.randn(48, 16, generator=g).t(),  # non-contiguous on purpose
        "bit_mlp.scale": torch.tensor(0.5, dtype=torch.float64),  # 0-dim
    }


META = {"payload": "bits", "bit_length": 48, "heads": {"hidden": 32, "layers": [2, 3]}}
FP = container_fingerprint({"mlp_opacity.0.weight": torch.ones(3, 3)})


def _assert_same(a, b):
    assert sorted(a) == sorted(b)
    for k in a:
        assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape, k
        assert torch.equal(a[k].reshape(-1).view(torch.uint8), b[k].reshape(-1).view(torch.uint8)), k


@pytest.fixture
def plain(tmp_path):
    p = tmp_path / "key.safetensors"
    save_key(p, _heads(), META, FP)
    return p


@pytest.fixture
def sealed(tmp_path):
    p = tmp_path / "key.sealed"
    save_key(p, _heads(), META, FP, passphrase=PASS)
    return p


def _header_end(blob):
    return blob.index(b"\n", len(SEALED_MAGIC)) + 1


def test_plain_round_trip(plain):
    tensors, meta = load_key(plain, expected_fingerprint=FP)
    _assert_same(tensors, _heads())
    assert meta == META


def test_sealed_round_trip(sealed):
    blob = sealed.read_bytes()
    assert blob.startswith(SEALED_MAGIC)
    assert b"offset_mlp" not in blob  # names are encrypted too, not just the values
    tensors, meta = load_key(sealed, passphrase=PASS, expected_fingerprint=FP)
    _assert_same(tensors, _heads())
    assert meta == META


def test_two_seals_of_the_same_key_differ(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    save_key(a, _heads(), META, FP, passphrase=PASS)
    save_key(b, _heads(), META, FP, passphrase=PASS)
    assert a.read_bytes() != b.read_bytes()  # fresh salt and nonce each time


def test_plain_key_is_an_ordinary_safetensors_file(plain):
    _assert_same(load_file(plain), _heads())
    with open(plain, "rb") as f:
        n = struct.unpack("<Q", f.read(8))[0]
        header = json.loads(f.read(n))["__metadata__"]
    assert header["format"] == "securegs-key" and header["version"] == "2"
    assert header["container"] == FP and json.loads(header["metadata"]) == META


def test_wrong_passphrase(sealed):
    with pytest.raises(KeyFileError, match="wrong passphrase") as e:
        load_key(sealed, passphrase="hunter2")
    assert str(sealed) in str(e.value)


def test_sealed_without_passphrase_asks_for_one(sealed):
    with pytest.raises(KeyFileError, match="give the passphrase"):
        load_key(sealed)


def test_flipped_ciphertext_byte_is_detected(sealed):
    blob = bytearray(sealed.read_bytes())
    blob[_header_end(blob) + 100] ^= 0x01
    sealed.write_bytes(bytes(blob))
    with pytest.raises(KeyFileError, match="modified"):
        load_key(sealed, passphrase=PASS)


@pytest.mark.parametrize("field, value", [("salt", "AAAAAAAAAAAAAAAAAAAAAA=="), ("n", 2**14)])
def test_edited_sealed_header_is_detected(sealed, field, value):
    blob = sealed.read_bytes()
    end = _header_end(blob)
    header = json.loads(blob[len(SEALED_MAGIC):end])
    assert header[field] != value
    header[field] = value
    sealed.write_bytes(SEALED_MAGIC + json.dumps(header).encode() + b"\n" + blob[end:])
    with pytest.raises(KeyFileError, match="wrong passphrase, or the key file was modified"):
        load_key(sealed, passphrase=PASS)


def test_huge_scrypt_cost_in_a_forged_header_is_refused(sealed):
    blob = sealed.read_bytes()
    end = _header_end(blob)
    header = json.loads(blob[len(SEALED_MAGIC):end])
    header["n"] = 2**30  # would make scrypt allocate 1 TiB
    sealed.write_bytes(SEALED_MAGIC + json.dumps(header).encode() + b"\n" + blob[end:])
    with pytest.raises(KeyFileError, match="header is damaged"):
        load_key(sealed, passphrase=PASS)


def test_scrypt_memory_and_runs_in_a_forged_header_are_bounded(sealed):
    # n and r each within their own range, but 128·r·n = 4 GiB together, or 16 runs of it.
    blob = sealed.read_bytes()
    end = _header_end(blob)
    for edit in ({"n": 2**20, "r": 32}, {"p": 16}):
        header = {**json.loads(blob[len(SEALED_MAGIC):end]), **edit}
        sealed.write_bytes(SEALED_MAGIC + json.dumps(header).encode() + b"\n" + blob[end:])
        with pytest.raises(KeyFileError, match="header is damaged"):
            load_key(sealed, passphrase=PASS)


def _edit_plain_header(path, edit):
    """Rewrite a plain key's safetensors header through ``edit(header)``, tensors untouched."""
    blob = path.read_bytes()
    n = struct.unpack("<Q", blob[:8])[0]
    header = json.loads(blob[8:8 + n])
    edit(header)
    text = json.dumps(header).encode()
    text += b" " * (-len(text) % 8)  # safetensors keeps the data 8-byte aligned
    path.write_bytes(struct.pack("<Q", len(text)) + text + blob[8 + n:])


@pytest.mark.parametrize("field", ["metadata", "container"])
def test_edited_plain_metadata_is_detected(plain, field):
    # reveal and verify read the message, bit seed and cameras from the metadata, and the container
    # fingerprint says which release the key opens: the checksum covers them as it covers a weight.
    def edit(header):
        meta = header["__metadata__"]
        meta[field] = json.dumps({**META, "bit_length": 47}) if field == "metadata" else "0" * 64
    _edit_plain_header(plain, edit)
    load_file(plain)  # still valid safetensors
    with pytest.raises(KeyFileError, match="the key file was modified"):
        load_key(plain)


def test_version_1_key_still_loads(plain):
    # Keys written before the checksum covered the metadata: their checksum is the tensors' alone.
    from securegs_warp.keys import _tensor_hash

    def edit(header):
        header["__metadata__"].update(version="1", sha256=_tensor_hash(load_file(plain)))
    _edit_plain_header(plain, edit)
    tensors, meta = load_key(plain)
    assert meta == META
    _assert_same(tensors, _heads())


@pytest.mark.parametrize("metadata", ['["not", "a", "mapping"]', '"text"'])
def test_key_metadata_that_is_not_an_object_is_refused(tmp_path, metadata):
    import securegs_warp.keys as keys

    p = tmp_path / "odd.key"
    save_key(p, _heads(), META, FP)
    def edit(header):
        meta = header["__metadata__"]
        meta["metadata"] = metadata
        meta["sha256"] = keys._checksum(load_file(p), FP, metadata)
    _edit_plain_header(p, edit)
    with pytest.raises(KeyFileError, match="metadata is not a JSON object"):
        load_key(p)
    _edit_plain_header(p, lambda header: header.update(__metadata__="oops"))
    with pytest.raises(KeyFileError, match="not a securegs key file"):
        load_key(p)


def test_flipped_plain_tensor_byte_is_detected(plain):
    blob = bytearray(plain.read_bytes())
    blob[-3] ^= 0x40  # inside the last tensor's data; the file stays valid safetensors
    plain.write_bytes(bytes(blob))
    load_file(plain)  # still parses: only the checksum can catch it
    with pytest.raises(KeyFileError, match="the key file was modified"):
        load_key(plain)


@pytest.mark.parametrize("keep", [20, 0.5, -4])
def test_truncated_plain_key(plain, keep):
    blob = plain.read_bytes()
    n = int(len(blob) * keep) if isinstance(keep, float) else keep
    plain.write_bytes(blob[:n])
    with pytest.raises(KeyFileError, match="truncated"):
        load_key(plain)


def test_truncated_sealed_key(sealed):
    blob = sealed.read_bytes()
    sealed.write_bytes(blob[:-10])
    with pytest.raises(KeyFileError, match="truncated"):
        load_key(sealed, passphrase=PASS)
    sealed.write_bytes(blob[: len(SEALED_MAGIC) + 10])  # cut inside the header line
    with pytest.raises(KeyFileError, match="truncated"):
        load_key(sealed, passphrase=PASS)


def test_key_for_another_container(plain, sealed):
    other = container_fingerprint({"mlp_opacity.0.weight": torch.zeros(3, 3)})
    with pytest.raises(KeyFileError, match="another container"):
        load_key(plain, expected_fingerprint=other)
    with pytest.raises(KeyFileError, match="another container"):
        load_key(sealed, passphrase=PASS, expected_fingerprint=other)


def test_random_file_is_not_a_key(tmp_path):
    p = tmp_path / "photo.jpg"
    p.write_bytes(os.urandom(4096))
    with pytest.raises(KeyFileError, match="not a securegs key"):
        load_key(p)


def test_pickle_is_refused_not_loaded(tmp_path):
    p = tmp_path / "heads.pt"
    torch.save(_heads(), p)
    with pytest.raises(KeyFileError, match="not a securegs key"):
        load_key(p)


def test_other_safetensors_file_is_not_a_key(tmp_path):
    p = tmp_path / "model.safetensors"
    save_file({"w": torch.ones(2)}, p, metadata={"format": "pt"})
    with pytest.raises(KeyFileError, match="not a securegs key"):
        load_key(p)


def test_missing_file(tmp_path):
    with pytest.raises(KeyFileError, match="no such key file"):
        load_key(tmp_path / "nope.key")


def test_unknown_versions(tmp_path, plain):
    meta = {"format": "securegs-key", "version": "3", "container": FP, "metadata": "{}", "sha256": ""}
    p = tmp_path / "v3.key"
    save_file({"w": torch.ones(2)}, p, metadata=meta)
    with pytest.raises(KeyFileError, match="version '3' is unknown"):
        load_key(p)
    p.write_bytes(b"SECUREGS-SEALED-KEY v2\n{}\n" + os.urandom(64))
    with pytest.raises(KeyFileError, match="unknown version"):
        load_key(p, passphrase=PASS)


def test_plain_key_with_passphrase_loads_and_warns(plain):
    with pytest.warns(UserWarning, match="not sealed"):
        tensors, meta = load_key(plain, passphrase=PASS)
    assert meta == META and sorted(tensors) == sorted(_heads())


def test_atomic_write_leaves_only_the_key_and_owner_only(tmp_path):
    p = tmp_path / "key.safetensors"
    save_key(p, _heads(), META, FP)
    save_key(p, _heads(), {"payload": "image"}, FP, passphrase=PASS)  # overwrite in place
    assert os.listdir(tmp_path) == ["key.safetensors"]
    assert load_key(p, passphrase=PASS)[1] == {"payload": "image"}
    if os.name == "posix":
        assert p.stat().st_mode & 0o777 == 0o600


def test_failed_save_leaves_old_key(plain):
    before = plain.read_bytes()
    with pytest.raises(ValueError):
        save_key(plain, _heads(), {"x": float("nan")}, FP)  # not strict JSON
    with pytest.raises(ValueError):
        save_key(plain, _heads(), META, "abc")  # not a fingerprint
    assert plain.read_bytes() == before
    assert os.listdir(plain.parent) == [plain.name]


def test_fingerprint_sees_names_dtypes_shapes_values_not_order():
    a = {"x": torch.arange(6.0).reshape(2, 3), "y": torch.ones(2)}
    fp = container_fingerprint(a)
    assert len(fp) == 64 and fp == container_fingerprint(dict(reversed(list(a.items()))))
    assert fp == container_fingerprint({k: v.clone() for k, v in a.items()})
    variants = [
        {"x": a["x"], "z": a["y"]},
        {"x": a["x"].double(), "y": a["y"]},
        {"x": a["x"].reshape(3, 2), "y": a["y"]},
        {"x": a["x"] + torch.tensor([[0, 0, 1e-6], [0, 0, 0]]), "y": a["y"]},
    ]
    assert len({fp, *map(container_fingerprint, variants)}) == 1 + len(variants)
