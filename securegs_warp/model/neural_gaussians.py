"""Per-view decoding of anchors into neural Gaussians (Scaffold-GS ``generate_neural_gaussians``),
and the visible-anchor prefilter that decides which anchors to decode.

The decoding is parameterised by a set of heads and an offset source, so one function serves both
SecureGS passes: the public pass uses the public :class:`~.heads.ScaffoldHeads` and the stored
offsets (``mu = x_v + O_v * l_v``); the hidden pass uses the private heads and an offset predictor
(``mu = x_v + F_o(f̂_v, delta_vc, d_vc)``) passed as ``offset_source``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
import torch.nn.functional as F

from .anchors import AnchorModel
from .heads import ScaffoldHeads


@dataclass
class AnchorViewInputs:
    """What an offset source may use, for the Nv visible anchors of one view.

    Attributes:
        anchor_index: [Nv] long, indices of the visible anchors in the model (None where the
            caller's offset source does not read it).
        xyz: [Nv, 3] anchor positions.
        feat: [Nv, d] blended anchor features f̂ (the raw features when the heads have no bank).
        ob_view: [Nv, 3] unit directions camera -> anchor.
        ob_dist: [Nv, 1] camera-anchor distances.
        scaling: [Nv, 6] linear scalings ``exp(model.scaling)``.
        offsets: [Nv, k, 3] the stored offsets ``model.offsets`` (None where the caller's offset
            source does not read them).
    """

    anchor_index: torch.Tensor | None
    xyz: torch.Tensor
    feat: torch.Tensor
    ob_view: torch.Tensor
    ob_dist: torch.Tensor
    scaling: torch.Tensor
    offsets: torch.Tensor | None


OffsetSource = Callable[[AnchorViewInputs], torch.Tensor]
"""Maps :class:`AnchorViewInputs` to world-space displacements [Nv, k, 3] of the k Gaussians from
their anchor."""

AnchorSource = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
"""Maps anchor positions [Nv, 3], features [Nv, d] and log scalings [Nv, 6] to the features [Nv, d]
and log scalings [Nv, 6] the heads decode (a key's private latent and codes added to the public
ones, see ``secure.heads.PrivateHeads``)."""

RowDecoder = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor], tuple]
"""Maps anchor positions [Nv, 3], features [Nv, d], log scalings [Nv, 6] and the camera centre [3]
to the Nv*k Gaussians of those anchors before the opacity test (see :func:`decode_rows`)."""


def stored_offsets(inputs: AnchorViewInputs) -> torch.Tensor:
    """Scaffold-GS's explicit offsets: ``offsets * scaling[:, :3]``, [Nv, k, 3]."""
    return inputs.offsets * inputs.scaling[:, None, :3]


def generate_neural_gaussians(
    model: AnchorModel,
    heads: ScaffoldHeads,
    camera_center: torch.Tensor,
    visible_mask: torch.Tensor | None = None,
    *,
    camera_index: int | None = None,
    offset_source: OffsetSource = stored_offsets,
    anchor_source: AnchorSource | None = None,
    feature_grad: float = 1.0,
    scaling_grad: float = 1.0,
    rows: RowDecoder | None = None,
    anchor_index: torch.Tensor | None = None,
    compact: bool = True,
    keep: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """Decode the visible anchors into the Gaussians of one view, exactly as Scaffold-GS does.

    For each visible anchor: ``ob_view = x_v - camera_center``, ``ob_dist = |ob_view|``, ``ob_view``
    normalised; the feature is blended by the heads' feature bank if they have one; the heads give
    per-Gaussian opacity (tanh), covariance (7) and colour. Gaussian j of anchor v is kept iff its
    opacity > 0; then ``scale = exp(l_v[3:]) * sigmoid(cov[:3])``, ``quat = normalize(cov[3:7])``,
    ``mean = x_v + offset_source(...)[v, j]``.

    Args:
        model: the anchors (N of them, k offsets, feature dimension d).
        heads: the heads to decode with (the model's d; the model's k unless ``offset_source`` is
            their own, which returns [Nv, heads.n_offsets, 3]).
        camera_center: [3] camera position in world space.
        visible_mask: [N] bool, the anchors to decode (see :func:`visible_anchor_mask`); None: all.
        camera_index: camera row of the heads' appearance embedding, when they have one.
        offset_source: where the Gaussians sit relative to their anchor; default the stored offsets.
        anchor_source: what the heads decode instead of the anchors' own features (before the
            feature bank) and log scalings, from their positions, features and log scalings; None:
            the anchors' own.
        feature_grad, scaling_grad: how much of this decoding's gradient reaches the anchor features
            f_v and scalings l_v (1: all, 0: none, between: scaled; the forward pass is unchanged).
            SecureGS's hidden pass reads these public attributes and may move them less than the
            public pass does, so that the public file is shaped mainly by the public loss.
        rows: a ``RowDecoder`` that decodes the visible anchors' rows in place of :func:`decode_rows`
            with ``heads``, ``offset_source``, ``anchor_source`` and ``camera_index`` (which it then
            ignores; its k must be ``heads.n_offsets``): the same decoding replayed from CUDA graphs
            (``secure.captured``).
        anchor_index: [Nv] long, the indices of ``visible_mask``'s True entries when the caller
            keeps them (finding them reads a count back from the device: a host synchronisation);
            only with ``visible_mask``.
        compact: False returns every decoded row (M = Nv * k), those that fail the opacity test at
            opacity 0, which the rasterizer leaves out of the image as it leaves out any Gaussian
            below its alpha_min: the same render and gradients without the host synchronisation that
            counts the kept rows, for a caller that reads no per-Gaussian statistics of them. Those
            rows reach the rasterizer, which refuses non-finite values in any row it is given.
        keep: [N] bool, the anchors whose Gaussians may pass the opacity test (None: all): the
            others' rows are decoded and then fail it, so that dropping anchors (robust training's
            pruning) leaves the row count as it is; the render and gradients are those of leaving
            them out of ``visible_mask``.

    Returns:
        dict with M Gaussians of the Nv * k decoded (Gaussian j of the i-th visible anchor is entry
        ``i * k + j`` of the [Nv * k] tensors): the kept ones, or all of them with ``compact=False``:

        * ``means`` [M, 3], ``quats`` [M, 4] (w first, unit), ``scales`` [M, 3] (linear; also what
          the volume regulariser ``volume_loss`` averages), ``opacities`` [M] (in (0, 1); 0 for the
          rows that fail the opacity test), ``colors`` [M, 3]: rasterizer inputs.
        * ``anchor_index`` [M] long: the model anchor each Gaussian came from.
        * ``neural_opacity`` [Nv * k]: raw tanh opacities, negative ones included (densification's
          opacity statistics).
        * ``mask`` [Nv * k] bool: opacity > 0 (and the anchor in ``keep``), which of the decoded
          Gaussians were kept.
        * ``visible_mask`` [N] bool: the anchors decoded.
        * ``compacted``: ``compact`` (False: the M rows are the Nv * k, ``mask`` says which passed).
    """
    # Heads with their own offset source may decode another number of Gaussians per anchor (a
    # private decoder's k_hid); the stored offsets fit only the anchors' own k.
    if heads.feat_dim != model.feat_dim or (offset_source is stored_offsets and heads.n_offsets != model.n_offsets):
        raise ValueError(
            f"heads decode d={heads.feat_dim}, k={heads.n_offsets} but the anchors have "
            f"d={model.feat_dim}, k={model.n_offsets}"
        )
    device = model.xyz.device
    if anchor_index is not None and visible_mask is None:
        raise ValueError("anchor_index names the rows of visible_mask: pass the mask with it")
    if visible_mask is None:
        visible_mask = torch.ones(model.num_anchors, dtype=torch.bool, device=device)
    if anchor_index is None:
        anchor_index = visible_mask.nonzero()[:, 0]
    k = heads.n_offsets

    xyz = model.xyz[anchor_index]
    feat = scale_gradient(model.feat[anchor_index], feature_grad)
    log_scaling = scale_gradient(model.scaling[anchor_index], scaling_grad)
    if rows is None:
        neural_opacity, means, quats, scales, colors = decode_rows(
            heads, offset_source, xyz, feat, log_scaling, camera_center.to(xyz), camera_index=camera_index,
            anchor_index=anchor_index, offsets=model.offsets[anchor_index], anchor_source=anchor_source)
    else:
        neural_opacity, means, quats, scales, colors = rows(xyz, feat, log_scaling, camera_center.to(xyz))

    mask = neural_opacity > 0.0
    if keep is not None:
        mask = mask & keep[anchor_index].repeat_interleave(k)
    gaussians = {"means": means, "quats": quats, "scales": scales, "opacities": neural_opacity, "colors": colors}
    if compact:
        # The kept rows found once (one host synchronisation; each boolean-mask index costs one).
        kept_rows = mask.nonzero()[:, 0]
        gaussians = {name: t[kept_rows] for name, t in gaussians.items()}
        gaussian_anchor = anchor_index[kept_rows // k]  # Gaussian i*k + j belongs to visible anchor i
    else:
        gaussians["opacities"] = torch.where(mask, neural_opacity, torch.zeros_like(neural_opacity))
        gaussian_anchor = anchor_index.repeat_interleave(k)
    return {**gaussians, "anchor_index": gaussian_anchor, "neural_opacity": neural_opacity, "mask": mask,
            "visible_mask": visible_mask, "compacted": compact}


def decode_rows(heads: ScaffoldHeads, offset_source: OffsetSource, xyz: torch.Tensor, feat: torch.Tensor,
                log_scaling: torch.Tensor, camera_center: torch.Tensor, *, camera_index: int | None = None,
                anchor_index: torch.Tensor | None = None, offsets: torch.Tensor | None = None,
                anchor_source: AnchorSource | None = None) -> tuple:
    """Every one of the k Gaussians of each of Nv anchors, before the opacity test (with ``heads``
    and ``offset_source`` bound, a ``RowDecoder``).

    Args:
        heads, offset_source, anchor_source, camera_index: as ``generate_neural_gaussians``.
        xyz: [Nv, 3] the anchors' positions; feat: [Nv, d] their features (before the feature bank);
        log_scaling: [Nv, 6] their scalings l_v (log); camera_center: [3].
        anchor_index, offsets: [Nv] and [Nv, k, 3], the anchors' model indices and stored offsets,
            for offset sources that read them (None where the source does not).

    Returns:
        ``neural_opacity`` [Nv*k] (tanh, negative ones included), ``means`` [Nv*k, 3], ``quats``
        [Nv*k, 4] (unit, w first), ``scales`` [Nv*k, 3] (linear), ``colors`` [Nv*k, 3]; row i*k + j
        is Gaussian j of anchor i.
    """
    ob_view = xyz - camera_center
    ob_dist = ob_view.norm(dim=1, keepdim=True)
    ob_view = ob_view / ob_dist
    if anchor_source is not None:
        feat, log_scaling = anchor_source(xyz, feat, log_scaling)
    feat = heads.blend_features(feat, ob_view, ob_dist)
    scaling = torch.exp(log_scaling)
    inputs = AnchorViewInputs(anchor_index, xyz, feat, ob_view, ob_dist, scaling, offsets)

    neural_opacity, cov, color = heads(feat, ob_view, ob_dist, camera_index)
    displacement = offset_source(inputs)  # [Nv, k, 3]
    return (
        neural_opacity.reshape(-1),
        (xyz[:, None, :] + displacement).reshape(-1, 3),
        F.normalize(cov[..., 3:7], dim=-1).reshape(-1, 4),
        (scaling[:, None, 3:] * torch.sigmoid(cov[..., :3])).reshape(-1, 3),
        color.reshape(-1, 3),
    )


def unit_fraction(name: str, value: float, meaning: str = "a share of a gradient") -> float:
    """``value`` as a float if it lies in [0, 1] (``meaning`` says of what); a ValueError naming it otherwise."""
    value = float(value)
    if not 0.0 <= value <= 1.0:
        raise ValueError(f"{name} must lie in [0, 1] ({meaning}), got {value}")
    return value


def scale_gradient(x: torch.Tensor, factor: float) -> torch.Tensor:
    """``x`` in the forward pass; its gradient multiplied by ``factor`` in the backward pass
    (0: detached, 1: ``x`` itself)."""
    factor = unit_fraction("a gradient factor", factor)
    if factor == 1.0:
        return x
    if factor == 0.0:
        return x.detach()
    return _ScaleGradient.apply(x, factor)


class _ScaleGradient(torch.autograd.Function):
    """Identity forward, gradient × factor backward: one op each way (``x.detach() + factor · (x −
    x.detach())`` computes the same gradient, ``grad · factor``, with five ops and three nodes)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, factor: float) -> torch.Tensor:
        ctx.factor = factor
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        return grad * ctx.factor, None


def camera_center_from_viewmat(viewmat: torch.Tensor) -> torch.Tensor:
    """Camera position [3] of a world-to-camera ``viewmat`` [4, 4]: ``-R^T t``."""
    return -viewmat[:3, :3].T @ viewmat[:3, 3]


@torch.no_grad()
def visible_anchor_mask(
    model: AnchorModel,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    eps2d: float = 0.3,
) -> torch.Tensor:
    """Anchors whose footprint reaches the image, [N] bool (Scaffold-GS ``prefilter_voxel``).

    Scaffold-GS runs its rasterizer's preprocessing on the anchors, with the anchor rotation and the
    offset scaling ``exp(scaling[:, :3])`` as a Gaussian, and keeps those with radius > 0. We compute
    that test in torch (no dependency on the Warp rasterizer, no gradients), as 3DGS / gsplat's
    classic projection does: depth > ``near_plane`` (gsplat's default; 3DGS uses 0.2); EWA 2D
    covariance with the Jacobian's x/z, y/z clamped to 1.3x the field of view, plus ``eps2d`` on the
    diagonal; radius ``ceil(3 sqrt(largest eigenvalue))`` pixels (the eigenvalues' discriminant
    floored at 0.01, gsplat's; 3DGS floors it at 0.1); visible iff the square of that half-width
    around the projected centre ``(fx x/z + cx, fy y/z + cy)`` overlaps the image (3DGS's pixel
    coordinates are half a pixel lower). 3DGS tests the overlap in 16-pixel tiles, so it keeps a few
    more anchors near the border than we do.

    Args:
        viewmat: [4, 4] world-to-camera, OpenCV axes.
        K: [3, 3] intrinsics.
    """
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    p = model.xyz @ R.T + t
    x, y, z = p.unbind(1)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    in_front = z > near_plane
    z = torch.where(in_front, z, torch.ones_like(z))  # keep the maths finite behind the camera

    rot = _quat_to_rotmat(F.normalize(model.rotation, dim=1))
    m = R @ (rot * torch.exp(model.scaling[:, None, :3]))  # [N, 3, 3] camera-space R S
    cov_cam = m @ m.transpose(1, 2)

    lim_x_pos = (width - cx) / fx + 0.3 * (0.5 * width / fx)
    lim_x_neg = cx / fx + 0.3 * (0.5 * width / fx)
    lim_y_pos = (height - cy) / fy + 0.3 * (0.5 * height / fy)
    lim_y_neg = cy / fy + 0.3 * (0.5 * height / fy)
    tx = z * torch.clamp(x / z, -lim_x_neg, lim_x_pos)
    ty = z * torch.clamp(y / z, -lim_y_neg, lim_y_pos)
    zeros = torch.zeros_like(z)
    J = torch.stack(
        [torch.stack([fx / z, zeros, -fx * tx / z**2], dim=1), torch.stack([zeros, fy / z, -fy * ty / z**2], dim=1)],
        dim=1,
    )  # [N, 2, 3]
    cov2d = J @ cov_cam @ J.transpose(1, 2)
    a, b, c = cov2d[:, 0, 0] + eps2d, cov2d[:, 0, 1], cov2d[:, 1, 1] + eps2d
    mid = 0.5 * (a + c)
    l_max = mid + torch.sqrt(torch.clamp(mid**2 - (a * c - b * b), min=0.01))
    radius = torch.ceil(3.0 * torch.sqrt(l_max))

    u, v = fx * x / z + cx, fy * y / z + cy
    on_image = (u + radius > 0) & (u - radius < width) & (v + radius > 0) & (v - radius < height)
    return in_front & on_image


def _quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [N, 3, 3] of unit quaternions [N, 4], w first."""
    w, x, y, z = q.unbind(1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=1,
    ).view(-1, 3, 3)
