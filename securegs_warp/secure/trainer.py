"""SecureGS training: the Scaffold-GS trainer plus a private hidden branch.

Per step: the public render of a training view gives ℓ_ori; the private heads decode the same
anchors into hidden Gaussians (positions from F_o†) rendered from the same camera against the
payload's hidden view (or, for an image payload, from the one chosen view) for λ·ℓ_hid; a bit
payload adds a BCE term on the per-anchor votes of F_b†. One backward through both renders, then
the region-aware strategy looks at both branches' gradients.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ..data import Camera, SceneData
from .. import evaluation
from ..model.neural_gaussians import unit_fraction
from ..train.losses import psnr
from ..train.trainer import ScaffoldTrainer, TrainConfig
from .heads import PrivateHeads
from .payload import BIT_WEIGHT, PayloadSpec, build_payload
from .strategy import RegionAwareStrategy

# Share of ℓ_hid's gradient that reaches the public anchor features f_v. The paper trains them on
# ℓ_ori + λ·ℓ_hid whole (1). Measured on the built-in scene (object + 48 bits, README), 2000
# iterations: at 1 the cover loses 1.25 dB (H100, 960×540) to 1.9 dB (1080p) against plain
# Scaffold-GS; at 0.1 it loses 0.44 / 1.25–1.85 dB (two 1080p runs) and the hidden mug still renders
# at 38.5 / 37.3–37.7 dB (at 0 it is never learnt: the private heads cannot decode it from features
# the hidden loss does not shape). At 4000 iterations and 0.1 the 1080p cover loses 0.02–0.35 dB in
# four runs of five.
HIDDEN_FEATURE_GRAD = 0.1

# The hidden render must beat the best flat image by this much to count as learnt (a collapsed
# branch scores at or below it; a learnt one, tens of dB above on the mug).
HIDDEN_LEARNT_MARGIN_DB = 1.0


class SecureTrainer(ScaffoldTrainer):
    """``private``: the key's heads; ``payload``: the hidden targets.

    hidden_weight: λ, overriding the payload's default (payload.HIDDEN_WEIGHT).
    hidden_feature_grad, hidden_scaling_grad: the share of ℓ_hid's gradient that reaches the
        anchor features f_v and scalings l_v (1: all of it, as in the paper; 0: none; the features'
        default is HIDDEN_FEATURE_GRAD). Both are public (stored in the release) and shape the public
        Gaussians; below 1 the public loss dominates them and the hidden branch leans more on its
        private heads.
    feature_grad_until: the fraction of the iterations during which hidden_feature_grad applies;
        after it no ℓ_hid gradient reaches f_v, so the public loss alone finishes the features while
        the private heads keep learning to decode them (1: the whole run).
    strategy_options: RegionAwareStrategy fields to override (r_down, hidden_every,
        hidden_growth_at, ...).
    """

    def __init__(self, scene: SceneData, config: TrainConfig, payload: PayloadSpec, device="cpu",
                 mode: str = "rdo", hdger: bool = True, hidden_weight: float | None = None,
                 hidden_feature_grad: float = HIDDEN_FEATURE_GRAD, hidden_scaling_grad: float = 1.0,
                 feature_grad_until: float = 1.0, strategy_options: dict | None = None):
        if hidden_weight is not None and not hidden_weight >= 0.0:
            raise ValueError(f"hidden_weight (λ) must be >= 0, got {hidden_weight}")
        # Checked before the base class builds anything, so that bad shares fail before training.
        self.hidden_feature_grad = unit_fraction("hidden_feature_grad", hidden_feature_grad)
        self.hidden_scaling_grad = unit_fraction("hidden_scaling_grad", hidden_scaling_grad)
        self.feature_grad_until = unit_fraction("feature_grad_until", feature_grad_until, "a fraction of the run")
        options = {"mode": mode, "use_bbox": payload.kind in ("object", "image"), **(strategy_options or {})}
        strategy = RegionAwareStrategy.for_iterations(config.iterations, **options)
        super().__init__(scene, config, device=device, strategy=strategy)
        self.payload = build_payload(payload, scene, self.device)
        if hidden_weight is not None:
            self.payload.weight = float(hidden_weight)
        strategy.hidden_weight = self.payload.weight  # ∇_hid per unit of ℓ_hid (RegionAwareStrategy)
        self.private = PrivateHeads(self.heads, bits=payload.bits, offsets=hdger,
                                    hidden=self.payload.has_images).to(self.device)
        if self.private.decoder is not None and not hdger:
            self.model.add_hidden_offsets()
        self.optimizer = self._make_optimizer()  # now with the private groups

    def head_groups(self) -> dict:
        groups = dict(self.heads.named_mlps())
        private = getattr(self, "private", None)  # absent while the base class builds its optimizer
        if private is not None:
            groups.update({"private_" + name: module for name, module in private.named_mlps().items()})
        return groups

    # -- rendering ------------------------------------------------------------------------------

    def render_hidden(self, cam: Camera, camera_index: int | None = None, **raster_options) -> dict:
        """The hidden branch's render of a view (needs the private heads: the key)."""
        if self.private.decoder is None:
            raise ValueError("this payload hides no image: there is no hidden view to render")
        source = self.private.hidden_offsets if self.private.offset_mlp is not None else self._explicit_offsets
        return self.render_branch(cam, self.private.decoder, self.payload.background, camera_index,
                                  offset_source=source, feature_grad=self.current_feature_grad(),
                                  scaling_grad=self.hidden_scaling_grad,
                                  **raster_options)

    def current_feature_grad(self) -> float:
        """hidden_feature_grad until feature_grad_until of the run, 0 after it."""
        if self.step_count > self.feature_grad_until * self.config.iterations:
            return 0.0
        return self.hidden_feature_grad

    def _explicit_offsets(self, inputs) -> torch.Tensor:
        """w/o HDGER: stored per-anchor hidden offsets [Nv, k, 3], scaled like the public ones."""
        return self.model.hidden_offsets[inputs.anchor_index] * inputs.scaling[:, None, :3]

    def extra_losses(self, index: int, loss: torch.Tensor):
        p, extra, hidden = self.payload, {}, None
        view = index if p.views is not None else p.image_view
        if view is not None:
            out = self.render_hidden(self.scene.train[view], camera_index=view)
            target = p.views[view] if p.views is not None else p.image
            loss = loss + p.weight * self.image_loss(out, target)
            hidden = (out["gaussians"], out["info"])
            extra["psnr_hidden"] = psnr(out["image"].detach(), target)
        if p.bits is not None:
            logits = self.private.bit_logits(self.model.feat)
            loss = loss + BIT_WEIGHT * F.binary_cross_entropy_with_logits(logits, p.bits.expand_as(logits))
        return loss, hidden, extra

    # -- evaluation -----------------------------------------------------------------------------

    @torch.no_grad()
    def evaluate_hidden(self) -> dict:
        """Hidden-branch metrics: PSNR/SSIM on held-out views (object, scene) or at the image's
        view, and bit accuracy."""
        from ..train import render_fps

        p, out = self.payload, {}
        if p.views is not None and p.test_views is not None:
            pairs = [(self.render_hidden(c)["image"].clamp(0, 1), t) for c, t in zip(self.scene.test, p.test_views)]
        elif p.views is not None:
            pairs = [(self.render_hidden(c, i)["image"].clamp(0, 1), t)
                     for i, (c, t) in enumerate(zip(self.scene.train, p.views))]
        elif p.image is not None:
            pairs = [(self.render_hidden(self.scene.train[p.image_view], p.image_view)["image"].clamp(0, 1), p.image)]
        else:
            pairs = []
        if pairs:
            metrics = evaluation.image_metrics(pairs, self.device, with_lpips=False)
            out["psnr_hidden"], out["ssim_hidden"] = metrics["psnr"], metrics["ssim"]
            # What the best flat image (each target's mean colour) scores. A hidden branch that
            # never learnt (too small a gradient share, too short a run) renders the bare
            # background or noise, no better than that: no failure to the metrics above, but one to
            # the person who hid something. None where a target is itself flat.
            flat = float(np.mean([psnr(target.mean(dim=(0, 1)).expand_as(target), target) for _, target in pairs]))
            if np.isfinite(flat):
                out["psnr_hidden_flat"] = flat
                out["hidden_learnt"] = out["psnr_hidden"] > flat + HIDDEN_LEARNT_MARGIN_DB
            else:
                out["psnr_hidden_flat"] = out["hidden_learnt"] = None
            cams = self.scene.test or self.scene.train
            out["fps_hidden"] = render_fps(self.render_hidden, cams, self.device)
        if p.bits is not None:
            out["bit_accuracy"] = self.bit_accuracy()
            out["bits"] = p.bits.long().tolist()
            out["bits_decoded"] = self.private.decode_bits(self.model.feat).tolist()
        return out

    @torch.no_grad()
    def bit_accuracy(self, feat: torch.Tensor | None = None) -> float | None:
        """The fraction of the hidden message the key's bit head reads from anchor features [N, d]:
        this container's by default, or another model's (a plain Scaffold-GS model's features show
        whether the head would "find" the message where it never was; 0.5 is chance). None
        without a bit payload."""
        if self.payload.bits is None:
            return None
        decoded = self.private.decode_bits(self.model.feat if feat is None else feat)
        return float((decoded == self.payload.bits.long()).float().mean())

    # -- checkpoints ----------------------------------------------------------------------------

    def checkpoint_state(self) -> dict:
        return {**super().checkpoint_state(), "private": self.private.state_dict()}

    def restore(self, state: dict, path) -> None:
        self.private.load_state_dict(state["private"])
        super().restore(state, path)
