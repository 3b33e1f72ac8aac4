"""Scaffold-GS training: one class with ``step()``, ``evaluate()`` and checkpoints (Warp examples style).

A step renders one training view through ``securegs_warp.rasterize``, takes the loss
0.8·L1 + 0.2·(1 − SSIM) + 0.01·volume, backpropagates, lets the densification strategy look at the
gradients, then steps Adam with Scaffold-GS's learning rates and schedules. A checkpoint holds
everything a step changes (anchors, heads, Adam, strategy statistics, random state), written
atomically, so an interrupted run resumes where it stopped.
"""
from __future__ import annotations

import dataclasses
import io
import time

import torch

from ..data import Camera, SceneData
from ..effects import infer_scene_effects
from .. import evaluation  # module import: evaluation itself imports train.losses
from ..io.atomic import atomic_write
from ..model import ANCHOR_PARAM_NAMES, AnchorModel, ScaffoldHeads, anchor_param_groups
from ..render import render_view
from .losses import photometric_loss, psnr, volume_loss
from .schedules import exponential_lr
from .strategy import ScaffoldStrategy


@dataclasses.dataclass
class TrainConfig:
    """Hyper-parameters; defaults are Scaffold-GS's (learning rates for its 30k-step runs)."""

    iterations: int = 30_000
    seed: int = 0
    feat_dim: int = 32
    n_offsets: int = 10
    voxel_size: float = 0.0  # <= 0: from the sparse points' nearest-neighbour distances
    use_feat_bank: bool = False
    appearance_dim: int = 0
    add_opacity_dist: bool = False
    add_cov_dist: bool = False
    add_color_dist: bool = False
    ssim_weight: float = 0.2
    volume_weight: float = 0.01
    feature_lr: float = 0.0075
    scaling_lr: float = 0.007
    offset_lr_init: float = 0.01
    offset_lr_final: float = 0.0001
    mlp_opacity_lr: tuple = (0.002, 0.00002)
    mlp_cov_lr: tuple = (0.004, 0.004)
    mlp_color_lr: tuple = (0.008, 0.00005)
    mlp_featurebank_lr: tuple = (0.01, 0.00001)
    appearance_lr: tuple = (0.05, 0.0005)
    mlp_offset_lr: tuple = (0.004, 0.0004)  # SecureGS's private offset predictor F_o† (no paper value)
    mlp_bits_lr: tuple = (0.01, 0.001)  # SecureGS's bit head F_b†: 256 bits exact within ~20 steps
    densify: bool = True
    tile_size: int = 16  # rasterizer tile; 8 is faster on the CPU (shorter per-tile lists)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown training options: {', '.join(sorted(unknown))}")
        d = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
        return cls(**d)


