"""3DGS's densification of explicit Gaussians as a strategy object (gsplat's ``DefaultStrategy``).

Per Gaussian it accumulates the NDC norm of the gradient of its projected mean over the views that
render it. Every ``refine_every`` steps between ``refine_start`` and ``refine_stop`` the Gaussians
whose mean gradient exceeds ``grow_grad2d`` are cloned when small (largest scale ≤
``grow_scale3d`` · scene scale) or split in two when large (samples from the Gaussian itself,
scales divided by 1.6); then those with opacity below ``prune_opa`` are pruned, and, after the first
opacity reset, those larger than ``prune_scale3d`` · scene scale. Every ``reset_every`` steps the
opacities are clamped to 2 · ``prune_opa`` (Adam's moments of the opacities zeroed). Nothing
changes after ``refine_stop``. The defaults are gsplat 1.5's, which are 3DGS's.
"""
from __future__ import annotations

import dataclasses

import torch

from ..gaussians.model import GAUSSIAN_PARAM_NAMES
from ..model.anchors import inverse_sigmoid
from ..reference import quat_to_rotmat
from .scaffold import ndc_grad_norms

# The schedule's steps are stated for 3DGS's 30k-step runs.
_REFERENCE_ITERATIONS = 30_000


@dataclasses.dataclass
class GaussianStrategy:
    """3DGS's densification options (gsplat ``DefaultStrategy`` defaults, for 30k steps).

    scene_scale: the scene's size (3DGS's cameras extent), which the 3D thresholds multiply.
    :meth:`scaled_to` fits the step schedule to a run's length.
    """

    scene_scale: float = 1.0
    prune_opa: float = 0.005
    grow_grad2d: float = 0.0002
    grow_scale3d: float = 0.01
    prune_scale3d: float = 0.1
    refine_start: int = 500
    refine_stop: int = 15_000
    reset_every: int = 3000
    refine_every: int = 100

    def scaled_to(self, iterations: int):
        """A copy whose step schedule is scaled from 30k steps to ``iterations``.

        The refinement interval keeps a floor of 20 steps (as the Scaffold-GS schedule's): its
        mean gradient needs several views of each Gaussian. The opacity reset keeps 3DGS's ratio of
        30 refinements per reset at least, so the Gaussians that survive a reset have time to
        regain their opacity before the next one.
        """
        f = iterations / _REFERENCE_ITERATIONS
        every = max(20, round(self.refine_every * f))
        return dataclasses.replace(self, refine_start=round(self.refine_start * f),
                                   refine_stop=round(self.refine_stop * f), refine_every=every,
                                   reset_every=max(round(self.reset_every * f), 30 * every))

    # -- state ---------------------------------------------------------------------------------

    def initialize_state(self, model) -> dict[str, torch.Tensor]:
        n, dev = model.num_gaussians, model.device
        return {"grad2d": torch.zeros(n, device=dev),  # Σ NDC gradient norm of the projected mean
                "count": torch.zeros(n, device=dev)}  # views that rendered the Gaussian

    @staticmethod
    @torch.no_grad()
    def accumulate(state: dict, info: dict) -> None:
        """Add one view's statistics from ``rasterize``'s info after backward."""
        rendered = info["radii"][:, 0] > 0
        state["grad2d"][rendered] += ndc_grad_norms(info)[rendered]
        state["count"][rendered] += 1

    # -- the hook -------------------------------------------------------------------------------

    def step_post_backward(self, model, optimizer, state, step, branches: dict, generator=None) -> dict:
        """Call after ``loss.backward()`` and before ``optimizer.step()``; returns what changed.
        branches: {"public": (gaussians, info)} (the trainers' common form)."""
        if step >= self.refine_stop:
            return {}
        self.accumulate(state, branches["public"][1])
        changed = {}
        if step > self.refine_start and step % self.refine_every == 0:
            changed = self.refine(model, optimizer, state, step, generator)
        return {**changed, **self.scheduled(model, optimizer, step)}

    def scheduled(self, model, optimizer, step: int) -> dict:
        """What step ``step`` does whatever its gradients (the opacity reset); the trainers call it
        alone for a step whose update was skipped, so a reset is not lost with it."""
        if step < self.refine_stop and step % self.reset_every == 0:
            self.reset_opacity(model, optimizer)
            return {"opacity_reset": True}
        return {}

    @torch.no_grad()
    def refine(self, model, optimizer, state, step: int, generator=None) -> dict:
        """Clone, split, prune; the statistics start again from zero."""
        grads = state["grad2d"] / state["count"].clamp_min(1)
        high = grads > self.grow_grad2d
        small = torch.exp(model.log_scales).max(dim=1).values <= self.grow_scale3d * self.scene_scale
        cloned = self.clone(model, optimizer, high & small)
        split = self.split(model, optimizer, torch.cat([high & ~small, high.new_zeros(cloned)]), generator)
        pruned = self.prune(model, optimizer, step)
        for name, value in self.initialize_state(model).items():
            state[name] = value
        return {"cloned": cloned, "split": split, "pruned": pruned}

    @staticmethod
    def clone(model, optimizer, mask: torch.Tensor) -> int:
        """Append a copy of each Gaussian in ``mask`` [N] bool; returns how many."""
        model.append_rows({name: getattr(model, name)[mask] for name in GAUSSIAN_PARAM_NAMES}, optimizer)
        return int(mask.sum())

    @staticmethod
    def split(model, optimizer, mask: torch.Tensor, generator=None) -> int:
        """Replace each Gaussian in ``mask`` [N] bool by two, centred at samples of itself, with
        scales divided by 1.6 and the other attributes copied; returns how many were split."""
        n = int(mask.sum())
        if n == 0:
            return 0
        scales = torch.exp(model.log_scales[mask])
        noise = torch.randn(2, n, 3, generator=generator).to(scales.device)
        samples = torch.einsum("nij,nj,bnj->bni", quat_to_rotmat(model.quats[mask]), scales, noise)
        rows = {name: getattr(model, name)[mask].repeat(2, *[1] * (getattr(model, name).dim() - 1))
                for name in GAUSSIAN_PARAM_NAMES}
        rows["means"] = (model.means[mask][None] + samples).reshape(-1, 3)
        rows["log_scales"] = torch.log(scales / 1.6).repeat(2, 1)
        model.keep_rows(~mask, optimizer)
        model.append_rows(rows, optimizer)
        return n

    def prune(self, model, optimizer, step: int) -> int:
        """Remove the Gaussians below ``prune_opa`` and, once opacities have been reset, the ones
        larger than ``prune_scale3d`` · scene scale; returns how many."""
        prune = torch.sigmoid(model.opacity_logits) < self.prune_opa
        if step > self.reset_every:
            prune |= torch.exp(model.log_scales).max(dim=1).values > self.prune_scale3d * self.scene_scale
        if prune.any():
            model.keep_rows(~prune, optimizer)
        return int(prune.sum())

    @torch.no_grad()
    def reset_opacity(self, model, optimizer) -> None:
        """Clamp every opacity to at most 2 · prune_opa and zero Adam's moments of the opacities."""
        ceiling = float(inverse_sigmoid(torch.tensor(2.0 * self.prune_opa)))
        model.opacity_logits.clamp_(max=ceiling)
        state = optimizer.state.get(model.opacity_logits, {})
        for key in ("exp_avg", "exp_avg_sq"):
            if key in state:
                state[key].zero_()
