"""Named rasterizer test scenes and the comparison of ``rasterize`` with the float64 reference.

``Scene`` holds one render's float32 inputs; ``random_scene`` and ``hard_scene`` build them,
``render_both`` renders a scene with ``rasterize`` and with ``securegs_warp.reference`` and
backpropagates the same cotangents through both, ``assert_matches_reference`` and ``error_row``
compare the two. The tests (tests/test_rasterizer*.py) and scripts/accuracy_vs_time.py use them;
``run_with_cpu_blocks`` runs such code in a fresh process with Warp's CPU blocks enabled.
"""
import dataclasses
import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import torch

from . import reference
from .rasterizer import rasterize

IMAGE_TOL = 1e-4
GRAD_TOL = 1e-3
# The device ``rasterize`` (and the SSIM kernels, tests/test_train.py) run on in these comparisons: the
# CPU, or CUDA on a GPU machine (SECUREGS_TEST_DEVICE=cuda pytest tests/test_rasterizer.py
# tests/test_train.py -k ssim); the reference always runs on the CPU.
TEST_DEVICE = os.environ.get("SECUREGS_TEST_DEVICE", "cpu")
DIFF_INPUTS = ("means", "quats", "scales", "opacities", "colors", "background")


@dataclasses.dataclass
class Scene:
    """float32 inputs of one render: means [N, 3], quats [N, 4], scales [N, 3], opacities [N],
    colors [N, C], viewmat [4, 4], K [3, 3], background [C]; ``kwargs`` are extra rasterize options."""

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor
    viewmat: torch.Tensor
    K: torch.Tensor
    width: int
    height: int
    background: torch.Tensor
    kwargs: dict = dataclasses.field(default_factory=dict)


def intrinsics(fx, fy, cx, cy):
    """[3, 3] float32 pinhole matrix."""
    return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float32)


