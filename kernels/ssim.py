"""SSIM of [B, H, W, C] images with the 11×11 Gaussian window, and its gradient, as four kernels.

The window is separable, so each blur is a row pass then a column pass (22 taps a pixel instead of
121), with zero padding as 3DGS's ``conv2d(padding=5)``. The forward blurs the five local statistics
(a, b, a², b², ab) of each pixel and channel and, where a gradient is wanted, stores the SSIM's
partial derivatives with respect to the three statistics that depend on the image a. The backward
blurs those partials (a zero-padded blur with a symmetric window is its own adjoint) and combines
them: ∂/∂a(q) = G·P_μ + 2a(q)·G·P_aa + b(q)·G·P_ab.

Every array is flat, index ((row · W) + x) · C + c with row = image · H + y (the rasterizer's [H, W,
C] layout, images stacked). One thread per pixel and channel: launch dims (B·H, W, C).
"""
import warp as wp

# 3DGS's SSIM: an 11×11 Gaussian window of σ 1.5, C1 = 0.01², C2 = 0.03² (images in [0, 1]).
WINDOW = 11
SIGMA = 1.5
C1, C2 = 0.01**2, 0.03**2
HALF = WINDOW // 2

vec5 = wp.types.vector(length=5, dtype=wp.float32)


@wp.kernel
def blur_rows_of_stats(a: wp.array(dtype=float), b: wp.array(dtype=float), window: wp.array(dtype=float),
                       width: int, channels: int, out: wp.array(dtype=vec5)):
    """out = the row pass of (a, b, a², b², ab)."""
    row, x, c = wp.tid()
    s = vec5()
    for k in range(WINDOW):
        xx = x + k - HALF
        if xx >= 0 and xx < width:
            i = (row * width + xx) * channels + c
            va = a[i]
            vb = b[i]
            s += window[k] * vec5(va, vb, va * va, vb * vb, va * vb)
    out[(row * width + x) * channels + c] = s


@wp.kernel
def ssim_columns(rows: wp.array(dtype=vec5), window: wp.array(dtype=float), height: int, width: int,
                 channels: int, c1: float, c2: float, with_partials: int,
                 ssim_map: wp.array(dtype=float), partials: wp.array(dtype=wp.vec3)):
    """The column pass of the statistics, then the SSIM of each pixel and channel (ssim_map, [B·H·W·C]);
    with_partials: also ∂SSIM/∂(μ_a, ⟨a²⟩, ⟨ab⟩) (partials, [B·H·W·C] vec3; without, a one-element
    placeholder), holding the other blurred statistics fixed."""
    row, x, c = wp.tid()
    image = row / height
    y = row - image * height
    s = vec5()
    for k in range(WINDOW):
        yy = y + k - HALF
        if yy >= 0 and yy < height:
            s += window[k] * rows[((image * height + yy) * width + x) * channels + c]
    mu_a = s[0]
    mu_b = s[1]
    a1 = 2.0 * mu_a * mu_b + c1
    a2 = 2.0 * (s[4] - mu_a * mu_b) + c2
    b1 = mu_a * mu_a + mu_b * mu_b + c1
    b2 = (s[2] - mu_a * mu_a) + (s[3] - mu_b * mu_b) + c2
    d = b1 * b2
    value = a1 * a2 / d
    i = (row * width + x) * channels + c
    ssim_map[i] = value
    if with_partials != 0:
        d_mu = (2.0 * mu_b * (a2 - a1) - 2.0 * mu_a * value * (b2 - b1)) / d
        partials[i] = wp.vec3(d_mu, -value / b2, 2.0 * a1 / d)


@wp.kernel
def blur_rows_of_partials(partials: wp.array(dtype=wp.vec3), window: wp.array(dtype=float), width: int,
                          channels: int, out: wp.array(dtype=wp.vec3)):
    """out = the row pass of the partials."""
    row, x, c = wp.tid()
    s = wp.vec3()
    for k in range(WINDOW):
        xx = x + k - HALF
        if xx >= 0 and xx < width:
            s += window[k] * partials[(row * width + xx) * channels + c]
    out[(row * width + x) * channels + c] = s


@wp.kernel
def ssim_image_gradient(rows: wp.array(dtype=wp.vec3), a: wp.array(dtype=float), b: wp.array(dtype=float),
                        window: wp.array(dtype=float), scale: wp.array(dtype=float), height: int, width: int,
                        channels: int, grad: wp.array(dtype=float)):
    """grad = scale[image] · (G·P_μ + 2a·G·P_aa + b·G·P_ab): the column pass, then the chain rule."""
    row, x, c = wp.tid()
    image = row / height
    y = row - image * height
    p = wp.vec3()
    for k in range(WINDOW):
        yy = y + k - HALF
        if yy >= 0 and yy < height:
            p += window[k] * rows[((image * height + yy) * width + x) * channels + c]
    i = (row * width + x) * channels + c
    grad[i] = scale[image] * (p[0] + 2.0 * a[i] * p[1] + b[i] * p[2])
