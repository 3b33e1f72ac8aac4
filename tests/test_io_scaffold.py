"""Scaffold-GS model folders: exact PLY layout, round trip, Scaffold-GS's own files, safe MLP loading."""

import importlib
import io
import re
import struct
import uuid
import warnings
import zipfile

import numpy as np
import plyfile
import pytest
import torch
from torch import nn

from securegs_warp.io import (
    MlpFileError,
    PlyFormatError,
    anchor_ply_properties,
    load_scaffold,
    load_weights,
    read_torchscript_state_dict,
    save_scaffold,
)
from securegs_warp.model import AnchorModel, ScaffoldHeads, generate_neural_gaussians

# The standard pickle module, for the tests' own malicious payloads: crafted here, unpickled once on
# purpose (to show a payload is live), and forbidden to every loader under test.
PICKLE = importlib.import_module("pickle")

CALLS = []


def record_call(*args):
    """What a malicious file would run on load; the tests check that it never does."""
    CALLS.append(args)


class Evil:
    def __reduce__(self):
        return (record_call, ("pwned",))


def random_model(n=20, k=10, d=32, seed=0):
    g = torch.Generator().manual_seed(seed)
    return AnchorModel(
        xyz=torch.randn(n, 3, generator=g), feat=torch.randn(n, d, generator=g),
        offsets=torch.randn(n, k, 3, generator=g), scaling=torch.randn(n, 6, generator=g),
        rotation=torch.randn(n, 4, generator=g), opacity=torch.randn(n, 1, generator=g),
    )


def test_property_order_is_scaffold_gs_order():
    names = anchor_ply_properties(n_offsets=2, feat_dim=3)
    assert names == [
        "x", "y", "z", "nx", "ny", "nz",
        "f_offset_0", "f_offset_1", "f_offset_2", "f_offset_3", "f_offset_4", "f_offset_5",
        "f_anchor_feat_0", "f_anchor_feat_1", "f_anchor_feat_2",
        "opacity", "scale_0", "scale_1", "scale_2", "scale_3", "scale_4", "scale_5",
        "rot_0", "rot_1", "rot_2", "rot_3",
    ]


def test_round_trip_is_exact(tmp_path):
    torch.manual_seed(0)
    model = random_model()
    heads = ScaffoldHeads(32, 10, use_feat_bank=True, appearance_dim=16, num_cameras=4, add_color_dist=True)
    save_scaffold(tmp_path, model, heads)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([
        "point_cloud.ply", "opacity_mlp.pt", "cov_mlp.pt", "color_mlp.pt",
        "feature_bank_mlp.pt", "embedding_appearance.pt",
    ])
    vertex = plyfile.PlyData.read(str(tmp_path / "point_cloud.ply"))["vertex"]
    assert [p.name for p in vertex.properties] == anchor_ply_properties(10, 32)
    assert all(p.val_dtype == "f4" for p in vertex.properties)
    # coordinate-major offsets: f_offset_{c * k + j} is coordinate c of offset j
    assert np.array_equal(vertex["f_offset_13"], model.offsets[:, 3, 1].detach().numpy())
    assert not np.any(vertex["nx"])

    loaded, loaded_heads = load_scaffold(tmp_path)
    for name in ("xyz", "feat", "offsets", "scaling", "rotation", "opacity"):
        assert torch.equal(getattr(loaded, name), getattr(model, name)), name
    assert loaded_heads.use_feat_bank and loaded_heads.add_color_dist
    assert not loaded_heads.add_opacity_dist and not loaded_heads.add_cov_dist
    assert loaded_heads.embedding_appearance.weight.shape == (4, 16)
    for key, value in heads.state_dict().items():
        assert torch.equal(loaded_heads.state_dict()[key], value), key
    cam = torch.tensor([1.0, 2.0, 3.0])
    a = generate_neural_gaussians(model, heads, cam, camera_index=2)
    b = generate_neural_gaussians(loaded, loaded_heads, cam, camera_index=2)
    for key in ("means", "quats", "scales", "opacities", "colors"):
        assert torch.equal(a[key], b[key]), key


def test_save_removes_stale_optional_mlps(tmp_path):
    model = random_model(k=10, d=32)
    save_scaffold(tmp_path, model, ScaffoldHeads(32, 10, use_feat_bank=True))
    save_scaffold(tmp_path, model, ScaffoldHeads(32, 10))
    assert not (tmp_path / "feature_bank_mlp.pt").exists()
    assert not load_scaffold(tmp_path)[1].use_feat_bank


def write_scaffold_gs_ply(path, model):
    """point_cloud.ply exactly as Scaffold-GS's save_ply builds it, property by property."""
    anchor = model.xyz.detach().numpy()
    offset = model.offsets.detach().transpose(1, 2).flatten(start_dim=1).contiguous().numpy()
    attributes = np.concatenate((anchor, np.zeros_like(anchor), offset, model.feat.detach().numpy(),
                                 model.opacity.detach().numpy(), model.scaling.detach().numpy(),
                                 model.rotation.detach().numpy()), axis=1)
    names = ["x", "y", "z", "nx", "ny", "nz"]
    names += [f"f_offset_{i}" for i in range(offset.shape[1])]
    names += [f"f_anchor_feat_{i}" for i in range(model.feat.shape[1])]
    names += ["opacity"] + [f"scale_{i}" for i in range(6)] + [f"rot_{i}" for i in range(4)]
    elements = np.empty(anchor.shape[0], dtype=[(name, "f4") for name in names])
    elements[:] = list(map(tuple, attributes))
    plyfile.PlyData([plyfile.PlyElement.describe(elements, "vertex")]).write(str(path))


