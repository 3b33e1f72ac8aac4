"""Region-aware density optimization (RDO, the paper's Algorithm 1) and its ablations.

Two sets of gradient statistics: ∇_ori from the public render every step, ∇_hid from the hidden
render every ``hidden_every`` steps (accumulating it more slowly holds back the growth of anchors
that serve only the hidden object). Anchors grown from ∇_hid form Γ_hid; they are placed where the
hidden Gaussians were seen (the mean of each one's positions over the views that counted in ∇_hid;
F_o† places them view by view), so Γ_hid follows the hidden object as the paper's figure of the
∇_hid anchor cloud shows (``hidden_growth_at="public"``: at the public offsets' positions instead); DBSCAN over Γ_hid gives
the bounding box of the dense hidden region, inside which the public growth threshold drops to
τ_fix / r_down, so public anchors multiply there and cover the hidden ones. Γ_hid grows at τ_fix;
pruning (by opacity, from both branches) runs over Γ_ori ∪ Γ_hid.

Modes (the ablations of the paper's Table 4 and appendix):
- "rdo": the above.
- "scaffold" (w/o RDO): Scaffold-GS's strategy on one gradient accumulated from both renders at
  every step, one threshold, no Γ_hid and no box.
- "global": RDO's two statistics, but τ_fix / r_down everywhere (no box): the costly alternative.
- "shared": one gradient (both renders, every step) drives both Γ_ori and Γ_hid growth, box kept.
- "cover": the density of plain Scaffold-GS from the public render alone: no ∇_hid, no Γ_hid, no
  box, pruning by the public opacity. The hidden branch never changes which anchors exist, so it
  needs private heads that decode the hidden object from the cover's own anchors
  (``PrivateHeads(frame="box")``, SecureConfig.hidden_frame).
"""
from __future__ import annotations

import dataclasses
import typing

import numpy as np
import torch

from .scaffold import ScaffoldStrategy

MODES = ("rdo", "scaffold", "global", "shared", "cover")


