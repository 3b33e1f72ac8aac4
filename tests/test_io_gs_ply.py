"""Standard 3DGS PLY export: layout and the logit / log / f_dc conventions."""

import numpy as np
import plyfile
import pytest
import torch

from securegs_warp.io import GS_PLY_PROPERTIES, SH_C0, PlyFormatError, export_3dgs_ply, read_3dgs_ply


def random_gaussians(m=50, seed=0):
    g = torch.Generator().manual_seed(seed)
    return {
        "means": torch.randn(m, 3, generator=g),
        "quats": torch.randn(m, 4, generator=g) * 3,
        "scales": torch.rand(m, 3, generator=g) * 0.1 + 1e-3,
        "opacities": torch.rand(m, generator=g) * 0.98 + 0.01,
        "colors": torch.rand(m, 3, generator=g),
    }


def test_layout_and_conventions(tmp_path):
    gaussians = random_gaussians()
    path = tmp_path / "splat.ply"
    export_3dgs_ply(path, **gaussians)
    vertex = plyfile.PlyData.read(str(path))["vertex"]
    assert [p.name for p in vertex.properties] == GS_PLY_PROPERTIES == [
        "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
        "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
    ]
    assert all(vertex[p.name].dtype == np.float32 for p in vertex.properties)
    o = gaussians["opacities"].double()
    np.testing.assert_allclose(vertex["opacity"], torch.log(o / (1 - o)).numpy(), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(vertex["scale_1"], torch.log(gaussians["scales"][:, 1]).numpy(), rtol=1e-6)
    f_dc = (gaussians["colors"][:, 2] - 0.5) / 0.28209479
    np.testing.assert_allclose(vertex["f_dc_2"], f_dc.numpy(), rtol=1e-5, atol=1e-6)
    q = torch.nn.functional.normalize(gaussians["quats"], dim=1)
    np.testing.assert_allclose(vertex["rot_0"], q[:, 0].numpy(), rtol=1e-6, atol=1e-7)  # w first
    assert not np.any(vertex["nx"])
    assert SH_C0 == pytest.approx(0.28209479)


def test_round_trip(tmp_path):
    gaussians = random_gaussians(seed=1)
    path = tmp_path / "splat.ply"
    export_3dgs_ply(path, **gaussians)
    back = read_3dgs_ply(path)
    assert torch.equal(back["means"], gaussians["means"])
    assert torch.allclose(back["quats"], torch.nn.functional.normalize(gaussians["quats"], dim=1), atol=1e-7)
    for key in ("scales", "opacities", "colors"):
        assert torch.allclose(back[key], gaussians[key], rtol=1e-5, atol=1e-6), key


def test_saturated_opacity_and_zero_scale_stay_finite(tmp_path):
    gaussians = random_gaussians(m=3)
    gaussians["opacities"] = torch.tensor([0.0, 1.0, 0.5])
    gaussians["scales"][0] = 0.0
    export_3dgs_ply(tmp_path / "s.ply", **gaussians)
    vertex = plyfile.PlyData.read(str(tmp_path / "s.ply"))["vertex"]
    assert np.all(np.isfinite(vertex["opacity"])) and np.all(np.isfinite(vertex["scale_0"]))
    assert vertex["opacity"][0] < -10 and vertex["opacity"][1] > 10


def test_shape_errors_and_unreadable_files(tmp_path):
    gaussians = random_gaussians(m=4)
    with pytest.raises(ValueError, match="opacities"):
        export_3dgs_ply(tmp_path / "x.ply", **{**gaussians, "opacities": gaussians["opacities"][:, None]})
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"not a ply at all")
    with pytest.raises(PlyFormatError, match="bad.ply"):
        read_3dgs_ply(bad)
    vertex = np.zeros(2, dtype=[(n, "f4") for n in GS_PLY_PROPERTIES if n != "scale_2"])
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")]).write(str(tmp_path / "m.ply"))
    with pytest.raises(PlyFormatError, match="'scale_2' is missing"):
        read_3dgs_ply(tmp_path / "m.ply")
    # Headers that plyfile refuses with a bare ValueError: the error names the file.
    header = b"ply\nformat binary_little_endian 1.0\nelement vertex %s\n%send_header\n"
    for name, text in (("twice.ply", header % (b"2", b"property float x\nproperty float x\n")),
                       ("negative.ply", header % (b"-2", b"property float x\n"))):
        (tmp_path / name).write_bytes(text + bytes(8))
        with pytest.raises(PlyFormatError, match=f"{name}: not a readable PLY file"):
            read_3dgs_ply(tmp_path / name)
