"""Anchors: the per-voxel parameters Scaffold-GS stores in point_cloud.ply, how they are initialised
from a sparse point cloud, and the row operations densification applies to them.

An anchor ``v`` holds its position ``x_v``, a feature ``f_v`` (d = 32), k learnable offsets
``O_v`` (k = 10), a 6-vector of log scalings ``l_v`` (``[:3]`` scale the offsets, ``[3:]`` are the
base scales of its neural Gaussians), a rotation (w first) and an opacity logit. Scaffold-GS keeps
rotation and opacity in its files, does not render with them and does not train them
(``requires_grad=False``); we do the same so that files stay identical.

Growing and pruning replace the parameter tensors (their row count changes). Any Adam that holds
them is updated in the same call so that ``exp_avg`` / ``exp_avg_sq`` stay row-aligned with the
parameters, as Scaffold-GS's ``cat_tensors_to_optimizer`` / ``_prune_anchor_optimizer`` do.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Mapping

import numpy as np
import torch
from sklearn.neighbors import NearestNeighbors
from torch import nn

ANCHOR_PARAM_NAMES = ("xyz", "feat", "offsets", "scaling", "rotation", "opacity")
"""Attribute names of the per-anchor parameters, in Scaffold-GS's file order of meaning."""

INITIAL_OPACITY = 0.1
"""Anchor opacity at creation, stored as its logit (Scaffold-GS: inverse_sigmoid(0.1))."""


def inverse_sigmoid(x: torch.Tensor) -> torch.Tensor:
    """logit(x) = log(x / (1 - x))."""
    return torch.log(x / (1 - x))


# ----------------------------------------------------------------------------------------------
# Initialisation from a point cloud
# ----------------------------------------------------------------------------------------------


