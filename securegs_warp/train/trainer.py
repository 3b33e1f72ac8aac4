"""Scaffold-GS training: anchors + MLP heads, Adam with Scaffold-GS's learning rates and schedules,
and its anchor densification, on the shared loop of ``ViewTrainer``.

A step's loss is 0.8·L1 + 0.2·(1 − SSIM) + 0.01·volume.
"""
from __future__ import annotations

import torch

from ..config import TrainConfig
from ..data import SceneData
from ..model import ANCHOR_PARAM_NAMES, AnchorModel, anchor_param_groups
from ..scaffold_model import ScaffoldModel, build_heads
from ..strategies import ScaffoldStrategy
from .base import ViewTrainer
from .losses import volume_loss
from .schedules import exponential_lr


class ScaffoldTrainer(ViewTrainer):
    """Trains a Scaffold-GS model on a ``SceneData``: composes a model, an Adam optimizer and a
    densification strategy.

    Attributes: ``model`` (a ``ScaffoldModel``: anchors + public heads), ``optimizer``,
    ``strategy`` and its ``strategy_state``, ``step_count``.
    strategy: the densification strategy to use as given; default Scaffold-GS's, scaled to the run.
    """

    model_state_keys = ("model", "heads", "voxel_size")

    def __init__(self, scene: SceneData, config: TrainConfig, device: str | torch.device = "cpu",
                 strategy: ScaffoldStrategy | None = None):
        super().__init__(scene, config, device)
        torch.manual_seed(config.seed)  # MLP initialisation
        anchors = AnchorModel.from_points(scene.points, voxel_size=config.voxel_size,
                                          feat_dim=config.heads.feat_dim, n_offsets=config.heads.n_offsets,
                                          device=self.device)
        self.model = self._make_model(anchors, build_heads(config.heads, len(scene.train)).to(self.device))
        self.optimizer = self._make_optimizer()
        self.strategy = strategy or ScaffoldStrategy().scaled_to(config.iterations)
        self.strategy_state = self.strategy.initialize_state(self.model.anchors)

    def _make_model(self, anchors, heads) -> ScaffoldModel:
        return ScaffoldModel(anchors, heads)

    def start_from(self, model: ScaffoldModel) -> None:
        """Train ``model`` (its anchors and public heads, in place) instead of the fresh one, with a
        fresh optimizer and strategy state: fine-tuning a saved release."""
        self.model = model
        self.optimizer = self._make_optimizer()
        self.strategy_state = self.strategy.initialize_state(model.anchors)

    # -- optimisation ---------------------------------------------------------------------------

    def _mlp_schedule(self, group_name: str) -> tuple:
        """(initial, final) learning rate of a head group (an MLP, or a key's latent grid); private
        copies (``private_NAME``, ``private2_NAME`` ...) share the public schedule."""
        c = self.config
        schedules = {"mlp_opacity": c.mlp_opacity_lr, "mlp_cov": c.mlp_cov_lr, "mlp_color": c.mlp_color_lr,
                     "mlp_featurebank": c.mlp_featurebank_lr, "appearance": c.appearance_lr,
                     "mlp_offset": c.mlp_offset_lr, "latent": c.latent_lr, "codes": c.code_lr or (c.feature_lr,) * 2}
        return schedules[group_name.split("_", 1)[1] if group_name.startswith("private") else group_name]

    def head_groups(self) -> dict:
        """Name → module of every trained MLP (the SecureGS trainer adds its private ones)."""
        return self.model.heads.named_mlps()

    def _make_optimizer(self) -> torch.optim.Adam:
        c = self.config
        offset_lr = c.offset_lr[0] * self.spatial_scale
        # Positions train at learning rate 0 for the whole run, so their gradient would never be used:
        # not computing it spares the backward every path through the view directions to the anchor
        # positions (densification replaces the parameter with the same requires_grad).
        self.model.anchors.xyz.requires_grad_(False)
        groups = anchor_param_groups(self.model.anchors, {
            "xyz": 0.0,  # Scaffold-GS keeps anchors where voxelisation put them
            "feat": c.feature_lr, "offsets": offset_lr, "hidden_offsets": offset_lr,
            "scaling": c.scaling_lr, "rotation": 0.0, "opacity": 0.0,
        })
        for name, module in self.head_groups().items():
            groups.append({"params": list(module.parameters()), "lr": self._mlp_schedule(name)[0], "name": name})
        return self.adam(groups)

    def _update_learning_rates(self, step: int) -> None:
        c = self.config
        for group in self.optimizer.param_groups:
            name = group.get("name")
            if name in ("offsets", "hidden_offsets"):
                group["lr"] = exponential_lr(c.offset_lr[0] * self.spatial_scale,
                                             c.offset_lr[1] * self.spatial_scale, c.iterations, step)
            elif name in self.head_groups():
                group["lr"] = exponential_lr(*self._mlp_schedule(name), c.iterations, step)

    def regularizer(self, out: dict) -> torch.Tensor:
        """β·volume of one render: with the photometric term, the paper's ℓ_ori and ℓ_hid."""
        gaussians = out["gaussians"]
        kept = None if gaussians["compacted"] else gaussians["mask"]
        return self.config.volume_weight * volume_loss(gaussians["scales"], kept)

    def densify(self, step: int, branches: dict) -> dict:
        return self.strategy.step_post_backward(self.model.anchors, self.optimizer, self.strategy_state, step,
                                                branches, generator=self.generator)

    def size_stats(self) -> dict:
        return {"anchors": self.model.anchors.num_anchors}

    # -- checkpoints ----------------------------------------------------------------------------

    def model_state(self) -> dict:
        return {"voxel_size": float(self.model.anchors.voxel_size), "model": self.model.anchors.state_dict(),
                "heads": self.model.heads.state_dict()}

    def restore_model(self, state: dict) -> None:
        model_state = state["model"]
        anchors = AnchorModel(**{name: model_state[name] for name in ANCHOR_PARAM_NAMES},
                              voxel_size=state["voxel_size"])
        if "hidden_offsets" in model_state:
            anchors.hidden_offsets = torch.nn.Parameter(model_state["hidden_offsets"])
        self.model.anchors = anchors
        self.model.heads.load_state_dict(state["heads"])
        self.optimizer = self._make_optimizer()
