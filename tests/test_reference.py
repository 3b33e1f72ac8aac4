"""The float64 reference is itself checked: its autograd gradients against finite differences."""
import math

import torch

from securegs_warp import reference
from securegs_warp.raster_cases import random_scene


def test_reference_gradients_match_finite_differences():
    s = random_scene(20, n=4, width=10, height=8, scale=(0.1, 0.3))
    inputs = [t.double().requires_grad_(True) for t in (s.means, s.quats, s.scales, s.opacities, s.colors, s.background)]
    g = torch.Generator().manual_seed(0)
    w_img = torch.randn(8, 10, 3, generator=g, dtype=torch.float64)

    def f(means, quats, scales, opacities, colors, background):
        image, alpha, depth, _ = reference.render(means, quats, scales, opacities, colors, s.viewmat.double(),
                                                  s.K.double(), 10, 8, background=background)
        return (image * w_img).sum() + alpha.sum() + 0.1 * depth.sum()

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_reference_single_gaussian_closed_form():
    """One isotropic Gaussian at the image centre: the centre pixel's alpha is o·exp(-σ)."""
    means = torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64)
    K = torch.tensor([[10.0, 0, 5.0], [0, 10.0, 5.0], [0, 0, 1]], dtype=torch.float64)
    image, alpha, _, _ = reference.render(means, torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
                                          torch.full((1, 3), 0.2, dtype=torch.float64),
                                          torch.tensor([0.5], dtype=torch.float64),
                                          torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64),
                                          torch.eye(4, dtype=torch.float64), K, 10, 10)
    var = (10.0 * 0.2 / 2.0) ** 2 + 0.3  # projected variance in pixels² plus the low-pass
    sigma = 0.5 * (0.5**2 + 0.5**2) / var  # pixel centre (5.5, 5.5) vs mean (5, 5)
    assert abs(float(alpha[5, 5, 0]) - 0.5 * math.exp(-sigma)) < 1e-12
    assert abs(float(image[5, 5, 0]) - float(alpha[5, 5, 0])) < 1e-12