class ScaffoldEmbedding(nn.Module):
    """Scaffold-GS's Embedding wrapper (its parameter is `embedding.weight`)."""

    def __init__(self, num, dim):
        super().__init__()
        self.embedding = nn.Embedding(num, dim)

    def forward(self, index):
        return self.embedding(index)


@pytest.mark.filterwarnings("ignore:`torch.jit")
def test_scaffold_gs_folder_with_torchscript_mlps_loads_without_executing_code(tmp_path, monkeypatch):
    torch.manual_seed(1)
    model = random_model(n=15, k=10, d=32)
    write_scaffold_gs_ply(tmp_path / "point_cloud.ply", model)
    # Scaffold-GS's save_mlp_checkpoints: torch.jit.trace(...).save(), appearance_dim 32, no distances
    reference = ScaffoldHeads(32, 10, use_feat_bank=True, appearance_dim=32, num_cameras=5)
    for name, width in (("opacity_mlp", 35), ("cov_mlp", 35), ("color_mlp", 67), ("feature_bank_mlp", 4)):
        torch.jit.trace(getattr(reference, name).eval(), torch.rand(1, width)).save(str(tmp_path / f"{name}.pt"))
    embedding = ScaffoldEmbedding(5, 32)
    embedding.embedding.weight.data.copy_(reference.embedding_appearance.weight.data)
    traced = torch.jit.trace(embedding.eval(), torch.zeros((1,), dtype=torch.long))
    traced.save(str(tmp_path / "embedding_appearance.pt"))
    # What torch.jit.load gives, taken before the loader runs with torch.jit.load and unpickling disabled.
    expected = {name: torch.jit.load(str(tmp_path / f"{name}.pt")).state_dict()
                for name in ("opacity_mlp", "cov_mlp", "color_mlp", "feature_bank_mlp", "embedding_appearance")}

    forbid_code_execution(monkeypatch)
    for name, state in expected.items():
        read = load_weights(tmp_path / f"{name}.pt")
        assert list(read) == list(state), name
        for key, value in state.items():
            assert read[key].dtype == value.dtype and torch.equal(read[key], value), (name, key)
    loaded, heads = load_scaffold(tmp_path)
    assert loaded.n_offsets == 10 and loaded.feat_dim == 32
    for name in ("xyz", "feat", "offsets", "scaling", "rotation", "opacity"):
        assert torch.equal(getattr(loaded, name), getattr(model, name)), name
    assert heads.appearance_dim == 32 and heads.use_feat_bank
    for key, value in reference.state_dict().items():
        assert torch.equal(heads.state_dict()[key], value), key


def forbid_code_execution(monkeypatch):
    """Make torch.jit.load and every way of unpickling fail, so a loader that uses them fails."""

    def forbidden(*args, **kwargs):
        raise AssertionError("a file was loaded with code execution")

    monkeypatch.setattr(torch.jit, "load", forbidden)
    for name in ("load", "loads", "Unpickler"):
        monkeypatch.setattr(PICKLE, name, forbidden)
    real_torch_load = torch.load

    def torch_load(f, *args, **kwargs):
        # torch.load is only for torch.save files, and only with weights_only
        assert kwargs.get("weights_only") is True
        with zipfile.ZipFile(f) as archive:
            assert not any(n.endswith("/constants.pkl") for n in archive.namelist()), f
        return real_torch_load(f, *args, **kwargs)

    monkeypatch.setattr(torch, "load", torch_load)


@pytest.mark.filterwarnings("ignore:`torch.jit")
def test_saved_mlps_are_traced_torchscript_as_scaffold_gs_writes_them(tmp_path):
    torch.manual_seed(2)
    model = random_model(n=6, k=5, d=8)
    heads = ScaffoldHeads(8, 5, use_feat_bank=True, appearance_dim=4, num_cameras=3,
                          add_opacity_dist=True, add_color_dist=True)
    heads.train()
    before = {key: (value, value.clone()) for key, value in heads.state_dict(keep_vars=True).items()}
    rng = torch.get_rng_state()
    save_scaffold(tmp_path, model, heads)
    # Tracing works on a copy: same parameter objects and values, still training, no random draws.
    assert all(module.training for module in heads.modules())
    for key, value in heads.state_dict(keep_vars=True).items():
        assert value is before[key][0] and torch.equal(value, before[key][1]), key
    assert torch.equal(torch.get_rng_state(), rng)

    widths = {"opacity_mlp": 8 + 3 + 1, "cov_mlp": 8 + 3, "color_mlp": 8 + 3 + 1 + 4, "feature_bank_mlp": 3 + 1}
    for name, width in widths.items():
        with zipfile.ZipFile(tmp_path / f"{name}.pt") as archive:
            assert any(n.endswith("/constants.pkl") for n in archive.namelist())
        traced = torch.jit.load(str(tmp_path / f"{name}.pt"))  # trusted: written by this test
        assert not traced.training
        x = torch.randn(7, width)
        assert torch.equal(traced(x), getattr(heads, name)(x)), name
    emb = torch.jit.load(str(tmp_path / "embedding_appearance.pt"))
    index = torch.tensor([2, 0, 1, 2])
    assert torch.equal(emb(index), heads.embedding_appearance(index))
    assert emb(torch.zeros((1,), dtype=torch.long)).shape == (1, 4)


