"""The private decoders of SecureGS (the key): F_o†, F_α†, F_cov†, F_c† and the bit head F_b†.

They read the same public anchors as the public heads; nothing of them is in the public release.
"""
from __future__ import annotations

import torch
from torch import nn

from ..model import ScaffoldHeads, make_mlp
from ..model.neural_gaussians import AnchorViewInputs

FRAMES = ("anchor", "box")


class PrivateHeads(nn.Module):
    """Private MLPs. ``decoder`` has exactly the public heads' shapes (F_α†, F_cov†, F_c†).

    offset_mlp (F_o†): Linear(d+3, d), ReLU, Linear(d, 3k) — the hidden Gaussians' offsets from the
        blended anchor feature and view direction, so that no hidden offset is stored in the file
        (the paper's hybrid decoupled Gaussian encryption, HDGER). ``None`` in the "w/o HDGER"
        ablation, where the anchors carry explicit hidden offsets instead
        (``AnchorModel.hidden_offsets``; measured by the training scripts, not saved in a release).
    bit_mlp (F_b†): Linear(d, d), ReLU, Linear(d, L), both without bias — per-anchor bit logits;
        the message is the average over anchors (each anchor votes). Without biases the head cannot
        learn the message as a constant of its own (F_b†(0) = 0): it is read from the features.
        It is not a watermark test, though: features trained on the same scene without the
        message can decode it too (docs/results.md), since the head maps what such features
        have in common to the message.
    scale_offsets: hidden offsets are in units of the anchor's offset scale exp(l_v[:3]), as the
        public offsets are. The paper writes x_v + F_o†(...) without l_v; scaling keeps the MLP's
        output range independent of the scene's size and of the anchor's voxel level, which is what
        lets one small MLP place Gaussians for anchors grown at several levels. Switchable.
    frame: where F_o† places the hidden Gaussians.
        "anchor" (the paper): x_v + F_o†(f̂_v, d_vc), near their anchor, so hidden Gaussians need
            anchors on the hidden surface (RDO grows them there: the release shows the shape).
        "box": c + h ⊙ tanh(F_o†(f̂_v, (x_v − c) / h)), anywhere in the key's box (``box``: centre c
            [3] and half-extent h [3], world units; F_o† reads the anchor's position in the box's
            frame instead of the view direction, so the hidden geometry is the same from every view).
            Only the ``serving`` anchors nearest the box decode hidden Gaussians; they are the
            cover's own anchors, wherever the cover put them.
    n_hidden: k_hid, hidden Gaussians per anchor (None: the public k).
    width: hidden width of the private MLPs (None: d).
    serving: the number of anchors, nearest the box first, that decode hidden Gaussians in the box
        frame (0: every anchor that the view shows).
    """

    def __init__(self, public: ScaffoldHeads, *, bits: int = 0, offsets: bool = True, scale_offsets: bool = True,
                 hidden: bool = True, frame: str = "anchor", n_hidden: int | None = None, width: int | None = None,
                 serving: int = 0):
        super().__init__()
        if frame not in FRAMES:
            raise ValueError(f"frame must be one of {FRAMES}, got {frame!r}")
        if frame == "box" and not offsets:
            raise ValueError("the box frame places hidden Gaussians with F_o†: it needs offsets=True")
        d = public.feat_dim
        k = public.n_offsets if n_hidden is None else int(n_hidden)
        w = d if width is None else int(width)
        self.feat_dim, self.n_offsets, self.scale_offsets = d, k, scale_offsets
        self.frame, self.width, self.serving = frame, w, int(serving)
        self.decoder = ScaffoldHeads(d, k, use_feat_bank=public.use_feat_bank,
                                     add_opacity_dist=public.add_opacity_dist, add_cov_dist=public.add_cov_dist,
                                     add_color_dist=public.add_color_dist, width=w) if hidden else None
        self.offset_mlp = make_mlp(d + 3, w, 3 * k) if hidden and offsets else None
        self.bit_mlp = make_mlp(d, d, bits, bias=False) if bits > 0 else None
        if frame == "box":  # set by the trainer from the hidden object's bounds; saved in the key
            self.register_buffer("box", torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]))

    @property
    def n_bits(self) -> int:
        return 0 if self.bit_mlp is None else self.bit_mlp[-1].out_features

    def hidden_offsets(self, inputs: AnchorViewInputs) -> torch.Tensor:
        """World-space displacements [Nv, k_hid, 3] of the hidden Gaussians of the decoded anchors."""
        if self.frame == "box":
            centre, half = self.box[0], self.box[1]
            where = (inputs.xyz.detach() - centre) / half
            raw = self.offset_mlp(torch.cat([inputs.feat, where], dim=1)).view(-1, self.n_offsets, 3)
            return centre + half * torch.tanh(raw) - inputs.xyz[:, None, :].detach()
        raw = self.offset_mlp(torch.cat([inputs.feat, inputs.ob_view], dim=1)).view(-1, self.n_offsets, 3)
        return raw * inputs.scaling[:, None, :3] if self.scale_offsets else raw

    def set_box(self, lo, hi) -> None:
        """The box frame's region: corners ``lo``, ``hi`` [3] in world units."""
        lo, hi = (torch.as_tensor(v, dtype=torch.float32, device=self.box.device) for v in (lo, hi))
        self.box.copy_(torch.stack([0.5 * (lo + hi), (0.5 * (hi - lo)).clamp_min(1e-6)]))

    @torch.no_grad()
    def serving_mask(self, xyz: torch.Tensor) -> torch.Tensor | None:
        """[N] bool, the anchors that decode hidden Gaussians in the box frame (the ``serving``
        nearest the box, by distance to it: 0 inside), from anchor positions [N, 3]; None in the
        anchor frame or with ``serving`` 0 (the view's visible anchors decode)."""
        if self.frame != "box" or self.serving <= 0:
            return None
        outside = ((xyz - self.box[0]).abs() - self.box[1]).clamp_min(0.0).norm(dim=1)
        mask = torch.zeros(len(xyz), dtype=torch.bool, device=xyz.device)
        mask[outside.topk(min(self.serving, len(xyz)), largest=False).indices] = True
        return mask

    def bit_logits(self, feat: torch.Tensor) -> torch.Tensor:
        """Per-anchor bit logits [N, L] from anchor features [N, d]."""
        return self.bit_mlp(feat)

    @torch.no_grad()
    def decode_bits(self, feat: torch.Tensor) -> torch.Tensor:
        """The message [L] (0/1 ints): each anchor votes with its sigmoid, the mean decides."""
        return (torch.sigmoid(self.bit_logits(feat)).mean(dim=0) > 0.5).to(torch.int64)

    def named_mlps(self) -> dict[str, nn.Module]:
        """Trainable parts by learning-rate schedule (the decoder's names are the public ones)."""
        parts = dict(self.decoder.named_mlps()) if self.decoder is not None else {}
        if self.offset_mlp is not None:
            parts["mlp_offset"] = self.offset_mlp
        if self.bit_mlp is not None:
            parts["mlp_bits"] = self.bit_mlp
        return parts

    def describe(self) -> dict:
        """The constructor arguments, for the key's metadata."""
        return {"bits": self.n_bits, "offsets": self.offset_mlp is not None, "scale_offsets": self.scale_offsets,
                "hidden": self.decoder is not None, "frame": self.frame, "n_hidden": self.n_offsets,
                "width": self.width, "serving": self.serving}
