"""Scaffold-GS's anchor densification as a strategy object with a hook after backward.

``ScaffoldStrategy`` is Scaffold-GS's schedule: per neural Gaussian it accumulates the screen-space
gradient norm of its mean, per anchor the opacity its Gaussians reach; every ``update_interval``
steps it grows anchors where the mean gradient exceeds a threshold and prunes anchors whose
Gaussians stayed transparent. The SecureGS region-aware strategy subclasses it and replaces
``growth_threshold``/``step_post_backward``; the state is a dict of tensors so checkpoints hold it.
"""
from __future__ import annotations

import dataclasses

import torch

from ..model import AnchorModel, growth_candidates

# Scaffold-GS's schedule, for 30k iterations.
_REFERENCE_ITERATIONS = 30_000


def ndc_grad_norms(info: dict) -> torch.Tensor:
    """[M] norms of the loss gradient with respect to each Gaussian's projected mean, in NDC units
    (3DGS and gsplat measure it so: d/d ndc = d/d pixel · (W/2, H/2)), from ``rasterize``'s info
    after backward. The densification statistic of Scaffold-GS and of 3DGS."""
    grad = info["means2d_grad"]
    scale = torch.tensor([info["width"] / 2.0, info["height"] / 2.0], device=grad.device)
    return (grad * scale).norm(dim=1)


