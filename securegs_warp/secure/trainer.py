"""SecureGS training: the Scaffold-GS trainer plus a private hidden branch.

Per step: the public render of a training view gives ℓ_ori; the private heads decode the same
anchors into hidden Gaussians (positions from F_o†) rendered from the same camera against the
payload's hidden view (or, for an image payload, from the one chosen view) for λ·ℓ_hid; a bit
payload moves each anchor feature onto its bit of the keyed decoder F_b† after every step. One
backward through both renders, then the region-aware strategy looks at both branches' gradients.
"""
from __future__ import annotations

import numpy as np
import torch

from .. import evaluation
from ..config import SecureConfig, TrainConfig
from ..data import Camera, SceneData
from ..train.losses import psnr
from ..train.trainer import ScaffoldTrainer
from .heads import PrivateHeads
from .keyed_bits import BIT_CELL_VOXELS, new_seed
from .model import SecureModel
from .payload import PayloadSpec, build_payload, message_string
from .robust import parse_robust, perturb, public_opacity

# The hidden render must beat the best flat image by this much to count as learnt (a collapsed
# branch scores at or below it; a learnt one, tens of dB above on the mug).
HIDDEN_LEARNT_MARGIN_DB = 1.0
# The box frame's box: the hidden object's bounds grown by this fraction of their diagonal.
BOX_MARGIN = 0.05