class ScaffoldTrainer:
    """Trains a Scaffold-GS model on a ``SceneData``.

    Attributes: ``model`` (anchors), ``heads`` (public MLPs), ``optimizer``, ``strategy`` and its
    ``strategy_state``, ``step_count``.
    """

    def __init__(self, scene: SceneData, config: TrainConfig, device: str | torch.device = "cpu",
                 strategy: ScaffoldStrategy | None = None):
        if not scene.train:
            raise ValueError(f"scene {scene.name!r} has no training views")
        self.scene = scene
        self.config = config
        self.device = torch.device(device)
        self.generator = torch.Generator().manual_seed(config.seed)
        self.background = torch.tensor(
            scene.background if scene.background is not None else (0.0, 0.0, 0.0),
            dtype=torch.float32, device=self.device)
        torch.manual_seed(config.seed)  # MLP initialisation
        self.model = AnchorModel.from_points(scene.points, voxel_size=config.voxel_size, feat_dim=config.feat_dim,
                                             n_offsets=config.n_offsets, device=self.device)
        # Only the head inputs the effects ask for are built (effects.py).
        self.effects = infer_scene_effects(scene, config=config)
        self.heads = ScaffoldHeads(config.feat_dim, config.n_offsets, **self.effects.head_kwargs()).to(self.device)
        self.spatial_scale = float(scene.cameras_extent)
        self.optimizer = self._make_optimizer()
        self.strategy = strategy or ScaffoldStrategy.for_iterations(config.iterations)
        self.strategy_state = self.strategy.initialize_state(self.model)
        self.step_count = 0
        self.train_seconds = 0.0  # wall time spent in step(), kept across resumes
        self._targets = [torch.as_tensor(c.image, device=self.device) for c in scene.train]
        self._order: list[int] = []

    # -- optimisation ---------------------------------------------------------------------------

    def _mlp_schedule(self, group_name: str) -> tuple:
        """(initial, final) learning rate of an MLP group; private copies share the public schedule."""
        c = self.config
        schedules = {"mlp_opacity": c.mlp_opacity_lr, "mlp_cov": c.mlp_cov_lr, "mlp_color": c.mlp_color_lr,
                     "mlp_featurebank": c.mlp_featurebank_lr, "appearance": c.appearance_lr,
                     "mlp_offset": c.mlp_offset_lr, "mlp_bits": c.mlp_bits_lr}
        return schedules[group_name.removeprefix("private_")]

    def head_groups(self) -> dict:
        """Name → module of every trained MLP (the SecureGS trainer adds its private ones)."""
        return self.heads.named_mlps()

    def _make_optimizer(self) -> torch.optim.Adam:
        c = self.config
        offset_lr = c.offset_lr_init * self.spatial_scale
        groups = anchor_param_groups(self.model, {
            "xyz": 0.0,  # Scaffold-GS keeps anchors where voxelisation put them
            "feat": c.feature_lr, "offsets": offset_lr, "hidden_offsets": offset_lr,
            "scaling": c.scaling_lr, "rotation": 0.0, "opacity": 0.0,
        })
        for name, module in self.head_groups().items():
            groups.append({"params": list(module.parameters()), "lr": self._mlp_schedule(name)[0], "name": name})
        return torch.optim.Adam(groups, lr=0.0, eps=1e-15)

    def _update_learning_rates(self) -> None:
        c, step = self.config, self.step_count
        for group in self.optimizer.param_groups:
            name = group.get("name")
            if name in ("offsets", "hidden_offsets"):
                group["lr"] = exponential_lr(c.offset_lr_init * self.spatial_scale,
                                             c.offset_lr_final * self.spatial_scale, c.iterations, step)
            elif name in self.head_groups():
                group["lr"] = exponential_lr(*self._mlp_schedule(name), c.iterations, step)

    def _next_view(self) -> int:
        """Training views in a random order, each once per epoch (as 3DGS picks them)."""
        if not self._order:
            self._order = torch.randperm(len(self.scene.train), generator=self.generator).tolist()
        return self._order.pop()

    # -- rendering ------------------------------------------------------------------------------

    def render(self, cam: Camera, camera_index: int | None = None, **raster_options) -> dict:
        """The public render of one view; see ``render_branch``."""
        return self.render_branch(cam, self.heads, self.background, camera_index, **raster_options)

    def render_branch(self, cam: Camera, heads, background, camera_index=None, offset_source=None,
                      **raster_options) -> dict:
        """``render_view`` with this run's tile size."""
        raster_options.setdefault("tile_size", self.config.tile_size)
        return render_view(self.model, heads, cam, background, camera_index=camera_index,
                           offset_source=offset_source, **raster_options)

    def image_loss(self, out: dict, target: torch.Tensor) -> torch.Tensor:
        """(1 − α)·L1 + α·(1 − SSIM) + β·volume for one render (the paper's ℓ_ori and ℓ_hid)."""
        loss = photometric_loss(out["image"], target, self.config.ssim_weight)
        return loss + self.config.volume_weight * volume_loss(out["gaussians"]["scales"])

    def step(self) -> dict:
        """One training iteration. Returns {"loss", "psnr", "anchors", "grown", "pruned", ...}."""
        t0 = time.perf_counter()
        self.step_count += 1
        self._update_learning_rates()
        index = self._next_view()
        out = self.render(self.scene.train[index], camera_index=index)
        target = self._targets[index]
        loss, hidden, extra = self.extra_losses(index, self.image_loss(out, target))
        loss.backward()
        bad = nonfinite_gradient_counts(self.optimizer)
        changed = {}
        if bad:
            # Skip the whole update, as mixed-precision training does on overflow: see
            # nonfinite_gradient_counts for why zeroing the bad entries is not enough.
            extra = {**extra, "nonfinite_grads": sum(bad.values()), "nonfinite_groups": sorted(bad)}
        else:
            if self.config.densify:
                changed = self.strategy.step_post_backward(self.model, self.optimizer, self.strategy_state,
                                                           self.step_count, out["gaussians"], out["info"],
                                                           generator=self.generator, hidden=hidden)
            self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        result = {"loss": loss.item(), "psnr": psnr(out["image"].detach(), target),
                  "anchors": self.model.num_anchors, **extra, **changed}
        self.train_seconds += time.perf_counter() - t0
        return result

    def extra_losses(self, index: int, loss: torch.Tensor):
        """Hook for the hidden branch: (total loss, (gaussians, info) of a hidden render or None,
        numbers to report). Scaffold-GS has only the public loss."""
        return loss, None, {}

    @torch.no_grad()
    def evaluate(self, cameras: list[Camera] | None = None, timing_repeats: int = 3, with_lpips: bool = False,
                 on_render=None) -> dict:
        """PSNR, SSIM (and LPIPS when asked and possible) on held-out views (the test split by
        default), and rendering FPS. ``on_render(cam, image [H, W, 3])`` sees each render (to save it)."""
        cameras = self.scene.test if cameras is None else cameras
        if not cameras:
            raise ValueError("no held-out views to evaluate on")
        pairs = []
        for cam in cameras:
            image = self.render(cam)["image"].clamp(0, 1)
            if on_render is not None:
                on_render(cam, image)
            pairs.append((image, torch.as_tensor(cam.image, device=self.device)))
        metrics = evaluation.image_metrics(pairs, self.device, with_lpips=with_lpips)
        return {**metrics, "fps": render_fps(self.render, cameras, self.device, timing_repeats),
                "anchors": self.model.num_anchors, "views": len(cameras)}

    # -- checkpoints ----------------------------------------------------------------------------

    def checkpoint_state(self) -> dict:
        """Everything a step changes, as tensors and plain numbers (loadable with weights_only)."""
        return {
            "step": self.step_count,
            "train_seconds": self.train_seconds,
            "config": self.config.to_dict(),
            "voxel_size": float(self.model.voxel_size),
            "model": self.model.state_dict(),
            "heads": self.heads.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "strategy": self.strategy_state,
            "generator": self.generator.get_state(),
            "order": list(self._order),
        }

    def save_checkpoint(self, path) -> None:
        buffer = io.BytesIO()
        torch.save(self.checkpoint_state(), buffer)
        atomic_write(path, lambda f: f.write(buffer.getvalue()))

    def load_checkpoint(self, path) -> None:
        """Restore a checkpoint written by ``save_checkpoint`` (tensors and numbers only)."""
        state = torch.load(path, map_location=self.device, weights_only=True)
        self.restore(state, path)

    def restore(self, state: dict, path) -> None:
        if state["config"] != self.config.to_dict():
            raise ValueError(f"{path}: checkpoint was written with other training options; resume with the "
                             "run's own config")
        model_state = state["model"]
        self.model = AnchorModel(**{name: model_state[name] for name in ANCHOR_PARAM_NAMES},
                                 voxel_size=state["voxel_size"])
        if "hidden_offsets" in model_state:
            self.model.hidden_offsets = torch.nn.Parameter(model_state["hidden_offsets"])
        self.heads.load_state_dict(state["heads"])
        self.optimizer = self._make_optimizer()
        self.optimizer.load_state_dict(state["optimizer"])
        self.strategy_state = state["strategy"]
        self.generator.set_state(state["generator"])
        self._order = list(state["order"])
        self.step_count = int(state["step"])
        self.train_seconds = float(state["train_seconds"])