class Strided(nn.Module):
    """Tensors that are views: a transposed weight and two buffers sharing one storage at offsets."""

    def __init__(self):
        super().__init__()
        self.weight = nn.Parameter(torch.randn(5, 3).t())
        base = torch.arange(12, dtype=torch.float64)
        self.register_buffer("low", base[2:6])
        self.register_buffer("high", base.view(3, 4)[:, 1:3])
        self.register_buffer("count", torch.tensor(7, dtype=torch.int64))
        self.register_buffer("halves", torch.randn(2, 2).half())
        self.register_buffer("empty", torch.zeros(0, 3))
        self.inner = nn.Linear(5, 2, bias=False)

    def forward(self, x):
        return self.inner(x @ self.weight) + self.low.sum().float() + self.high.sum().float() + self.count


@pytest.mark.filterwarnings("ignore:`torch.jit")
@pytest.mark.parametrize("make", [
    lambda: (nn.Sequential(nn.Linear(6, 4), nn.ReLU(True), nn.Linear(4, 3), nn.Softmax(dim=1)), torch.rand(1, 6)),
    lambda: (nn.Sequential(nn.Linear(6, 4, bias=False), nn.ReLU(True), nn.Linear(4, 3, bias=False)), torch.rand(1, 6)),
    lambda: (nn.Embedding(4, 3), torch.zeros((1,), dtype=torch.long)),
    lambda: (ScaffoldEmbedding(4, 3), torch.zeros((1,), dtype=torch.long)),
    lambda: (Strided(), torch.rand(1, 3)),
], ids=["mlp", "no-bias", "embedding", "scaffold-embedding", "views-and-dtypes"])
def test_reader_gives_what_torch_jit_load_gives(tmp_path, make):
    module, example = make()
    path = tmp_path / "m.pt"
    torch.jit.trace(module.eval(), example).save(str(path))
    expected = torch.jit.load(str(path)).state_dict()  # trusted: written by this test
    read = read_torchscript_state_dict(path)
    assert list(read) == list(expected)
    for key, value in expected.items():
        assert read[key].dtype == value.dtype and read[key].shape == value.shape, key
        assert torch.equal(read[key], value), key


@pytest.mark.filterwarnings("ignore:`torch.jit")
def test_reader_takes_gpu_archives_of_older_torch_and_big_endian_ones(tmp_path):
    module = nn.Sequential(nn.Linear(6, 4), nn.ReLU(True), nn.Linear(4, 3))
    path = tmp_path / "cov_mlp.pt"
    torch.jit.trace(module.eval(), torch.rand(1, 6)).save(str(path))
    expected = module.state_dict()

    def rewrite(target, prefix, data_pkl=None, byteorder=None, swap=False):
        with zipfile.ZipFile(path) as src, zipfile.ZipFile(target, "w") as dst:
            for info in src.infolist():
                record = info.filename.split("/", 1)[1]
                content = src.read(info)
                if record == "data.pkl" and data_pkl is not None:
                    content = data_pkl(content)
                if record == "byteorder":
                    if byteorder is None:
                        continue
                    content = byteorder
                if swap and record.startswith("data/"):
                    content = np.frombuffer(content, "<f4").astype(">f4").tobytes()
                dst.writestr(f"{prefix}/{record}", content)

    # Scaffold-GS traces on the GPU (location 'cuda:0'); older torch names the top folder after the
    # file and writes no byteorder record.
    gpu = tmp_path / "gpu.pt"
    rewrite(gpu, "cov_mlp", data_pkl=lambda b: b.replace(b"X\x03\x00\x00\x00cpu", b"X\x06\x00\x00\x00cuda:0"))
    assert b"cuda:0" in zipfile.ZipFile(gpu).read("cov_mlp/data.pkl")
    big = tmp_path / "big.pt"
    rewrite(big, "archive", byteorder=b"big", swap=True)
    for target in (gpu, big):
        read = load_weights(target)
        assert list(read) == list(expected)
        for key, value in expected.items():
            assert torch.equal(read[key], value), (target.name, key)


def test_state_dict_files_still_load(tmp_path):
    # The MLP files this package wrote before it wrote TorchScript: torch.save(state_dict).
    model = random_model(n=5, k=3, d=8)
    heads = ScaffoldHeads(8, 3, use_feat_bank=True, appearance_dim=2, num_cameras=2, add_cov_dist=True)
    save_scaffold(tmp_path, model, heads)
    for attribute in ("opacity_mlp", "cov_mlp", "color_mlp", "feature_bank_mlp", "embedding_appearance"):
        torch.save(getattr(heads, attribute).state_dict(), tmp_path / f"{attribute}.pt")
    _, loaded = load_scaffold(tmp_path)
    assert loaded.add_cov_dist and loaded.use_feat_bank and loaded.appearance_dim == 2
    for key, value in heads.state_dict().items():
        assert torch.equal(loaded.state_dict()[key], value), key