@dataclasses.dataclass
class RegionAwareStrategy(ScaffoldStrategy):
    # None: chosen by the payload (SecureConfig.strategy_mode): cover for a hidden object, rdo otherwise.
    mode: str | None = None
    r_down: float = 4.0
    hidden_every: int = 2
    dbscan_eps_voxels: float = 12.0  # DBSCAN radius in base voxels
    dbscan_min_samples: int = 8
    hidden_growth_at: str = "hidden"  # where Γ_hid anchors are placed: "hidden" or "public" positions
    # Γ_hid grows at τ_fix · hidden_tau_scale (the paper: 1). Above 1 fewer anchors serve only the
    # hidden object: less of its shape in the release, less hidden fidelity; inf: no Γ_hid at all.
    hidden_tau_scale: float = 1.0
    # The hidden Gaussians' opacity counts in the pruning statistic (an anchor that serves only the
    # hidden branch is kept); False prunes by the public opacity alone, as Scaffold-GS.
    hidden_opacity_keeps: bool = True
    # The hidden render's gradients come from λ·ℓ_hid. Divided by λ (each hidden branch's own), ∇_hid
    # measures the hidden image's own error, so τ_fix means the same for both branches and for
    # every payload (λ is 10 for objects, 0.1 for an image: undivided, an object grows ten times the
    # hidden anchors a public Gaussian with the same error would, and an image almost none).
    # hidden_grad_per_lambda=False accumulates λ·∇ as Algorithm 1 writes it (∇ℓ_total).
    hidden_grad_per_lambda: bool = True
    # Whether the hidden payloads have a region to box (an object, an image); False with a whole hidden
    # scene, whose box would be the whole scene. Set by SecureTrainer from the payloads.
    use_bbox: typing.ClassVar[bool] = True
    anchor_state_keys = ScaffoldStrategy.anchor_state_keys + ("is_hidden",)

    def __post_init__(self):
        if self.mode is not None and self.mode not in MODES:
            raise ValueError(f"the density mode must be one of {MODES}, got {self.mode!r}")
        if not self.r_down >= 1.0:
            raise ValueError(f"r_down must be >= 1 (it divides the growth threshold), got {self.r_down}")
        if self.hidden_every < 1:
            raise ValueError(f"hidden_every must be >= 1, got {self.hidden_every}")
        if not self.hidden_tau_scale >= 1.0:
            raise ValueError(f"hidden_tau_scale must be >= 1 (it multiplies τ_fix), got {self.hidden_tau_scale}")
        if self.hidden_growth_at not in ("hidden", "public"):
            raise ValueError(f"hidden_growth_at must be 'hidden' or 'public', got {self.hidden_growth_at!r}")

    def initialize_state(self, model) -> dict[str, torch.Tensor]:
        if self.mode is None:
            raise ValueError("the density mode is chosen by the payload (SecureConfig.strategy_mode) before training")
        state = super().initialize_state(model)
        state["hid_grad_accum"] = torch.zeros_like(state["grad_accum"])
        state["hid_grad_denom"] = torch.zeros_like(state["grad_denom"])
        state["hid_pos_accum"] = torch.zeros(state["grad_denom"].shape[0], 3, device=model.xyz.device)  # Σ positions
        state["is_hidden"] = torch.zeros_like(state["anchor_denom"])  # 1: the anchor is in Γ_hid
        state["bbox"] = torch.full((6,), float("nan"), device=model.xyz.device)  # min xyz, max xyz
        return state

    @property
    def reads_hidden(self) -> bool:
        """Whether ``step_post_backward`` reads the hidden renders' Gaussians (their opacities and
        gradients per row); the cover mode grows and prunes by the public render alone."""
        return self.mode != "cover"

    def step_post_backward(self, model, optimizer, state, step, branches: dict, generator=None):
        """branches: ``"public"``: (gaussians, info), and, when the step rendered hidden views,
        ``"hidden"``: a list of (gaussians, info, λ), one per secret rendered (λ: the weight of its
        loss, which ∇_hid is divided by; see hidden_grad_per_lambda)."""
        if not self.gathers_at(step):
            return {}
        k = model.n_offsets
        self.accumulate(state, *branches["public"], k)
        for g_hid, info_hid, weight in (branches.get("hidden", []) if self.reads_hidden else []):
            if self.hidden_opacity_keeps:  # an anchor that only serves the hidden branch is still useful
                self.add_opacity(state, g_hid)
            scale = 1.0 / weight if self.hidden_grad_per_lambda and weight > 0 else 1.0
            if self.mode in ("scaffold", "shared"):  # one gradient for both branches, every step
                self.accumulate(state, g_hid, info_hid, k, opacity=False, grad_scale=scale)
            elif step % self.hidden_every == 0:  # ∇_hid, accumulated more slowly
                rows, rendered = self.accumulate(state, g_hid, info_hid, k, prefix="hid_", opacity=False,
                                                 grad_scale=scale)
                state["hid_pos_accum"][rows] += g_hid["means"].detach()[rendered]
        if step > self.update_from and step % self.update_interval == 0:
            return self.adjust(model, optimizer, state, generator)
        return {}

    def public_threshold(self, model, state) -> float | torch.Tensor:
        """τ for growing Γ_ori: τ_fix, τ_fix / r_down inside the hidden box (per Gaussian [N·k])."""
        if self.mode == "global":
            return self.grad_threshold / self.r_down
        if self.mode in ("scaffold", "cover") or not self.use_bbox or torch.isnan(state["bbox"]).any():
            return self.grad_threshold
        lo, hi = state["bbox"][:3], state["bbox"][3:]
        inside = ((model.xyz >= lo) & (model.xyz <= hi)).all(dim=1)
        tau = torch.full((model.num_anchors,), self.grad_threshold, device=model.xyz.device)
        tau[inside] = self.grad_threshold / self.r_down
        return tau.repeat_interleave(model.n_offsets)

    def hidden_positions(self, model, state) -> torch.Tensor | None:
        """[N, k, 3] where Γ_hid growth proposes anchors: each neural Gaussian's mean hidden
        position over the views counted in ∇_hid (its public position where it has none), or
        None for the public positions (``hidden_growth_at="public"``, or modes whose ∇_hid is the
        shared gradient)."""
        if self.hidden_growth_at == "public" or self.mode in ("scaffold", "shared"):
            return None
        denom = state["hid_grad_denom"][:, None]
        public = model.gaussian_positions().reshape(-1, 3)
        mean = torch.where(denom > 0, state["hid_pos_accum"] / denom.clamp_min(1.0), public)
        return mean.view(model.num_anchors, model.n_offsets, 3)

    @torch.no_grad()
    def update_bbox(self, model, state) -> None:
        """DBSCAN over Γ_hid; the box of its largest cluster (noise points ignored)."""
        from sklearn.cluster import DBSCAN

        pts = model.xyz[state["is_hidden"] > 0].cpu().numpy()
        if len(pts) < self.dbscan_min_samples:
            return
        labels = DBSCAN(eps=self.dbscan_eps_voxels * model.voxel_size, min_samples=self.dbscan_min_samples).fit(pts).labels_
        clustered = labels[labels >= 0]
        if clustered.size == 0:
            return
        biggest = pts[labels == np.bincount(clustered).argmax()]
        box = np.concatenate([biggest.min(0), biggest.max(0)])
        state["bbox"] = torch.as_tensor(box, dtype=torch.float32, device=model.xyz.device)

    def adjust(self, model, optimizer, state, generator=None) -> dict:
        if self.mode in ("rdo", "shared") and self.use_bbox:
            self.update_bbox(model, state)
        if self.mode == "shared":  # Γ_hid grows from the very gradient that grows Γ_ori
            state["hid_grad_accum"] = state["grad_accum"].clone()
            state["hid_grad_denom"] = state["grad_denom"].clone()
        grown_ori = self.grow(model, optimizer, state, threshold=self.public_threshold(model, state),
                              generator=generator)
        grown_hid = 0
        if self.mode not in ("scaffold", "cover"):
            n_before = model.num_anchors
            grown_hid = self.grow(model, optimizer, state, prefix="hid_",
                                  threshold=self.grad_threshold * self.hidden_tau_scale,
                                  generator=generator, positions=self.hidden_positions(model, state))
            state["is_hidden"][n_before:] = 1.0
        pruned = self.prune(model, optimizer, state)
        return {"grown": grown_ori, "grown_hidden": grown_hid, "pruned": pruned,
                "hidden_anchors": int(state["is_hidden"].sum())}
