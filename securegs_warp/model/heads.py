"""The MLP heads that decode an anchor's feature into its k neural Gaussians (Scaffold-GS).

One :class:`ScaffoldHeads` is one complete decoder: opacity, covariance and colour MLPs, plus the
optional feature bank and appearance embedding. SecureGS uses two of them with identical shapes:
the public heads (F_alpha, F_cov = F_q + F_s, F_c), saved beside point_cloud.ply, and the private
heads (F_alpha†, F_cov†, F_c†), kept in the key file.

Shapes follow Scaffold-GS exactly (d = feature dimension, also the hidden width; k = offsets per
anchor; A = appearance dimension; each ``+1`` is present only when the matching ``add_*_dist`` flag
is set)::

    opacity_mlp       Linear(d+3(+1), d)   ReLU  Linear(d, k)    Tanh
    cov_mlp           Linear(d+3(+1), d)   ReLU  Linear(d, 7k)
    color_mlp         Linear(d+3(+1)+A, d) ReLU  Linear(d, 3k)   Sigmoid
    feature_bank_mlp  Linear(3+1, d)       ReLU  Linear(d, 3)    Softmax(dim=1)   (optional)
    embedding_appearance  Embedding(num_cameras, A)                             (optional)

Inputs are concatenated in Scaffold-GS's order: ``[feature, view direction, distance, appearance]``.
"""

from __future__ import annotations

import torch
from torch import nn


def make_mlp(in_dim: int, hidden_dim: int, out_dim: int, activation: nn.Module | None = None,
             bias: bool = True, depth: int = 1) -> nn.Sequential:
    """Scaffold-GS's two-layer head: Linear, ReLU, Linear, then ``activation`` if given (``bias``:
    whether the Linear layers have biases); ``depth`` hidden layers (Linear, ReLU each) before the
    last Linear.

    The Linear layers are modules ``0`` and ``2`` (then ``4``, ... with more depth), so state-dict
    keys are ``0.weight``, ``0.bias``, ``2.weight``, ``2.bias`` (no ``.bias`` keys without biases)
    whatever the activation, as in Scaffold-GS's files.
    """
    layers = [nn.Linear(in_dim, hidden_dim, bias=bias), nn.ReLU(True)]
    for _ in range(depth - 1):
        layers += [nn.Linear(hidden_dim, hidden_dim, bias=bias), nn.ReLU(True)]
    layers.append(nn.Linear(hidden_dim, out_dim, bias=bias))
    if activation is not None:
        layers.append(activation)
    return nn.Sequential(*layers)