@pytest.mark.parametrize("with_bank", [False, True])
def test_scaffold_gs_unite_checkpoint_loads(tmp_path, with_bank):
    torch.manual_seed(3)
    model = random_model(n=7, k=4, d=8)
    write_scaffold_gs_ply(tmp_path / "point_cloud.ply", model)
    reference = ScaffoldHeads(8, 4, use_feat_bank=with_bank, appearance_dim=6, num_cameras=3, add_color_dist=True)
    embedding = ScaffoldEmbedding(3, 6)
    embedding.embedding.weight.data.copy_(reference.embedding_appearance.weight.data)
    # Scaffold-GS's save_mlp_checkpoints(mode='unite')
    content = {"opacity_mlp": reference.opacity_mlp.state_dict(), "cov_mlp": reference.cov_mlp.state_dict(),
               "color_mlp": reference.color_mlp.state_dict()}
    if with_bank:
        content["feature_bank_mlp"] = reference.feature_bank_mlp.state_dict()
    content["appearance"] = embedding.state_dict()
    torch.save(content, tmp_path / "checkpoints.pth")

    loaded, heads = load_scaffold(tmp_path)
    assert torch.equal(loaded.offsets, model.offsets)
    assert heads.use_feat_bank == with_bank and heads.add_color_dist and heads.appearance_dim == 6
    for key, value in reference.state_dict().items():
        assert torch.equal(heads.state_dict()[key], value), key

    del content["cov_mlp"]
    torch.save(content, tmp_path / "checkpoints.pth")
    with pytest.raises(MlpFileError, match="checkpoints.pth: has no 'cov_mlp' entry"):
        load_scaffold(tmp_path)


def test_missing_property_is_named(tmp_path):
    model = random_model(n=4, k=2, d=4)
    save_scaffold(tmp_path, model, ScaffoldHeads(4, 2))
    vertex = plyfile.PlyData.read(str(tmp_path / "point_cloud.ply"))["vertex"]
    for missing in ("scale_3", "f_anchor_feat_1", "rot_0", "nz"):
        kept = [p.name for p in vertex.properties if p.name != missing]
        data = np.empty(vertex.count, dtype=[(n, "f4") for n in kept])
        for n in kept:
            data[n] = vertex[n]
        plyfile.PlyData([plyfile.PlyElement.describe(data, "vertex")]).write(str(tmp_path / "point_cloud.ply"))
        with pytest.raises(PlyFormatError, match=f"point_cloud.ply: vertex property '{missing}' is missing"):
            load_scaffold(tmp_path)


def test_mlp_shape_mismatch_is_named(tmp_path):
    save_scaffold(tmp_path, random_model(n=4, k=2, d=4), ScaffoldHeads(4, 2))
    torch.save(ScaffoldHeads(4, 3).cov_mlp.state_dict(), tmp_path / "cov_mlp.pt")
    with pytest.raises(MlpFileError, match=r"cov_mlp.pt: '2.weight' has shape \[21, 4\], expected \[14, 4\]"):
        load_scaffold(tmp_path)
    (tmp_path / "color_mlp.pt").unlink()
    with pytest.raises(FileNotFoundError, match="color_mlp.pt"):
        load_scaffold(tmp_path)


def test_a_folder_without_a_release_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"not a Scaffold-GS release \(no point_cloud.ply there"):
        load_scaffold(tmp_path / "run")


def test_pickled_objects_are_refused(tmp_path):
    path = tmp_path / "opacity_mlp.pt"
    torch.save({"0.weight": torch.zeros(2, 2), "payload": Evil()}, path)
    with pytest.raises(MlpFileError, match="weights_only"):
        load_weights(path)
    assert CALLS == []


def test_torchscript_archive_that_would_run_code_is_refused(tmp_path):
    path = tmp_path / "opacity_mlp.pt"
    # The layout of a torch.jit.save archive; its data.pkl would run os.system if it were unpickled.
    # It is interpreted symbolically instead, and its global is not one a TorchScript module uses.
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("opacity_mlp/data.pkl", b"\x80\x02cos\nsystem\nq\x00X\x04\x00\x00\x00trueq\x01\x85q\x02Rq\x03.")
        archive.writestr("opacity_mlp/constants.pkl", b"\x80\x02).")
        archive.writestr("opacity_mlp/byteorder", "little")
    with pytest.raises(MlpFileError, match="TorchScript archive"):
        load_weights(path)
    with pytest.raises(MlpFileError, match="names the global os.system"):
        load_weights(path)


