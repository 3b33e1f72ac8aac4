"""Dense float64 reference rasterizer: every Gaussian at every pixel, no tiles, torch autograd.

It applies the same rules as the Warp rasterizer (gsplat 1.5 classic): the same projection, the
same radius and tile-rectangle cut-off, alpha clamp, alpha cut-off and exclusive transmittance
stop, but evaluates them as [pixels × Gaussians] tensors in float64 so that it is a trustworthy
oracle for both the image and, through torch autograd, every input gradient.
"""
import math

import torch

ALPHA_MIN = 1.0 / 255.0


def quat_to_rotmat(q):
    """[N, 4] w-first (any norm) → [N, 3, 3]; the zero quaternion maps to the identity."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)


def project(means, quats, scales, opacities, viewmat, K, width, height, near_plane=0.01, far_plane=1e10,
            eps2d=0.3, alpha_min=ALPHA_MIN, antialiased=False, radius_rule="opacity_aware", radius_clip=0.0):
    """Float64 projection. Returns means2d [N,2], conics [N,3], depths [N], opacities [N], radii [N,2]."""
    rot, trans = viewmat[:3, :3], viewmat[:3, 3]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    mc = means @ rot.T + trans
    x, y, z = mc.unbind(-1)
    m = rot @ quat_to_rotmat(quats) * scales[:, None, :]
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos, lim_x_neg = (width - cx) / fx + 0.3 * tan_fovx, cx / fx + 0.3 * tan_fovx
    lim_y_pos, lim_y_neg = (height - cy) / fy + 0.3 * tan_fovy, cy / fy + 0.3 * tan_fovy
    safe_z = torch.where(z > 0, z, torch.ones_like(z))
    tx = safe_z * torch.minimum(torch.maximum(x / safe_z, -lim_x_neg), lim_x_pos)
    ty = safe_z * torch.minimum(torch.maximum(y / safe_z, -lim_y_neg), lim_y_pos)
    zero = torch.zeros_like(z)
    j0 = torch.stack([fx / safe_z, zero, -fx * tx / safe_z**2], -1)
    j1 = torch.stack([zero, fy / safe_z, -fy * ty / safe_z**2], -1)
    a0 = torch.einsum("ni,nij->nj", j0, m)
    a1 = torch.einsum("ni,nij->nj", j1, m)
    c00, c01, c11 = (a0 * a0).sum(-1), (a0 * a1).sum(-1), (a1 * a1).sum(-1)
    det = c00 * c11 - c01 * c01 + eps2d * (c00 + c11) + eps2d * eps2d
    b00, b11 = c00 + eps2d, c11 + eps2d
    opac = opacities
    if antialiased:
        opac = opac * torch.sqrt(((c00 * c11 - c01 * c01) / det).clamp_min(0.0) + 1e-30)
    conics = torch.stack([b11 / det, -c01 / det, b00 / det], -1)
    means2d = torch.stack([fx * x / safe_z + cx, fy * y / safe_z + cy], -1)

    with torch.no_grad():
        visible = (z >= near_plane) & (z <= far_plane) & (det > 0)
        if radius_rule == "3sigma":
            half = 0.5 * (b00 + b11)
            lam = half + torch.sqrt((half * half - det).clamp_min(0.1))
            rx = torch.ceil(3.0 * torch.sqrt(lam))
            ry = rx.clone()
        else:
            visible &= opac >= alpha_min
            extend = torch.sqrt(2.0 * torch.log((opac / alpha_min).clamp_min(1.0))).clamp_max(3.33)
            rx = torch.ceil(extend * torch.sqrt(b00))
            ry = torch.ceil(extend * torch.sqrt(b11))
        rx, ry = rx.clamp_max(1e9), ry.clamp_max(1e9)
        visible &= ~((rx <= radius_clip) & (ry <= radius_clip))
        u, v = means2d[:, 0], means2d[:, 1]
        visible &= ~((u + rx <= 0) | (u - rx >= width) | (v + ry <= 0) | (v - ry >= height))
        radii = torch.stack([rx, ry], -1) * visible[:, None]
    return means2d, conics, z, opac, radii


def render(means, quats, scales, opacities, colors, viewmat, K, width, height, background=None, tile_size=16,
           alpha_max=0.999, transmittance_min=1e-4, alpha_min=ALPHA_MIN, **proj_kwargs):
    """Float64 dense render. Returns image [H,W,C], alpha [H,W,1], accumulated depth [H,W,1], radii."""
    means2d, conics, depths, opac, radii = project(means, quats, scales, opacities, viewmat, K, width, height,
                                                   alpha_min=alpha_min, **proj_kwargs)
    c = colors.shape[1]
    if background is None:
        background = torch.zeros(c, dtype=colors.dtype)
    valid = radii[:, 0] > 0
    idx = torch.nonzero(valid).flatten()
    idx = idx[torch.argsort(depths[idx].detach(), stable=True)]
    m2, cn, op, col, dep, rad = means2d[idx], conics[idx], opac[idx], colors[idx], depths[idx], radii[idx]

    ys, xs = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64),
                            indexing="ij")
    px, py = xs.reshape(-1, 1) + 0.5, ys.reshape(-1, 1) + 0.5
    with torch.no_grad():
        ts = float(tile_size)
        tiles_x, tiles_y = math.ceil(width / ts), math.ceil(height / ts)
        gx, gy = m2[:, 0].float().double() / ts, m2[:, 1].float().double() / ts
        rx, ry = rad[:, 0] / ts, rad[:, 1] / ts
        x0 = torch.floor(gx - rx).clamp(0, tiles_x)
        x1 = torch.ceil(gx + rx).clamp(0, tiles_x)
        y0 = torch.floor(gy - ry).clamp(0, tiles_y)
        y1 = torch.ceil(gy + ry).clamp(0, tiles_y)
        tpx, tpy = torch.floor(xs.reshape(-1, 1) / ts), torch.floor(ys.reshape(-1, 1) / ts)
        in_rect = (tpx >= x0) & (tpx < x1) & (tpy >= y0) & (tpy < y1)

    dx, dy = m2[:, 0] - px, m2[:, 1] - py
    sigma = 0.5 * (cn[:, 0] * dx * dx + cn[:, 2] * dy * dy) + cn[:, 1] * dx * dy
    alpha = torch.clamp(op * torch.exp(-sigma), max=alpha_max)
    with torch.no_grad():
        use = in_rect & (sigma >= 0) & (alpha >= alpha_min)
    a = torch.where(use, alpha, torch.zeros_like(alpha))
    t_after = torch.cumprod(1.0 - a, dim=1)
    t_before = t_after / (1.0 - a)
    with torch.no_grad():
        keep = use & (t_after > transmittance_min)
    w = torch.where(keep, a * t_before, torch.zeros_like(a))
    t_final = torch.prod(torch.where(keep, 1.0 - a, torch.ones_like(a)), dim=1, keepdim=True)
    image = w @ col + t_final * background
    depth = w @ dep[:, None]
    return (image.reshape(height, width, c), (1.0 - t_final).reshape(height, width, 1),
            depth.reshape(height, width, 1), radii)
