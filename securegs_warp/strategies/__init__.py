"""Densification strategies: when and where anchors grow and are pruned (gsplat's ``Strategy`` style).

A strategy is a dataclass of options with a state dict of tensors (checkpointed with the run) and a
hook the trainer calls after backward with the branches it rendered (``{"public": (gaussians,
info), "hidden": ...}``): Scaffold-GS's schedule (:class:`ScaffoldStrategy`) reads the public
branch, SecureGS's region-aware density optimization (:class:`RegionAwareStrategy`) both;
3DGS's clone/split/prune of explicit Gaussians (:class:`GaussianStrategy`) reads the public branch.
"""
from .gaussian import GaussianStrategy
from .region_aware import MODES, RegionAwareStrategy
from .scaffold import ScaffoldStrategy

__all__ = ["GaussianStrategy", "MODES", "RegionAwareStrategy", "ScaffoldStrategy"]
