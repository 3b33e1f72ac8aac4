"""securegs-warp: SecureGS 3D Gaussian Splatting steganography on an NVIDIA Warp rasterizer."""
from .rasterizer import RasterOptions, rasterize

__all__ = ["RasterOptions", "rasterize"]
