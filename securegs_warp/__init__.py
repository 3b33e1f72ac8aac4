"""securegs-warp: SecureGS 3D Gaussian Splatting steganography on an NVIDIA Warp rasterizer."""
from .rasterizer import RasterOptions, UnknownOptionError, rasterize

__all__ = ["RasterOptions", "UnknownOptionError", "rasterize"]
