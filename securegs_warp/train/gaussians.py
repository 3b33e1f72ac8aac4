"""Plain 3DGS training: explicit Gaussians, Adam with 3DGS's learning rates, the SH degree raised
during the run, and 3DGS's densification (``GaussianStrategy``), on the shared loop of
``ViewTrainer``. A step's loss is 0.8·L1 + 0.2·(1 − SSIM), as 3DGS's.
"""
from __future__ import annotations

import torch

from ..config import TrainConfig
from ..data import Camera, SceneData
from ..gaussians import GAUSSIAN_PARAM_NAMES, GaussianModel
from ..strategies import GaussianStrategy
from .base import ViewTrainer
from .schedules import exponential_lr

# 3DGS's schedules are stated for 30k steps; the SH interval is scaled with the run like the
# densification schedule.
_REFERENCE_ITERATIONS = 30_000


class GaussianTrainer(ViewTrainer):
    """Trains a ``GaussianModel`` (3DGS) on a ``SceneData``.

    Attributes: ``model``, ``optimizer`` (one Adam group per parameter, named as the parameter),
    ``strategy`` (3DGS's, scaled to the run and to the scene's camera extent) and
    ``strategy_state``, ``step_count``. model: train this model instead of one initialised from
    the scene's points (its SH degree must be the config's; a raw feature field has none).
    """

    def __init__(self, scene: SceneData, config: TrainConfig, device: str | torch.device = "cpu",
                 strategy: GaussianStrategy | None = None, model: GaussianModel | None = None):
        super().__init__(scene, config, device)
        self.gs = config.gaussians
        if model is None:
            model = GaussianModel.from_points(torch.as_tensor(scene.points), torch.as_tensor(scene.colors),
                                              sh_degree=self.gs.sh_degree)
        self.model = model.to(self.device)
        self.optimizer = self._make_optimizer()
        self.strategy = strategy or GaussianStrategy(scene_scale=self.spatial_scale).scaled_to(config.iterations)
        self.strategy_state = self.strategy.initialize_state(self.model)
        self.sh_interval = max(1, round(self.gs.sh_interval * config.iterations / _REFERENCE_ITERATIONS))

    def _learning_rates(self) -> dict:
        gs = self.gs
        return {"means": gs.means_lr[0] * self.spatial_scale, "log_scales": gs.scale_lr, "quats": gs.quat_lr,
                "opacity_logits": gs.opacity_lr, "features_dc": gs.sh_lr, "features_rest": gs.sh_lr / 20.0}

    def _make_optimizer(self) -> torch.optim.Adam:
        lr = self._learning_rates()
        groups = [{"params": [getattr(self.model, name)], "lr": lr[name], "name": name} for name in GAUSSIAN_PARAM_NAMES]
        return self.adam(groups)

    def _update_learning_rates(self, step: int) -> None:
        gs = self.gs
        for group in self.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = exponential_lr(gs.means_lr[0] * self.spatial_scale, gs.means_lr[1] * self.spatial_scale,
                                             self.config.iterations, step)

    def active_sh_degree(self, step: int | None = None) -> int:
        """The SH degree in use at ``step`` (default the current one): one more every sh_interval steps."""
        step = self.step_count if step is None else step
        return min(self.gs.sh_degree, step // self.sh_interval)

    def render(self, cam: Camera, camera_index: int | None = None) -> dict:
        return self.model.render(cam, self.config.raster, background=self.background,
                                 sh_degree=self.active_sh_degree())

    def densify(self, step: int, branches: dict) -> dict:
        return self.strategy.step_post_backward(self.model, self.optimizer, self.strategy_state, step, branches,
                                                generator=self.generator)

    def densify_skipped(self, step: int) -> dict:
        return self.strategy.scheduled(self.model, self.optimizer, step)

    def size_stats(self) -> dict:
        return {"gaussians": self.model.num_gaussians}

    def model_state(self) -> dict:
        return {"model": {name: getattr(self.model, name).detach() for name in GAUSSIAN_PARAM_NAMES}}

    def restore_model(self, state: dict) -> None:
        self.model = GaussianModel(**state["model"], sh_degree=self.model.sh_degree).to(self.device)
        self.optimizer = self._make_optimizer()
