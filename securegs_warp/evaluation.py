"""Held-out evaluation of a model: PSNR, SSIM, LPIPS when possible, and rendering speed."""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import torch

from .train.losses import psnr, ssim

# LPIPS (AlexNet) needs torchvision's ImageNet weights, which no package ships and nothing here
# downloads: it is computed only when they are already in torch's hub cache.
ALEXNET_WEIGHTS = "alexnet-owt-7be5be79.pth"


def lpips_model(device):
    """(LPIPS network, None) when it can run offline, else (None, the reason it cannot)."""
    weights = Path(torch.hub.get_dir()) / "checkpoints" / ALEXNET_WEIGHTS
    if not weights.is_file():
        return None, f"LPIPS not computed: AlexNet weights not found at {weights} (nothing is downloaded)"
    try:
        import lpips
    except ImportError:
        return None, "LPIPS not computed: the `lpips` package is not installed (pip install lpips)"
    return lpips.LPIPS(net="alex", verbose=False).to(device).eval(), None


@torch.no_grad()
def image_metrics(pairs, device, with_lpips: bool = True, psnr_cap: float | None = None) -> dict:
    """Mean PSNR / SSIM (/ LPIPS) over (render [H,W,3], target [H,W,3]) pairs; ``psnr_cap``: each
    view's PSNR at most this (an identical view's is inf, which would make the mean inf)."""
    pairs = list(pairs)
    cap = math.inf if psnr_cap is None else psnr_cap
    out = {"psnr": float(np.mean([min(psnr(a, b), cap) for a, b in pairs])),
           "ssim": float(np.mean([float(ssim(a.clamp(0, 1), b)) for a, b in pairs]))}
    net, reason = lpips_model(device) if with_lpips else (None, "LPIPS not requested")
    if net is None:
        out["lpips"] = None
        out["lpips_note"] = reason
    else:
        to_net = lambda x: x.clamp(0, 1).permute(2, 0, 1)[None] * 2 - 1  # noqa: E731
        out["lpips"] = float(np.mean([float(net(to_net(a), to_net(b))) for a, b in pairs]))
    return out


@torch.no_grad()
def evaluate_views(render, cameras, device, timing_repeats: int = 3, with_lpips: bool = False,
                   on_render=None) -> dict:
    """PSNR/SSIM (/LPIPS) of ``render(cam)["image"]`` against each camera's image, and FPS.

    on_render(cam, image [H, W, 3]) sees each clamped render (to save it). Returns psnr, ssim,
    lpips (None with lpips_note when it cannot run), fps and views.
    """
    if not cameras:
        raise ValueError("no held-out views to evaluate on")
    pairs = []
    for cam in cameras:
        if cam.image is None:
            raise ValueError(f"camera {cam.name!r} has no image to compare with")
        image = render(cam)["image"].clamp(0, 1)
        if on_render is not None:
            on_render(cam, image)
        pairs.append((image, torch.as_tensor(cam.image, device=device)))
    metrics = image_metrics(pairs, device, with_lpips=with_lpips)
    return {**metrics, "fps": render_fps(render, cameras, device, timing_repeats), "views": len(cameras)}


def render_fps(render, cameras, device, repeats: int = 3) -> float:
    """Frames per second of ``render(cam)`` over the cameras (after one warm-up pass)."""
    render(cameras[0])
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(repeats):
        for cam in cameras:
            render(cam)
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()
    return repeats * len(cameras) / (time.perf_counter() - t0)


# Where an image's error can lie against an object's coverage: inside it, on its silhouette, outside.
REGIONS = ("interior", "silhouette", "outside")


def silhouette_regions(alpha: torch.Tensor, band: int = 2) -> dict[str, torch.Tensor]:
    """REGIONS of an object's coverage ``alpha`` [H, W] in [0, 1], as bool masks [H, W] that split
    every pixel once: ``silhouette`` the pixels within ``band`` px (a square neighbourhood) of the
    boundary of alpha > 0.5, ``interior`` the rest of the object, ``outside`` the rest."""
    if band < 1:
        raise ValueError(f"band must be >= 1 pixel, got {band}")
    inside = (alpha > 0.5).float()[None, None]
    grow = lambda m: torch.nn.functional.max_pool2d(m, 2 * band + 1, stride=1, padding=band)  # noqa: E731
    dilated, eroded = grow(inside)[0, 0] > 0, grow(1.0 - inside)[0, 0] == 0
    silhouette = dilated & ~eroded
    return {"interior": eroded, "silhouette": silhouette, "outside": ~dilated}


def error_by_region(pairs, band: int = 2) -> dict[str, dict]:
    """Squared error of (render [H, W, 3], truth [H, W, 3], alpha [H, W]) triples summed over views,
    split by ``silhouette_regions``: per region of REGIONS its share of the error and of the pixels,
    and its PSNR (None where it holds no pixel); under "all", the same of every pixel pooled.
    ValueError without a view."""
    pairs = list(pairs)
    if not pairs:
        raise ValueError("error_by_region needs at least one (render, truth, alpha) view")
    error = dict.fromkeys(REGIONS, 0.0)
    pixels = dict.fromkeys(REGIONS, 0)
    for render, truth, alpha in pairs:
        squared = ((render - truth) ** 2).sum(-1)
        for name, mask in silhouette_regions(alpha, band).items():
            error[name] += float(squared[mask].sum())
            pixels[name] += int(mask.sum())
    error["all"], pixels["all"] = sum(error.values()), sum(pixels.values())
    return {name: {"error_share": error[name] / error["all"] if error["all"] > 0 else 0.0,
                   "pixel_share": pixels[name] / pixels["all"],
                   "psnr": (10 * math.log10(3 * pixels[name] / error[name]) if error[name] > 0 else math.inf)
                   if pixels[name] else None}
            for name in (*REGIONS, "all")}
