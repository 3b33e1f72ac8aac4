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
    """[channels, 1, 11] 1-D Gaussian window (σ 1.5, sums to 1), one row per channel: 3DGS's 11×11
    window is its outer product with itself, so two 1-D passes give the same blur."""
    x = torch.arange(SSIM_WINDOW, dtype=torch.float32) - SSIM_WINDOW // 2
    g = torch.exp(-(x**2) / (2 * SSIM_SIGMA**2))
    g = g / g.sum()
    return g.expand(channels, 1, SSIM_WINDOW).contiguous().to(device)


def _blur(x: torch.Tensor) -> torch.Tensor:
    """Each channel of x [B, K, H, W] convolved with the 11×11 Gaussian window, zero padded: a row
    pass then a column pass (22 taps a pixel instead of 121; with zero padding the separable blur
    is the 2-D one exactly, up to float rounding)."""
    k = x.shape[1]
    g = _gaussian_window(k, x.device)
    pad = SSIM_WINDOW // 2
    x = F.conv2d(x, g[:, :, None, :], padding=(0, pad), groups=k)
    return F.conv2d(x, g[:, :, :, None], padding=(pad, 0), groups=k)


def ssim(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two [H, W, C] images: 11×11 Gaussian window (σ 1.5), zero padding, C1 = 0.01²,
    C2 = 0.03², averaged over pixels and channels — the ``ssim`` of the 3DGS code base."""
    if image.shape != target.shape or image.ndim != 3:
        raise ValueError(f"ssim needs two [H, W, C] images of one shape, got {list(image.shape)}, {list(target.shape)}")
    return batch_ssim(image[None], target[None])[0]


def batch_ssim(images: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """[B] mean SSIM of each pair of [B, H, W, C] images (as ``ssim``), all B in one blur."""
    if images.shape != targets.shape or images.ndim != 4:
        raise ValueError(f"batch_ssim needs two [B, H, W, C] batches of one shape, got {list(images.shape)}, "
                         f"{list(targets.shape)}")
    c = images.shape[-1]
    a = images.permute(0, 3, 1, 2)
    b = targets.permute(0, 3, 1, 2)
    # The five local statistics in one blur: [B, 5C, H, W] → means, second moments.
    mu_a, mu_b, aa, bb, ab = _blur(torch.cat([a, b, a * a, b * b, a * b], dim=1)).split(c, dim=1)
    var_a = aa - mu_a**2
    var_b = bb - mu_b**2
    cov = ab - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    ssim_map = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    return ssim_map.mean(dim=(1, 2, 3))


def psnr(image: torch.Tensor, target: torch.Tensor) -> float:
    """PSNR in dB of images in [0, 1] (the render is clamped to [0, 1] first, as evaluation does)."""
    mse = float(((image.clamp(0, 1) - target) ** 2).mean())
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def photometric_loss(image: torch.Tensor, target: torch.Tensor, ssim_weight: float = 0.2) -> torch.Tensor:
    """(1 − λ)·L1 + λ·(1 − SSIM), λ = 0.2: the image term of Scaffold-GS and SecureGS."""
    return batch_photometric_loss(image[None], target[None], ssim_weight)[0]


def batch_photometric_loss(images: torch.Tensor, targets: torch.Tensor, ssim_weight: float = 0.2) -> torch.Tensor:
    """[B] ``photometric_loss`` of each pair of [B, H, W, C] images, in one pass over the batch (a
    SecureGS step's public and hidden renders: half the launches of two calls)."""
    l1 = (images - targets).abs().mean(dim=(1, 2, 3))
    return (1.0 - ssim_weight) * l1 + ssim_weight * (1.0 - batch_ssim(images, targets))


def volume_loss(scales: torch.Tensor) -> torch.Tensor:
    """Scaffold-GS's volume regulariser: mean over Gaussians of the product of their 3 scales."""
    return scales.prod(dim=1).mean() if scales.shape[0] else scales.sum()
