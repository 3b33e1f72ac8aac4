"""Scaffold-GS model folders: exact PLY layout, round trip, Scaffold-GS's own files, safe MLP loading."""

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


@pytest.mark.filterwarnings("ignore:`torch.jit.trace")
def test_scaffold_gs_folder_with_torchscript_mlps_loads_after_conversion(tmp_path):
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

    # Refused as it is (reading it means unpickling), with the conversion to run where it is trusted.
    with pytest.raises(MlpFileError, match="TorchScript archive.*torch.jit.load"):
        load_scaffold(tmp_path)
    for name in ("opacity_mlp", "cov_mlp", "color_mlp", "feature_bank_mlp", "embedding_appearance"):
        path = str(tmp_path / f"{name}.pt")
        torch.save(torch.jit.load(path).state_dict(), path)

    loaded, heads = load_scaffold(tmp_path)
    assert loaded.n_offsets == 10 and loaded.feat_dim == 32
    for name in ("xyz", "feat", "offsets", "scaling", "rotation", "opacity"):
        assert torch.equal(getattr(loaded, name), getattr(model, name)), name
    assert heads.appearance_dim == 32 and heads.use_feat_bank
    for key, value in reference.state_dict().items():
        assert torch.equal(heads.state_dict()[key], value), key


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


def test_torchscript_archive_is_refused_without_reading_it(tmp_path):
    path = tmp_path / "opacity_mlp.pt"
    # The layout of a torch.jit.save archive; its data.pkl would run os.system if it were unpickled.
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("opacity_mlp/data.pkl", b"\x80\x02cos\nsystem\nq\x00X\x04\x00\x00\x00trueq\x01\x85q\x02Rq\x03.")
        archive.writestr("opacity_mlp/constants.pkl", b"\x80\x02).")
        archive.writestr("opacity_mlp/byteorder", "little")
    with pytest.raises(MlpFileError, match="TorchScript archive"):
        load_weights(path)