def random_scene(seed=0, n=60, channels=3, width=40, height=30, depth=4.0, spread=1.2, scale=(0.03, 0.3), **kwargs):
    """Random Gaussians in front of a camera at the origin looking down +z."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * 2 * spread + torch.tensor([0.0, 0.0, depth])
    quats = torch.randn(n, 4, generator=g)
    lo, hi = np.log(scale[0]), np.log(scale[1])
    scales = torch.exp(torch.rand(n, 3, generator=g) * (hi - lo) + lo)
    opacities = torch.rand(n, generator=g) * 0.9 + 0.05
    colors = torch.rand(n, channels, generator=g)
    background = torch.rand(channels, generator=g)
    f = 0.9 * width
    return Scene(means, quats, scales, opacities, colors, torch.eye(4), intrinsics(f, f, width / 2, height / 2),
                 width, height, background, kwargs)


def hard_scene(means, quats=None, scales=None, opacities=None, colors=None, width=32, height=24, viewmat=None,
               K=None, **kwargs):
    """A scene around the given means [N, 3] (camera at the origin looking down +z, 30 px focal
    length); inputs left as None get seeded defaults: random quats, ``aniso_scales(N, 0.1)``,
    opacities 0.7, random RGB colours."""
    n = means.shape[0]
    g = torch.Generator().manual_seed(n)
    return Scene(
        means=means.float(),
        quats=torch.randn(n, 4, generator=g) if quats is None else quats.float(),
        scales=aniso_scales(n, 0.1) if scales is None else scales.float(),
        opacities=torch.full((n,), 0.7) if opacities is None else opacities.float(),
        colors=torch.rand(n, 3, generator=g) if colors is None else colors.float(),
        viewmat=torch.eye(4) if viewmat is None else viewmat.float(),
        K=intrinsics(30.0, 30.0, width / 2, height / 2) if K is None else K,
        width=width, height=height, background=torch.tensor([0.2, 0.3, 0.4]), kwargs=kwargs,
    )


def aniso_scales(n, size):
    """[n, 3] anisotropic scales around ``size``: with isotropic ones rotations would not matter
    and their gradients would be exactly zero, which a relative error cannot check."""
    return size * torch.tensor([1.0, 0.6, 1.4]).repeat(n, 1)


def layered_scene(n_thin=300, n_opaque=40, width=20, height=18, jitter=0.05):
    """Layers along the optical axis: ``n_thin`` translucent ones (opacity 0.015) between depths 2
    and 3, then ``n_opaque`` opaque ones (0.6) between 3.01 and 4, scattered by ``jitter`` sideways,
    so that the pixels near the centre blend a long list crossing several batches of Gaussians."""
    n = n_thin + n_opaque
    z = torch.cat([torch.linspace(2.0, 3.0, n_thin), torch.linspace(3.01, 4.0, n_opaque)])
    means = torch.stack([torch.zeros_like(z), torch.zeros_like(z), z], dim=1)
    means[:, :2] += torch.randn(n, 2, generator=torch.Generator().manual_seed(3)) * jitter
    opac = torch.cat([torch.full((n_thin,), 0.015), torch.full((n_opaque,), 0.6)])
    return hard_scene(means, opacities=opac, scales=aniso_scales(n, 0.05), width=width, height=height)


def reference_kwargs(kwargs):
    """Rasterize options → reference options, with thresholds rounded to float32 as the kernels see them."""
    out = {}
    f32 = lambda v: float(np.float32(v))  # noqa: E731
    for key, value in kwargs.items():
        if key in ("near_plane", "far_plane", "eps2d", "alpha_max", "transmittance_min", "alpha_min", "radius_clip"):
            out[key] = f32(value)
        elif key in ("tile_size", "antialiased", "radius_rule"):
            out[key] = value
    out.setdefault("near_plane", f32(0.01))
    out.setdefault("eps2d", f32(0.3))
    out.setdefault("alpha_min", f32(1.0 / 255.0))
    out.setdefault("alpha_max", f32(0.999))
    out.setdefault("transmittance_min", f32(1e-4))
    return out


def render_both(scene: Scene, seed=1):
    """Render with ``rasterize`` and the reference; backprop the same random cotangents through both.

    Returns (ours, ref): dicts with image, alpha, depth and the gradient of every input.
    """
    g = torch.Generator().manual_seed(seed)
    h, w, c = scene.height, scene.width, scene.colors.shape[1]
    w_img = torch.randn(h, w, c, generator=g, dtype=torch.float64)
    w_alpha = torch.randn(h, w, 1, generator=g, dtype=torch.float64)
    w_depth = torch.randn(h, w, 1, generator=g, dtype=torch.float64)
    results = []
    for dtype in (torch.float32, torch.float64):
        inputs = {name: getattr(scene, name).detach().to(dtype).requires_grad_(True) for name in DIFF_INPUTS}
        if dtype == torch.float32:
            on_device = {name: t.to(TEST_DEVICE) for name, t in inputs.items()}
            image, alpha, info = rasterize(**on_device, viewmat=scene.viewmat.to(TEST_DEVICE),
                                           K=scene.K.to(TEST_DEVICE), width=w, height=h,
                                           render_depth="accumulated", **scene.kwargs)
            image, alpha, depth = image.cpu(), alpha.cpu(), info["depth"].cpu()
        else:
            image, alpha, depth, _ = reference.render(**inputs, viewmat=scene.viewmat.double(), K=scene.K.double(),
                                                      width=w, height=h, **reference_kwargs(scene.kwargs))
        loss = (image.double() * w_img).sum() + (alpha.double() * w_alpha).sum() + (depth.double() * w_depth).sum()
        loss.backward()
        out = {"image": image.detach().double(), "alpha": alpha.detach().double(), "depth": depth.detach().double()}
        for name, t in inputs.items():
            out["grad_" + name] = t.grad.double() if t.grad is not None else torch.zeros_like(t, dtype=torch.float64)
        results.append(out)
    return results


def relative_error(a, b):
    """‖a − b‖ / ‖b‖, or ‖a‖ when the reference is exactly zero."""
    denom = b.norm()
    return float((a - b).norm() / denom) if denom > 0 else float(a.norm())


def assert_matches_reference(scene: Scene, image_tol=IMAGE_TOL, grad_tol=GRAD_TOL, depth_tol=None):
    ours, ref = render_both(scene)
    for key in ("image", "alpha"):
        err = float((ours[key] - ref[key]).abs().max()) if ours[key].numel() else 0.0
        assert err <= image_tol, f"{key} max error {err:.3g} > {image_tol}"
    depth_scale = max(1.0, float(ref["depth"].abs().max())) if ref["depth"].numel() else 1.0
    depth_err = float((ours["depth"] - ref["depth"]).abs().max()) / depth_scale if ref["depth"].numel() else 0.0
    assert depth_err <= (depth_tol or image_tol), f"depth relative error {depth_err:.3g}"
    for name in DIFF_INPUTS:
        g, gr = ours["grad_" + name], ref["grad_" + name]
        assert torch.isfinite(g).all(), f"non-finite gradient for {name}"
        err = relative_error(g, gr)
        worst = int((g - gr).abs().flatten().argmax()) if g.numel() else -1
        assert err <= grad_tol, (f"gradient of {name}: relative error {err:.3g} > {grad_tol} "
                                 f"(worst entry {worst}: {g.flatten()[worst]:.6g} vs {gr.flatten()[worst]:.6g})")
    return ours, ref


def render_with_grads(scene: Scene, **options):
    """[image [H, W, C], alpha [H, W, 1], then the gradient of each of DIFF_INPUTS] of one render with
    ``rasterize`` (on the CPU; fixed random cotangents), ``options`` on top of the scene's."""
    inputs = {name: getattr(scene, name).detach().clone().requires_grad_(True) for name in DIFF_INPUTS}
    image, alpha, _ = rasterize(**inputs, viewmat=scene.viewmat, K=scene.K, width=scene.width,
                                height=scene.height, **options)
    g = torch.Generator().manual_seed(5)
    ((image * torch.randn(image.shape, generator=g)).sum() + (alpha * torch.randn(alpha.shape, generator=g)).sum()
     ).backward()
    return [image, alpha] + [inputs[name].grad for name in DIFF_INPUTS]


def float16_rounding(colors):
    """Largest change of a colour when stored as float16 (≤ 2⁻¹¹·|c|; ≤ 2⁻¹² for |c| < 1)."""
    return float((colors.to(torch.float16).float() - colors).abs().max())


def error_row(ours: dict, ref: dict) -> dict:
    """Max image and alpha errors and each input's relative gradient error, as plain floats."""
    row = {key: float((ours[key] - ref[key]).abs().max()) for key in ("image", "alpha")}
    row.update({name: relative_error(ours["grad_" + name], ref["grad_" + name]) for name in DIFF_INPUTS})
    return row


def run_with_cpu_blocks(body: str, timeout: int = 600):
    """Run test code in a fresh process with ``wp.config.enable_cpu_blocks`` (a global flag), so the
    cooperative CUDA code path runs on the CPU with real multi-thread blocks.

    ``body`` finds ``json``, ``torch`` and ``wp`` imported, imports what else it needs by package
    name (``from securegs_warp.raster_cases import ...``) and must ``print("RESULT" + json.dumps(...))``;
    the decoded object is returned.
    """
    preamble = ("import json\nimport torch\nimport warp as wp\nwp.config.quiet = True\n"
                "wp.config.enable_cpu_blocks = True\n")
    code = preamble + textwrap.dedent(body)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.split("RESULT", 1)[1])
