"""A release written by ``save_scaffold``, opened the way Scaffold-GS itself opens a trained model.

Scaffold-GS (https://github.com/city-super/Scaffold-GS) loads a model folder in ``scene/__init__.py``
with ``GaussianModel.load_ply_sparse_gaussian(.../point_cloud.ply)`` and
``GaussianModel.load_mlp_checkpoints(folder)`` (``scene/gaussian_model.py``; the default
``mode='split'`` calls ``torch.jit.load`` on ``opacity_mlp.pt``, ``cov_mlp.pt``, ``color_mlp.pt``,
on ``feature_bank_mlp.pt`` when ``use_feat_bank`` and on ``embedding_appearance.pt`` when
``appearance_dim > 0``), then decodes the anchors with ``generate_neural_gaussians`` in
``gaussian_renderer/__init__.py``. :class:`ScaffoldGSModel` and :func:`scaffold_gs_decode` below are
those functions statement for statement, without CUDA (``.cuda()`` and ``device="cuda"`` dropped)
and without einops (its ``repeat(x, 'n (c) -> (n k) (c)', k=k)`` is ``repeat_interleave``).
``torch.jit.load`` is legitimate here: the test opens files that our own code has just written.
"""

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from plyfile import PlyData
from torch import nn

from securegs_warp.io import load_scaffold, save_scaffold
from securegs_warp.model import AnchorModel, ScaffoldHeads, generate_neural_gaussians

pytestmark = pytest.mark.filterwarnings("ignore:`torch.jit")


class ScaffoldGSModel:
    """The loading half of Scaffold-GS's ``GaussianModel`` (scene/gaussian_model.py), on the CPU."""

    # Scaffold-GS's getters, by the names its generate_neural_gaussians reads.
    _GETTERS = {"get_appearance": "embedding_appearance", "get_featurebank_mlp": "mlp_feature_bank",
                "get_opacity_mlp": "mlp_opacity", "get_cov_mlp": "mlp_cov", "get_color_mlp": "mlp_color",
                "get_anchor": "_anchor"}

    def __init__(self, feat_dim, n_offsets, use_feat_bank, appearance_dim, add_opacity_dist, add_cov_dist,
                 add_color_dist):
        vars(self).update(feat_dim=feat_dim, n_offsets=n_offsets, use_feat_bank=use_feat_bank,
                          appearance_dim=appearance_dim, embedding_appearance=None,
                          add_opacity_dist=add_opacity_dist, add_cov_dist=add_cov_dist, add_color_dist=add_color_dist,
                          scaling_activation=torch.exp, rotation_activation=torch.nn.functional.normalize)

    def __getattr__(self, name):
        if name in ScaffoldGSModel._GETTERS:
            return getattr(self, ScaffoldGSModel._GETTERS[name])
        raise AttributeError(name)

    @property
    def get_scaling(self):
        return 1.0 * self.scaling_activation(self._scaling)

    def load_ply_sparse_gaussian(self, path):
        plydata = PlyData.read(path)

        anchor = np.stack((np.asarray(plydata.elements[0]["x"]),
                           np.asarray(plydata.elements[0]["y"]),
                           np.asarray(plydata.elements[0]["z"])), axis=1).astype(np.float32)
        opacities = np.asarray(plydata.elements[0]["opacity"])[..., np.newaxis].astype(np.float32)

        # Scaffold-GS repeats this block for scale_, rot, f_anchor_feat and f_offset: the properties
        # with the prefix, sorted by their trailing index, as float32 columns of a float64 array.
        def columns(prefix):
            names = [p.name for p in plydata.elements[0].properties if p.name.startswith(prefix)]
            names = sorted(names, key=lambda x: int(x.split('_')[-1]))
            values = np.zeros((anchor.shape[0], len(names)))
            for idx, attr_name in enumerate(names):
                values[:, idx] = np.asarray(plydata.elements[0][attr_name]).astype(np.float32)
            return values

        scales, rots = columns("scale_"), columns("rot")
        anchor_feats, offsets = columns("f_anchor_feat"), columns("f_offset")
        offsets = offsets.reshape((offsets.shape[0], 3, -1))

        self._anchor_feat = nn.Parameter(torch.tensor(anchor_feats, dtype=torch.float).requires_grad_(True))
        self._offset = nn.Parameter(torch.tensor(offsets, dtype=torch.float).transpose(1, 2).contiguous()
                                    .requires_grad_(True))
        self._anchor = nn.Parameter(torch.tensor(anchor, dtype=torch.float).requires_grad_(True))
        self._opacity = nn.Parameter(torch.tensor(opacities, dtype=torch.float).requires_grad_(True))
        self._scaling = nn.Parameter(torch.tensor(scales, dtype=torch.float).requires_grad_(True))
        self._rotation = nn.Parameter(torch.tensor(rots, dtype=torch.float).requires_grad_(True))

    def load_mlp_checkpoints(self, path):
        # mode == 'split'
        self.mlp_opacity = torch.jit.load(f"{path}/opacity_mlp.pt")
        self.mlp_cov = torch.jit.load(f"{path}/cov_mlp.pt")
        self.mlp_color = torch.jit.load(f"{path}/color_mlp.pt")
        if self.use_feat_bank:
            self.mlp_feature_bank = torch.jit.load(f"{path}/feature_bank_mlp.pt")
        if self.appearance_dim > 0:
            self.embedding_appearance = torch.jit.load(f"{path}/embedding_appearance.pt")


