"""Plain 3DGS: explicit Gaussians (``GaussianModel``), rendered through the same rasterizer."""
from .model import GAUSSIAN_PARAM_NAMES, PLY_FILE, GaussianModel, sh_basis, sh_degree_of

__all__ = ["GAUSSIAN_PARAM_NAMES", "PLY_FILE", "GaussianModel", "sh_basis", "sh_degree_of"]