class ScaffoldHeads(nn.Module):
    """Opacity, covariance and colour MLPs (+ optional feature bank and appearance embedding).

    Args:
        feat_dim: d, the anchor feature dimension (32 in Scaffold-GS and SecureGS); also the hidden
            width of every MLP.
        n_offsets: k, neural Gaussians per anchor (10).
        use_feat_bank: blend the feature at three resolutions with view-dependent weights.
        appearance_dim: A, width of the per-camera appearance code fed to the colour MLP (0: none;
            Scaffold-GS's later configurations use 32).
        num_cameras: rows of the appearance embedding (training cameras); needed when A > 0.
        add_opacity_dist, add_cov_dist, add_color_dist: feed the anchor-camera distance to that
            MLP as well as the view direction.
        width: hidden width of the opacity, covariance and colour MLPs (None: d, as Scaffold-GS;
            a private decoder may be wider, since nothing of its shape is published).
    """

    def __init__(
        self,
        feat_dim: int = 32,
        n_offsets: int = 10,
        *,
        use_feat_bank: bool = False,
        appearance_dim: int = 0,
        num_cameras: int = 0,
        add_opacity_dist: bool = False,
        add_cov_dist: bool = False,
        add_color_dist: bool = False,
        width: int | None = None,
    ):
        super().__init__()
        if use_feat_bank and feat_dim % 4 != 0:
            raise ValueError(f"the feature bank splits the feature in 4; feat_dim {feat_dim} is not divisible by 4")
        if appearance_dim > 0 and num_cameras <= 0:
            raise ValueError("an appearance embedding needs num_cameras > 0")
        self.feat_dim = feat_dim
        self.n_offsets = n_offsets
        self.appearance_dim = appearance_dim
        self.add_opacity_dist = add_opacity_dist
        self.add_cov_dist = add_cov_dist
        self.add_color_dist = add_color_dist

        d, k = feat_dim, n_offsets
        w = self.width = d if width is None else width
        self.opacity_mlp = make_mlp(d + 3 + int(add_opacity_dist), w, k, nn.Tanh())
        self.cov_mlp = make_mlp(d + 3 + int(add_cov_dist), w, 7 * k)
        self.color_mlp = make_mlp(d + 3 + int(add_color_dist) + appearance_dim, w, 3 * k, nn.Sigmoid())
        self.feature_bank_mlp = make_mlp(3 + 1, d, 3, nn.Softmax(dim=1)) if use_feat_bank else None
        self.embedding_appearance = nn.Embedding(num_cameras, appearance_dim) if appearance_dim > 0 else None

    @property
    def use_feat_bank(self) -> bool:
        return self.feature_bank_mlp is not None

    def named_mlps(self) -> dict[str, nn.Module]:
        """The trainable parts, under the names of their learning-rate schedules in Scaffold-GS."""
        parts = {"mlp_opacity": self.opacity_mlp, "mlp_cov": self.cov_mlp, "mlp_color": self.color_mlp,
                 "mlp_featurebank": self.feature_bank_mlp, "appearance": self.embedding_appearance}
        return {name: module for name, module in parts.items() if module is not None}

    def bank_weights(self, ob_view: torch.Tensor, ob_dist: torch.Tensor) -> torch.Tensor:
        """Feature-bank weights [N, 3] (softmax, rows sum to 1) for the coarse (every 4th channel),
        middle (every 2nd) and full resolution, from view directions [N, 3] and distances [N, 1]."""
        if self.feature_bank_mlp is None:
            raise ValueError("these heads have no feature bank (use_feat_bank=False)")
        return self.feature_bank_mlp(torch.cat([ob_view, ob_dist], dim=1))

    def blend_features(self, feat: torch.Tensor, ob_view: torch.Tensor, ob_dist: torch.Tensor) -> torch.Tensor:
        """The view-dependent multi-resolution feature f̂ [N, d] (``feat`` itself without a bank).

        As Scaffold-GS: ``w0 * tile(f[::4], 4) + w1 * tile(f[::2], 2) + w2 * f``, where tile
        repeats the whole sub-sampled vector (it does not interleave).
        """
        if self.feature_bank_mlp is None:
            return feat
        w = self.bank_weights(ob_view, ob_dist)
        return (
            feat[:, ::4].repeat(1, 4) * w[:, 0:1]
            + feat[:, ::2].repeat(1, 2) * w[:, 1:2]
            + feat * w[:, 2:3]
        )

    def forward(
        self,
        feat: torch.Tensor,
        ob_view: torch.Tensor,
        ob_dist: torch.Tensor,
        camera_index: int | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Decode per-anchor inputs into raw per-Gaussian head outputs.

        Args:
            feat: [N, d] the (already blended) anchor features.
            ob_view: [N, 3] unit directions from the camera centre to the anchors.
            ob_dist: [N, 1] camera-anchor distances.
            camera_index: the camera's row in the appearance embedding; required when A > 0.

        Returns:
            ``neural_opacity`` [N, k] (tanh, in (-1, 1)), ``cov`` [N, k, 7] (raw: 3 scale logits
            then a 4-vector quaternion, w first, not normalised) and ``color`` [N, k, 3] (sigmoid).
        """
        n, k = feat.shape[0], self.n_offsets
        with_view = torch.cat([feat, ob_view], dim=1)
        with_dist = (torch.cat([feat, ob_view, ob_dist], dim=1)
                     if self.add_opacity_dist or self.add_cov_dist or self.add_color_dist else None)
        color_in = with_dist if self.add_color_dist else with_view
        if self.embedding_appearance is not None:
            if camera_index is None:
                raise ValueError("these heads have an appearance embedding: pass camera_index")
            index = torch.full((n,), int(camera_index), dtype=torch.long, device=feat.device)
            color_in = torch.cat([color_in, self.embedding_appearance(index)], dim=1)
        mlps = (self.opacity_mlp, self.cov_mlp, self.color_mlp)
        inputs = (with_dist if self.add_opacity_dist else with_view, with_dist if self.add_cov_dist else with_view,
                  color_in)
        if inputs[0] is inputs[1] is inputs[2]:
            hidden = shared_first_layers(inputs[0], mlps)
        else:
            hidden = [mlp[1](mlp[0](x)) for mlp, x in zip(mlps, inputs)]
        neural_opacity, cov, color = (_after_first_layer(mlp, h) for mlp, h in zip(mlps, hidden))
        return neural_opacity, cov.view(n, k, 7), color.view(n, k, 3)


def shared_first_layers(x: torch.Tensor, mlps) -> list[torch.Tensor]:
    """``relu(mlp[0](x))`` [N, width_i] of each ``make_mlp`` head in ``mlps`` that reads the same
    input x [N, C], as one matmul with their weights stacked: one launch instead of one per head
    each way (the gradient of x is one matmul, not one per head and their sum); the same values up
    to float rounding."""
    first = [mlp[0] for mlp in mlps]
    weight = torch.cat([layer.weight for layer in first])
    bias = torch.cat([layer.bias for layer in first]) if first[0].bias is not None else None
    hidden = torch.nn.functional.linear(x, weight, bias).relu_()
    return hidden.split([layer.out_features for layer in first], dim=1)


def _after_first_layer(mlp: nn.Sequential, hidden: torch.Tensor) -> torch.Tensor:
    """The rest of a ``make_mlp`` head (second Linear, then its activation if any) on its hidden layer."""
    out = mlp[2](hidden)
    return mlp[3](out) if len(mlp) > 3 else out