def scaffold_gs_decode(viewpoint_camera, pc, visible_mask=None):
    """Scaffold-GS's generate_neural_gaussians (gaussian_renderer/__init__.py), is_training=False."""
    if visible_mask is None:
        visible_mask = torch.ones(pc.get_anchor.shape[0], dtype=torch.bool, device=pc.get_anchor.device)

    feat = pc._anchor_feat[visible_mask]
    anchor = pc.get_anchor[visible_mask]
    grid_offsets = pc._offset[visible_mask]
    grid_scaling = pc.get_scaling[visible_mask]

    ob_view = anchor - viewpoint_camera.camera_center
    ob_dist = ob_view.norm(dim=1, keepdim=True)
    ob_view = ob_view / ob_dist

    if pc.use_feat_bank:
        cat_view = torch.cat([ob_view, ob_dist], dim=1)
        bank_weight = pc.get_featurebank_mlp(cat_view).unsqueeze(dim=1)  # [n, 1, 3]
        feat = feat.unsqueeze(dim=-1)
        feat = feat[:, ::4, :1].repeat([1, 4, 1]) * bank_weight[:, :, :1] + \
            feat[:, ::2, :1].repeat([1, 2, 1]) * bank_weight[:, :, 1:2] + \
            feat[:, ::1, :1] * bank_weight[:, :, 2:]
        feat = feat.squeeze(dim=-1)  # [n, c]

    cat_local_view = torch.cat([feat, ob_view, ob_dist], dim=1)  # [N, c+3+1]
    cat_local_view_wodist = torch.cat([feat, ob_view], dim=1)  # [N, c+3]
    if pc.appearance_dim > 0:
        camera_indicies = torch.ones_like(cat_local_view[:, 0], dtype=torch.long,
                                          device=ob_dist.device) * viewpoint_camera.uid
        appearance = pc.get_appearance(camera_indicies)

    if pc.add_opacity_dist:
        neural_opacity = pc.get_opacity_mlp(cat_local_view)  # [N, k]
    else:
        neural_opacity = pc.get_opacity_mlp(cat_local_view_wodist)

    neural_opacity = neural_opacity.reshape([-1, 1])
    mask = (neural_opacity > 0.0)
    mask = mask.view(-1)
    opacity = neural_opacity[mask]

    if pc.appearance_dim > 0:
        if pc.add_color_dist:
            color = pc.get_color_mlp(torch.cat([cat_local_view, appearance], dim=1))
        else:
            color = pc.get_color_mlp(torch.cat([cat_local_view_wodist, appearance], dim=1))
    else:
        if pc.add_color_dist:
            color = pc.get_color_mlp(cat_local_view)
        else:
            color = pc.get_color_mlp(cat_local_view_wodist)
    color = color.reshape([anchor.shape[0] * pc.n_offsets, 3])

    if pc.add_cov_dist:
        scale_rot = pc.get_cov_mlp(cat_local_view)
    else:
        scale_rot = pc.get_cov_mlp(cat_local_view_wodist)
    scale_rot = scale_rot.reshape([anchor.shape[0] * pc.n_offsets, 7])

    offsets = grid_offsets.view([-1, 3])

    concatenated = torch.cat([grid_scaling, anchor], dim=-1)
    concatenated_repeated = concatenated.repeat_interleave(pc.n_offsets, dim=0)  # einops 'n (c) -> (n k) (c)'
    concatenated_all = torch.cat([concatenated_repeated, color, scale_rot, offsets], dim=-1)
    masked = concatenated_all[mask]
    scaling_repeat, repeat_anchor, color, scale_rot, offsets = masked.split([6, 3, 3, 7, 3], dim=-1)

    scaling = scaling_repeat[:, 3:] * torch.sigmoid(scale_rot[:, :3])
    rot = pc.rotation_activation(scale_rot[:, 3:7])

    offsets = offsets * scaling_repeat[:, :3]
    xyz = repeat_anchor + offsets
    return xyz, color, opacity, scaling, rot