@torch.no_grad()
def nonfinite_gradient_counts(optimizer: torch.optim.Optimizer) -> dict[str, int]:
    """Parameter group name -> number of inf/NaN gradient entries, for the groups that have any
    (empty: every gradient is finite). One host sync.

    The trainer skips a step with any such entry: no optimizer step, and no densification step
    either (neither its statistics nor, on an update step, growth and pruning, which wait for the
    next update). Both ways of going on can damage the model:
    - Applied, an inf or NaN reaches Adam, whose update of an anchor trained at learning rate 0
      (its position, as in Scaffold-GS) is 0 · m/√v = NaN for good; the anchor drops out of every
      view and is never pruned. Seen on an H100 (2026-11-22, SecureGS λ=3, 960×540).
    - Zeroing just those entries (this project's rule until 2026-11-23) applies the rest of a
      gradient computed through an overflow, whose finite entries may be huge as well; one huge
      gradient fills Adam's second moment, and the entry then barely moves for thousands of steps.
      Mixed-precision training skips such steps for the same reason.
    One source was found and fixed (the opacity-aware radius at opacity == alpha_min, see
    kernels/projection.py). Under the zeroing rule a 1080p SecureGS run with one step of it ended
    8.5 dB below its baseline outside the hidden object (H100, 2026-11-23, seed 1, 4000
    iterations); a rerun that skipped the step ended 0.35 dB below. Whether that step caused the
    loss was not established (GPU runs are not bitwise repeatable).
    """
    named = [(group.get("name", f"group {i}"), [p.grad for p in group["params"] if p.grad is not None])
             for i, group in enumerate(optimizer.param_groups)]
    named = [(name, grads) for name, grads in named if grads]
    if not named:
        return {}
    totals = torch.stack([sum((~torch.isfinite(g)).sum() for g in grads) for _, grads in named]).tolist()
    return {name: int(n) for (name, _), n in zip(named, totals) if n}


def render_fps(render, cameras, device, repeats: int = 3) -> float:
    """Frames per second of ``render(cam)`` over the cameras (after one warm-up pass)."""
    render(cameras[0])
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(repeats):
        for cam in cameras:
            render(cam)
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()
    return repeats * len(cameras) / (time.perf_counter() - t0)
