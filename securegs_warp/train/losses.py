"""Image losses and metrics as 3DGS and Scaffold-GS compute them.

Images are [H, W, C] float tensors in [0, 1] (the rasterizer's layout).
"""
import functools
import math

import torch
import warp as wp

from ..kernels import ssim as ssim_kernels
from ..warp_scope import WarpScope


@functools.lru_cache(maxsize=8)
def _gaussian_window(device: torch.device) -> torch.Tensor:
    """[11] 1-D Gaussian window (σ 1.5, sums to 1): 3DGS's 11×11 window is its outer product with
    itself, so a row pass and a column pass give the same blur."""
    x = torch.arange(ssim_kernels.WINDOW, dtype=torch.float32) - ssim_kernels.HALF
    g = torch.exp(-(x**2) / (2 * ssim_kernels.SIGMA**2))
    return (g / g.sum()).to(device)


class _BatchSSIM(torch.autograd.Function):
    """[B] mean SSIM of [B, H, W, C] images against targets, by the Warp kernels of
    ``securegs_warp.kernels.ssim``; the gradient reaches the images only. Written as kernels because
    torch's grouped convolutions (cuDNN's depthwise kernels, handed the rasterizer's channels-last
    images) made the loss the largest part of a 1080p training step on the GPU; these read the
    rasterizer's layout as it is, and keep what the backward needs from the forward. On the CPU,
    where Warp runs one thread, they are slower than torch's convolutions (docs/results.md)."""

    @staticmethod
    def forward(ctx, images: torch.Tensor, targets: torch.Tensor, with_partials: bool) -> torch.Tensor:
        """with_partials: whether a backward will follow (inside forward grad mode is off, and
        needs_input_grad says only whether the images require grad, also under no_grad)."""
        wp.init()  # idempotent; Warp must be up before its devices can be named
        a, b = images.detach().float().contiguous(), targets.detach().float().contiguous()
        n, h, w, c = a.shape
        window = _gaussian_window(a.device)
        rows = torch.empty((a.numel(), 5), dtype=torch.float32, device=a.device)
        ssim_map = torch.empty_like(a)
        partials = torch.empty((a.numel(), 3) if with_partials else (1, 3), dtype=torch.float32, device=a.device)
        dims = (n * h, w, c)
        with WarpScope(wp.device_from_torch(a.device), a.device):
            flat_a, flat_b, flat_window = _flat(a), _flat(b), _flat(window)
            wp.launch(ssim_kernels.blur_rows_of_stats, dim=dims,
                      inputs=[flat_a, flat_b, flat_window, w, c], outputs=[wp.from_torch(rows, dtype=ssim_kernels.vec5)])
            wp.launch(ssim_kernels.ssim_columns, dim=dims,
                      inputs=[wp.from_torch(rows, dtype=ssim_kernels.vec5), flat_window, h, w, c, ssim_kernels.C1,
                              ssim_kernels.C2, int(with_partials)],
                      outputs=[_flat(ssim_map), wp.from_torch(partials, dtype=wp.vec3)])
        if with_partials:
            ctx.save_for_backward(a, b, partials)
        return ssim_map.mean(dim=(1, 2, 3))

    @staticmethod
    @torch.autograd.function.once_differentiable  # the partials are not themselves differentiated
    def backward(ctx, grad_out: torch.Tensor):
        a, b, partials = ctx.saved_tensors
        n, h, w, c = a.shape
        scale = (grad_out.float() / (h * w * c)).contiguous()
        rows = torch.empty_like(partials)
        grad = torch.empty_like(a)
        dims = (n * h, w, c)
        with WarpScope(wp.device_from_torch(a.device), a.device):
            flat_window = _flat(_gaussian_window(a.device))
            wp.launch(ssim_kernels.blur_rows_of_partials, dim=dims,
                      inputs=[wp.from_torch(partials, dtype=wp.vec3), flat_window, w, c],
                      outputs=[wp.from_torch(rows, dtype=wp.vec3)])
            wp.launch(ssim_kernels.ssim_image_gradient, dim=dims,
                      inputs=[wp.from_torch(rows, dtype=wp.vec3), _flat(a), _flat(b), flat_window, _flat(scale),
                              h, w, c],
                      outputs=[_flat(grad)])
        return grad, None, None


def _flat(t: torch.Tensor):
    """Warp float view of a contiguous float32 tensor, flattened."""
    return wp.from_torch(t.view(-1), dtype=wp.float32)


def ssim(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two [H, W, C] images: 11×11 Gaussian window (σ 1.5), zero padding, C1 = 0.01²,
    C2 = 0.03², averaged over pixels and channels — the ``ssim`` of the 3DGS code base."""
    if image.shape != target.shape or image.ndim != 3:
        raise ValueError(f"ssim needs two [H, W, C] images of one shape, got {list(image.shape)}, {list(target.shape)}")
    return batch_ssim(image[None], target[None])[0]


def batch_ssim(images: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """[B] mean SSIM of each pair of [B, H, W, C] images (as ``ssim``), all B in one blur, computed in
    float32 whatever the inputs' type. The gradient reaches the images only: targets that require
    one are refused."""
    if images.shape != targets.shape or images.ndim != 4:
        raise ValueError(f"batch_ssim needs two [B, H, W, C] batches of one shape, got {list(images.shape)}, "
                         f"{list(targets.shape)}")
    grad = torch.is_grad_enabled()
    if targets.requires_grad and grad:
        raise ValueError("batch_ssim's gradient reaches the images only: pass the targets detached")
    if images.device != targets.device:
        raise ValueError(f"batch_ssim needs images and targets on one device, got {images.device} and {targets.device}")
    return _BatchSSIM.apply(images, targets, grad and images.requires_grad)


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


def volume_loss(scales: torch.Tensor, kept: torch.Tensor | None = None) -> torch.Tensor:
    """Scaffold-GS's volume regulariser: mean over Gaussians of the product of their 3 scales
    [M, 3]; over the rows in ``kept`` [M] bool only, when given (an uncompacted decoding's, see
    ``generate_neural_gaussians``), counted on the device."""
    # The product written out: prod's backward reads back from the device whether any factor is 0
    # (a host synchronisation in every training step's backward).
    if kept is not None:  # the left-out rows replaced, not multiplied by 0: one may hold an inf
        scales = torch.where(kept[:, None], scales, torch.ones_like(scales))
    volume = scales[:, 0] * scales[:, 1] * scales[:, 2]
    if kept is not None:
        return (volume * kept).sum() / kept.sum().clamp_min(1)
    return volume.mean() if scales.shape[0] else scales.sum()