class OpenFile:
    """Unpickling this creates the file at ``path``: the test's witness of code execution."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def archive_with_data_pkl(path, data_pkl):
    """A torch.jit.save archive of a small MLP whose data.pkl is replaced by ``data_pkl``."""
    buffer = io.BytesIO()
    module = nn.Sequential(nn.Linear(3, 2))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.jit.save(torch.jit.trace(module.eval(), torch.rand(1, 3)), buffer)
    with zipfile.ZipFile(buffer) as src, zipfile.ZipFile(path, "w") as dst:
        for info in src.infolist():
            content = src.read(info)
            if info.filename.endswith("/data.pkl") and data_pkl is not None:
                content = data_pkl(content)
            dst.writestr(info, content)
    return path


@pytest.mark.parametrize("protocol", [2, 4])
@pytest.mark.parametrize("where", ["top", "module attribute"])
def test_malicious_torchscript_archive_is_never_executed(tmp_path, protocol, where):
    witness = tmp_path / "executed"
    # The payload is live: unpickling it (here, on purpose) creates its file.
    PICKLE.loads(PICKLE.dumps(OpenFile(tmp_path / "control"), protocol=protocol))
    assert (tmp_path / "control").exists()

    if where == "top":
        payload = PICKLE.dumps(OpenFile(witness), protocol=protocol)
    else:
        payload = PICKLE.dumps({"training": False, "weight": OpenFile(witness)}, protocol=protocol)
    path = archive_with_data_pkl(tmp_path / "opacity_mlp.pt", lambda _: payload)
    refused = r"opacity_mlp.pt: TorchScript archive refused: .*global (io|builtins)\.open"
    with pytest.raises(MlpFileError, match=refused):
        load_weights(path)
    assert not witness.exists()
    assert CALLS == []


@pytest.mark.filterwarnings("ignore:`torch.jit")
@pytest.mark.parametrize("damage, problem", [
    (lambda b: b[: len(b) // 2], "not a complete pickle"),
    (lambda b: b.replace(b"collections\nOrderedDict", b"collections\nnamedtuple"), "global collections.namedtuple"),
    (lambda b: b.replace(b"torch\nFloatStorage", b"torch\nBoolStorage"), "global torch.BoolStorage"),
    (lambda b: b.replace(b"K\x02K\x03t", b"K\x09K\x03t"), "reaches element"),  # weight size 2x3 -> 9x3
    (lambda b: b.replace(b"X\x01\x00\x00\x000", b"X\x01\x00\x00\x009"), "storage record archive/data/9 is missing"),
    (lambda b: b[:-1] + b"0.", "pickle opcode POP"),
    (lambda b: b"\x80\x02K\x01.", "holds a value of type int, not a module"),
], ids=["truncated", "global", "storage-type", "out-of-bounds", "missing-storage", "opcode", "not-a-module"])
def test_damaged_torchscript_archive_is_refused(tmp_path, damage, problem):
    path = archive_with_data_pkl(tmp_path / "cov_mlp.pt", damage)
    with pytest.raises(MlpFileError, match=f"cov_mlp.pt: TorchScript archive refused: .*{problem}"):
        load_weights(path)


def _module_doubling_pickle(depth: int) -> bytes:
    """A pickle of ``depth`` nested modules, each holding its one child twice through the memo: a
    few hundred bytes that a walk visiting every reference would visit 2^depth times."""
    def text(s):
        return b"\x8c" + bytes([len(s)]) + s.encode()  # SHORT_BINUNICODE

    out = bytearray(b"\x80\x02c__torch__\nM\nq\x00")  # PROTO 2, GLOBAL __torch__.M, BINPUT 0
    def module(level, slot):
        if slot:
            out.extend(b"h\x00")  # BINGET 0: the class
        out.extend(b")\x81}")  # EMPTY_TUPLE, NEWOBJ, EMPTY_DICT
        if level:
            out.extend(b"(" + text("a"))  # MARK, key
            module(level - 1, True)
            memo = struct.pack("<I", level)
            out.extend(b"r" + memo + text("b") + b"j" + memo + b"u")  # the child put, fetched again, SETITEMS
        out.extend(b"b")  # BUILD
    module(depth, False)
    return bytes(out) + b"."


def test_a_module_graph_of_shared_children_is_refused_quickly(tmp_path):
    path = archive_with_data_pkl(tmp_path / "cov_mlp.pt", lambda _: _module_doubling_pickle(60))
    with pytest.raises(MlpFileError, match="more than 4096 modules to walk"):
        load_weights(path)


def test_files_that_are_not_weights_are_refused(tmp_path):
    random_bytes = tmp_path / "random.pt"
    random_bytes.write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(MlpFileError, match="random.pt: "):
        load_weights(random_bytes)

    other_zip = tmp_path / "other.pt"
    with zipfile.ZipFile(other_zip, "w") as archive:
        archive.writestr("readme.txt", "hello")
    with pytest.raises(MlpFileError, match="other.pt: is a zip archive but neither a TorchScript archive"):
        load_weights(other_zip)

    # A truncated TorchScript file: the zip's central directory is gone.
    truncated = tmp_path / "truncated.pt"
    whole = archive_with_data_pkl(tmp_path / "whole.pt", None).read_bytes()
    truncated.write_bytes(whole[: len(whole) - 200])
    with pytest.raises(MlpFileError, match="truncated.pt: "):
        load_weights(truncated)

    # A torch.save file cut in half: torch's zip reader raises OSError(EINVAL), with no file name.
    buffer = io.BytesIO()
    torch.save({"weight": torch.ones(100, 100)}, buffer)
    half = tmp_path / "half.pt"
    half.write_bytes(buffer.getvalue()[: len(buffer.getvalue()) // 2])
    with pytest.raises(MlpFileError, match="half.pt: not a readable torch weights file"):
        load_weights(half)


# ----------------------------------------------------------------------------------------------
# A release is written as one unit
# ----------------------------------------------------------------------------------------------


def folder_bytes(path):
    return {p.name: p.read_bytes() for p in path.iterdir()}


def assert_same_release(path, model, heads):
    loaded, loaded_heads = load_scaffold(path)
    for name in ("xyz", "feat", "offsets", "scaling", "rotation", "opacity"):
        assert torch.equal(getattr(loaded, name), getattr(model, name)), name
    assert sorted(loaded_heads.state_dict()) == sorted(heads.state_dict())
    for key, value in heads.state_dict().items():
        assert torch.equal(loaded_heads.state_dict()[key], value), key


class Crash(Exception):
    """Stands for the process dying at that point."""


# The old release has all five MLPs; the new one fewer and another size, so a mix of the two is
# visible in the file list as well as in the content. Writes: 3 MLPs, then the PLY.
CRASH_POINTS = [("mlp", 0, "before"), ("mlp", 1, "before"), ("mlp", 2, "after"),
                ("ply", 0, "before"), ("ply", 0, "after"), ("publish", 0, "before")]


@pytest.mark.parametrize("writer, index, when", CRASH_POINTS, ids=["-".join(map(str, p)) for p in CRASH_POINTS])
def test_interrupted_save_leaves_the_old_release_byte_for_byte(tmp_path, monkeypatch, writer, index, when):
    import securegs_warp.io.atomic as atomic
    import securegs_warp.io.scaffold as scaffold

    target = tmp_path / "release"
    torch.manual_seed(4)
    old_model = random_model(n=9, k=2, d=8, seed=1)
    old_heads = ScaffoldHeads(8, 2, use_feat_bank=True, appearance_dim=3, num_cameras=2, add_cov_dist=True)
    save_scaffold(target, old_model, old_heads)
    before = folder_bytes(target)
    new_model, new_heads = random_model(n=5, k=2, d=8, seed=2), ScaffoldHeads(8, 2)

    calls = {"mlp": 0, "ply": 0, "publish": 0}

    def crashing(name, real):
        def write(*args, **kwargs):
            calls[name] += 1
            if calls[name] - 1 == index and when == "before":
                raise Crash(f"{name} {index}")
            real(*args, **kwargs)
            if calls[name] - 1 == index and when == "after":
                raise Crash(f"{name} {index}")
        return write

    if writer == "mlp":
        monkeypatch.setattr(scaffold, "atomic_write", crashing("mlp", scaffold.atomic_write))
    elif writer == "ply":
        monkeypatch.setattr(scaffold, "write_vertex_ply", crashing("ply", scaffold.write_vertex_ply))
    else:  # the swap of the complete new folder with the old one
        monkeypatch.setattr(atomic, "_publish_folder", crashing("publish", atomic._publish_folder))
    with pytest.raises(Crash):
        save_scaffold(target, new_model, new_heads)
    monkeypatch.undo()

    assert folder_bytes(target) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["release"]  # no temporary file or folder
    assert_same_release(target, old_model, old_heads)

    save_scaffold(target, new_model, new_heads)
    assert sorted(p.name for p in target.iterdir()) == ["color_mlp.pt", "cov_mlp.pt", "opacity_mlp.pt",
                                                        "point_cloud.ply"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["release"]
    assert_same_release(target, new_model, new_heads)


def test_leftovers_are_ignored_by_loading_and_removed_by_the_next_save(tmp_path):
    target = tmp_path / "release"
    model, heads = random_model(n=4, k=2, d=4), ScaffoldHeads(4, 2)
    save_scaffold(target, model, heads)
    # What kill -9 can leave: a release under construction, an old one renamed aside, and inside an
    # older folder (written file by file) a temporary file of an interrupted atomic_write.
    for kind in ("tmp", "old"):
        leftover = tmp_path / f".release.{kind}-{uuid.uuid4().hex}"
        leftover.mkdir()
        (leftover / "point_cloud.ply").write_bytes(b"garbage")
    (target / f".cov_mlp.pt.{'a' * 32}.tmp").write_bytes(b"half")
    assert_same_release(target, model, heads)

    other = random_model(n=6, k=2, d=4, seed=5)
    save_scaffold(target, other, heads)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["release"]
    assert sorted(p.name for p in target.iterdir()) == ["color_mlp.pt", "cov_mlp.pt", "opacity_mlp.pt",
                                                        "point_cloud.ply"]
    assert_same_release(target, other, heads)


def test_save_refuses_to_delete_what_is_not_a_release(tmp_path):
    target = tmp_path / "release"
    model, heads = random_model(n=4, k=2, d=4), ScaffoldHeads(4, 2)
    save_scaffold(target, model, heads)
    (target / "notes.txt").write_bytes(b"mine")
    before = folder_bytes(target)
    with pytest.raises(FileExistsError, match=r"release: holds 'notes.txt', which is not part of a Scaffold-GS"):
        save_scaffold(target, random_model(n=3, k=2, d=4), heads)
    assert folder_bytes(target) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["release"]


def test_save_into_a_file_is_refused(tmp_path):
    target = tmp_path / "release"
    target.write_bytes(b"a file")
    with pytest.raises(NotADirectoryError):
        save_scaffold(target, random_model(n=4, k=2, d=4), ScaffoldHeads(4, 2))
    assert target.read_bytes() == b"a file"


# A release whose every file carries the number of the save that wrote it, and whose file list and
# sizes change from save to save: a folder mixing two saves shows it in the numbers, the file list
# or the shapes. Run both here and in the killed subprocess.
NUMBERED_RELEASE = '''
import torch
from securegs_warp.model import AnchorModel, ScaffoldHeads

def numbered_release(i):
    n, appearance = 3 + i % 4, 2 if i % 3 == 0 else 0
    heads = ScaffoldHeads(8, 2, use_feat_bank=i % 2 == 1, appearance_dim=appearance,
                          num_cameras=1 + i % 5 if appearance else 0)
    with torch.no_grad():
        for module in (heads.opacity_mlp, heads.cov_mlp, heads.color_mlp, heads.feature_bank_mlp):
            if module is not None:
                module[0].bias.fill_(float(i))
        if heads.embedding_appearance is not None:
            heads.embedding_appearance.weight.fill_(float(i))
    model = AnchorModel(xyz=torch.randn(n, 3), feat=torch.randn(n, 8), offsets=torch.randn(n, 2, 3),
                        scaling=torch.randn(n, 6), rotation=torch.randn(n, 4),
                        opacity=torch.full((n, 1), float(i)))
    return model, heads
'''

SAVE_IN_A_LOOP = NUMBERED_RELEASE + '''
import sys, time
from securegs_warp.io import save_scaffold

torch.set_num_threads(1)
target, first = sys.argv[1], int(sys.argv[2])
deadline = time.monotonic() + 30  # stops by itself if nobody kills it
for i in range(first, first + 400):
    if time.monotonic() > deadline:
        break
    save_scaffold(target, *numbered_release(i))
    print(i, flush=True)
'''


def release_number(path):
    """The number of the save that wrote the release at ``path``; fails unless every file agrees."""
    model, heads = load_scaffold(path)
    i = int(model.opacity[0, 0])
    assert torch.equal(model.opacity, torch.full_like(model.opacity, float(i)))
    assert model.num_anchors == 3 + i % 4
    assert heads.use_feat_bank == (i % 2 == 1)
    assert heads.appearance_dim == (2 if i % 3 == 0 else 0)
    for module in (heads.opacity_mlp, heads.cov_mlp, heads.color_mlp, heads.feature_bank_mlp):
        if module is not None:
            assert torch.equal(module[0].bias, torch.full_like(module[0].bias, float(i)))
    if heads.embedding_appearance is not None:
        weight = heads.embedding_appearance.weight
        assert weight.shape[0] == 1 + i % 5 and torch.equal(weight, torch.full_like(weight, float(i)))
    return i


def test_kill_9_while_saving_leaves_a_whole_release(tmp_path):
    import os
    import random
    import select
    import signal
    import subprocess
    import sys
    import time

    import securegs_warp.io.atomic as atomic

    namespace = {}
    exec(NUMBERED_RELEASE, namespace)
    numbered_release = namespace["numbered_release"]
    rng = random.Random(0)
    targets = [tmp_path / f"release{j}" for j in range(3)]
    for target in targets:
        save_scaffold(target, *numbered_release(0))
        assert release_number(target) == 0
    # Several savers at once: one Python start-up (torch's import) for several kills.
    savers = [subprocess.Popen([sys.executable, "-c", SAVE_IN_A_LOOP, str(target), "1"], stdout=subprocess.PIPE)
              for target in targets]
    try:
        for saver in savers:
            ready, _, _ = select.select([saver.stdout], [], [], 60)
            assert ready and saver.stdout.readline().strip() == b"1", "the saver did not start saving"
        for saver in savers:
            # Anywhere in one of the next few saves: writing the MLPs, the PLY, publishing, cleaning.
            time.sleep(rng.uniform(0.0, 0.3))
            os.kill(saver.pid, signal.SIGKILL)
        for target, saver in zip(targets, savers):
            assert saver.wait(30) == -signal.SIGKILL
            last_reported = int((b"1 " + saver.stdout.read()).split()[-1])
            # Nothing lost, nothing mixed: the last save reported complete, or the one in flight.
            assert release_number(target) in (last_reported, last_reported + 1)
            assert len(atomic.folder_leftovers(target)) <= 1
    finally:
        for saver in savers:
            if saver.poll() is None:
                saver.kill()
                saver.wait()
    for target in targets:
        save_scaffold(target, *numbered_release(7))
        assert release_number(target) == 7 and atomic.folder_leftovers(target) == []
    assert sorted(p.name for p in tmp_path.iterdir()) == [t.name for t in targets]


# ----------------------------------------------------------------------------------------------
# A damaged release is refused, naming the file and the problem
# ----------------------------------------------------------------------------------------------


def rewrite_ply(path, change):
    """Rewrite point_cloud.ply with ``change(data)`` applied to its vertex records."""
    vertex = plyfile.PlyData.read(str(path))["vertex"]
    data = vertex.data.copy()
    data = change(data)
    plyfile.PlyData([plyfile.PlyElement.describe(data, "vertex")]).write(str(path))


def test_release_without_anchors_is_refused(tmp_path):
    save_scaffold(tmp_path, random_model(n=4, k=2, d=4), ScaffoldHeads(4, 2))
    rewrite_ply(tmp_path / "point_cloud.ply", lambda data: data[:0])
    with pytest.raises(PlyFormatError, match=r"point_cloud.ply: has no anchors"):
        load_scaffold(tmp_path)


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf], ids=["nan", "inf", "-inf"])
@pytest.mark.parametrize("prop, group", [
    ("x", "x/y/z"), ("z", "x/y/z"), ("f_offset_4", "f_offset_*"), ("f_anchor_feat_3", "f_anchor_feat_*"),
    ("opacity", "opacity"), ("scale_5", "scale_*"), ("rot_0", "rot_*"),
])
def test_non_finite_anchor_attributes_are_refused(tmp_path, prop, group, value):
    save_scaffold(tmp_path, random_model(n=6, k=2, d=4), ScaffoldHeads(4, 2))

    def spoil(data):
        data[prop][[1, 4]] = value
        return data

    rewrite_ply(tmp_path / "point_cloud.ply", spoil)
    with pytest.raises(PlyFormatError, match=rf"point_cloud.ply: {re.escape(group)} holds NaN or inf in 2 of 6 "
                                             r"anchors \(the first is anchor 1\)"):
        load_scaffold(tmp_path)


def test_normals_are_not_read(tmp_path):
    # Scaffold-GS writes zeros there and never reads them; neither do we.
    model = random_model(n=4, k=2, d=4)
    save_scaffold(tmp_path, model, ScaffoldHeads(4, 2))

    def spoil(data):
        data["nx"][:] = np.nan
        return data

    rewrite_ply(tmp_path / "point_cloud.ply", spoil)
    assert torch.equal(load_scaffold(tmp_path)[0].feat, model.feat)


def test_float64_anchor_beyond_float32_is_refused(tmp_path):
    model = random_model(n=3, k=2, d=4)
    save_scaffold(tmp_path, model, ScaffoldHeads(4, 2))
    vertex = plyfile.PlyData.read(str(tmp_path / "point_cloud.ply"))["vertex"]
    data = np.empty(vertex.count, dtype=[(p.name, "f8") for p in vertex.properties])
    for p in vertex.properties:
        data[p.name] = vertex[p.name]
    data["scale_2"][0] = 1e300  # finite in the file, inf as the float32 the model holds
    plyfile.PlyData([plyfile.PlyElement.describe(data, "vertex")]).write(str(tmp_path / "point_cloud.ply"))
    with pytest.raises(PlyFormatError, match=r"scale_\* holds NaN or inf in 1 of 3 anchors"):
        load_scaffold(tmp_path)


def test_inconsistent_point_cloud_is_refused(tmp_path):
    save_scaffold(tmp_path, random_model(n=4, k=2, d=4), ScaffoldHeads(4, 2))
    path = tmp_path / "point_cloud.ply"
    good = path.read_bytes()

    # f_offset_* that are not 3k
    def drop_offset(data):
        kept = [n for n in data.dtype.names if n != "f_offset_5"]
        fewer = np.empty(len(data), dtype=[(n, "f4") for n in kept])
        for n in kept:
            fewer[n] = data[n]
        return fewer

    rewrite_ply(path, drop_offset)
    with pytest.raises(PlyFormatError, match="has 5 f_offset_\\* properties; expected 3k"):
        load_scaffold(tmp_path)

    # a property that is a list per vertex instead of one number
    vertex = plyfile.PlyData.read(io.BytesIO(good))["vertex"]
    dtype = [(p.name, "f4") if p.name != "opacity" else ("opacity", "O") for p in vertex.properties]
    data = np.empty(vertex.count, dtype=dtype)
    for p in vertex.properties:
        data[p.name] = vertex[p.name] if p.name != "opacity" else [np.zeros(2, "f4")] * vertex.count
    plyfile.PlyData([plyfile.PlyElement.describe(data, "vertex", len_types={"opacity": "u1"},
                                                 val_types={"opacity": "f4"})]).write(str(path))
    with pytest.raises(PlyFormatError, match="vertex property 'opacity' is a list"):
        load_scaffold(tmp_path)

    # the body ends early, and bytes that are no PLY at all
    path.write_bytes(good[:-10])
    with pytest.raises(PlyFormatError, match="point_cloud.ply: not a readable PLY file"):
        load_scaffold(tmp_path)
    path.write_bytes(np.random.default_rng(0).bytes(300))
    with pytest.raises(PlyFormatError, match="point_cloud.ply: not a readable PLY file"):
        load_scaffold(tmp_path)


@pytest.mark.parametrize("attribute, key", [
    ("opacity_mlp", "0.weight"), ("cov_mlp", "2.bias"), ("color_mlp", "2.weight"),
    ("feature_bank_mlp", "0.bias"), ("embedding_appearance", "weight"),
])
def test_non_finite_mlp_weights_are_refused(tmp_path, attribute, key):
    heads = ScaffoldHeads(4, 2, use_feat_bank=True, appearance_dim=3, num_cameras=2)
    save_scaffold(tmp_path, random_model(n=4, k=2, d=4), heads)
    state = getattr(heads, attribute).state_dict()
    state[key] = state[key].clone()
    state[key].view(-1)[:3] = torch.tensor([float("nan"), float("inf"), 1.0])
    torch.save(state, tmp_path / f"{attribute}.pt")
    count = state[key].numel()
    with pytest.raises(MlpFileError, match=rf"{attribute}.pt: '{re.escape(key)}' holds NaN or inf in 2 of {count}"):
        load_scaffold(tmp_path)


@pytest.mark.filterwarnings("ignore:`torch.jit")
def test_non_finite_weights_in_a_torchscript_archive_are_refused(tmp_path):
    heads = ScaffoldHeads(4, 2)
    save_scaffold(tmp_path, random_model(n=4, k=2, d=4), heads)
    with torch.no_grad():
        heads.cov_mlp[0].weight[1, 1] = float("nan")
    torch.jit.trace(heads.cov_mlp.eval(), torch.rand(1, 7)).save(str(tmp_path / "cov_mlp.pt"))
    with pytest.raises(MlpFileError, match=r"cov_mlp.pt: '0.weight' holds NaN or inf in 1 of 28 values"):
        load_scaffold(tmp_path)


def test_mlps_that_do_not_fit_the_anchors_are_refused(tmp_path):
    # A feature bank needs d divisible by 4; an embedding needs a camera.
    save_scaffold(tmp_path, random_model(n=4, k=2, d=6), ScaffoldHeads(6, 2))
    torch.save(ScaffoldHeads(8, 2, use_feat_bank=True).feature_bank_mlp.state_dict(),
               tmp_path / "feature_bank_mlp.pt")
    with pytest.raises(MlpFileError, match="feature_bank_mlp.pt: a feature bank splits the feature in 4, but the "
                                           "anchors' feature dimension is 6"):
        load_scaffold(tmp_path)
    (tmp_path / "feature_bank_mlp.pt").unlink()
    torch.save({"weight": torch.zeros(0, 3)}, tmp_path / "embedding_appearance.pt")
    with pytest.raises(MlpFileError, match=r"embedding_appearance.pt: 'weight' has shape \[0, 3\]"):
        load_scaffold(tmp_path)
