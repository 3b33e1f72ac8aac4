"""Image losses and metrics as 3DGS and Scaffold-GS compute them.

Images are [H, W, C] float tensors in [0, 1] (the rasterizer's layout).
"""
import functools
import math

import torch
import torch.nn.functional as F

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5


@functools.lru_cache(maxsize=8)
def _gaussian_window(channels: int, device: torch.device) -> torch.Tensor:
    """[C, 1, 11, 11] separable Gaussian window (σ 1.5), one per channel (grouped convolution)."""
    x = torch.arange(SSIM_WINDOW, dtype=torch.float32) - SSIM_WINDOW // 2
    g = torch.exp(-(x**2) / (2 * SSIM_SIGMA**2))
    g = g / g.sum()
    window = (g[:, None] @ g[None, :]).expand(channels, 1, SSIM_WINDOW, SSIM_WINDOW)
    return window.contiguous().to(device)


def ssim(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two [H, W, C] images: 11×11 Gaussian window (σ 1.5), zero padding, C1 = 0.01²,
    C2 = 0.03², averaged over pixels and channels — the ``ssim`` of the 3DGS code base."""
    if image.shape != target.shape or image.ndim != 3:
        raise ValueError(f"ssim needs two [H, W, C] images of one shape, got {list(image.shape)}, {list(target.shape)}")
    c = image.shape[-1]
    a = image.permute(2, 0, 1)[None]
    b = target.permute(2, 0, 1)[None]
    w = _gaussian_window(c, image.device)
    pad = SSIM_WINDOW // 2
    mu_a = F.conv2d(a, w, padding=pad, groups=c)
    mu_b = F.conv2d(b, w, padding=pad, groups=c)
    var_a = F.conv2d(a * a, w, padding=pad, groups=c) - mu_a**2
    var_b = F.conv2d(b * b, w, padding=pad, groups=c) - mu_b**2
    cov = F.conv2d(a * b, w, padding=pad, groups=c) - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    ssim_map = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    return ssim_map.mean()


def psnr(image: torch.Tensor, target: torch.Tensor) -> float:
    """PSNR in dB of images in [0, 1] (the render is clamped to [0, 1] first, as evaluation does)."""
    mse = float(((image.clamp(0, 1) - target) ** 2).mean())
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def photometric_loss(image: torch.Tensor, target: torch.Tensor, ssim_weight: float = 0.2) -> torch.Tensor:
    """(1 − λ)·L1 + λ·(1 − SSIM), λ = 0.2: the image term of Scaffold-GS and SecureGS."""
    return (1.0 - ssim_weight) * (image - target).abs().mean() + ssim_weight * (1.0 - ssim(image, target))


def volume_loss(scales: torch.Tensor) -> torch.Tensor:
    """Scaffold-GS's volume regulariser: mean over Gaussians of the product of their 3 scales."""
    return scales.prod(dim=1).mean() if scales.shape[0] else scales.sum()
