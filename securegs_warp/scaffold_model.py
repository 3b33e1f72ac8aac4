"""``ScaffoldModel``: what a Scaffold-GS release holds (anchors + public heads), and how it renders."""
from __future__ import annotations

import dataclasses
import os

import torch
from torch import nn

from .config import HeadsConfig
from .io import load_scaffold, save_scaffold
from .model import AnchorModel, ScaffoldHeads, generate_neural_gaussians
from .model.neural_gaussians import camera_center_from_viewmat
from .rasterizer import RasterOptions
from .render import camera_tensors, render_view


def decode_all(anchors: AnchorModel, heads: ScaffoldHeads, camera, *, camera_index: int | None = None,
               offset_source=None, anchor_source=None, anchor_mask: torch.Tensor | None = None) -> dict:
    """``generate_neural_gaussians`` of every anchor (or of those in ``anchor_mask`` [N] bool) as
    seen from ``camera`` (no visibility test), with its ``offset_source`` and ``anchor_source``."""
    viewmat, _ = camera_tensors(camera, anchors.xyz.device)
    appearance = (camera_index or 0) if heads.appearance_dim else None
    extra = {"offset_source": offset_source} if offset_source is not None else {}
    return generate_neural_gaussians(anchors, heads, camera_center_from_viewmat(viewmat), anchor_mask,
                                     camera_index=appearance, anchor_source=anchor_source, **extra)


def build_heads(config: HeadsConfig, num_cameras: int = 0) -> ScaffoldHeads:
    """Fresh heads with exactly the inputs ``config`` switches on (an appearance embedding needs the
    number of training cameras)."""
    return ScaffoldHeads(config.feat_dim, config.n_offsets, use_feat_bank=config.feature_bank,
                         appearance_dim=config.appearance_dim,
                         num_cameras=num_cameras if config.appearance_dim else 0,
                         add_opacity_dist=config.opacity_dist, add_cov_dist=config.cov_dist,
                         add_color_dist=config.color_dist)


class ScaffoldModel(nn.Module):
    """Anchors and the public MLP heads that decode them: a model that renders, loads and saves.

    anchors: the per-anchor parameters (densification replaces their tensors; hold the model, not
    its tensors). heads: the opacity, covariance and colour MLPs (+ optional feature bank and
    appearance embedding).
    """

    def __init__(self, anchors: AnchorModel, heads: ScaffoldHeads):
        super().__init__()
        if heads.feat_dim != anchors.feat_dim or heads.n_offsets != anchors.n_offsets:
            raise ValueError(f"heads decode d={heads.feat_dim}, k={heads.n_offsets} but the anchors have "
                             f"d={anchors.feat_dim}, k={anchors.n_offsets}")
        self.anchors = anchors
        self.heads = heads

    @property
    def device(self) -> torch.device:
        return self.anchors.xyz.device

    def render(self, camera, options: RasterOptions | None = None, *, background: torch.Tensor | None = None,
               camera_index: int | None = None) -> dict:
        """The public render of one view (see ``render_view``): ``image`` [H, W, 3], ``alpha``
        [H, W, 1], ``info``, ``gaussians``. background: [3] colour, or None for black."""
        return render_view(self.anchors, self.heads, camera, background, options, camera_index=camera_index)

    @torch.no_grad()
    def gaussians(self, camera, *, camera_index: int | None = None) -> dict:
        """Every anchor decoded into its Gaussians with the view directions of ``camera``, without
        frustum culling (a render decodes only the anchors it sees): the whole scene, for export.
        Scaffold-GS's decoding depends on the view, so an export is that of one camera's decoding.
        Returns ``generate_neural_gaussians``' dict (means [M, 3], quats, scales, opacities, colors)."""
        return decode_all(self.anchors, self.heads, camera, camera_index=camera_index)

    def save(self, directory: str | os.PathLike) -> None:
        """Write Scaffold-GS's files (point_cloud.ply + the MLPs) into ``directory``."""
        save_scaffold(directory, self.anchors, self.heads)

    @classmethod
    def load(cls, directory: str | os.PathLike, device="cpu", voxel_size: float | None = None) -> "ScaffoldModel":
        """Read a Scaffold-GS model folder (ours or Scaffold-GS's own)."""
        anchors, heads = load_scaffold(directory, device=device, voxel_size=voxel_size)
        return cls(anchors, heads)


def neutral_heads(plain: ScaffoldHeads, config: HeadsConfig, num_cameras: int = 0) -> ScaffoldHeads:
    """Heads with ``config``'s inputs that compute exactly what ``plain`` (heads with no optional
    input) computes: plain's first-layer weights in the shared input columns, zeros in the extra
    distance / appearance columns, and a feature bank whose softmax selects the full-resolution
    feature. For checking a specialised variant against the general one, and for timing an
    optional input on the same Gaussians (fresh random heads would keep a different number)."""
    d = plain.feat_dim
    heads = build_heads(dataclasses.replace(config, feat_dim=d, n_offsets=plain.n_offsets), num_cameras)
    heads = heads.to(plain.opacity_mlp[0].weight.device)
    with torch.no_grad():
        for name in ("opacity_mlp", "cov_mlp", "color_mlp"):
            src, dst = getattr(plain, name), getattr(heads, name)
            dst.load_state_dict({k: v for k, v in src.state_dict().items() if k != "0.weight"}, strict=False)
            dst[0].weight.zero_()
            dst[0].weight[:, : d + 3] = src[0].weight
        if heads.feature_bank_mlp is not None:
            heads.feature_bank_mlp[2].weight.zero_()
            heads.feature_bank_mlp[2].bias.copy_(torch.tensor([-1e4, -1e4, 1e4]))  # softmax -> (0, 0, 1)
    return heads