@dataclasses.dataclass
class ScaffoldStrategy:
    """Scaffold-GS's densification options. The schedule (``start_stat`` .. ``update_until``) is
    stated for Scaffold-GS's 30k-step runs; :meth:`scaled_to` fits it to a run's length."""

    grad_threshold: float = 0.0002
    min_opacity: float = 0.005
    success_threshold: float = 0.8
    start_stat: int = 500
    update_from: int = 1500
    update_interval: int = 100
    update_until: int = 15_000
    update_depth: int = 3
    update_hierachy_factor: int = 4
    update_init_factor: int = 16

    def scaled_to(self, iterations: int):
        """A copy whose schedule is this one's scaled from 30k steps to ``iterations``.

        The check interval shrinks with the run but not below 20 steps: growing needs a Gaussian
        to be seen in 40% of the interval's views before its gradient average is trusted.
        """
        f = iterations / _REFERENCE_ITERATIONS
        return dataclasses.replace(
            self, start_stat=round(self.start_stat * f), update_from=round(self.update_from * f),
            update_interval=max(20, round(self.update_interval * f)), update_until=round(self.update_until * f))

    @classmethod
    def for_iterations(cls, iterations: int, **overrides):
        """Scaffold-GS's schedule scaled to ``iterations`` steps, then ``overrides`` set as given."""
        return dataclasses.replace(cls().scaled_to(iterations), **overrides)

    # -- state ---------------------------------------------------------------------------------

    def initialize_state(self, model: AnchorModel) -> dict[str, torch.Tensor]:
        n, k, dev = model.num_anchors, model.n_offsets, model.xyz.device
        return {
            "grad_accum": torch.zeros(n * k, device=dev),  # Σ |d loss / d mean2d| (NDC units)
            "grad_denom": torch.zeros(n * k, device=dev),  # views in which the Gaussian was rendered
            "opacity_accum": torch.zeros(n, device=dev),  # Σ of the anchor's positive opacities
            "anchor_denom": torch.zeros(n, device=dev),  # views in which the anchor was visible
        }

    # Per-anchor statistics (one row per anchor); subclasses add theirs. Gradient statistics are
    # per neural Gaussian (N·k rows); any other state entry is not indexed by anchor.
    anchor_state_keys = ("opacity_accum", "anchor_denom")

    @staticmethod
    @torch.no_grad()
    def accumulate(state: dict, gaussians: dict, info: dict, k: int, prefix: str = "",
                   opacity: bool = True, grad_scale: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
        """Add one view's statistics (Scaffold-GS ``training_statis``).

        gaussians: the output of ``generate_neural_gaussians`` for the view (compacted); info: the matching
        ``rasterize`` info after backward. ``prefix`` selects a second set of gradient statistics
        (SecureGS keeps one per branch); ``opacity`` also counts the view in the opacity statistics;
        ``grad_scale`` multiplies the gradient norms (SecureGS divides out its loss weight λ).
        Returns (rows [N·k] bool: the neural Gaussians counted, rendered [M] bool: which of the
        view's M kept Gaussians they are), for statistics a subclass adds alongside.
        """
        if not gaussians["compacted"]:
            raise ValueError("the statistics are per kept Gaussian: decode with compact=True")
        visible = gaussians["visible_mask"]
        if opacity:
            ScaffoldStrategy.add_opacity(state, gaussians)
            state["anchor_denom"][visible] += 1
        rows = torch.zeros_like(state[prefix + "grad_denom"], dtype=torch.bool)
        rows[visible.repeat_interleave(k)] = gaussians["mask"]
        rendered = info["radii"][:, 0] > 0
        kept = rows.clone()
        rows[kept] = rendered
        state[prefix + "grad_accum"][rows] += grad_scale * ndc_grad_norms(info)[rendered]
        state[prefix + "grad_denom"][rows] += 1
        return rows, rendered

    @staticmethod
    def add_opacity(state: dict, gaussians: dict) -> None:
        """Add each anchor's kept Gaussians' opacities to ``opacity_accum`` (Scaffold-GS's sum of
        its positive neural opacities): a row that failed the opacity test, or whose anchor was
        dropped (``generate_neural_gaussians``'s ``keep``), adds nothing, compacted or not."""
        opacities = gaussians["opacities"].detach()
        if not gaussians["compacted"]:
            opacities = torch.where(gaussians["mask"], opacities, torch.zeros_like(opacities))
        state["opacity_accum"].index_add_(0, gaussians["anchor_index"], opacities)

    # -- hooks ----------------------------------------------------------------------------------

    def step_post_backward(self, model, optimizer, state, step, branches: dict, generator=None) -> dict:
        """Call after ``loss.backward()`` and before ``optimizer.step()``. Returns what changed.

        branches: name -> (gaussians, info) of each render of the step: ``"public"`` always,
        ``"hidden"`` for SecureGS. Scaffold-GS densifies from the public render alone.
        """
        if not self.gathers_at(step):
            return {}
        self.accumulate(state, *branches["public"], model.n_offsets)
        if step > self.update_from and step % self.update_interval == 0:
            return self.adjust(model, optimizer, state, generator)
        return {}

    def gathers_at(self, step: int) -> bool:
        """Whether step ``step`` gathers statistics (and may adjust): start_stat < step <= update_until.
        Scaffold-GS stops before update_until; here the window keeps update_until, one adjustment
        more, as every table in docs/results.md was measured ("Scaffold-GS's schedule window and scale
        clamp" there has both ways)."""
        return self.start_stat < step <= self.update_until

    def growth_threshold(self, model: AnchorModel, state: dict) -> float | torch.Tensor:
        """Gradient threshold for growing: one number, or one per neural Gaussian [N·k]."""
        return self.grad_threshold

    # -- growing and pruning --------------------------------------------------------------------

    @torch.no_grad()
    def grow(self, model, optimizer, state, prefix="", threshold=None, generator=None, positions=None) -> int:
        """Grow anchors from the gradient statistics under ``prefix``; returns the number added.

        positions: [N, k, 3] where each neural Gaussian proposes its new anchor; default the
        stored offsets' positions (``model.gaussian_positions()``), as Scaffold-GS.
        """
        denom = state[prefix + "grad_denom"]
        grads = torch.nan_to_num(state[prefix + "grad_accum"] / denom, nan=0.0)
        seen = denom > self.update_interval * self.success_threshold * 0.5
        if model.voxel_size is None:
            raise ValueError("anchor growing needs the model's voxel_size (pass it when loading a model)")
        found = growth_candidates(
            model.xyz, model.feat, model.gaussian_positions() if positions is None else positions, grads, seen,
            self.growth_threshold(model, state) if threshold is None else threshold,
            model.voxel_size, update_depth=self.update_depth,
            update_hierachy_factor=self.update_hierachy_factor, update_init_factor=self.update_init_factor,
            generator=generator,
        )
        for name in (prefix + "grad_accum", prefix + "grad_denom", prefix + "pos_accum"):
            if name in state:
                state[name][seen] = 0.0
        added = found.xyz.shape[0]
        if added:
            model.add_anchors(**found.anchor_rows(model.n_offsets), optimizer=optimizer)
            self._pad(state, added, model.n_offsets)
        return added

    @torch.no_grad()
    def prune(self, model, optimizer, state) -> int:
        """Remove anchors seen often enough whose Gaussians stayed nearly transparent."""
        checked = state["anchor_denom"] > self.update_interval * self.success_threshold
        prune = (state["opacity_accum"] < self.min_opacity * state["anchor_denom"]) & checked
        state["opacity_accum"][checked] = 0.0
        state["anchor_denom"][checked] = 0.0
        if prune.any():
            keep = ~prune
            k = model.n_offsets
            for name, value in state.items():
                if _per_gaussian(name):
                    rest = value.shape[1:]
                    state[name] = value.view(-1, k, *rest)[keep].reshape(-1, *rest)
                elif name in self.anchor_state_keys:
                    state[name] = value[keep]
            # Scaffold-GS prunes, and so clamps the Gaussians' log scales (prune_anchors), at every
            # adjustment; here only where an anchor goes, as every table in docs/results.md was
            # measured ("Scaffold-GS's schedule window and scale clamp" there has both ways).
            model.prune_anchors(prune, optimizer)
        return int(prune.sum())

    def adjust(self, model, optimizer, state, generator=None) -> dict:
        grown = self.grow(model, optimizer, state, generator=generator)
        pruned = self.prune(model, optimizer, state)
        return {"grown": grown, "pruned": pruned}

    def _pad(self, state: dict, added: int, k: int) -> None:
        """Zero statistics for ``added`` new anchors (per-anchor and per-Gaussian entries)."""
        for name, value in state.items():
            if _per_gaussian(name) or name in self.anchor_state_keys:
                rows = added * k if _per_gaussian(name) else added
                state[name] = torch.cat([value, value.new_zeros((rows, *value.shape[1:]))])


def _per_gaussian(state_key: str) -> bool:
    """Gradient (and position) statistics have one row per neural Gaussian (N·k), the others one
    per anchor."""
    return state_key.endswith(("grad_accum", "grad_denom", "pos_accum"))