CONFIGS = {
    "plain": dict(use_feat_bank=False, appearance_dim=0, add_opacity_dist=False, add_cov_dist=False,
                  add_color_dist=False),
    "bank+appearance": dict(use_feat_bank=True, appearance_dim=6, add_opacity_dist=False, add_cov_dist=False,
                            add_color_dist=False),
    "distances+appearance": dict(use_feat_bank=False, appearance_dim=6, add_opacity_dist=True, add_cov_dist=True,
                                 add_color_dist=True),
    "bank+distances": dict(use_feat_bank=True, appearance_dim=0, add_opacity_dist=True, add_cov_dist=False,
                           add_color_dist=True),
}


@pytest.mark.parametrize("config", CONFIGS.values(), ids=CONFIGS.keys())
def test_scaffold_gs_opens_our_release_and_decodes_the_same_gaussians(tmp_path, config):
    d, k, n, cameras = 16, 5, 40, 4
    g = torch.Generator().manual_seed(7)
    model = AnchorModel(
        xyz=torch.randn(n, 3, generator=g), feat=torch.randn(n, d, generator=g),
        offsets=torch.randn(n, k, 3, generator=g), scaling=torch.randn(n, 6, generator=g) - 2,
        rotation=torch.randn(n, 4, generator=g), opacity=torch.randn(n, 1, generator=g),
    )
    torch.manual_seed(8)
    heads = ScaffoldHeads(d, k, num_cameras=cameras if config["appearance_dim"] else 0, **config)
    save_scaffold(tmp_path, model, heads)

    pc = ScaffoldGSModel(d, k, **config)
    pc.load_ply_sparse_gaussian(str(tmp_path / "point_cloud.ply"))
    pc.load_mlp_checkpoints(str(tmp_path))
    ours, our_heads = load_scaffold(tmp_path)

    # Every anchor array Scaffold-GS reads equals what was saved and what our loader reads.
    for theirs, name in ((pc._anchor, "xyz"), (pc._offset, "offsets"), (pc._anchor_feat, "feat"),
                         (pc._opacity, "opacity"), (pc._scaling, "scaling"), (pc._rotation, "rotation")):
        assert theirs.dtype == torch.float32 and theirs.shape == getattr(model, name).shape, name
        assert torch.equal(theirs.detach(), getattr(model, name)), name
        assert torch.equal(theirs.detach(), getattr(ours, name)), name

    # Every MLP Scaffold-GS loads computes what our heads compute, on the same random inputs.
    mlps = {"opacity_mlp": pc.mlp_opacity, "cov_mlp": pc.mlp_cov, "color_mlp": pc.mlp_color}
    if config["use_feat_bank"]:
        mlps["feature_bank_mlp"] = pc.mlp_feature_bank
    with torch.no_grad():
        for attribute, theirs in mlps.items():
            width = getattr(heads, attribute)[0].in_features
            x = torch.randn(64, width, generator=g)
            expected = getattr(heads, attribute)(x)
            assert torch.equal(theirs(x), expected), attribute
            assert torch.equal(getattr(our_heads, attribute)(x), expected), attribute
        if config["appearance_dim"]:
            index = torch.randint(0, cameras, (64,), generator=g)
            assert torch.equal(pc.embedding_appearance(index), heads.embedding_appearance(index))
        else:
            assert not (tmp_path / "embedding_appearance.pt").exists()
        if not config["use_feat_bank"]:
            assert not (tmp_path / "feature_bank_mlp.pt").exists()

        # And the Gaussians Scaffold-GS decodes for a view are ours.
        camera = SimpleNamespace(camera_center=torch.tensor([0.5, -3.0, 2.0]), uid=cameras - 1)
        xyz, color, opacity, scaling, rot = scaffold_gs_decode(camera, pc)
        decoded = generate_neural_gaussians(model, heads, camera.camera_center,
                                            camera_index=camera.uid if config["appearance_dim"] else None)
    assert 0 < xyz.shape[0] < n * k
    for name, theirs in (("means", xyz), ("colors", color), ("opacities", opacity.reshape(-1)),
                         ("scales", scaling), ("quats", rot)):
        assert torch.equal(theirs, decoded[name]), name