class SecureTrainer(ScaffoldTrainer):
    """Trains a ``SecureModel``: the Scaffold-GS trainer plus the key's private heads and payload.

    secure: the SecureGS options (payload, λ, gradient shares, HDGER, density strategy); its
    strategy's schedule is scaled to ``config.iterations``. Attributes beyond the base class:
    ``secure``, ``payload`` (the hidden targets).
    """

    def __init__(self, scene: SceneData, config: TrainConfig, secure: SecureConfig, device="cpu"):
        self.secure = secure
        self.robust = parse_robust(secure.robust) if secure.robust else []
        # Built before the model, so that a payload the scene cannot carry fails before training.
        self.payload = build_payload(PayloadSpec.parse(secure.payload), scene, torch.device(device))
        if secure.hidden_weight is not None:
            self.payload.weight = float(secure.hidden_weight)
        # The bit decoder's seed is secret like the message (not from the training seed, which
        # config.json records); a checkpoint keeps both.
        self.bit_seed = new_seed() if self.payload.bits is not None else None
        strategy = secure.strategy.scaled_to(config.iterations)
        strategy.hidden_weight = self.payload.weight  # ∇_hid per unit of ℓ_hid (RegionAwareStrategy)
        strategy.use_bbox = self.payload.spec.kind in ("object", "image")
        super().__init__(scene, config, device=device, strategy=strategy)

    def _make_model(self, anchors, heads) -> SecureModel:
        options = self.secure.private_options()
        bit_cell = BIT_CELL_VOXELS * anchors.voxel_size if self.payload.bits is not None else None
        private = PrivateHeads(heads, message=message_string(self.payload.bits), bit_seed=self.bit_seed, bit_cell=bit_cell,
                               offsets=self.secure.hdger, hidden=self.payload.has_images,
                               **options).to(anchors.xyz.device)
        if options["frame"] == "box" and private.decoder is not None:
            bounds = getattr(self.scene, "hidden_bbox", None)
            if bounds is None or self.payload.spec.kind != "object":
                raise ValueError("hidden_frame 'box' decodes a hidden object inside its bounds: it needs an object "
                                 "payload on a scene that knows the object's box")
            lo, hi = np.asarray(bounds, dtype=np.float32)
            margin = BOX_MARGIN * float(np.linalg.norm(hi - lo))  # room for splats that reach past the surface
            private.set_box(lo - margin, hi + margin)
        if private.decoder is not None and not self.secure.hdger:
            anchors.add_hidden_offsets()
        return SecureModel(anchors, heads, private)

    def head_groups(self) -> dict:
        groups = dict(self.model.heads.named_mlps())
        groups.update({"private_" + name: module for name, module in self.model.private.named_mlps().items()})
        return groups

    def config_sections(self) -> dict:
        return {**super().config_sections(), "secure": self.secure}

    # -- rendering ------------------------------------------------------------------------------

    def render_hidden(self, cam: Camera, camera_index: int | None = None, step: int | None = None,
                      anchors=None, visible: torch.Tensor | None = None) -> dict:
        """The hidden branch's render of a view, with the gradient shares of training ``step``
        (default: the step counter); ``anchors``: robust training's perturbed anchors; ``visible``:
        see ``SecureModel.render_hidden``."""
        return self.model.render_hidden(cam, self.config.raster, background=self.payload.background,
                                        camera_index=camera_index, feature_grad=self.current_feature_grad(step),
                                        scaling_grad=self.secure.hidden_scaling_grad, anchors=anchors,
                                        visible=visible)

    def current_feature_grad(self, step: int | None = None) -> float:
        """hidden_feature_grad until feature_grad_until of the run, 0 after it."""
        step = self.step_count if step is None else step
        if step > self.secure.feature_grad_until * self.config.iterations:
            return 0.0
        return self.secure.hidden_feature_grad

    def extra_losses(self, index: int, loss: torch.Tensor, branches: dict, step: int):
        p, extra = self.payload, {}
        # Robust training: this step's hidden render reads randomly attacked anchors (the bits are
        # projected into every anchor after the update, see after_update).
        anchors = perturb(self.model.anchors, self.robust, self.generator,
                          public_opacity(branches["public"][0], self.model.anchors)) if self.robust else None
        view = index if p.views is not None else p.image_view
        if view is not None:
            # Same view and same anchors as the public render: its visibility test holds as it is.
            visible = branches["public"][0]["visible_mask"] if view == index and anchors is None else None
            out = self.render_hidden(self.scene.train[view], camera_index=view, step=step, anchors=anchors,
                                     visible=visible)
            target = p.views[view] if p.views is not None else p.image
            loss = loss + p.weight * self.image_loss(out, target)
            branches["hidden"] = (out["gaussians"], out["info"])
            image = out["image"].detach()
            extra["psnr_hidden"] = lambda: psnr(image, target)
        return loss, extra

    @torch.no_grad()
    def after_update(self) -> None:
        """Move each anchor feature the least distance that makes its vote agree with its bit of
        the message by bit_margin (a projection, not a loss: a loss's gradient goes through Adam,
        which turns it into steps of the learning rate on every coordinate and cost the cover
        0.3-1.2 dB; the projection moves a feature along one direction, only as far as needed)."""
        if self.payload.bits is not None:
            anchors = self.model.anchors
            anchors.feat.copy_(self.model.private.bits.project(anchors.feat, anchors.xyz, self.secure.bit_margin))

    # -- evaluation -----------------------------------------------------------------------------

    @torch.no_grad()
    def evaluate_hidden(self) -> dict:
        """Hidden-branch metrics: PSNR/SSIM on held-out views (object, scene) or at the image's
        view, and bit accuracy."""
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
            out["fps_hidden"] = evaluation.render_fps(self.render_hidden, cams, self.device)
        if p.bits is not None:
            anchors = self.model.anchors
            out["bit_accuracy"] = self.bit_accuracy()
            # One bit per anchor: a message longer than a model's anchors can carry reads 0 where no
            # anchor votes.
            out["bits_without_voters"] = int((self.model.private.bits.vote(anchors.feat, anchors.xyz)[1] == 0).sum())
        return out

    @torch.no_grad()
    def bit_accuracy(self, anchors=None) -> float | None:
        """The fraction of the hidden message the key's bit decoder reads from ``anchors`` (an
        ``AnchorModel``): this container's by default, or another model's (on a model trained
        without this key it is a fair coin per bit: 0.5 on average). None without a bit payload."""
        if self.payload.bits is None:
            return None
        decoded = self.model.decode_bits(anchors)
        return float((decoded == self.payload.bits.long()).float().mean())

    # -- checkpoints ----------------------------------------------------------------------------

    def checkpoint_state(self) -> dict:
        state = {**super().checkpoint_state(), "private": self.model.private.state_dict()}
        if self.payload.bits is not None:  # drawn at random when the run began: resuming keeps them
            state["message"] = self.payload.bits.detach().cpu()
            state["bit_seed"] = self.bit_seed
        return state

    def restore(self, state: dict, path) -> None:
        super().restore(state, path)
        self.model.private.load_state_dict(state["private"])
        if self.payload.bits is not None:
            self.payload.bits, self.bit_seed = state["message"].to(self.device), state["bit_seed"]
            self.model.private.set_message(message_string(self.payload.bits), self.bit_seed,
                                           self.model.private.bits.cell)
            self.model.private.to(self.device)