def mean_sq_knn_distance(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """Mean squared distance of each point to its k nearest other points, [P] float32.

    The exact counterpart of simple-knn's ``distCUDA2`` (which Scaffold-GS and 3DGS call with k = 3;
    it is approximate at box borders). With fewer than k + 1 points, the available neighbours are
    averaged. Computed on the CPU with a KD-tree in float64; the result is on ``points.device``.

    Args:
        points: [P, 3] with P >= 2.
    """
    if points.shape[0] < 2:
        raise ValueError(f"need at least 2 points for nearest-neighbour distances, got {points.shape[0]}")
    xyz = points.detach().to("cpu", torch.float64).numpy()
    n_neighbours = min(k, xyz.shape[0] - 1)
    # Ask for one more neighbour than needed: each point is its own nearest neighbour (distance 0).
    dist, _ = NearestNeighbors(n_neighbors=n_neighbours + 1).fit(xyz).kneighbors(xyz)
    mean_sq = (dist[:, 1:] ** 2).mean(axis=1)
    return torch.from_numpy(mean_sq).to(points.device, torch.float32)


def voxel_size_from_points(points: torch.Tensor) -> float:
    """Scaffold-GS's automatic voxel size (its ``voxel_size <= 0`` case).

    Scaffold-GS takes ``torch.kthvalue(distCUDA2(points), int(P * 0.5))``: the lower median of the
    *mean squared* 3-NN distance, used as a length without a square root. We reproduce that value
    exactly (it is smaller than the median NN distance whenever that distance is below 1).

    Args:
        points: [P, 3] with P >= 2.
    """
    sq = mean_sq_knn_distance(points)
    return float(torch.kthvalue(sq.cpu(), int(sq.shape[0] * 0.5)).values)


def voxelize(points: torch.Tensor, voxel_size: float) -> torch.Tensor:
    """Unique voxel centres ``round(p / voxel) * voxel`` of ``points`` [P, 3], as [N, 3] float32.

    Rounding and de-duplication run in float64 (Scaffold-GS does them in numpy on COLMAP's float64
    points) and the result is cast to float32. Rows come out sorted lexicographically by voxel index,
    as ``np.unique(axis=0)`` returns them.
    """
    if voxel_size <= 0:
        raise ValueError(f"voxel_size must be > 0, got {voxel_size}")
    cells = torch.unique(torch.round(points.detach().to(torch.float64) / voxel_size), dim=0)
    return (cells * voxel_size).to(torch.float32)


# ----------------------------------------------------------------------------------------------
# Optimizer bookkeeping
# ----------------------------------------------------------------------------------------------


def swap_optimizer_param(
    optimizer: torch.optim.Optimizer,
    old: nn.Parameter,
    new: nn.Parameter,
    update_moment: Callable[[torch.Tensor], torch.Tensor],
) -> None:
    """Put ``new`` where ``optimizer`` holds ``old``, carrying its state across.

    The parameter is found by identity, so param-group names do not matter. Every state tensor
    shaped like ``old`` (Adam's ``exp_avg``, ``exp_avg_sq``, and ``max_exp_avg_sq`` with amsgrad) is
    mapped through ``update_moment`` (which must give it ``new``'s shape); other entries (``step``)
    are kept. Nothing happens if ``optimizer`` does not hold ``old``.
    """
    for group in optimizer.param_groups:
        for i, p in enumerate(group["params"]):
            if p is not old:
                continue
            group["params"][i] = new
            state = optimizer.state.pop(old, None)
            if state is not None:
                optimizer.state[new] = {
                    key: update_moment(value) if torch.is_tensor(value) and value.shape == old.shape else value
                    for key, value in state.items()
                }
            return


def replace_parameter(module: nn.Module, name: str, value: torch.Tensor,
                      optimizer: torch.optim.Optimizer | None,
                      update_moment: Callable[[torch.Tensor], torch.Tensor]) -> None:
    """Swap ``module``'s parameter ``name`` for a new one holding ``value`` (its row count may
    differ), in the module and in ``optimizer`` (moments mapped through ``update_moment``)."""
    old = getattr(module, name)
    new = nn.Parameter(value.contiguous(), requires_grad=old.requires_grad)
    setattr(module, name, new)
    if optimizer is not None:
        swap_optimizer_param(optimizer, old, new, update_moment)


def anchor_param_groups(model: "AnchorModel", lr: Mapping[str, float]) -> list[dict]:
    """One Adam param group per anchor parameter, named as in :data:`ANCHOR_PARAM_NAMES`.

    ``lr`` maps each of those names to its learning rate (Scaffold-GS: xyz 0 (anchors stay put),
    offsets 0.01 * spatial scale, feat 0.0075, opacity 0.02, scaling 0.007, rotation 0.002).
    """
    return [{"params": [getattr(model, name)], "lr": lr[name], "name": name} for name in model.param_names]


# ----------------------------------------------------------------------------------------------
# The anchor parameters
# ----------------------------------------------------------------------------------------------


class AnchorSizes:
    """N, d and k of anything holding anchor tensors ``xyz`` [N, 3], ``feat`` [N, d] and
    ``offsets`` [N, k, 3] (an ``AnchorModel``, robust training's ``PerturbedAnchors``)."""

    @property
    def num_anchors(self) -> int:
        return self.xyz.shape[0]

    @property
    def feat_dim(self) -> int:
        return self.feat.shape[1]

    @property
    def n_offsets(self) -> int:
        return self.offsets.shape[1]


class AnchorModel(AnchorSizes, nn.Module):
    """The anchors of one scene, as ``nn.Parameter`` attributes of an ``nn.Module``.

    Parameters (N anchors, k offsets, d feature channels), all float32 on one device:
        xyz: [N, 3] anchor positions.
        feat: [N, d] anchor features.
        offsets: [N, k, 3] offsets in units of ``exp(scaling[:, :3])``.
        scaling: [N, 6] log scalings; ``[:, :3]`` scale the offsets, ``[:, 3:]`` the Gaussians.
        rotation: [N, 4] quaternion, w first (stored, not rendered, not trained).
        opacity: [N, 1] opacity logit (stored, not rendered, not trained).

    ``voxel_size`` is the base voxel edge that growing quantises to (``None`` when unknown, e.g.
    after loading a file: Scaffold-GS does not store it).

    Being a module, ``.to(device)`` and ``state_dict()`` work as usual. Growing and pruning replace
    the parameter objects: hold the model, not its parameters.
    """

    def __init__(
        self,
        xyz: torch.Tensor,
        feat: torch.Tensor,
        offsets: torch.Tensor,
        scaling: torch.Tensor,
        rotation: torch.Tensor,
        opacity: torch.Tensor,
        voxel_size: float | None = None,
    ):
        super().__init__()
        n = xyz.shape[0]
        if feat.ndim != 2 or offsets.ndim != 3:
            raise ValueError(
                f"feat must be [N, d] and offsets [N, k, 3]; got {list(feat.shape)}, {list(offsets.shape)}"
            )
        _check_rows(
            n, feat.shape[1], offsets.shape[1],
            xyz=xyz, feat=feat, offsets=offsets, scaling=scaling, rotation=rotation, opacity=opacity,
        )
        self.voxel_size = voxel_size
        for name, value in zip(ANCHOR_PARAM_NAMES, (xyz, feat, offsets, scaling, rotation, opacity)):
            trainable = name not in ("rotation", "opacity")
            setattr(self, name, nn.Parameter(value.detach().to(torch.float32).clone(), requires_grad=trainable))

    @classmethod
    def from_points(
        cls,
        points: torch.Tensor | np.ndarray,
        voxel_size: float = 0.001,
        feat_dim: int = 32,
        n_offsets: int = 10,
        device: torch.device | str | None = None,
    ) -> "AnchorModel":
        """Anchors at the occupied voxels of a sparse point cloud [P, 3], as Scaffold-GS initialises.

        ``voxel_size <= 0`` takes it from the points (:func:`voxel_size_from_points`). Features and
        offsets start at zero; both scalings at ``log(sqrt(mean squared 3-NN distance))`` between
        anchors (clamped to >= 1e-7 before the root); rotation identity; opacity logit(0.1).
        """
        points = torch.as_tensor(points)
        device = torch.device(device) if device is not None else points.device
        if voxel_size <= 0:
            voxel_size = voxel_size_from_points(points)
        xyz = voxelize(points, voxel_size).to(device)
        n = xyz.shape[0]
        dist2 = mean_sq_knn_distance(xyz).clamp_min(1e-7)
        rotation = torch.zeros(n, 4, device=device)
        rotation[:, 0] = 1.0
        return cls(
            xyz=xyz,
            feat=torch.zeros(n, feat_dim, device=device),
            offsets=torch.zeros(n, n_offsets, 3, device=device),
            scaling=torch.log(torch.sqrt(dist2))[:, None].repeat(1, 6),
            rotation=rotation,
            opacity=inverse_sigmoid(torch.full((n, 1), INITIAL_OPACITY, device=device)),
            voxel_size=voxel_size,
        )

    @property
    def param_names(self) -> tuple[str, ...]:
        """The per-anchor parameters: Scaffold-GS's six, plus ``hidden_offsets`` [N, k, 3] when a
        SecureGS ablation ("w/o HDGER") stores the hidden Gaussians' offsets explicitly."""
        return ANCHOR_PARAM_NAMES + (("hidden_offsets",) if hasattr(self, "hidden_offsets") else ())

    def add_hidden_offsets(self) -> None:
        """Start explicit hidden offsets at zero (w/o HDGER); they grow and prune with the anchors."""
        self.hidden_offsets = nn.Parameter(torch.zeros_like(self.offsets))

    def gaussian_positions(self) -> torch.Tensor:
        """Positions [N, k, 3] of the neural Gaussians the stored offsets place:
        ``xyz + offsets * exp(scaling[:, :3])`` (Scaffold-GS's ``all_xyz`` in anchor growing)."""
        return self.xyz[:, None, :] + self.offsets * torch.exp(self.scaling[:, None, :3])

    def prune_anchors(
        self,
        prune_mask: torch.Tensor,
        optimizer: torch.optim.Optimizer | None = None,
        max_log_gaussian_scale: float | None = 0.05,
    ) -> None:
        """Remove the anchors where ``prune_mask`` [N] is True; drop their rows of Adam's moments.

        Scaffold-GS also clamps ``scaling[:, 3:]`` (log space) to at most 0.05 every time it prunes
        (``_prune_anchor_optimizer``); ``max_log_gaussian_scale=None`` skips that clamp.
        """
        prune_mask = prune_mask.to(self.xyz.device)
        if prune_mask.shape != (self.num_anchors,) or prune_mask.dtype != torch.bool:
            raise ValueError(
                f"prune_mask must be a bool [{self.num_anchors}] tensor, "
                f"got {prune_mask.dtype} {list(prune_mask.shape)}"
            )
        keep = ~prune_mask
        with torch.no_grad():
            for name in self.param_names:
                value = getattr(self, name)[keep]
                if name == "scaling" and max_log_gaussian_scale is not None:
                    value[:, 3:] = value[:, 3:].clamp_max(max_log_gaussian_scale)
                self._replace(name, value, optimizer, lambda moment: moment[keep])

    def add_anchors(
        self,
        xyz: torch.Tensor,
        feat: torch.Tensor,
        offsets: torch.Tensor,
        scaling: torch.Tensor,
        rotation: torch.Tensor,
        opacity: torch.Tensor,
        optimizer: torch.optim.Optimizer | None = None,
    ) -> None:
        """Append G anchors (shapes as the parameters, with G rows); Adam's moments get zero rows."""
        g = xyz.shape[0]
        _check_rows(g, self.feat_dim, self.n_offsets,
                    xyz=xyz, feat=feat, offsets=offsets, scaling=scaling, rotation=rotation, opacity=opacity)
        new_rows = dict(zip(ANCHOR_PARAM_NAMES, (xyz, feat, offsets, scaling, rotation, opacity)))
        new_rows["hidden_offsets"] = torch.zeros_like(offsets)  # used only when the model has them
        with torch.no_grad():
            for name in self.param_names:
                old = getattr(self, name)
                extra = new_rows[name].to(old.device, old.dtype)
                self._replace(name, torch.cat([old, extra]), optimizer,
                              lambda moment, extra=extra: torch.cat([moment, torch.zeros_like(extra)]))

    def _replace(self, name, value, optimizer, update_moment) -> None:
        replace_parameter(self, name, value, optimizer, update_moment)


def _check_rows(n: int, d: int, k: int, **tensors: torch.Tensor) -> None:
    """Check that anchor tensors have n rows and their trailing shapes."""
    trailing = {"xyz": (3,), "feat": (d,), "offsets": (k, 3), "scaling": (6,), "rotation": (4,), "opacity": (1,)}
    for name, tensor in tensors.items():
        if tuple(tensor.shape) != (n, *trailing[name]):
            raise ValueError(f"{name} must have shape {[n, *trailing[name]]}, got {list(tensor.shape)}")


# ----------------------------------------------------------------------------------------------
# Anchor growing (Scaffold-GS's anchor_growing, as a pure function)
# ----------------------------------------------------------------------------------------------


@dataclass
class GrowthCandidates:
    """New anchors proposed by :func:`growth_candidates` (G of them).

    Attributes:
        xyz: [G, 3] positions (voxel centres of the level that proposed them).
        feat: [G, d] features: per channel, the max over the parent anchors of the neural Gaussians
            that fell into the voxel.
        cell_size: [G] voxel edge of the proposing level; Scaffold-GS initialises both scalings of a
            grown anchor to its log.
    """

    xyz: torch.Tensor
    feat: torch.Tensor
    cell_size: torch.Tensor

    def anchor_rows(self, n_offsets: int) -> dict[str, torch.Tensor]:
        """Keyword arguments for :meth:`AnchorModel.add_anchors`, initialised as Scaffold-GS does:
        zero offsets, ``scaling = log(cell_size)`` x 6, identity rotation, opacity logit(0.1)."""
        g, device = self.xyz.shape[0], self.xyz.device
        rotation = torch.zeros(g, 4, device=device)
        rotation[:, 0] = 1.0
        return {
            "xyz": self.xyz,
            "feat": self.feat,
            "offsets": torch.zeros(g, n_offsets, 3, device=device),
            "scaling": torch.log(self.cell_size)[:, None].repeat(1, 6),
            "rotation": rotation,
            "opacity": inverse_sigmoid(torch.full((g, 1), INITIAL_OPACITY, device=device)),
        }


@torch.no_grad()
def growth_candidates(
    anchor_xyz: torch.Tensor,
    anchor_feat: torch.Tensor,
    gaussian_xyz: torch.Tensor,
    grads: torch.Tensor,
    gaussian_mask: torch.Tensor,
    threshold: float | torch.Tensor,
    voxel_size: float,
    *,
    update_depth: int = 3,
    update_hierachy_factor: int = 4,
    update_init_factor: int = 16,
    generator: torch.Generator | None = None,
) -> GrowthCandidates:
    """New anchor positions from neural Gaussians with large gradients (Scaffold-GS anchor_growing).

    For level ``i`` in ``0 .. update_depth - 1``:

    * candidates: Gaussians with ``grads >= threshold * (update_hierachy_factor // 2) ** i`` and
      ``gaussian_mask``, each kept with probability ``1 - 0.5 ** (i + 1)``;
    * level voxel ``cell = voxel_size * (update_init_factor // update_hierachy_factor ** i)``
      (16, 4, 1 voxels with the defaults: the coarsest level has the lowest threshold);
    * candidates are quantised to ``round(x / cell)``; a cell already holding an anchor (existing
      or proposed at an earlier level) is dropped, the others become anchors at ``index * cell``
      with the channel-wise max of their parents' features.

    As in Scaffold-GS, a level after the first runs only if an earlier level proposed something
    (its ``if length_inc == 0: if i > 0: continue``); the random draw is taken before that check.

    Args:
        anchor_xyz: [N, 3] existing anchors.
        anchor_feat: [N, d] their features.
        gaussian_xyz: [N, k, 3] neural Gaussian positions (e.g. :meth:`AnchorModel.gaussian_positions`).
        grads: [N*k] accumulated mean screen-space gradient norm per neural Gaussian (row-major,
            Gaussian j of anchor a at ``a * k + j``).
        gaussian_mask: [N*k] bool, Gaussians with enough statistics to be considered.
        threshold: base gradient threshold, a float or a [N*k] tensor (a per-Gaussian threshold, for
            region-aware schemes such as SecureGS's RDO).
        voxel_size: base voxel edge.
        generator: random source for the per-level sub-sampling, on ``anchor_xyz``'s device.

    Returns:
        :class:`GrowthCandidates`, no two in one cell and none in a cell of an existing anchor.
    """
    n, k = gaussian_xyz.shape[:2]
    device = anchor_xyz.device
    if update_init_factor // update_hierachy_factor ** (update_depth - 1) < 1:
        raise ValueError(
            f"update_depth {update_depth} makes the finest level's voxel zero: update_init_factor "
            f"{update_init_factor} // update_hierachy_factor {update_hierachy_factor} ** {update_depth - 1} == 0"
        )
    if grads.shape != (n * k,) or gaussian_mask.shape != (n * k,):
        raise ValueError(
            f"grads and gaussian_mask must be [{n * k}] (N*k), got {list(grads.shape)}, {list(gaussian_mask.shape)}"
        )
    positions = gaussian_xyz.reshape(n * k, 3)
    parent_feat = anchor_feat.repeat_interleave(k, dim=0)  # [N*k, d]
    occupied = anchor_xyz
    found_xyz, found_feat, found_cell = [], [], []
    for level in range(update_depth):
        selected = (grads >= threshold * (update_hierachy_factor // 2) ** level) & gaussian_mask
        # Drawn on the CPU (the generator lives there), so runs are the same on every device.
        selected &= torch.rand(n * k, generator=generator).to(device) > 0.5 ** (level + 1)
        if level > 0 and not found_xyz:
            continue
        cell = voxel_size * (update_init_factor // update_hierachy_factor**level)
        cells, inverse = torch.unique(torch.round(positions[selected] / cell).int(), dim=0, return_inverse=True)
        fresh = ~_rows_in(cells, torch.round(occupied / cell).int())
        if not fresh.any():
            continue
        feat = torch.zeros(cells.shape[0], anchor_feat.shape[1], dtype=anchor_feat.dtype, device=device)
        feat.scatter_reduce_(0, inverse[:, None].expand(-1, feat.shape[1]), parent_feat[selected],
                             reduce="amax", include_self=False)
        xyz = cells[fresh].to(anchor_xyz.dtype) * cell
        found_xyz.append(xyz)
        found_feat.append(feat[fresh])
        found_cell.append(torch.full((xyz.shape[0],), cell, dtype=anchor_xyz.dtype, device=device))
        occupied = torch.cat([occupied, xyz])
    if not found_xyz:
        return GrowthCandidates(
            xyz=anchor_xyz.new_zeros(0, 3), feat=anchor_feat.new_zeros(0, anchor_feat.shape[1]),
            cell_size=anchor_xyz.new_zeros(0),
        )
    return GrowthCandidates(torch.cat(found_xyz), torch.cat(found_feat), torch.cat(found_cell))


def _rows_in(rows: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
    """[R] bool: whether each row of ``rows`` [R, 3] equals some row of ``table`` [T, 3].

    Both go through one ``unique`` so each distinct row gets one id; membership is then ``isin``
    on ids, O((R + T) log(R + T)) instead of Scaffold-GS's chunked R x T comparison.
    """
    _, ids = torch.unique(torch.cat([table, rows]), dim=0, return_inverse=True)
    return torch.isin(ids[table.shape[0]:], ids[: table.shape[0]])
