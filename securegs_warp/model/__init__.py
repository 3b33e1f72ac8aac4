"""Scaffold-GS model: anchors, MLP heads, and their per-view decoding into neural Gaussians."""

from .anchors import (
    ANCHOR_PARAM_NAMES,
    AnchorModel,
    GrowthCandidates,
    anchor_param_groups,
    growth_candidates,
    inverse_sigmoid,
    mean_sq_knn_distance,
    replace_parameter,
    swap_optimizer_param,
    voxel_size_from_points,
    voxelize,
)
from .heads import ScaffoldHeads, make_mlp
from .neural_gaussians import (
    AnchorViewInputs,
    OffsetSource,
    camera_center_from_viewmat,
    generate_neural_gaussians,
    stored_offsets,
    visible_anchor_mask,
)

__all__ = [
    "ANCHOR_PARAM_NAMES",
    "AnchorModel",
    "AnchorViewInputs",
    "GrowthCandidates",
    "OffsetSource",
    "ScaffoldHeads",
    "anchor_param_groups",
    "camera_center_from_viewmat",
    "generate_neural_gaussians",
    "growth_candidates",
    "inverse_sigmoid",
    "make_mlp",
    "mean_sq_knn_distance",
    "replace_parameter",
    "stored_offsets",
    "swap_optimizer_param",
    "visible_anchor_mask",
    "voxel_size_from_points",
    "voxelize",
]
