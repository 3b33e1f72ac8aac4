"""Scaffold-GS model folders: exact PLY layout, round trip, Scaffold-GS's own files, safe MLP loading."""

import io
import pickle
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
    monkeypatch.setattr(pickle, "load", forbidden)
    monkeypatch.setattr(pickle, "loads", forbidden)
    monkeypatch.setattr(pickle, "Unpickler", forbidden)
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
    pickle.loads(pickle.dumps(OpenFile(tmp_path / "control"), protocol=protocol))
    assert (tmp_path / "control").exists()

    if where == "top":
        payload = pickle.dumps(OpenFile(witness), protocol=protocol)
    else:
        payload = pickle.dumps({"training": False, "weight": OpenFile(witness)}, protocol=protocol)
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
